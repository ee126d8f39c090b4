# heliocal: reproducible runs with real file targets (Make skips what is fresh).
# `make help` lists the targets.

PYTHON ?= python3
VENV ?= .venv
LOCK ?= requirements.lock
LOCK_VENV ?= .venv-lock
LATEST_VENV ?= /tmp/heliocal-latest-venv
UV_VERSION ?= 0.13.9
# Where pip finds the locked CPU build of torch: a folder holding the wheel (TORCH_WHEELS) when it
# has it, else PyTorch's own CPU wheel index (TORCH_INDEX); the lock's SHA-256 checks it either way.
TORCH_WHEELS ?= /opt/wheels
TORCH_INDEX ?= https://download.pytorch.org/whl/cpu
TORCH_PIN := $(shell sed -n 's/^torch==\([^ ]*\).*/\1/p' $(LOCK) 2>/dev/null)
TORCH_LOCAL = $(wildcard $(TORCH_WHEELS)/torch-$(TORCH_PIN)-*.whl)
TORCH_SOURCE = $(if $(TORCH_LOCAL),--find-links $(TORCH_WHEELS),--extra-index-url $(TORCH_INDEX))
HELIOCAL = $(VENV)/bin/heliocal
WORKDIR ?= runs/sample
SOURCES ?= sample_data/juelich/paint
SEED ?= 0
PRESET ?= auto
BASELINES ?= nn-only
STUDY ?= 10
TEST_WORKERS ?= 2
# the modules that hold tests marked `alone` (tests/test_suite_layout.py checks the list): the
# serial pass collects only these
ALONE_TESTS = tests/test_shutdown.py tests/test_workdir_lock.py

SOURCE_FILES := $(shell find $(SOURCES) -type f 2>/dev/null)
CODE := $(shell find pipeline cli -name '*.py' 2>/dev/null)

.DEFAULT_GOAL := help
.PHONY: help install check-lock lock lock-upgrade test-latest sample sweep report test test-fast regression clean

## help: list the targets
help:
	@grep -E '^## ' $(MAKEFILE_LIST) | sed 's/^## /  /'

## install: create $(VENV) with exactly the versions of $(LOCK) (pinned CPU torch included), then heliocal
install: $(VENV)/.installed

# The lock is the one source of installed versions: every package pinned with its SHA-256, resolved
# for this Python (3.11) on x86_64 Linux. pyproject.toml keeps the ranges for people who install
# heliocal into their own environment. The venv is made anew whenever the lock changes, so nothing
# from an earlier resolution survives, and `check-lock` proves it. The lock's own --find-links
# line (the folder it was resolved with) is left out: TORCH_SOURCE says where torch is here.
$(VENV)/.installed: $(LOCK) pyproject.toml
	$(if $(TORCH_LOCAL),,$(PYTHON) .ci/torch_index.py $(TORCH_INDEX) $(TORCH_PIN) $(TORCH_WHEELS))
	rm -rf $(VENV)
	$(PYTHON) -m venv $(VENV)
	grep -v '^--find-links' $(LOCK) > $(VENV)/requirements.lock
	$(VENV)/bin/pip install --quiet --require-hashes --no-deps $(TORCH_SOURCE) -r $(VENV)/requirements.lock
	$(VENV)/bin/pip install --quiet --no-deps --no-build-isolation -e .
	$(VENV)/bin/python .ci/check_lock.py $(LOCK)
	touch $@

## check-lock: verify that $(VENV) holds exactly the versions of $(LOCK)
check-lock: $(VENV)/.installed
	$(VENV)/bin/python .ci/check_lock.py $(LOCK)

## lock: resolve $(LOCK) from pyproject.toml, keeping today's pins where the ranges allow (needs PyPI)
## lock-upgrade: the same, moving every package to the newest version the ranges allow
lock-upgrade: UV_UPGRADE = --upgrade
lock lock-upgrade: $(LOCK_VENV)/bin/uv
	test ! -f $(LOCK) || cp $(LOCK) $(LOCK).tmp
	$(PYTHON) -c "import tomllib; print(*tomllib.load(open('pyproject.toml', 'rb'))['build-system']['requires'], sep='\n')" \
	  | $(LOCK_VENV)/bin/uv pip compile pyproject.toml - --extra test $(UV_UPGRADE) --generate-hashes \
	      --python-version 3.11 --python-platform x86_64-manylinux_2_28 \
	      --find-links $(TORCH_WHEELS) --emit-find-links --no-header --quiet -o $(LOCK).tmp
	{ echo "# heliocal's locked dependencies, written by 'make lock' (keeps pins) or 'make lock-upgrade'"; \
	  echo "# (newest the ranges of pyproject.toml allow) with uv $(UV_VERSION); build backend included;"; \
	  echo "# torch is the CPU wheel found in $(TORCH_WHEELS)."; \
	  cat $(LOCK).tmp; } > $(LOCK) && rm -f $(LOCK).tmp
	@echo "$(LOCK) written: review 'git diff $(LOCK)', run 'make test', commit it on its own." >&2

