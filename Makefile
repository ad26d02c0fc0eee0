# The two commands of the README. Each installs what it needs into .venv first.
PYTHON ?= python3
VENV   ?= .venv
PY      = $(VENV)/bin/python
STAMP   = $(VENV)/.installed

.PHONY: demo test test-fast lint bench docs install clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[test]'
	touch $(STAMP)

install: $(STAMP)

## Run the demos: simulate -> m-modes -> normal equations -> solve -> maps (runs/demo/maps); then a
## corrupted scan through calibrate -> peel -> terrestrial (runs/demo-calibrate) and, for comparison,
## the same data imaged without them (runs/demo-calibrate-before)
demo: $(STAMP)
	$(VENV)/bin/mmflow run workflows/demo.yaml
	$(VENV)/bin/mmflow run workflows/demo-calibrate.yaml --no-progress
	$(VENV)/bin/mmflow run workflows/demo-calibrate.yaml calibrate.enabled=false peel.enabled=false \
	    terrestrial.enabled=false run.directory=runs/demo-calibrate-before --no-progress

## Lint: ruff (pyproject.toml's [tool.ruff]); make test runs it first
lint: $(STAMP)
	$(VENV)/bin/ruff check .

## Run the test suite: ruff first, then every tier (tests/unit, tests/workflow, tests/acceptance, tests/cluster:
## a real SLURM cluster in network namespaces, skipped saying why without root), four test files at a time
## (pytest-xdist; a file's tests share one process and its fixtures; four on two cores: the SLURM tier and the
## CLI subprocesses mostly wait, 12 min 34 s against 13 min 17 s with three, docs/performance.md; each on
## usable cores / 4 threads, tests/conftest.py;
## --no-loadscope-reorder keeps the longest files first, tests/conftest.py, where xdist would start the files
## with most tests first)
test: $(STAMP) lint
	$(PY) -m pytest -q -n 4 --dist loadfile --no-loadscope-reorder

## The unit tier only (kernels on in-memory arrays), two files at a time as make test
test-fast: $(STAMP)
	$(PY) -m pytest -q -n 2 --dist loadfile tests/unit

## Benchmarks (JSON figures on stdout)
bench: $(STAMP)
	$(VENV)/bin/mmflow bench transfer
	$(VENV)/bin/mmflow bench solve

## Regenerate docs/configuration.md from the schema and docs/stores.md from the declared stores
docs: $(STAMP)
	{ echo '# Configuration reference'; echo; \
	  echo 'Every workflow YAML is validated against one schema. This page is `mmflow config show` (regenerate with `make docs`; a test keeps it in sync). Override any key on the command line with `section.key=value` (YAML syntax for the value; `beam={type: pyuvdata, file: beam.fits}` replaces a whole section).'; \
	  echo; echo '```yaml'; $(VENV)/bin/mmflow config show; echo '```'; } > docs/configuration.md
	$(VENV)/bin/mmflow stores show > docs/stores.md

clean:
	rm -rf $(VENV) runs .pytest_cache
