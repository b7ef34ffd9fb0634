# tissuebench: the two commands of the README, and their helpers.
#   make report   install what is missing (the engines' venv too), then write the default report under reports/
#   make test     install what is missing (the engines' venv too), then lint and run the test suite
#   make check    lint and the suite without the slow tests or the engines' venv: a contributor's loop
# Both first compile the engine's kernels ahead (realtime.precompile) when they are not cached yet.
# Set-up is idempotent: it checks Debian packages and the venv, and reinstalls the project only when
# pyproject.toml changed.

SHELL := /bin/bash
VENV := .venv
PY := $(VENV)/bin/python
APT_PACKAGES := python3-dolfinx python3-gmsh python3-meshio python3-h5py python3-venv python3-scipy libgomp1 libopenblas0-pthread chromium
STAMP := $(VENV)/.tissuebench-installed
SUDO := $(shell [ "$$(id -u)" = 0 ] || echo sudo)
export OMPI_ALLOW_RUN_AS_ROOT := 1
export OMPI_ALLOW_RUN_AS_ROOT_CONFIRM := 1
export OMPI_MCA_rmaps_base_oversubscribe := 1

.PHONY: setup apt venv precompile engines genesis report test check lint bench bench-peers clean-cache

setup: apt $(STAMP) precompile

apt:
	@missing=""; for p in $(APT_PACKAGES); do \
	  dpkg-query -W -f='$${Status}' $$p 2>/dev/null | grep -q "install ok installed" || missing="$$missing $$p"; \
	done; \
	if [ -n "$$missing" ]; then \
	  echo "installing Debian packages:$$missing"; \
	  $(SUDO) apt-get update -q && DEBIAN_FRONTEND=noninteractive $(SUDO) apt-get install -y -q --no-install-recommends $$missing; \
	fi

# Every target that makes, installs into or runs a venv waits for the Debian packages (order-only: apt
# is phony), or under -j2 pip runs before Debian's numpy exists; tests/house/test_makefile_order.py reads make's
# own database to hold every target to it.
$(VENV)/bin/python: | apt
	/usr/bin/python3 -m venv --system-site-packages $(VENV)

# numpy is pinned to Debian's own version: dolfinx and scipy are compiled against it. No numpy, no
# constraint: the line fails rather than write "numpy==".
$(STAMP): pyproject.toml | apt $(VENV)/bin/python
	version=$$(/usr/bin/python3 -c 'import numpy; print(numpy.__version__)') && echo "numpy==$$version" > $(VENV)/constraints.txt
	$(PY) -m pip install -q -c $(VENV)/constraints.txt -e '.[dev]'
	$(PY) -c "import dolfinx, gmsh, meshio, numba, numpy; assert numpy.__version__.startswith('1.')"
	touch $(STAMP)

# The engine's numba kernels compiled into numba's cache on every core, once per version of the engine
# (about 50 s on 2 cores, instead of minutes on one core inside the first run or the test suite); the
# threaded kernels only a simulator or make bench builds compile when first built (realtime.precompile.jobs).
precompile: apt $(STAMP)
	$(PY) -m realtime.precompile

# The default report puts the engines users pick (newton and MuJoCo, through their adapters) beside the
# built-in models on every scene, the contact scene's force along the travel included (docs/engines.md).
report:
	$(MAKE) --no-print-directory -j2 setup engines
	$(VENV)/bin/tissuebench report --engine newton --engine mujoco

lint: setup
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .

# The engines users pick (NVIDIA newton with warp, MuJoCo, PyBullet, MuJoCo Warp), from PyPI at the versions adapters/requirements.txt
# pins, in a venv of their own: its numpy is PyPI's, the project's stays Debian's. The adapters in adapters/ run
# there (docs/engines.md); the project never imports them.
ENGINES_VENV := .venv-engines
ENGINES_STAMP := $(ENGINES_VENV)/.tissuebench-installed
engines: $(ENGINES_STAMP)
$(ENGINES_STAMP): adapters/requirements.txt | apt
	[ -x $(ENGINES_VENV)/bin/python ] || /usr/bin/python3 -m venv $(ENGINES_VENV)
	$(ENGINES_VENV)/bin/python -m pip install -q -r adapters/requirements.txt
	$(ENGINES_VENV)/bin/python -c "import mujoco, mujoco_warp, newton, pybullet, warp"
	touch $@

