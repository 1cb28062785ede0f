# The front door. `make table` and `make test` are all a fresh clone needs; each sets up .venv itself.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed-stamp
THOR   ?= ../shared/thor_data

.PHONY: table baselines figures screenshot test lint kitchens tasks encoder bench docs clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --disable-pip-version-check -e '.[dev]'
	touch $(STAMP)

## table: the main job. Regenerates the paper's Table I from tables/table1.toml: for each row and
## seed (a job), train (unless a finished run with the same config exists; an unfinished one resumes),
## take the checkpoint with the best validation SR, evaluate it on the fixed episodes, then write
## tables/table1.{md,csv,tex} with intervals and the ablation check, and print the table. PRESET=quick
## (default: the paper's nine rows, 3 seeds), quick-all (and our extra rows), paper (the paper's
## budget), smoke (seconds). WORKERS jobs run at once (default: one per core; the table is the same
## for any number). Killed and re-run, it continues.
## The vector code paths of MKL (products) and ATen (the rest) pinned to AVX2, the development
## machine's: the floats of a run depend on them, and an AVX-512 CPU would otherwise take others
## (NUMERICS= to let each library pick the fastest; see docs/reproducibility.md).
PRESET ?= quick
WORKERS ?= $(shell nproc 2>/dev/null || echo 1)
NUMERICS ?= MKL_CBWR=AVX2 ATEN_CPU_CAPABILITY=avx2
table: $(STAMP)
	$(BIN)/kgnavbench prepare
	$(NUMERICS) $(BIN)/kgnavbench table --preset $(PRESET) --workers $(WORKERS)

## baselines: the methods that need no training, under Table I's rule and SAVN's (EPISODES per target)
EPISODES ?= 20
baselines: $(STAMP)
	$(BIN)/kgnavbench eval --method oracle --episodes $(EPISODES)
	$(BIN)/kgnavbench eval --method random_walk --episodes $(EPISODES)
	$(BIN)/kgnavbench eval --method random_walk --success-rule visible --episodes $(EPISODES)

## test: lint (rules and formatting) and the test suite, one pytest-xdist worker per core (TEST_WORKERS=;
## 0 for one process). A test file runs whole on one worker, in its order: a module's fixtures are
## built once, and tests/test_ray.py's one cluster ends with the test that kills its head. Files are
## handed out longest first (tests/conftest.py's LONGEST_FIRST), as collected.
TEST_WORKERS ?= auto
test: $(STAMP)
	$(BIN)/ruff check kgnavbench baselines benchmarks tests docs examples
	$(BIN)/ruff format --check kgnavbench baselines benchmarks tests docs examples
	$(BIN)/pytest -n $(TEST_WORKERS) --dist loadfile --no-loadscope-reorder

lint: $(STAMP)
	$(BIN)/ruff check kgnavbench baselines benchmarks tests docs examples
	$(BIN)/ruff format --check kgnavbench baselines benchmarks tests docs examples

## kitchens: recompile kgnavbench/data from ../shared/thor_data (the files are committed)
kitchens: $(STAMP)
	$(BIN)/python -m kgnavbench.kitchens $(THOR)

## tasks: rebuild kgnavbench/data/tasks.json.gz (splits, targets, fixed episodes; committed)
tasks: $(STAMP)
	$(BIN)/python -m kgnavbench.tasks

## figures: the paper's figures from the table's runs into docs/figures (runs what is missing first)
figures: $(STAMP)
	$(BIN)/kgnavbench figures --preset $(PRESET)

## screenshot: the rerun viewer on a recording, headless (rerun's own --screenshot-to, no display),
## into docs/figures/rerun_viewer.png; RRD=FILE.rrd (default: two oracle episodes, recorded if missing)
RRD ?= runs/oracle_episodes.rrd
screenshot: $(STAMP)
	test -f $(RRD) || $(BIN)/kgnavbench eval --method oracle --kitchens FloorPlan1 --episodes 1 --record $(RRD)
	$(BIN)/python docs/screenshot.py $(RRD) docs/figures/rerun_viewer.png

## encoder: retrain the committed view encoder kgnavbench/data/encoder.pt (deterministic, ~3 min)
encoder: $(STAMP)
	$(BIN)/kgnavbench encoder pretrain

## bench: speed figures with units
bench: $(STAMP)
	$(BIN)/python benchmarks/render_speed.py
	$(BIN)/python benchmarks/env_speed.py
	$(BIN)/python benchmarks/state_graphs.py
	$(BIN)/python benchmarks/models_speed.py
	$(BIN)/python benchmarks/train_speed.py

## docs: the contact sheet of views
docs: $(STAMP)
	$(BIN)/python docs/contact_sheet.py

clean:
	rm -rf $(VENV) runs *.egg-info
