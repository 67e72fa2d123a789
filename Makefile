# admc: every target sets up the machine first (idempotent, seconds when already done).
PY      := .venv/bin/python
ADMC    := .venv/bin/admc-pipe
CONFIG  ?=
ARGS    ?=
CFGARG  := $(if $(CONFIG),--config $(CONFIG),)

.PHONY: setup demo render dataset train eval ood test bench clean

setup:
	@bash scripts/setup.sh

# make demo: the shipped admc fine-tuned on a domain pretraining never saw (a house under sun and sky,
# scripts/make_domain_scenes.py), then scored on that domain's test frames beside OIDN and the shipped weights;
# its references are shorter than the recipe's (the exterior's sunlight converges: they cost render time here)
DEMO_DIR := .admc-demo
DEMO     := --config configs/domain.toml --set run.workdir=$(DEMO_DIR) --set 'corpus.xml_dirs=["$(DEMO_DIR)/scenes"]' \
            --set 'render.resolution=[160, 160]' --set train.minutes=4 --set train.oidn_minutes=0 \
            --set eval.reference_spp=512 --set render.val_reference_spp=0
demo: setup                 ## fine-tune the shipped admc on a new domain (4 minutes), Table 1 on its test frames
	$(PY) scripts/make_domain_scenes.py $(DEMO_DIR)/scenes --domain exterior --frames 20 --seed 1
	$(ADMC) train --stage finetune $(DEMO) $(ARGS)
	$(ADMC) eval $(DEMO) $(ARGS) --weights admc-shipped=weights/admc-small-pretrained.pt \
	    --weights admc-finetuned=$(DEMO_DIR)/train/finetune/weights-fp16.pt \
	    --weights admc+oidn-shipped=weights/admc-small-refiner.pt

render: setup               ## render the scene corpus to EXR (cached, resumable)
	$(ADMC) render $(CFGARG) $(ARGS)

dataset: setup              ## render + tile the corpus into the Zarr patch store, then summarise it
	$(ADMC) dataset $(CFGARG) $(ARGS)

train: setup                ## pretrain on the corpus (STAGE=finetune to start from the shipped weights)
	$(ADMC) train --stage $(or $(STAGE),pretrain) $(CFGARG) $(ARGS)

eval: setup                 ## Table 1, error vs time and the HTML page for the default test set (25 scenes)
	$(ADMC) eval $(CFGARG) $(ARGS)

ood: setup                  ## Table 1 on the out-of-family set (family 'ood', held out of training; docs/corpus.md)
	$(ADMC) eval --set eval.split=ood --set eval.out_dir=eval-ood $(CFGARG) $(ARGS)

test: setup                 ## the test suite (real renders, tiny sizes), in one pytest process
	$(PY) -m pytest -q --durations=15 $(ARGS)

bench: setup                ## print measured speed and size figures (each script: --help)
	@for b in benchmarks/bench_*.py; do echo "== $$b"; $(PY) $$b || exit 1; done

clean:                      ## remove the default and demo workdirs (cache, renders)
	rm -rf .admc $(DEMO_DIR)
