# Two commands do all set-up: `make demo` and `make test`. Both create .venv when missing.
PY ?= python3.11
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: demo test venv extension clean

$(STAMP): pyproject.toml
	@# Open3D (the Poisson baseline) links libusb; install it from Debian when we may and it is missing
	@if ! ldconfig -p | grep -q libusb-1.0.so.0; then \
	  if [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null; then \
	    (apt-get update -qq && apt-get install -y -qq libusb-1.0-0) >/dev/null; \
	  else echo "warning: libusb-1.0 is missing; Open3D (eval extra) will not import"; fi; fi
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
