# roboshape: `make demo` runs the smallest end-to-end pipeline, `make test` the test suite.
# Both set up what is missing first (scripts/setup.sh) and are cheap the second time.
PY := .venv/bin/python
DEMO_WORKDIR ?= runs/demo

.PHONY: setup demo test bench clean-demo
setup:
	@bash scripts/setup.sh

demo: setup
	$(PY) launch.py --config=configs/reproduce.py:tiny --workdir=$(DEMO_WORKDIR)

# Every core runs tests (-n auto, tests handed out one by one as workers free up); the 25 slowest are listed at the end.
test: setup
	JAX_PLATFORMS=cpu $(PY) -m pytest -q -n auto --durations=25 tests

clean-demo:
	rm -rf $(DEMO_WORKDIR)
