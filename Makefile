# shapefleet: `make demo` runs the fleet on its default scenario, `make test` runs the suite.
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed

.PHONY: install compile demo test bench clean docker-test

install: $(STAMP)

$(STAMP): pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[test]'
	touch $(STAMP)

# Byte-compile the project once per run: every robot process and CLI subprocess a test starts then
# skips compiling ~15k lines (0.3 s each), also where PYTHONDONTWRITEBYTECODE is set.
compile: install
	$(PY) -m compileall -q agents protocol launcher examples > /dev/null

demo: compile
	$(VENV)/bin/shapefleet launch

# Two pytest-xdist workers (2 cores), one test file at a time each: tests/conftest.py makes every
# file that starts robot or router processes one unit (one worker, one fleet at a time); each other
# file stays on one worker (its module fixtures computed once). `make test WORKERS=0`: serially.
WORKERS ?= 2
test: compile
	$(PY) -m pytest -q -n $(WORKERS) --dist loadscope

bench: install
	$(PY) benchmarks/rounds.py
	$(PY) benchmarks/zenoh_fleet.py
	$(PY) benchmarks/ct_delay.py
	$(PY) benchmarks/newton.py

# Not part of `make test`: as root, installs a Docker engine and debootstrap if missing, builds a
# base image and the project image, runs docker/compose.yaml's fleet (plain and mutual TLS) on
# loopback and checks it against `simulate`, then removes everything (docker/e2e.py; about 15 min).
docker-test: install
	$(PY) docker/e2e.py

clean:
	rm -rf $(VENV) runs .pytest_cache
