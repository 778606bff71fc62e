# twindelta — a few targets. `make demo` and `make test` install what they need.
SHELL := /bin/bash
.DEFAULT_GOAL := help
PYTHON ?= python3
UV_VERSION := 0.13.9
VENV := .venv
UV := .tools/bin/uv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
# Shared libraries Open3D links, and the Debian packages that provide them.
SYSTEM_LIBS := libusb-1.0.so.0 libGL.so.1 libEGL.so.1 libX11.so.6 libgomp.so.1
SYSTEM_PACKAGES := libusb-1.0-0 libgl1 libegl1 libx11-6 libgomp1
HOST ?= 127.0.0.1
PORT ?= 8000
export HOST PORT
# The operator console (console/, an npm project built by vite into console/dist, served at /ui/).
# It is rebuilt when dist is missing or older than a source, the manifest or the lock file.
CONSOLE_SOURCES := $(shell find console/src -type f 2>/dev/null) $(wildcard console/index.html console/package.json console/vite.config.ts console/tsconfig.json console/public/*)
CONSOLE_BUILT := console/dist/index.html
CONSOLE_DEPS := console/node_modules/.installed
NODE_MIN := 20.19

.PHONY: help install system-packages node-tools console test-tools demo serve test bench lint format openapi option-schema option-docs clean

help:
	@echo "make demo    - run the whole service on a generated before/after scene and print the changes"
	@echo "               (KEEP=1: keep it running at the end and open the console it prints)"
	@echo "make console - build the operator console (console/ -> console/dist, served at /ui/)"
	@echo "make test    - the test suite (needs PostgreSQL and Redis on 127.0.0.1, see README)"
	@echo "make serve   - the embedded service (API + workers, no external servers) on HOST:PORT"
	@echo "make bench   - benchmarks; JSON results under bench/results/"
	@echo "make lint    - ruff, mypy, import-linter, function size and complexity, generated files fresh"
	@echo "make openapi - regenerate openapi/openapi.json"
	@echo "make option-schema - regenerate app/core/option_schema.json from the workers' options"
	@echo "make option-docs - regenerate docs/options.md from the workers' option classes"

$(UV):
	@$(PYTHON) -c 'import sys; sys.exit(sys.version_info < (3, 11))' || { echo "twindelta needs Python >= 3.11 as $(PYTHON)"; exit 1; }
	$(PYTHON) -m venv .tools
	.tools/bin/pip install --quiet uv==$(UV_VERSION)

$(STAMP): pyproject.toml uv.lock | $(UV)
	$(UV) sync --frozen --python $(PYTHON)
	@touch $@

install: system-packages $(STAMP)

# Installs the missing shared libraries with apt when run as root; otherwise says what to run.
system-packages:
	@missing=""; for lib in $(SYSTEM_LIBS); do ldconfig -p | grep -q "$$lib" || missing="$$missing $$lib"; done; \
	if [ -n "$$missing" ]; then \
	  if [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null; then \
	    echo "installing system packages for:$$missing"; \
	    DEBIAN_FRONTEND=noninteractive apt-get update -qq && \
	    DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends $(SYSTEM_PACKAGES) >/dev/null; \
	  else \
	    echo "Missing shared libraries:$$missing"; \
	    echo "Install them first:  sudo apt-get install $(SYSTEM_PACKAGES)"; exit 1; \
	  fi; \
	fi

# Node.js >= $(NODE_MIN) and npm (vite's minimum) for the console's build; installed with apt
# when run as root, otherwise says what to install. Not needed at run time (no CDN either).
node-tools:
	@ok() { command -v npm >/dev/null && node -e 'const [a, b] = process.versions.node.split(".").map(Number); const [x, y] = "$(NODE_MIN)".split(".").map(Number); process.exit(a > x || (a === x && b >= y) ? 0 : 1)' 2>/dev/null; }; \
	ok || { \
	  if [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null; then \
	    echo "installing nodejs and npm (to build the console)"; \
	    DEBIAN_FRONTEND=noninteractive apt-get update -qq && \
	    DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends nodejs npm >/dev/null; \
	  fi; \
	  ok || { echo "The console's build needs Node.js >= $(NODE_MIN) with npm (found: $$(node --version 2>/dev/null || echo none))."; \
	    echo "Install them first, e.g. sudo apt-get install nodejs npm (Debian 13), or Node.js 22 from nodejs.org / NodeSource."; exit 1; }; }

$(CONSOLE_DEPS): console/package.json console/package-lock.json | node-tools
	cd console && npm ci --no-audit --no-fund --loglevel=error
	@touch $@

$(CONSOLE_BUILT): $(CONSOLE_DEPS) $(CONSOLE_SOURCES)
	cd console && npm run build
	@touch $@

console: $(CONSOLE_BUILT)

demo: install console
	$(PY) -m workers.demo $(if $(KEEP),--keep --port $(PORT))

serve: install console
	$(VENV)/bin/twindelta serve --host $(HOST) --port $(PORT)

# The suite also validates docker-compose.yml with Debian's docker-compose (no engine needed).
test-tools:
	@command -v docker-compose >/dev/null || { \
	  if [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null; then \
	    echo "installing docker-compose (to validate docker-compose.yml)"; \
	    DEBIAN_FRONTEND=noninteractive apt-get update -qq && \
	    DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends docker-compose >/dev/null; \
	  else echo "Install docker-compose first: sudo apt-get install docker-compose"; exit 1; fi; }
	@command -v npm >/dev/null || { \
	  if [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null; then \
	    echo "installing nodejs and npm (the Khronos glTF validator the export tests run)"; \
	    DEBIAN_FRONTEND=noninteractive apt-get update -qq && \
	    DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends nodejs npm >/dev/null; \
	  else echo "Install nodejs and npm first: sudo apt-get install nodejs npm"; exit 1; fi; }
	@[ -d tools/gltf-validator/node_modules ] || { \
	  echo "installing the glTF validator (tools/gltf-validator, from its package-lock.json)"; \
	  cd tools/gltf-validator && npm ci --no-audit --no-fund --loglevel=error; }
	@{ command -v chromium >/dev/null && command -v chromedriver >/dev/null; } || { \
	  if [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null; then \
	    echo "installing chromium and chromium-driver (the console's browser tests)"; \
	    DEBIAN_FRONTEND=noninteractive apt-get update -qq && \
	    DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends chromium chromium-driver >/dev/null; \
	  else echo "Install Chromium first: sudo apt-get install chromium chromium-driver"; exit 1; fi; }

test: install test-tools console
	$(VENV)/bin/pytest -q $(PYTEST_ARGS)

bench: install
	$(PY) -m bench.run $(BENCH_ARGS)

lint: install
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .
	$(VENV)/bin/mypy app workers/pipeline
	$(VENV)/bin/mypy workers --exclude workers/pipeline
	$(VENV)/bin/lint-imports
	$(VENV)/bin/twindelta openapi | diff -q - openapi/openapi.json >/dev/null || { echo "openapi/openapi.json is stale: run make openapi"; exit 1; }
	$(VENV)/bin/python -m workers.pipeline option-schema | diff -q - app/core/option_schema.json >/dev/null || { echo "app/core/option_schema.json is stale: run make option-schema"; exit 1; }
	$(VENV)/bin/python -m app.formats.cameras | diff -q - openapi/cameras.schema.json >/dev/null || { echo "openapi/cameras.schema.json is stale: run $(VENV)/bin/python -m app.formats.cameras > openapi/cameras.schema.json"; exit 1; }
	$(VENV)/bin/python -m app.core.eventschema | diff -q - openapi/events.schema.json >/dev/null || { echo "openapi/events.schema.json is stale: run $(VENV)/bin/python -m app.core.eventschema > openapi/events.schema.json"; exit 1; }
	$(VENV)/bin/python -m workers.pipeline option-docs | diff -q - docs/options.md >/dev/null || { echo "docs/options.md is stale: run make option-docs"; exit 1; }
	$(VENV)/bin/python .ci/function_size.py app workers
	$(VENV)/bin/ruff check --select C901 app workers

format: install
	$(VENV)/bin/ruff check --fix .
	$(VENV)/bin/ruff format .

openapi: install
	$(VENV)/bin/twindelta openapi --out openapi/openapi.json

option-schema: install
	$(VENV)/bin/python -m workers.pipeline option-schema --out app/core/option_schema.json

option-docs: install
	$(VENV)/bin/python -m workers.pipeline option-docs --out docs/options.md

clean:
	rm -rf .tools $(VENV) twindelta-data demo-output console/dist console/node_modules
