# hybridqcm — the two commands a newcomer needs:
#   make demo   install, simulate a small dataset, train the networks, run the hybrid estimator, print the tables
#   make test   install and run the test suite
PYTHON ?= python3
VENV   ?= .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed

.PHONY: install demo noise test lint test-slow reproduce reproduce-plan results bench tensorboard clean-outputs help

help:
	@echo "make demo       - end-to-end hybrid pipeline on a small dataset (about 15-20 min on 2 CPU cores)"
	@echo "make test       - install and run the default test suite"
	@echo "make lint       - ruff check and ruff format --check over src, tests, bench"
	@echo "make test-slow  - also the long end-to-end checks (pytest -m slow)"
	@echo "make reproduce  - the full reference protocol, all experiments (hours; see 'make reproduce-plan')"
	@echo "make noise      - after make demo: occupant mass with and without the road at sensor noise 0-10 % (~30 min)"
	@echo "make results    - regenerate docs/RESULTS.md from the run folders"
	@echo "make bench      - benchmarks (simulation, road, Gauss-Newton)"

# torch is pinned through constraints.txt: an unpinned `torch` would pull a multi-GB CUDA build.
$(STAMP): pyproject.toml constraints.txt
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q -c constraints.txt torch==2.13.0
	$(BIN)/python -m pip install -q -c constraints.txt -e '.[dev,search]'
	touch $(STAMP)

install: $(STAMP)

demo: install
	$(BIN)/qcm-pipeline demo

# the suite's files spread over TEST_WORKERS processes (pytest-xdist), each file whole on one of them, so that
# a module's fixtures are built once; TEST_WORKERS=0 runs it in this process
TEST_WORKERS ?= 2

test: install
	$(BIN)/python -m pytest -q -n $(TEST_WORKERS) --dist loadfile

lint: install
	$(BIN)/ruff check src tests bench
	$(BIN)/ruff format --check src tests bench

test-slow: install
	$(BIN)/python -m pytest -q -m slow

noise: install
	$(BIN)/qcm-pipeline noise

reproduce-plan: install
	$(BIN)/qcm-pipeline reproduce --plan

reproduce: install
	$(BIN)/qcm-pipeline reproduce

results: install
	$(BIN)/qcm-results

bench: install
	$(BIN)/python bench/bench_simulate.py --quick
	$(BIN)/python bench/bench_gauss_newton.py

tensorboard: install
	$(BIN)/tensorboard --logdir outputs

clean-outputs:
	rm -rf outputs/demo outputs/reproduce outputs/noise
