# The front door. `make table` and `make test` are all a fresh clone needs; each sets up .venv itself.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed-stamp
THOR   ?= ../shared/thor_data

.PHONY: table test lint kitchens bench docs clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --disable-pip-version-check -e '.[dev]'
	touch $(STAMP)

## table: the main job. For now: the kitchens and a walk; Table I arrives with the env/training issues.
table: $(STAMP)
	$(BIN)/kgnavbench kitchens
	$(BIN)/kgnavbench walk --kitchen FloorPlan1 --actions random:20 --out runs/walk-FloorPlan1
	@echo
	@echo "Table I is not there yet: it needs the tasks and env stage (issue 3) and the trained plugins."
	@echo "What exists today: 30 compiled kitchens, the pymunk world, the 2.5D renderer and the CLI above."

## test: lint and the test suite
test: $(STAMP)
	$(BIN)/ruff check kgnavbench baselines benchmarks tests docs
	$(BIN)/pytest

lint: $(STAMP)
	$(BIN)/ruff check kgnavbench baselines benchmarks tests docs
	$(BIN)/ruff format --check kgnavbench baselines benchmarks tests docs

## kitchens: recompile kgnavbench/data from ../shared/thor_data (the files are committed)
kitchens: $(STAMP)
	$(BIN)/python -m kgnavbench.kitchens $(THOR)

## bench: speed figures with units
bench: $(STAMP)
	$(BIN)/python benchmarks/render_speed.py

## docs: the contact sheet of views
docs: $(STAMP)
	$(BIN)/python docs/contact_sheet.py

clean:
	rm -rf $(VENV) runs *.egg-info
