# Oblique City: the two commands of the README are `make demo` and `make test`.
PYTHON ?= python3
DEMO ?= demo

.PHONY: setup demo test lint extension clean

setup:
	@bash tools/setup.sh

demo: setup
	$(PYTHON) -m oblique_city demo $(DEMO)
	$(PYTHON) tools/make_blend.py $(DEMO)/workspace $(DEMO)/city.blend

test: setup
	$(PYTHON) -m ruff check .
	$(PYTHON) -m pytest -q -p no:dash -n 2 --dist loadgroup tests

lint: setup
	$(PYTHON) -m ruff check .

extension: setup
	$(PYTHON) tools/build_extension.py

clean:
	rm -rf build dist demo .pytest_cache .setup-stamp

bench-at:
	$(PYTHON) benchmarks/bench_at.py $(ARGS)

bench-buildings:
	$(PYTHON) benchmarks/bench_buildings.py $(ARGS)

bench-surface:
	$(PYTHON) benchmarks/bench_surface.py $(ARGS)
