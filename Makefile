# Two commands set everything up on a fresh machine: `make demo` and `make test`.
PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed
OUT    ?= build/demo

.PHONY: install demo test lint bench clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e ".[dev]"
	touch $(STAMP)

install: $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/fdjax reproduce --quick --out $(OUT)

# Three processes on a 2-core machine (a process compiling leaves its core partly idle; three
# keep both busy: 1.97 cores used on average), a test file per process at a time: the
# files' tests share compiled programs.  `$(PY) -m pytest -q` runs the same tests in one.
# The 25 slowest tests are listed at the end.
test: $(STAMP)
	$(PY) -m pytest -q -n 3 --dist loadfile --durations=25

lint: $(STAMP)
	$(VENV)/bin/ruff check .

bench: $(STAMP)
	$(PY) benchmarks/frf_sweep.py

clean:
	rm -rf build .pytest_cache
