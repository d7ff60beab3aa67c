# Two commands do all set-up: `make demo` and `make test`. Both create .venv when missing.
PY ?= python3.11
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: demo test test-slow test-blender venv extension clean

$(STAMP): pyproject.toml
	@# Open3D (the Poisson baseline) links libusb; install it from Debian when we may and it is missing
	@if ! ldconfig -p | grep -q libusb-1.0.so.0; then \
	  if [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null; then \
	    (apt-get update -qq && apt-get install -y -qq libusb-1.0-0) >/dev/null; \
	  else echo "warning: libusb-1.0 is missing; Open3D (eval extra) will not import"; fi; fi
	test -x $(BIN)/python || $(PY) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip wheel setuptools
	$(BIN)/python -m pip install -q "torch==2.13.0" "numpy<2"
	$(BIN)/python -m pip install -q -e ".[test,eval,real,ray,recordings]"
	touch $(STAMP)

venv: $(STAMP)

# The add-on on each Blender line it supports (manifest: 4.2+): bpy 5.0.1 is in .venv (the test extra), the LTS
# lines get a venv each with only what tests/blender imports; the add-on's core runs from .venv (HGCA_PYTHON).
BPY42 := 4.2.23
BPY45 := 4.5.15
BPY_TEST_DEPS := "numpy<2" "pytest>=8" "pytest-timeout>=2.3" "laspy>=2.5" "lazrs>=0.6"
BLENDER_TESTS = HGCA_PYTHON=$(abspath $(BIN)/python) $(1)/bin/python -m pytest -q --confcutdir=tests/blender tests/blender

.venv-bpy%/.installed: Makefile
	test -x .venv-bpy$*/bin/python || $(PY) -m venv .venv-bpy$*
	.venv-bpy$*/bin/python -m pip install -q "bpy==$(BPY$*)" $(BPY_TEST_DEPS)
	touch $@

# DEMO_ARGS: more `hgca demo` options, e.g. make demo DEMO_ARGS=--semantics (a class on every face)
demo: $(STAMP)
	$(BIN)/hgca demo --out demo_out $(DEMO_ARGS)

# The core's tests in a worker per core (at most 4: each completion holds up to ~2.5 GiB), then the add-on's tests
# on bpy 4.2 LTS in one process: <= 15 minutes on 2 cores. Tests marked slow (Ray stress runs, training runs, the
# whole way from the zip through Install Core) and the other Blender lines (5.0, 4.5) run in `make test-slow`,
# which CI runs after `make test`.
PYTEST_PARALLEL := -n auto --maxprocesses 4


test: $(STAMP) .venv-bpy42/.installed
	$(BIN)/python -m pytest -q $(PYTEST_PARALLEL) -m "not slow" tests --ignore=tests/blender
	$(call BLENDER_TESTS,.venv-bpy42) -m "not slow"

test-slow: $(STAMP) .venv-bpy42/.installed .venv-bpy45/.installed
	$(BIN)/python -m pytest -q $(PYTEST_PARALLEL) -m slow tests --ignore=tests/blender
	$(BIN)/python -m pytest -q tests/blender
	$(call BLENDER_TESTS,.venv-bpy45) -m "not slow"
	$(call BLENDER_TESTS,.venv-bpy42) -m slow

test-blender: $(STAMP) .venv-bpy42/.installed .venv-bpy45/.installed
	$(BIN)/python -m pytest -q tests/blender
	$(call BLENDER_TESTS,.venv-bpy45)
	$(call BLENDER_TESTS,.venv-bpy42)

# The zip a Blender user installs (Edit > Preferences > Get Extensions > Install from Disk): any Python 3.11 with
# pip, no test venv, seconds. Blender's own builder and validator are used where bpy is installed.
extension:
	$(PY) -m hgca_blender.build_extension --out build/extension

clean:
	rm -rf build dist *.egg-info
