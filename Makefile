# heliocal: reproducible runs with real file targets (Make skips what is fresh).
# `make help` lists the targets.

PYTHON ?= python3
VENV ?= .venv
HELIOCAL = $(VENV)/bin/heliocal
WORKDIR ?= runs/sample
SOURCES ?= sample_data/juelich/paint
SEED ?= 0
PRESET ?= auto
BASELINES ?= nn-only

SOURCE_FILES := $(shell find $(SOURCES) -type f 2>/dev/null)
CODE := $(shell find pipeline cli -name '*.py' 2>/dev/null)

.DEFAULT_GOAL := help
.PHONY: help install sample sweep report test regression clean

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

## sample: run the whole pipeline on sample_data into WORKDIR (default runs/sample; ~2 min)
sample: $(WORKDIR)/report/index.html

## report: HTML report, figures and metrics.json of the run ($(WORKDIR)/report/)
report: $(WORKDIR)/report/index.html

## test: install and run the test suite
test: $(VENV)/.installed
	$(VENV)/bin/python -m pytest -q

## regression: run the sample pipeline and compare its metrics.json with the committed baseline
regression: $(WORKDIR)/report/index.html
	$(VENV)/bin/python -m heliocal.pipeline.regression $(WORKDIR)/report/metrics.json tests/baseline/metrics_sample.json

$(WORKDIR)/measurements.parquet $(WORKDIR)/heliostats.parquet $(WORKDIR)/rejected.parquet &: $(SOURCE_FILES) $(CODE) $(VENV)/.installed
	$(HELIOCAL) ingest $(SOURCES) --workdir $(WORKDIR) --quiet

$(WORKDIR)/split.parquet: $(WORKDIR)/measurements.parquet
	$(HELIOCAL) split-knn --workdir $(WORKDIR) --seed $(SEED) --quiet

$(WORKDIR)/coarse_params.parquet $(WORKDIR)/coarse_predictions.parquet &: $(WORKDIR)/split.parquet $(WORKDIR)/heliostats.parquet
	$(HELIOCAL) fit-coarse --workdir $(WORKDIR) --preset $(PRESET) --quiet

## sweep: weight-decay sweep and training-size study (BASELINES=nn-only,pretrained-nn for both)
sweep: $(WORKDIR)/selection.parquet

$(WORKDIR)/sweep.parquet $(WORKDIR)/selection.parquet $(WORKDIR)/selected_predictions.parquet &: $(WORKDIR)/coarse_params.parquet
	$(HELIOCAL) sweep --workdir $(WORKDIR) --seeds $(SEED) --baselines $(BASELINES) --quiet

$(WORKDIR)/report/index.html $(WORKDIR)/report/report.md $(WORKDIR)/report/metrics.json &: $(WORKDIR)/coarse_predictions.parquet $(WORKDIR)/selection.parquet $(wildcard $(WORKDIR)/hybrid_predictions.parquet)
	$(HELIOCAL) report --workdir $(WORKDIR) --quiet

## clean: remove run outputs (not the virtual environment)
clean:
	rm -rf runs
