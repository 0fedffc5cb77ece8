# Entry points; every target sets up .venv first (idempotent, fast when already done).
VENV := .venv/bin
export DVC_NO_ANALYTICS := 1
# DVC runs each stage's `python -m ...` through the shell: the venv's python must come first.
export PATH := $(CURDIR)/.venv/bin:$(PATH)

.PHONY: setup pipeline exp-show data results test test-fast lint typecheck format bench clean

setup:
	bash scripts/setup.sh

## The main job: the DVC pipeline on the embedded defaults (no server needed).
pipeline: setup
	$(VENV)/dvc repro

## The DVC experiments and what they changed, without the file-dep hash columns (one full
## MD5 each: docs/pipeline.md, "DVC views").
exp-show:
	$(VENV)/dvc exp show --only-changed --drop '^(conf|data|models|reports|src)/[^:]*$$|^(Created|epochs|n_parameters|train/loss|val/loss|closed_loop/diverged|closed_loop/log10_mse_mean|bar_checked|diverged|RMSE_ratio)$$'

## Only the data stage.
data: setup
	$(VENV)/dvc repro generate

## The results page, docs/results.md, and the ablation's figures (docs/figures/), regenerated
## from the committed reports (written atomically; tests/test_results_page.py checks them).
results: setup
	$(VENV)/python -m generalist_control.reports.results_page

## Lint, type check and the whole test suite (what CI runs), on PYTEST_WORKERS processes
## (pytest-xdist; whole test files per worker, so a file's fixtures are built once; the
## longest files first, tests/conftest.py's order: xdist's own reorders by test count). One
## process took 14.5-16 min on 2 cores; CI has 2. PYTEST_WORKERS=0 runs in this process.
## mypy runs beside the tests, its report after theirs; either failing fails the target.
## The suite keeps both cores 97-98 % busy (a fresh clone, idle), so this saves little, and
## more pytest workers than cores would not help (docs/development.md).
PYTEST_WORKERS ?= 2
test: setup
	$(VENV)/ruff check src analysis tests benchmarks scripts train.py tune.py adapt.py
	@typing=$$(mktemp); trap 'rm -f "$$typing"' EXIT; \
	$(VENV)/mypy >"$$typing" 2>&1 & mypy=$$!; trap 'kill $$mypy 2>/dev/null; exit 130' INT TERM; \
	$(VENV)/python -m pytest -q -n $(PYTEST_WORKERS) --dist loadfile --no-loadscope-reorder --durations=25; \
	tests=$$?; wait $$mypy; typed=$$?; echo "mypy:"; cat "$$typing"; \
	[ $$tests -ne 0 ] && exit $$tests; exit $$typed

## The fast tests only (no whole-stage runs: those are marked slow), a minute or two.
test-fast: setup
	$(VENV)/python -m pytest -q -m "not slow" -n $(PYTEST_WORKERS) --dist loadfile --no-loadscope-reorder

lint: setup
	$(VENV)/ruff check src analysis tests benchmarks scripts train.py tune.py adapt.py
	$(VENV)/ruff format --check src analysis tests benchmarks scripts train.py tune.py adapt.py
	$(VENV)/mypy

## The type checker alone (mypy on src/, settings in pyproject.toml).
typecheck: setup
	$(VENV)/mypy

format: setup
	$(VENV)/ruff format src analysis tests benchmarks scripts train.py tune.py adapt.py
	$(VENV)/ruff check --fix src analysis tests benchmarks scripts train.py tune.py adapt.py

bench: setup
	$(VENV)/python benchmarks/bench_generate.py

clean:
	rm -rf outputs multirun .pytest_cache .ruff_cache
