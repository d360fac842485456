# dran-edge — a newcomer needs two targets:  make demo   and   make test
# Both create/refresh .venv and install everything themselves (system packages via
# apt-get, the draft-enabled ZeroMQ build, the Python dependencies).

PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
# One BLAS thread: the solver's small dense blocks get slower, not faster, with more
# (measured 50-100x slower sparse Cholesky on an oversubscribed 2-core box).
export OPENBLAS_NUM_THREADS ?= 1
export OMP_NUM_THREADS ?= 1
STAMP  := $(VENV)/.dran-edge-installed
# Extras that install everywhere the project claims to support (x86-64 and aarch64 Linux,
# CPython >= 3.10). The camera drivers (DRIVERS: extras realsense, oak) are tried one by one by
# tools/install_drivers.py after them: one without a wheel for this Python/architecture is
# reported (with what to do instead) and never aborts the install; its tests skip.
EXTRAS ?= perception,comms,systemd,eval,viz,test
DRIVERS ?= realsense
DEMO_DIR ?= demo-run
# pytest-xdist worker processes for make test / test-all ("auto": one per core; 0: in this process).
# --dist loadfile keeps each test file on one worker: module- and session-scoped fixtures (the
# simulated and replayed runs, the benchmark scripts tests/test_bench_quick.py starts together)
# are built once per file instead of once per worker. --no-loadscope-reorder hands the files out
# in collection order, which tests/conftest.py makes longest first (LONGEST_FILES).
PYTEST_WORKERS ?= auto
PYTEST_PARALLEL := -n $(PYTEST_WORKERS) --dist loadfile --no-loadscope-reorder

.PHONY: help setup test suite lint types test-all demo bench bundle clean

help:
	@echo "make demo      simulate a 6-robot mission, replay it through the robot code, score it"
	@echo "make test      run the test suite (hardware tests skip without a device)"
	@echo "make test-all  also run tests marked slow"
	@echo "make bench     run the benchmarks that need no dataset (all: docs/benchmarks.md)"
	@echo "make setup     only install (.venv, system packages, draft ZeroMQ)"
	@echo "make bundle    offline installer for an aarch64 robot (dist/; docs/bundle.md)"
	@echo "make clean     remove .venv and build outputs"

setup: $(STAMP)

$(STAMP): pyproject.toml tools/setup_system.sh tools/build_zmq_draft.sh tools/deb_src_entries.py tools/install_drivers.py tools/patches/*.patch
	bash tools/setup_system.sh
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --disable-pip-version-check -U pip setuptools wheel
	bash tools/build_zmq_draft.sh $(VENV)
	$(PY) -m pip install -q --disable-pip-version-check -e '.[$(EXTRAS)]'
	$(PY) tools/install_drivers.py '-e .' $(DRIVERS)
	touch $@

# lint first; then mypy (one process, ~25 s from an empty cache) beside the suite, at the lowest
# CPU priority: it takes the cycles the suite's workers leave while they wait on sockets and
# child processes, and does not slow them. The suite prints its progress as it runs; mypy's
# report ("Success: ..." or its errors) appears among it when mypy is done. Either failing fails
# the target. `make types` / `make suite` run one of them.
test: setup lint
	@$(MAKE) --no-print-directory -j 2 TYPES_NICE="nice -n 19" types suite

suite: setup
	$(PY) -m pytest -q $(PYTEST_PARALLEL) -m "not slow and not hardware"

# ruff (pyproject [tool.ruff]): pyflakes-level checks and the formatting; the layer contracts
# are tests/test_layering.py (part of the test run)
lint: setup
	$(VENV)/bin/ruff check dran_edge comms perception tests tools
	$(VENV)/bin/ruff format --check dran_edge comms perception tests tools

# mypy (pyproject [tool.mypy]): the package at mypy's default level, solver/ and dran/ strict
types: setup
	$(TYPES_NICE) $(PY) -m mypy

test-all: setup
	$(PY) -m pytest -q $(PYTEST_PARALLEL) -m "not hardware"

demo: setup
	$(VENV)/bin/dran-edge demo --out $(DEMO_DIR)

# Benchmarks that need no dataset; those over the g2o graphs take a data directory
# (default ../shared/data/g2o) and are listed with their commands in docs/benchmarks.md.
bench: setup
	$(PY) tools/bench/bench_comms.py
	$(PY) tools/bench/bench_schur.py
	$(PY) tools/bench/bench_perception.py

# Offline installer for an aarch64 robot (root: builds the C parts in an arm64 root under
# qemu; BUNDLE_PY=3.11 by default, docs/bundle.md). Not part of setup/test.
bundle:
	PYTHON="$$(test -x $(PY) && echo $(PY) || command -v $(PYTHON))" bash tools/bundle/build_bundle.sh

clean:
	rm -rf $(VENV) build dist *.egg-info .pytest_cache .hypothesis $(DEMO_DIR)
