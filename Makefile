# Two commands do all set-up: `make demo` and `make test`. Both create .venv when missing.
PY ?= python3.11
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: demo test venv extension clean

$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PY) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip wheel setuptools
	$(BIN)/python -m pip install -q "torch==2.13.0" "numpy<2"
	$(BIN)/python -m pip install -q -e ".[test,eval]"
	touch $(STAMP)

venv: $(STAMP)

demo: $(STAMP)
	$(BIN)/hgca demo

test: $(STAMP)
	$(BIN)/python -m pytest -q tests

extension: $(STAMP)
	$(BIN)/python -m hgca_blender.build_extension --out build/extension

clean:
	rm -rf build dist *.egg-info
