# Quick start: `make demo` (main job on the bundled synthetic scene) and `make test`.
PY ?= python3
.PHONY: install demo test lint bench

install:
	bash scripts/install.sh

demo: install
	bash scripts/demo.sh

test: install
	$(PY) -m pytest -q

lint:
	snakefmt --check Snakefile workflow
	snakemake --lint --cores 1

bench: install
	$(PY) -m benchmarks
