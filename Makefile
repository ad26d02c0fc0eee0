# The two commands of the README. Each installs what it needs into .venv first.
PYTHON ?= python3
VENV   ?= .venv
PY      = $(VENV)/bin/python
STAMP   = $(VENV)/.installed

.PHONY: demo test bench install clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[test]'
	touch $(STAMP)

install: $(STAMP)

## Run the demo end to end: simulate -> m-modes -> normal equations -> solve -> maps (runs/demo/maps)
demo: $(STAMP)
	$(VENV)/bin/mmflow run workflows/demo.yaml

## Run the test suite
test: $(STAMP)
	$(PY) -m pytest -q

## Benchmarks (JSON figures on stdout)
bench: $(STAMP)
	$(VENV)/bin/mmflow bench transfer
	$(VENV)/bin/mmflow bench solve

clean:
	rm -rf $(VENV) runs .pytest_cache
