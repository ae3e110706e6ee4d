# Every target sets up (or reuses) the local virtual environment .venv and installs what it needs.
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed-stamp
# The operator page's message catalogues (server/web/locale): .po in the repository, .mo compiled
# here (and by the Dockerfile), never committed.
LOCALES := server/web/locale
MO := $(patsubst %.po,%.mo,$(wildcard $(LOCALES)/*/LC_MESSAGES/messages.po))

.PHONY: demo test bench lint venv clean messages

venv: $(STAMP) $(MO)

$(MO): %.mo: %.po $(STAMP)
	$(BIN)/pybabel compile -i $< -o $@

# After changing the page's English texts: the template and every language's catalogue follow
# (then translate the new or changed messages; tests/server/test_i18n.py finds any left over).
messages: $(STAMP)
	$(BIN)/pybabel extract -F babel.cfg -k N_ --no-location --sort-output --project mvpose \
		--copyright-holder "the mvpose authors" -o $(LOCALES)/messages.pot server/web
	$(BIN)/pybabel update -i $(LOCALES)/messages.pot -d $(LOCALES) \
		--ignore-obsolete --width 100

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

demo: $(STAMP) $(MO)
	$(BIN)/mvpose demo --triggers 10

test: $(STAMP) $(MO)
	$(BIN)/python -m pytest -q tests --durations=25

bench: $(STAMP) $(MO)
	$(BIN)/python -m bench

lint: $(STAMP)
	$(BIN)/ruff check mvpose_core drivers server tests bench
	$(BIN)/mypy mvpose_core drivers server bench

clean:
	rm -rf $(VENV) var .pytest_cache
