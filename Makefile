# nerfpipe: `make demo` (install + the whole chain on the built-in scene), `make test`,
# `make PHOTOS=~/captures/mug OUT=runs/mug` (your photos), `make POSED=path/to/dataset OUT=runs/x` (posed data).
SHELL := bash
.SHELLFLAGS := -eu -o pipefail -c
.DELETE_ON_ERROR:
MAKEFLAGS += --warn-undefined-variables --no-builtin-rules
.SUFFIXES:
.DEFAULT_GOAL := all

PYTHON ?= python3
VENV := .venv
INSTALLED := $(VENV)/.installed
NERFPIPE := $(VENV)/bin/nerfpipe

# ------------------------------------------------------------------------------------------- install
# torch first, pinned: on our machines torch==2.13.0 is a local CPU wheel (any other spec downloads GBs).
$(INSTALLED): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(VENV)/bin/pip install --quiet torch==2.13.0
	$(VENV)/bin/pip install --quiet -e '.[dev]'
	touch $@

.PHONY: install
install: $(INSTALLED)

# ------------------------------------------------------------------------------------------- checks
.PHONY: test lint format browser js
test: $(INSTALLED) browser js
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .
	$(VENV)/bin/pytest

# Debian's chromium for the viewer's browser test (tests/test_view.py skips, saying why, where it is missing).
# Installed from the distribution's packages only, never a browser build downloaded at run time.
browser:
	@if command -v chromium >/dev/null; then :; \
	elif [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null; then \
	  apt-get install -y -q chromium >/dev/null || { apt-get update -q >/dev/null && apt-get install -y -q chromium >/dev/null; } \
	  || echo "make browser: apt-get could not install chromium; the browser test will skip"; \
	else echo "make browser: needs root and apt-get to install chromium; the browser test will skip"; fi

# The third-party clients the export tests open our files in (tests/test_export_clients.py): the Khronos glTF
# validator, three.js and gsplat.js, pinned in tests/js/package-lock.json and installed from the npm registry by
# `npm ci` (tests only: the product downloads nothing); node and npm from Debian's packages where they are missing
# (as `browser` does for chromium). Without them, or without the registry, the tests skip, saying why.
JS_MODULES := tests/js/node_modules/.package-lock.json
js: $(JS_MODULES)
$(JS_MODULES): tests/js/package.json tests/js/package-lock.json
	@if ! command -v npm >/dev/null && [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null; then \
	  apt-get install -y -q nodejs npm >/dev/null || { apt-get update -q >/dev/null && apt-get install -y -q nodejs npm >/dev/null; } \
	  || echo "make js: apt-get could not install nodejs and npm"; fi
	@if command -v npm >/dev/null; then \
	  (cd tests/js && npm ci --no-audit --no-fund --loglevel=error) \
	  || echo "make js: npm ci failed; the export client tests will skip"; \
	else echo "make js: no npm; the export client tests will skip"; fi

lint: $(INSTALLED)
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .

format: $(INSTALLED)
	$(VENV)/bin/ruff format .
	$(VENV)/bin/ruff check --fix .

# ------------------------------------------------------------------------------------------- pipelines
# Inputs: exactly one of PHOTOS (folder of photos or a video file) or POSED (an already-posed dataset).
PHOTOS ?=
POSED ?=
OUT ?= runs/default
include pipelines/common.mk
include pipelines/photos.mk
include pipelines/posed.mk
include pipelines/demo.mk
include pipelines/bench.mk
include pipelines/study.mk
include pipelines/xray.mk
include pipelines/pretrain.mk

.PHONY: all
all: $(INSTALLED)
ifneq ($(PHOTOS),)
all: $(PIPELINE_OUTPUTS)
	$(SUSPECTS)
else ifneq ($(POSED),)
all: $(PIPELINE_OUTPUTS)
	$(SUSPECTS)
else ifneq ($(XRAY),)
all: $(XRAY_OUTPUTS)
else
all:
	@echo "nothing to do: give PHOTOS=dir|video.mp4, POSED=dataset or XRAY=volume (and OUT=runs/name), or run 'make demo'"
endif

.PHONY: clean-runs
clean-runs:
	rm -rf runs
