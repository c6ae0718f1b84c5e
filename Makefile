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

test: install
	$(PY) -m pytest -q

lint: install
	snakefmt --check Snakefile workflow
	snakemake --lint --cores 1

bench: install
	$(PY) -m benchmarks

# The .test config through a real one-node SLURM (root on Debian; installs slurm-wlm, munge,
# slurmdbd, mariadb-server with apt). Exit 3 of the script is a skip (not root, no apt).
cluster-test: install
	PYTHON=$(abspath $(PY)) bash scripts/slurm_test.sh || [ $$? -eq 3 ]