$(LOCK_VENV)/bin/uv:
	$(PYTHON) -m venv $(LOCK_VENV)
	$(LOCK_VENV)/bin/pip install --quiet uv==$(UV_VERSION)

## test-latest: drift check, the tests in a throwaway venv with the newest versions the ranges allow
test-latest:
	rm -rf $(LATEST_VENV)
	$(PYTHON) -m venv $(LATEST_VENV)
	$(LATEST_VENV)/bin/pip install --quiet torch==2.13.0
	$(LATEST_VENV)/bin/pip install --quiet --upgrade --upgrade-strategy eager -e ".[test]"
	@echo "test-latest: versions that differ from $(LOCK):" >&2
	-$(LATEST_VENV)/bin/python .ci/check_lock.py $(LOCK) --report
	$(LATEST_VENV)/bin/python -m pytest -q -p no:cacheprovider; status=$$?; \
	  echo "test-latest: pytest exit $$status with the versions above" >&2; \
	  rm -rf $(LATEST_VENV); exit $$status

## sample: run the whole pipeline on sample_data into WORKDIR (default runs/sample; ~2 min)
sample: $(WORKDIR)/report/index.html

## report: HTML report, figures and metrics.json of the run ($(WORKDIR)/report/)
report: $(WORKDIR)/report/index.html

## test: install and run the test suite (all tests, as CI does): in TEST_WORKERS processes (default
##       2), then the tests marked alone (time windows) by themselves; about 6 minutes on 2 cores
# A module (or a class) goes to one worker, those with slow tests first (tests/conftest.py); each
# pass runs even if the other fails, and the target fails if either did.
test: $(VENV)/.installed
	$(VENV)/bin/python -m pytest -q -n $(TEST_WORKERS) --dist loadscope --no-loadscope-reorder \
	  -m "not alone"; parallel=$$?; \
	$(VENV)/bin/python -m pytest -q -m alone $(ALONE_TESTS); alone=$$?; \
	test $$parallel = 0 && test $$alone = 0

## test-fast: the developer's loop: every test not marked slow (unit tests; under a minute), in
##            the same two processes as make test
test-fast: $(VENV)/.installed
	$(VENV)/bin/python -m pytest -q -n $(TEST_WORKERS) -m "not slow"

## regression: run the sample pipeline and compare its metrics.json with the committed baseline
regression: $(WORKDIR)/report/index.html
	$(VENV)/bin/python -m heliocal.pipeline.report.regression $(WORKDIR)/report/metrics.json tests/baseline/metrics_sample.json

$(WORKDIR)/measurements.parquet $(WORKDIR)/heliostats.parquet $(WORKDIR)/rejected.parquet &: $(SOURCE_FILES) $(CODE) $(VENV)/.installed
	$(HELIOCAL) ingest $(SOURCES) --workdir $(WORKDIR) --quiet

$(WORKDIR)/split.parquet: $(WORKDIR)/measurements.parquet
	$(HELIOCAL) split-knn --workdir $(WORKDIR) --seed $(SEED) --quiet

$(WORKDIR)/coarse_params.parquet $(WORKDIR)/coarse_predictions.parquet &: $(WORKDIR)/split.parquet $(WORKDIR)/heliostats.parquet
	$(HELIOCAL) fit-coarse --workdir $(WORKDIR) --preset $(PRESET) --quiet

## sweep: every heliostat's model, and the training-size study of STUDY heliostats (default 10;
##        BASELINES=nn-only,pretrained-nn adds the paper-002 baseline to the study, none drops it)
sweep: $(WORKDIR)/selection.parquet

$(WORKDIR)/sweep.parquet $(WORKDIR)/selection.parquet $(WORKDIR)/selected_predictions.parquet &: $(WORKDIR)/coarse_params.parquet
	$(HELIOCAL) sweep --workdir $(WORKDIR) --seeds $(SEED) --study $(STUDY) --baselines $(BASELINES) --quiet

$(WORKDIR)/report/index.html $(WORKDIR)/report/report.md $(WORKDIR)/report/metrics.json &: $(WORKDIR)/coarse_predictions.parquet $(WORKDIR)/selection.parquet $(wildcard $(WORKDIR)/hybrid_predictions.parquet)
	$(HELIOCAL) report --workdir $(WORKDIR) --quiet

## clean: remove run outputs (not the virtual environment)
clean:
	rm -rf runs
