# endo3d workspace. A newcomer needs two commands: `make demo` and `make test`.
# Both create .venv when it is missing and install only what is missing.
SHELL := /bin/bash
.DEFAULT_GOAL := demo

PYTHON ?= python3
VENV := .venv
VBIN := $(VENV)/bin
STAMP := $(VENV)/.endo3d-installed
KERNELS := $(VENV)/.endo3d-kernels
PACKAGES := $(sort $(patsubst %/setup.py,%,$(wildcard src/*/setup.py)))

# DDS stays on this machine: Fast DDS's default discovery multicasts on every
# interface, and only loopback may carry traffic here. Every target below
# inherits these; each target also gets a DDS domain of its own, so a demo and
# a test run on the same machine never see each other's topics.
export ROS_AUTOMATIC_DISCOVERY_RANGE := LOCALHOST
export RMW_IMPLEMENTATION := rmw_fastrtps_cpp
export PYTHONDONTWRITEBYTECODE := 1
DEMO_DOMAIN_ID ?= 41
TEST_DOMAIN_ID ?= 42
BENCH_DOMAIN_ID ?= 43
DOCTOR_DOMAIN_ID ?= 44
FUZZ_DOMAIN_ID ?= 45
TEST_WORKERS ?= 2
# Examples per fuzz property in `make fuzz` (`make test` runs each with 30).
FUZZ_EXAMPLES ?= 2000

.PHONY: venv demo test fuzz lint bench doctor constraints clean

$(VBIN)/python:
	$(PYTHON) -m venv $(VENV)

# Re-runs only when the pins or a package's setup files change; a second
# `make` finds the stamp up to date and does no network work at all.
$(STAMP): $(VBIN)/python requirements.txt constraints.txt $(wildcard src/*/setup.py src/*/setup.cfg)
	$(VBIN)/python -m pip install --disable-pip-version-check -q -c constraints.txt pip
	$(VBIN)/python -m pip install --disable-pip-version-check -q -c constraints.txt -r requirements.txt
	@# PEP 660 editable installs put console scripts in .venv/bin; setup.cfg's
	@# script_dir (for `ros2 run` under colcon) applies only to colcon builds.
	$(VBIN)/python -m pip install --disable-pip-version-check -q --no-deps --no-build-isolation \
	  --use-pep517 $(addprefix -e ,$(PACKAGES))
	@touch $@
	@echo "endo3d: environment ready in $(VENV)"

# The SFS solver's numba kernels, compiled once into the kernel cache
# (~/.cache/endo3d/numba, or NUMBA_CACHE_DIR; see endo_io.kernel_cache) after
# installing and again when their sources change: about 20 s of CPU the first
# time, a second to check after that. Nodes then start without compiling.
$(KERNELS): $(STAMP) $(wildcard src/endo_sfs/endo_sfs/*.py)
	$(VBIN)/python -m endo_sfs.warm_up
	@touch $@

venv: $(STAMP) $(KERNELS)

demo: export ROS_DOMAIN_ID := $(DEMO_DOMAIN_ID)
demo: $(STAMP) $(KERNELS)
	$(VBIN)/endo-demo --output-dir out

# Two workers (pytest-xdist; TEST_WORKERS=0 runs in this process): about half
# of the suite waits on DDS discovery and real-time replays, so two at a time
# nearly halve the time on two cores. A file's tests stay on one worker (its
# module fixtures are built once), each worker has a DDS domain of its own
# (conftest.py). The 25 slowest tests are listed at the end, so that a CI log
# shows where the time goes.
test: export ROS_DOMAIN_ID := $(TEST_DOMAIN_ID)
test: $(STAMP) $(KERNELS)
	$(VBIN)/python -m pytest -n $(TEST_WORKERS) --dist loadfile --durations=25

# The fuzz tests of untrusted input (bags, CDR messages) with a large budget.
fuzz: export ROS_DOMAIN_ID := $(FUZZ_DOMAIN_ID)
fuzz: export ENDO3D_FUZZ_EXAMPLES := $(FUZZ_EXAMPLES)
fuzz: $(STAMP)
	$(VBIN)/python -m pytest -m fuzz

# ruff over everything; mypy (settings: pyproject.toml [tool.mypy]) over each
# package's code, src/<package>/<package>.
lint: $(STAMP)
	$(VBIN)/ruff check src tests bench conftest.py
	$(VBIN)/mypy $(foreach p,$(PACKAGES),$(p)/$(notdir $(p)))

bench: export ROS_DOMAIN_ID := $(BENCH_DOMAIN_ID)
bench: $(STAMP) $(KERNELS)
	@for b in bench/bench_*.py; do echo "== $$b"; $(VBIN)/python $$b || exit 1; done

# Prints the DDS settings a node started by this Makefile actually gets.
doctor: export ROS_DOMAIN_ID := $(DOCTOR_DOMAIN_ID)
doctor: $(STAMP)
	@$(VBIN)/endo-doctor

# Re-pin every version after editing requirements.txt (needs the network).
constraints:
	rm -rf .venv-pin && $(PYTHON) -m venv .venv-pin
	.venv-pin/bin/python -m pip install -q -r requirements.txt
	( echo "# Every version pin of the endo3d virtual environment, in one place."; \
	  echo "# Regenerate after changing requirements.txt: make constraints"; \
	  .venv-pin/bin/python -m pip freeze --all | grep -E '^(ros-|[A-Za-z0-9._-]+==)' \
	  | grep -vE '^[a-z_]+_(msgs|interfaces)==|^(rclpy|rcutils|rmw_dds_common|rosidl_[a-z_]+)==' | sort -f ) > constraints.txt
	rm -rf .venv-pin

clean:
	rm -rf $(VENV) build install log .pytest_cache
