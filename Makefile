# The two commands of the README. Each prepares .venv itself (deploy/bootstrap.sh).
SHELL := /bin/bash
VENV := .venv/bin

.PHONY: demo test test-fast lint venv schemas firmware clean

venv:
	@bash deploy/bootstrap.sh all,dev

demo: venv
	$(VENV)/mrslam demo $(ARGS)

test: venv lint
	$(VENV)/python -m pytest -q

# everything but the tests that start other processes (pytest -m e2e runs those)
test-fast: venv lint
	$(VENV)/python -m pytest -q -m "not e2e"

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
