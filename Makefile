# The two commands of the README: `make demo` and `make test`. Each creates the
# virtualenv and installs what is missing on first use.
PYTHON ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
ARGS ?=
# pytest's worker processes in `make test` (pytest-xdist; 0: one process, which
# `-s` needs to show a test's output). The tests wait on real processes more
# than they compute, so two workers on CI's 2 cores halve the wall time. A test
# file's tests run on one worker, in order (a module's SITL tests share one SITL).
PYTEST_WORKERS ?= 2

.PHONY: demo test lint typecheck proto install clean image compose-test

$(STAMP): pyproject.toml
	@$(PYTHON) -c 'import sys; assert sys.version_info >= (3, 11), "baton needs Python 3.11+, found " + sys.version' 
	@test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[dev]'
	@touch $(STAMP)

install: $(STAMP)

# What `make demo` runs when no ARGS are given: the range-driven corridor (four
# stations along 1.5 km, radio range, the nearest policy, no handover script), its
# ring and first master chosen by mission admission over the stations (--admit).
# ARGS replace it: `make demo ARGS="--mission grid"` is the paper's grid with
# scripted handovers (`baton testbed`'s defaults).
DEMO_ARGS ?= --config examples/corridor.yaml --mission corridor --spacing 100 --admit

demo: $(STAMP)
	$(BIN)/baton testbed $(if $(ARGS),$(ARGS),$(DEMO_ARGS))

# deploy/install-chromium.sh: Debian's chromium for the HTML report's browser test
# (installed as root when missing; at once when it is there).
test: $(STAMP)
	deploy/install-chromium.sh
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .
	$(BIN)/mypy
	$(BIN)/python -m pytest -n $(PYTEST_WORKERS) --dist loadfile $(ARGS)

lint: $(STAMP)
	$(BIN)/ruff check . && $(BIN)/ruff format --check .

typecheck: $(STAMP)
	$(BIN)/mypy

# Regenerates the Python and mypy stubs beside the .proto files (tools/protogen.py,
# configured by pyproject.toml's [tool.baton.protogen]; not part of the package).
proto: $(STAMP)
	$(BIN)/python tools/protogen.py

# The compose testbed's images in the local Docker engine (deploy/images.sh):
# BATON_BASE=auto (default), public or local (a debootstrap base, no registry).
image: $(STAMP)
	PYTHON=$(BIN)/python deploy/images.sh

# The compose testbed for real (deploy/compose-test.sh): installs Docker and
# what it needs, builds the images, runs the grid mission, the range-driven
# corridor and a fleet (BATON_COMPOSE_RUNS), fails unless every run passes.
compose-test: $(STAMP)
	PYTHON=$(BIN)/python deploy/compose-test.sh

clean:
	rm -rf $(VENV) .pytest_cache .mypy_cache .ruff_cache
