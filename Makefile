# Quick start: `make demo` (main job on the bundled synthetic scene) and `make test`.
# Everything runs in this clone's own virtual environment, $(VENV) (created by `make install`,
# scripts/install.sh); the targets put $(VENV)/bin first on PATH, so `python` and `snakemake`
# inside them are this clone's.
VENV ?= .venv
PY := $(VENV)/bin/python
export VENV
export PATH := $(abspath $(VENV))/bin:$(PATH)
export VIRTUAL_ENV := $(abspath $(VENV))
.PHONY: install demo test lint bench cluster-test

install:
	bash scripts/install.sh

demo: install
	bash scripts/demo.sh

# The suite on every core (pytest-xdist; tests/conftest.py: each worker's share of the cores,
# the units of work and their order); `$(PY) -m pytest -q` runs it serially, the same tests.
test: install
	$(PY) -m pytest -q -n auto --dist loadfile

lint: install
	snakefmt --check Snakefile workflow
	snakemake --lint --cores 1

bench: install
	$(PY) -m benchmarks

# The .test config through a real one-node SLURM (root on Debian; installs slurm-wlm, munge,
# slurmdbd, mariadb-server with apt). Exit 3 of the script is a skip (not root, no apt).
cluster-test: install
	PYTHON=$(abspath $(PY)) bash scripts/slurm_test.sh || [ $$? -eq 3 ]
