# prtbench — the two commands of the README's quick start:
#   make bench   install what is needed, run the smoke benchmark, print where the report is
#   make test    install what is needed, run the test suite
PYTHON ?= python3
OUT ?= out/smoke

.PHONY: setup bench test nightly clean
setup:
	bash scripts/setup.sh

bench: setup
	$(PYTHON) run_bench.py run --suite smoke --out $(OUT)

nightly: setup
	$(PYTHON) run_bench.py run --suite nightly --out out/nightly-$$(date +%Y%m%d)

test: setup
	$(PYTHON) -m pytest -n 2 -q --durations=25

clean:
	rm -rf out .cache
