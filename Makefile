# Two set-up commands: `make demo` and `make test`. Both create .venv when missing and install the project.
SHELL := /bin/bash
PY ?= python3.11
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed-$(shell cat pyproject.toml | sha256sum | cut -c1-12)
DEMO_ROOT ?= runs/demo

.PHONY: demo lint test test-slow venv sysdeps bench clean

sysdeps:
	@if ! ldconfig -p | grep -q 'libusb-1.0.so.0'; then \
	  echo "installing libusb-1.0-0 (needed by open3d)"; \
	  apt-get update -qq && apt-get install -y -qq libusb-1.0-0 >/dev/null; \
	fi

$(STAMP): pyproject.toml | sysdeps
	@test -x $(BIN)/python || $(shell command -v $(PY) || echo python3) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q -e '.[test]'
	@rm -f $(VENV)/.installed-*; touch $@

venv: sysdeps $(STAMP)

demo: venv
	$(BIN)/cornermap run workflows/demo.yaml --root $(DEMO_ROOT)

# Fast static checks (seconds): ruff (pyproject [tool.ruff]) and the import contracts (pyproject [tool.importlinter]).
lint: venv
	$(BIN)/ruff check .
	PYTHONPATH=$(CURDIR) $(BIN)/lint-imports

test: lint
	$(BIN)/python -m pytest -n 2 --dist loadfile -q

test-slow: venv
	$(BIN)/python -m pytest -m slow -q

bench: venv
	$(BIN)/python -m bench --help

clean:
	rm -rf runs .pytest_cache
