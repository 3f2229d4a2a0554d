# cranetwin — the two commands a new user runs: `make demo` and `make test`.
VENV   ?= .venv
PYTHON ?= python3
BIN    := $(VENV)/bin

.PHONY: setup system-deps demo test lint clean

# every extra plus the test and lint tools, at the versions pinned in constraints.txt
$(BIN)/.installed: pyproject.toml constraints.txt
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip
	$(BIN)/pip install -q -c constraints.txt -e '.[dev]'
	touch $@

setup: $(BIN)/.installed

# Debian packages the browser and report tests use (Chromium, pdftoppm). Skipped when present or
# when not root on a Debian-like system; the tests that need them then skip with a reason.
system-deps:
	@bash .ci/system-deps

demo: setup
	$(BIN)/cranetwin fleetdemo

test: system-deps setup
	@$(BIN)/python -m pytest -q -n 2 --dist loadfile --no-loadscope-reorder -m "not serial"; \
	rc=$$?; if [ $$rc -eq 5 ]; then echo "pytest collected no tests: treating as failure"; rc=1; fi; \
	$(BIN)/python -m pytest -q -m serial; rc2=$$?; \
	if [ $$rc2 -eq 5 ]; then echo "pytest collected no serial tests: treating as failure"; rc2=1; fi; \
	if [ $$rc -ne 0 ]; then exit $$rc; fi; exit $$rc2

lint: setup
	$(BIN)/ruff check src tests
	$(BIN)/mypy

clean:
	rm -rf $(VENV) .pytest_cache .mypy_cache .ruff_cache
