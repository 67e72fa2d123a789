# admc: every target sets up the machine first (idempotent, seconds when already done).
PY      := .venv/bin/python
ADMC    := .venv/bin/admc-pipe
CONFIG  ?=
ARGS    ?=
CFGARG  := $(if $(CONFIG),--config $(CONFIG),)

.PHONY: setup demo render dataset train eval ood test bench clean

setup:
	@bash scripts/setup.sh

demo: dataset               ## the whole product on the embedded default corpus: dataset, fine-tune both models, Table 1
	$(ADMC) train --stage finetune $(CFGARG) $(ARGS)
	$(ADMC) train --stage finetune --set model.base=oidn $(CFGARG) $(ARGS)
	$(ADMC) eval $(CFGARG) $(ARGS)

render: setup               ## render the scene corpus to EXR (cached, resumable)
	$(ADMC) render $(CFGARG) $(ARGS)

dataset: setup              ## render + tile the corpus into the Zarr patch store, then summarise it
	$(ADMC) dataset $(CFGARG) $(ARGS)

train: setup                ## pretrain on the corpus (STAGE=finetune to start from the shipped weights)
	$(ADMC) train --stage $(or $(STAGE),pretrain) $(CFGARG) $(ARGS)

eval: setup                 ## Table 1, error vs time and the HTML page for the test split
	$(ADMC) eval $(CFGARG) $(ARGS)

ood: setup                  ## Table 1 on the out-of-family set (family 'ood', held out of training; docs/corpus.md)
	$(ADMC) eval --set eval.split=ood --set eval.out_dir=eval-ood $(CFGARG) $(ARGS)

test: setup                 ## the test suite (real renders, tiny sizes), in one pytest process
	$(PY) -m pytest -q --durations=15 $(ARGS)

bench: setup                ## print measured speed and size figures (each script: --help)
	@for b in benchmarks/bench_*.py; do echo "== $$b"; $(PY) $$b || exit 1; done

clean:                      ## remove the default workdir (cache, renders)
	rm -rf .admc
