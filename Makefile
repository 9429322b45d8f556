# The two commands of the README. Each prepares .venv itself (deploy/bootstrap.sh).
SHELL := /bin/bash
VENV := .venv/bin

.PHONY: demo test test-fast lint venv schemas firmware clean

venv:
	@bash deploy/bootstrap.sh all,dev

demo: venv
	$(VENV)/mrslam demo $(ARGS)

# on several processes, a test file per process at a time (its module's missions run once);
# PYTEST_WORKERS=0 runs them one by one
PYTEST_WORKERS ?= 3
XDIST = $(if $(filter 0,$(PYTEST_WORKERS)),,-n $(PYTEST_WORKERS) --dist loadfile)

test: venv lint
	$(VENV)/python -m pytest -q $(XDIST) -m "not realtime"
	$(VENV)/python -m pytest -q -m realtime

# the quick tier: no other processes (e2e), no closed-loop missions or whole recordings (slow)
test-fast: venv lint
	$(VENV)/python -m pytest -q $(XDIST) -m "not e2e and not slow"

lint: venv
	$(VENV)/ruff check .
	$(VENV)/mypy

schemas: venv
	$(VENV)/python -m schemas.export

# the motor base's firmware (deploy/firmware/README.md); venv installs its toolchain (as root)
firmware: venv
	$(MAKE) -C deploy/firmware all harness

clean:
	rm -rf .venv .mypy_cache .pytest_cache .ruff_cache runs
