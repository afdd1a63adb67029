# skidkin_ros: every target creates the virtual environment and installs what it needs.
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed-stamp
PYTEST_ARGS ?=

.PHONY: demo test test-fast bench bench-smoke lint clean

$(STAMP): setup.py setup.cfg package.xml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[ros,dev]'
	touch $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/skidkin demo --out demo_out --force

test: $(STAMP)
	$(PY) -m pytest -q -ra $(PYTEST_ARGS)

test-fast: $(STAMP)
	$(PY) -m pytest -q -ra -m 'not heavy' $(PYTEST_ARGS)

bench: $(STAMP)
	$(PY) bench/run.py --out bench/results

bench-smoke: $(STAMP)
	$(PY) bench/run.py --smoke --out bench/results-smoke

lint: $(STAMP)
	$(PY) -m pytest -q test/test_lint.py

clean:
	rm -rf build install log demo_out .pytest_cache
