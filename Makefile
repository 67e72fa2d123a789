# admc: every target sets up the machine first (idempotent, seconds when already done).
PY      := .venv/bin/python
ADMC    := .venv/bin/admc-pipe
CONFIG  ?=
ARGS    ?=
CFGARG  := $(if $(CONFIG),--config $(CONFIG),)

.PHONY: setup demo render dataset test bench clean

setup:
	@bash scripts/setup.sh

demo: dataset               ## the main job on the embedded default corpus (grows with each stage)

render: setup               ## render the scene corpus to EXR (cached, resumable)
	$(ADMC) render $(CFGARG) $(ARGS)


dataset: setup              ## render + tile the corpus into the Zarr patch store, then summarise it
	$(ADMC) dataset $(CFGARG) $(ARGS)

test: setup                 ## the test suite (real renders, tiny sizes)
	$(PY) -m pytest -q --durations=15 $(ARGS)

bench: setup                ## print measured speed and size figures (each script: --help)
	@for b in benchmarks/bench_*.py; do echo "== $$b"; $(PY) $$b || exit 1; done

clean:                      ## remove the default workdir (cache, renders)
	rm -rf .admc
