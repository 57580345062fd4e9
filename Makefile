# shapefleet: `make demo` runs the fleet on its default scenario, `make test` runs the suite.
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed

.PHONY: install demo test bench clean

install: $(STAMP)

$(STAMP): pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[test]'
	touch $(STAMP)

demo: install
	$(VENV)/bin/shapefleet launch

test: install
	$(PY) -m pytest -q

bench: install
	$(PY) benchmarks/rounds.py
	$(PY) benchmarks/zenoh_fleet.py
	$(PY) benchmarks/ct_delay.py
	$(PY) benchmarks/newton.py

clean:
	rm -rf $(VENV) runs .pytest_cache
