# roboshape: `make demo` runs the smallest end-to-end pipeline, `make test` the test suite.
# Both set up what is missing first (scripts/setup.sh) and are cheap the second time.
PY := .venv/bin/python
DEMO_WORKDIR ?= runs/demo

.PHONY: setup demo test bench clean-demo

# Python keeps each module's compiled bytecode (__pycache__, ignored by git) even where the environment asks it not
# to (PYTHONDONTWRITEBYTECODE): the suite starts dozens of Python processes (test workers, launch.py, simulator
# workers, a notebook kernel), each of which would otherwise compile JAX's, TensorFlow's and SAPIEN's sources again.
unexport PYTHONDONTWRITEBYTECODE
setup:
	@bash scripts/setup.sh

demo: setup
	$(PY) launch.py --config=configs/reproduce.py:tiny --workdir=$(DEMO_WORKDIR)

# Every core runs tests (-n auto). --dist loadscope: each module runs on one worker, so its fixtures are built once;
# the modules start in the order tests/conftest.py gives them (longest first; --no-loadscope-reorder keeps it). The
# 25 slowest tests are listed at the end.
test: setup
	JAX_PLATFORMS=cpu $(PY) -m pytest -q -n auto --dist loadscope --no-loadscope-reorder --durations=25 tests

clean-demo:
	rm -rf $(DEMO_WORKDIR)
