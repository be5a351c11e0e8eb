# Two commands for a new user: `make demo` (mock collection session) and `make test`.
# Both create .venv on first use and install the project; later runs reuse it.
SHELL := /bin/bash
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
DEMO_ARGS ?=
# Test processes (pytest-xdist): each test file runs in one of them, so its fixtures are built once.
TEST_WORKERS ?= auto
PYTEST := $(BIN)/pytest -n $(TEST_WORKERS) --dist loadfile

.PHONY: demo test test-quick kernels lint bench system-deps clean docker-build docker-check

demo: $(STAMP) kernels
	$(BIN)/trackdeform demo $(DEMO_ARGS)

test: $(STAMP) kernels
	$(BIN)/ruff check .
	$(BIN)/lint-imports
	$(PYTEST)

test-quick: $(STAMP) kernels
	$(BIN)/ruff check .
	$(BIN)/lint-imports
	$(PYTEST) -m "not slow"

# Compile the numba kernels once (~15-30 s on a new machine, cached beside the code in tracking/__pycache__)
# before the demo's worker or the test processes would each compile them; later runs load them in ~0.3 s.
# The project's bytecode too: with PYTHONDONTWRITEBYTECODE set, every command would compile its modules again.
kernels: $(STAMP)
	@$(BIN)/python -m compileall -q orchestrator drivers tracking trajectories tdcommon tdrecord
	@$(BIN)/python -m tracking.kernels

lint: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/lint-imports

bench: $(STAMP)
	for b in benchmarks/*.py; do echo "== $$b"; $(BIN)/python $$b || exit 1; done

# Containers (README "Deployment"): the images, then a 30 s router + daemon + worker run on the mock config.
# docker-check prints "skipped: <reason>" and succeeds where docker cannot run (not root, no apt).
docker-build:
	bash docker/build.sh

docker-check:
	bash docker/check.sh

# open3d and pyrealsense2 need libusb-1.0 to import.
system-deps:
	@if ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0'; then :; \
	elif [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null; then \
	  echo "installing the system library libusb-1.0-0 (open3d needs it)"; \
	  apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libusb-1.0-0 >/dev/null; \
	else \
	  echo "error: the system library libusb-1.0 is missing (open3d needs it to import)." >&2; \
	  echo "       install it, e.g.: sudo apt-get install libusb-1.0-0   then run make again" >&2; \
	  exit 1; \
	fi

$(STAMP): pyproject.toml | system-deps
	@$(PYTHON) -c 'import sys; sys.exit(sys.version_info < (3, 10))' || \
	  { echo "error: Python >= 3.10 is needed ($(PYTHON) is $$($(PYTHON) --version))" >&2; exit 1; }
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q -e '.[dev,franka,ur,realsense,oak,cluster]'
	touch $(STAMP)

clean:
	rm -rf $(VENV) .pytest_cache .ruff_cache *.egg-info
