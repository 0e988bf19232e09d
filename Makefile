# Two commands matter: `make run` and `make test`. Both build .venv from nothing when needed.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
PACKAGES := core analysis daq live fleet web imunoise

.PHONY: run test lint bench clean bytecode

$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[test,fleet,plot,notebook]'
	touch $(STAMP)

# Every command is a new process that imports the package from this tree (an editable
# install). Where the environment sets PYTHONDONTWRITEBYTECODE, Python compiles each of its
# modules from source on every start, about 0.13 s a command here; the bytecode written
# below is read instead (and is ignored for any file edited since).
bytecode: $(STAMP)
	$(BIN)/python -m compileall -q $(PACKAGES)

run: bytecode
	$(BIN)/imunoise serve --device sim:adis16350 --out data

# Two passes: the tests that do not depend on the host keeping time, two at a time (one per
# core of a small machine); then the `realtime` ones (live acquisition, serving, lost-sample
# counts) alone, so that nothing else competes with them. Together they are the whole suite.
test: bytecode
	$(BIN)/ruff check .
	$(BIN)/python -m tests.typecheck
	$(BIN)/python -m pytest -q -n 2 --dist loadfile -m "not realtime"
	$(BIN)/python -m pytest -q -m realtime

lint: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/python -m tests.typecheck

bench: $(STAMP)
	for b in bench/*.py; do $(BIN)/python $$b || exit 1; done

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache .mypy_cache
