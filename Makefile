# Two commands on a fresh machine: `make demo` and `make test`.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

export VTK_DEFAULT_OPENGL_WINDOW ?= vtkOSOpenGLRenderWindow
# numpy's arrays without transparent huge pages, as the heartreg command runs (heartreg/cli.py): where the kernel
# defragments memory on their page faults the tests' volumes stall (test_aortic_cta 48 -> 40 s)
export NUMPY_MADVISE_HUGEPAGE ?= 0

.PHONY: demo test bench sysdeps clean

# Offscreen rendering needs Debian's OSMesa/EGL/GL libraries, and the test of the
# report's interactive 3-D view a headless chromium; install them when missing and
# we are allowed to (root), otherwise say what to install.
sysdeps:
	@if ! ldconfig -p | grep -q libOSMesa || ! command -v chromium >/dev/null; then \
	  if [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null; then \
	    (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libosmesa6 libegl1 libgl1 libxrender1 chromium >/dev/null) \
	      || echo "warning: could not install libosmesa6 libegl1 libgl1 chromium; 3-D pictures and the browser test will be skipped" >&2; \
	  else echo "note: install libosmesa6 libegl1 libgl1 for offscreen 3-D pictures and chromium for the report's browser test" >&2; fi; \
	fi

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -e ".[test]"
	touch $(STAMP)

demo: sysdeps $(STAMP)
	$(VENV)/bin/heartreg demo -o demo_out

test: sysdeps $(STAMP)
	$(PY) tests/data/fetch_real_cts.py  # more real CTs from PyPI source archives (the tests skip them offline)
	$(PY) -m pytest -q -n auto --dist loadfile  # one test file per worker: its module fixtures stay shared

bench: sysdeps $(STAMP)
	$(PY) bench/run_all.py

clean:
	rm -rf $(VENV) demo_out bench/out
