# `make test`  : install everything (system libs, .venv, project) and run the test suite (CPU, ~10 min).
# `make demo`  : install if needed, then run the full SLAM pipeline on a built-in synthetic sequence.
VENV ?= .venv
PY := $(VENV)/bin/python
PYTEST_ARGS ?=

.PHONY: install test test-fast demo bench clean

$(VENV)/.installed: pyproject.toml scripts/install.sh
	VENV=$(VENV) bash scripts/install.sh
	touch $@

install: $(VENV)/.installed

test: install
	$(PY) -m pytest $(PYTEST_ARGS)

test-fast: install
	$(PY) -m pytest -m "not slow" $(PYTEST_ARGS)

demo: install
	$(VENV)/bin/lrslam run --demo --out runs/demo

bench: install
	$(PY) benchmarks/field_speed.py

clean:
	rm -rf $(VENV) runs .pytest_cache
