# The front door. `make table` and `make test` are all a fresh clone needs; each sets up .venv itself.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed-stamp
THOR   ?= ../shared/thor_data

.PHONY: table test lint kitchens tasks bench docs clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --disable-pip-version-check -e '.[dev]'
	touch $(STAMP)

## table: the main job. Builds the state graphs and views of the 30 kitchens (cached after the first
## run), then evaluates the methods that need no training on the fixed episodes under Table I's
## protocol (Stop at the destination; Stop ends the episode): the oracle and the random walk, and the
## random walk under SAVN's "target visible" rule beside it. EPISODES=100 runs every fixed episode
## (the default, 20, is the first 20 per target). Table I's trained rows arrive with the training issue.
EPISODES ?= 20
table: $(STAMP)
	$(BIN)/kgnavbench prepare
	$(BIN)/kgnavbench eval --method oracle --episodes $(EPISODES)
	$(BIN)/kgnavbench eval --method random_walk --episodes $(EPISODES)
	$(BIN)/kgnavbench eval --method random_walk --success-rule visible --episodes $(EPISODES)

## test: lint (rules and formatting) and the test suite
test: $(STAMP)
	$(BIN)/ruff check kgnavbench baselines benchmarks tests docs
	$(BIN)/ruff format --check kgnavbench baselines benchmarks tests docs
	$(BIN)/pytest

lint: $(STAMP)
	$(BIN)/ruff check kgnavbench baselines benchmarks tests docs
	$(BIN)/ruff format --check kgnavbench baselines benchmarks tests docs

## kitchens: recompile kgnavbench/data from ../shared/thor_data (the files are committed)
kitchens: $(STAMP)
	$(BIN)/python -m kgnavbench.kitchens $(THOR)

## tasks: rebuild kgnavbench/data/tasks.json.gz (splits, targets, fixed episodes; committed)
tasks: $(STAMP)
	$(BIN)/python -m kgnavbench.tasks

## bench: speed figures with units
bench: $(STAMP)
	$(BIN)/python benchmarks/render_speed.py
	$(BIN)/python benchmarks/env_speed.py
	$(BIN)/python benchmarks/state_graphs.py

## docs: the contact sheet of views
docs: $(STAMP)
	$(BIN)/python docs/contact_sheet.py

clean:
	rm -rf $(VENV) runs *.egg-info
