# robocloud: `make up` runs the whole system locally, `make test` checks it.
SHELL := /bin/bash
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
# pytest-xdist workers for `make test`: one a core (`make test TEST_WORKERS=0` runs in process).
TEST_WORKERS ?= auto
NODE_STAMP := contracts/node_modules/.package-lock.json
REFERENCE_STAMP := tests/reference/node_modules/.package-lock.json

.PHONY: up test lint compose-up compose-down test-compose bench demo lock clean

$(STAMP): pyproject.toml constraints.txt
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet --constraint constraints.txt --editable ".[services,dev]"
	touch $(STAMP)

# solc-js (to check the committed contract artifacts) and anvil (a real Ethereum node for the
# SDK and external-node tests), pinned in contracts/package-lock.json.
$(NODE_STAMP): contracts/package-lock.json
	npm ci --prefix contracts --no-audit --no-fund

# js-ipfs-unixfs's importer: the independent implementation directory CIDs are compared with.
$(REFERENCE_STAMP): tests/reference/package-lock.json
	npm ci --prefix tests/reference --no-audit --no-fund

up: $(STAMP)
	$(PY) -m services.common.supervisor

lint: $(STAMP)
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .
	$(VENV)/bin/mypy

test: lint $(NODE_STAMP) $(REFERENCE_STAMP)
	$(VENV)/bin/pytest -n $(TEST_WORKERS) --dist loadfile

# Docker Compose on any machine, offline too: the engine, Compose, the wheelhouse and the base
# image when missing, then `docker compose up -d --wait --build` (scripts/docker/compose-up.sh).
# The venv builds the wheelhouse. ARGS go to `docker compose up` / `down` (`--volumes`).
compose-up: $(STAMP)
	bash scripts/docker/compose-up.sh $(ARGS)

compose-down:
	bash scripts/docker/compose-down.sh $(ARGS)

test-compose: $(STAMP)
	bash scripts/test-compose.sh

bench: $(STAMP)
	@for script in bench/*.py; do echo "== $$script"; $(PY) $$script || exit 1; done

lock:
	rm -rf .lock-venv && $(PYTHON) -m venv .lock-venv
	.lock-venv/bin/pip install --quiet --editable ".[services,dev]"
	.lock-venv/bin/pip freeze --exclude-editable | sort -f > constraints.txt
	rm -rf .lock-venv

clean:
	rm -rf $(VENV) data .pytest_cache .mypy_cache .ruff_cache
