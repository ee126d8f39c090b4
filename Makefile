# heliocal: reproducible runs with real file targets (Make skips what is fresh).
# `make help` lists the targets.

PYTHON ?= python3
VENV ?= .venv
HELIOCAL = $(VENV)/bin/heliocal
WORKDIR ?= runs/sample
SOURCES ?= sample_data/juelich/paint
SEED ?= 0
PRESET ?= auto

SOURCE_FILES := $(shell find $(SOURCES) -type f 2>/dev/null)
CODE := $(shell find pipeline cli -name '*.py' 2>/dev/null)

.DEFAULT_GOAL := help
.PHONY: help install sample test clean

## help: list the targets
help:
	@grep -E '^## ' $(MAKEFILE_LIST) | sed 's/^## /  /'

## install: create $(VENV) and install heliocal (pinned CPU torch first)
install: $(VENV)/.installed

$(VENV)/.installed: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(VENV)/bin/pip install --quiet --upgrade pip
	$(VENV)/bin/pip install --quiet torch==2.13.0
	$(VENV)/bin/pip install --quiet -e ".[test]"
	touch $@

## sample: run the whole pipeline on sample_data (WORKDIR=runs/sample)
sample: $(WORKDIR)/measurements.parquet $(WORKDIR)/split.parquet

## test: install and run the test suite
test: $(VENV)/.installed
	$(VENV)/bin/python -m pytest -q

$(WORKDIR)/measurements.parquet $(WORKDIR)/heliostats.parquet $(WORKDIR)/rejected.parquet &: $(SOURCE_FILES) $(CODE) $(VENV)/.installed
	$(HELIOCAL) ingest $(SOURCES) --workdir $(WORKDIR)

$(WORKDIR)/split.parquet: $(WORKDIR)/measurements.parquet
	$(HELIOCAL) split-knn --workdir $(WORKDIR) --seed $(SEED)

## clean: remove run outputs (not the virtual environment)
clean:
	rm -rf runs
