# Every target sets up (or reuses) the local virtual environment .venv and installs what it needs.
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed-stamp

.PHONY: demo test bench lint venv clean

venv: $(STAMP)

$(STAMP): pyproject.toml server/web/package-lock.json drivers/links/opcua_nodesets/package-lock.json \
		tests/peers/axe-core/package-lock.json tests/peers/node-opcua/package-lock.json
	@echo "mvpose: setting up $(VENV) (the first time takes a minute or two) ..."
	test -x $(BIN)/python || $(PY) -m venv $(VENV)
	@echo "mvpose: [1/3] pip"
	$(BIN)/python -m pip install --quiet --upgrade pip
	@echo "mvpose: [2/3] Python packages (numpy, OpenCV, FastAPI, pymodbus, camera SDKs, test peers)"
	$(BIN)/python -m pip install --quiet --progress-bar on -e ".[test,dev]"
	@echo "mvpose: [3/3] from npm, pinned: operator page assets (htmx, uPlot, Swagger UI), OPC UA NodeSets, axe-core and node-opcua (tests)"
	npm ci --prefix server/web --ignore-scripts --no-audit --no-fund --loglevel=error
	npm ci --prefix drivers/links/opcua_nodesets --ignore-scripts --no-audit --no-fund --loglevel=error
	npm ci --prefix tests/peers/axe-core --ignore-scripts --no-audit --no-fund --loglevel=error
	npm ci --prefix tests/peers/node-opcua --ignore-scripts --no-audit --no-fund --loglevel=error
	touch $(STAMP)
	@echo "mvpose: $(VENV) ready"

demo: $(STAMP)
	$(BIN)/mvpose demo --triggers 10

test: $(STAMP)
	$(BIN)/python -m pytest -q tests

bench: $(STAMP)
	$(BIN)/python -m bench

lint: $(STAMP)
	$(BIN)/ruff check mvpose_core drivers server tests bench
	$(BIN)/mypy mvpose_core drivers server

clean:
	rm -rf $(VENV) var .pytest_cache
