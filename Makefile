# The two commands of the README. Each prepares .venv itself (deploy/bootstrap.sh).
SHELL := /bin/bash
VENV := .venv/bin

.PHONY: demo test lint venv schemas clean

venv:
	@bash deploy/bootstrap.sh all,dev

demo: venv
	$(VENV)/mrslam demo $(ARGS)

test: venv lint
	$(VENV)/python -m pytest -q

lint: venv
	$(VENV)/ruff check .
	$(VENV)/mypy

schemas: venv
	$(VENV)/python -m schemas.export

clean:
	rm -rf .venv .mypy_cache .pytest_cache .ruff_cache runs
