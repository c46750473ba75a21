# Two commands for a new user: `make run` and `make test`. Both create .venv and install the
# project first; as root they also install the Debian libraries the stack needs when missing.
PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed-stamp
KERNELS := $(VENV)/.kernels-stamp
HOST ?= 127.0.0.1
PORT ?= 8080
DEBIAN_PACKAGES := libusb-1.0-0 chromium

.PHONY: run test lint bench bytecode kernels system-deps clean

$(STAMP): pyproject.toml
	@$(MAKE) --no-print-directory system-deps
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[test,bench]'
	touch $(STAMP)

system-deps:
	@missing=""; \
	ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0' || missing="$$missing libusb-1.0-0"; \
	[ -x /usr/bin/chromium ] || missing="$$missing chromium"; \
	if [ -z "$$missing" ]; then exit 0; fi; \
	if [ "$$(id -u)" = 0 ]; then \
		echo "installing Debian packages:$$missing"; \
		apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq $$missing; \
	else \
		echo "warning: missing Debian packages:$$missing (run as root or: sudo apt-get install$$missing)"; \
	fi

# The project's own bytecode, written ahead: with PYTHONDONTWRITEBYTECODE set (as in many
# containers) every start would otherwise recompile the engine's modules (~0.1 s per command).
bytecode: $(STAMP)
	@$(BIN)/python -m compileall -q slam6d app benchmarks > /dev/null

# numba compiles the engine's kernels on their first use and caches them beside the sources: ~25 s
# that would otherwise land on a user's first `slam6d run` (18 s instead of 3 s on the benchmark
# loop) or render. A small simulated session is registered and rendered once, again after the
# engine's sources change.
kernels: $(KERNELS)

$(KERNELS): $(STAMP) $(wildcard slam6d/*.py slam6d/io/*.py)
	@echo "compiling the engine's kernels (once, ~30 s)"
	@tmp=$$(mktemp -d) && trap 'rm -rf "$$tmp"' EXIT && ( \
	$(BIN)/slam6d simulate "$$tmp/session" --seed 0 --scans 12 --points-per-scan 15000 && \
	$(BIN)/slam6d run "$$tmp/session" --format uos --out "$$tmp/out" && \
	$(BIN)/slam6d render "$$tmp/session" --format uos --poses "$$tmp/out/poses_kitti.txt" \
		--frames 2 --size 64x48 --out "$$tmp/frames" \
	) > "$$tmp/log" 2>&1 || { cat "$$tmp/log"; exit 1; }
	@touch $@

run: $(STAMP) bytecode kernels
	$(BIN)/slam6d-workbench --host $(HOST) --port $(PORT) --sessions-dir sessions

test: $(STAMP) bytecode kernels
	$(BIN)/ruff check .
	$(BIN)/mypy
	$(BIN)/python -m pytest

lint: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .
	$(BIN)/mypy

bench: $(STAMP) bytecode kernels
	$(BIN)/python benchmarks/pair.py

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache .mypy_cache test-artifacts
