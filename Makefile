# Every target that runs code sets up .venv itself; `make setup` is a no-op when it is up to date.
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: setup pipeline test bench lint ui clean ablations datasets compare adapt

setup: $(STAMP)

# tools/install.py installs with uv (pip's indexes and constraints passed on), else with pip.
$(STAMP): pyproject.toml tools/install.py
	test -x $(PY) || python3 -m venv $(VENV)
	$(PY) tools/install.py torch==2.13.0 -e '.[dev]'
	touch $(STAMP)

pipeline: setup
	$(PY) -m pipeline $(ARGS)

# Two test processes (pytest-xdist): CI has two cores, and many tests wait on a pipeline subprocess of one thread.
# TEST_WORKERS=0 runs the suite in one process.
TEST_WORKERS ?= 2
test: setup
	$(PY) -m pytest -n $(TEST_WORKERS) --dist loadgroup $(ARGS)

ablations: setup
	for t in table1 table2 table3; do $(PY) -m pipeline experiment=$$t $(ARGS) || exit 1; done

datasets: setup
	$(PY) -m pipeline experiment=datasets $(ARGS)

# How many images of a new camera to label (docs/adapt.md): experiment=adapt, 28 jobs two at a time. Its finetune
# recipe starts from the default run: BASE_RUN=<MLflow run id>, else the newest finished default run of profile
# BASE_PROFILE (make pipeline's) in the tracking store, or a clear error. Then `make compare` draws the curves.
BASE_PROFILE ?= quick
adapt: setup
	@base="$(BASE_RUN)"; \
	if [ -z "$$base" ]; then base=$$($(PY) -m stages.tables.adapt_base --profile $(BASE_PROFILE)) || exit 1; fi; \
	echo "adapt: finetune starts from run $$base"; \
	$(PY) -m pipeline experiment=adapt adapt.base_run=$$base $(ARGS)

compare: setup
	$(PY) -m stages.tables --results docs/results.md --readme README.md $(ARGS)

bench: setup
	$(PY) -m benchmarks $(ARGS)

lint: setup
	$(VENV)/bin/ruff check pipeline stages deepword tests benchmarks tools

ui: setup
	$(PY) -m pipeline.ui $(ARGS)

clean:
	rm -rf outputs multirun .deepword_cache mlflow.db mlflow.db.lock mlartifacts mlruns