# Genesis and the PyTorch it needs, in a venv of their own and never part of `make test`: PyPI's Linux torch
# wheels bring the CUDA libraries (8.5 GB in all, loaded and unused on a CPU). This target builds it and runs
# the Genesis adapter's tests, which fail there, never skip, when it is missing (docs/engines.md).
# `import genesis` maps libGL and X11's client libraries (its viewer's, pyrender and PyOpenGL, even headless):
# GENESIS_APT_PACKAGES (tests/house/test_debian_packages.py checks the import against them).
GENESIS_VENV := .venv-genesis
GENESIS_STAMP := $(GENESIS_VENV)/.tissuebench-installed
GENESIS_APT_PACKAGES := libgl1 libopengl0 libglx0 libx11-6 libxext6 libxinerama1 libxrandr2 libxrender1 libxxf86vm1
genesis: setup $(GENESIS_STAMP)
	TISSUEBENCH_REQUIRE_GENESIS=1 $(PY) -m pytest -q -n $(TEST_WORKERS) --dist worksteal tests/verification/test_adapter_genesis.py
$(GENESIS_STAMP): adapters/requirements-genesis.txt | apt
	$(MAKE) --no-print-directory apt APT_PACKAGES="$(GENESIS_APT_PACKAGES)"
	[ -x $(GENESIS_VENV)/bin/python ] || /usr/bin/python3 -m venv $(GENESIS_VENV)
	$(GENESIS_VENV)/bin/python -m pip install -q -r adapters/requirements-genesis.txt
	$(GENESIS_VENV)/bin/python -c "import genesis, torch"
	touch $@

# One worker process per core this process may use (pytest-xdist; xdist's own "auto" counts physical
# cores where psutil is installed), each taking the next test as it ends one. TEST_WORKERS=1 for one.
# TISSUEBENCH_REQUIRE_ENGINES: the adapters' tests fail, never skip, when the engines' venv is missing.
# The two venvs are made side by side (-j2): the engines' download and install overlap the project's
# install and the engine's compilation ahead.
TEST_WORKERS ?= $(shell nproc)
test:
	$(MAKE) --no-print-directory -j2 setup engines
	$(MAKE) --no-print-directory lint
	TISSUEBENCH_REQUIRE_ENGINES=1 $(PY) -m pytest -q -n $(TEST_WORKERS) --dist worksteal

# The contributor's fast loop: lint and the suite without the slow tests and without the engines' venv
# (docs/contributing.md); make test stays the full one.
check: setup
	$(MAKE) --no-print-directory lint
	TISSUEBENCH_NO_ENGINES=1 $(PY) -m pytest -q -n $(TEST_WORKERS) --dist worksteal -m "not slow"

bench: setup
	$(VENV)/bin/tissuebench bench --out reports/bench.json --markdown docs/benchmarks.md

# Optional, never part of `make test`: the engines users pick (NVIDIA newton, pbatoolkit) timed beside ours
# in one run, in a venv of their own so that the project's never depends on them (numpy stays Debian's).
PEERS_VENV := .venv-peers
bench-peers: setup
	[ -x $(PEERS_VENV)/bin/python ] || /usr/bin/python3 -m venv --system-site-packages $(PEERS_VENV)
	$(PEERS_VENV)/bin/python -m pip install -q -c $(VENV)/constraints.txt -e . \
	  $$($(PY) -c 'from verification.bench.peers import PEERS; print(*(f"{k}=={v}" for k, v in PEERS.items()))')
	$(PEERS_VENV)/bin/python -m verification.bench.peers --out reports/bench-peers.json

clean-cache:
	rm -rf $${TISSUEBENCH_CACHE:-$$HOME/.cache/tissuebench}
