# Two entry points for a fresh machine (Python 3.11+): `make demo` and `make test`; `make docs` builds the guide.
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
BASE := $(VENV)/.installed-base
DEV := $(VENV)/.installed-dev


.PHONY: demo test lint docs bench clean

$(BIN)/python:
	$(PY) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip

# fieldtool is byte-compiled here as pip does for an installed package (its modules' start-up without compiling;
# the dependencies' are compiled by pip: with PYTHONDONTWRITEBYTECODE set, nothing is cached on first import)
$(BASE): $(BIN)/python pyproject.toml
	$(BIN)/pip install -q -e .
	$(BIN)/python -m compileall -q fieldtool
	touch $(BASE)

# one install (one resolve, one editable build) of the package with its dev extras; the base is then in place too
$(DEV): $(BIN)/python pyproject.toml
	$(BIN)/pip install -q -e '.[dev]'
	$(BIN)/python -m compileall -q fieldtool
	touch $(BASE) $(DEV)

demo: $(BASE)
	$(BIN)/fieldtool demo --out demo_out

lint: $(DEV)
	$(BIN)/ruff check fieldtool tests
	$(BIN)/ruff format --check fieldtool tests
	$(BIN)/mypy fieldtool

# the suite in two parts: the tests that wait on wall-clock time alone (tests/conftest.py SERIAL), the rest first on
# every core (pytest-xdist, TEST_WORKERS processes: on two cores the suite takes about half the time)
TEST_WORKERS ?= $(shell $(PY) -c "import os; print(min(4, max(1, len(os.sched_getaffinity(0)))))")

test: $(DEV) lint
	$(BIN)/python -m pytest -q -n $(TEST_WORKERS) -m "not serial" --durations=12
	$(BIN)/python -m pytest -q -m serial --durations=12

# The user guide (mkdocs, material theme) into site/, offline; open site/index.html.
docs: $(DEV)
	NO_MKDOCS_2_WARNING=1 $(BIN)/python -m mkdocs build --strict -d site

bench: $(DEV)
	$(BIN)/python benchmarks/piv_vs_openpiv.py

clean:
	rm -rf $(VENV) demo_out site
