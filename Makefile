# Two commands: `make demo` (set up, replay the default fixture) and `make test` (set up, run the tests).
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
FIXTURE ?= replay_fixtures/meeting_table
OUT ?= out/demo

.PHONY: setup demo test bench fixtures clean

$(STAMP): pyproject.toml tools/setup_system.sh
	bash tools/setup_system.sh
	test -x $(PY) || python3 -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -e '.[dev]'
	touch $(STAMP)

setup: $(STAMP)

demo: setup
	$(VENV)/bin/adhoc-array replay $(FIXTURE) --out $(OUT)

test: setup
	$(PY) -m pytest -q tests

fixtures: setup
	$(PY) replay_fixtures/build_fixtures.py --data ../shared/data

bench: setup
	$(PY) benchmarks/toa_table1.py
	$(PY) benchmarks/throughput.py
	$(PY) benchmarks/enhancement.py

clean:
	rm -rf $(VENV) out .pytest_cache
