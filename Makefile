PYTHON ?= python3
.PHONY: install demo test test-fast bench

install:
	PYTHON=$(PYTHON) bash scripts/install.sh

demo: install
	slamreloc demo --workdir slamreloc-demo

test: install
	$(PYTHON) -m pytest -q -n 2 --dist loadfile --durations=25

bench: install
	$(PYTHON) benchmarks/run_benchmark.py ../shared/data/7scenes_redkitchen --out BENCHMARKS-latest.md
