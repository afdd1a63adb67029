# skidkin_ros: every target creates the virtual environment and installs what it needs.
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed-stamp
PYTEST_ARGS ?=
# Pinned versions of every dependency for a reproducible install (CI, make test, make demo).
# `make CONSTRAINTS= test` installs today's releases instead; `make constraints` refreshes the file.
CONSTRAINTS ?= constraints.txt
PIP_C := $(if $(CONSTRAINTS),PIP_CONSTRAINT=$(abspath $(CONSTRAINTS)),)

.PHONY: demo test test-fast bench bench-smoke bench-online lint docs clean constraints

$(STAMP): setup.py setup.cfg package.xml $(CONSTRAINTS)
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PIP_C) $(PY) -m pip install --quiet -e '.[ros,dev]'
	touch $(STAMP)

# Refresh constraints.txt from today's releases, in a scratch environment; then run `make test`
# and commit the file if it passes.
constraints:
	rm -rf .venv-constraints
	$(PYTHON) -m venv .venv-constraints
	.venv-constraints/bin/python -m pip install --quiet --upgrade pip
	.venv-constraints/bin/python -m pip install --quiet -e '.[ros,dev]'
	.venv-constraints/bin/python -m pip freeze --all --exclude-editable \
	  | grep -v -e '^skidkin' -e '^pip==' > constraints.txt.tmp
	mv constraints.txt.tmp constraints.txt
	rm -rf .venv-constraints

demo: $(STAMP)
	$(VENV)/bin/skidkin demo --out demo_out --force

test: $(STAMP)
	$(PY) -m pytest -q -ra $(PYTEST_ARGS)

test-fast: $(STAMP)
	$(PY) -m pytest -q -ra -m 'not heavy' $(PYTEST_ARGS)

# `make bench DIAG_OLD=4a5fc0e` also times the diagnosis of an older commit (or checkout folder).
bench: $(STAMP)
	$(PY) lab/bench/run.py --out lab/bench/results $(if $(DIAG_OLD),--diag-old $(DIAG_OLD))

bench-smoke: $(STAMP)
	$(PY) lab/bench/run.py --smoke --out lab/bench/results-smoke

# Online calibration's cost per 1 kHz wheel sample, online on/off (process CPU, one run); with
# `ONLINE_OLD=CHECKOUT` the augmented learners of that checkout run beside, in a child process.
bench-online: $(STAMP)
	$(PY) -m lab.bench.online_bench --seconds 60 --repeats 3
	$(PY) -m lab.bench.online_bench --augmented --seconds 60 --repeats 3 \
	  $(if $(ONLINE_OLD),--old $(ONLINE_OLD))
	$(PY) -m lab.bench.online_bench --augmented --residual --seconds 60 --repeats 3 \
	  $(if $(ONLINE_OLD),--old $(ONLINE_OLD))

lint: $(STAMP)
	$(PY) -m pytest -q test/test_lint.py

# Paste the tables generated from the specs (skidkin models, skidkin models --node) into docs/.
docs: $(STAMP)
	$(PY) -m lab.docs

clean:
	rm -rf build install log demo_out .pytest_cache
