# worldbake: two commands from a fresh machine: `make bake`, then `make test`.
PYTHON ?= python3
VENV   ?= .venv
PY      = $(VENV)/bin/python
CONFIG ?= configs/default.toml

.PHONY: setup vdb-writer bake plan test bench docs clean dcc-env
.DELETE_ON_ERROR:

# The virtual environment, rebuilt when pyproject.toml changes.
$(VENV)/.installed: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[test,bench]'
	touch $@

setup: $(VENV)/.installed

# The .vdb writer: Debian's python3-openvdb in the system Python (no OpenVDB writer installs from PyPI;
# worldlib/volumes/vdb.py). Installed here when this is root on a Debian machine, so that `make bake` and
# `make test` on a fresh machine need nothing else; elsewhere the message says what to do.
vdb-writer:
	@/usr/bin/python3 -c "import pyopenvdb" 2>/dev/null || { \
	  if command -v apt-get >/dev/null && [ "$$(id -u)" = 0 ]; then \
	    echo "installing Debian's python3-openvdb (the .vdb writer of the volumes stages)"; \
	    (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq python3-openvdb >/dev/null) \
	      || echo "python3-openvdb could not be installed: bakes with volumes are refused unless vdb = false" >&2; \
	  else \
	    echo "python3-openvdb is missing: install Debian's python3-openvdb (as root: apt-get install python3-openvdb), or set vdb = false" >&2; \
	  fi; }

# Blender as a Python module for tests/dcc (a real USD client): its own environment, since bpy 5.0 needs
# numpy<2 and the project numpy>=2. The wheel is about 370 MB; without it tests/dcc skip and say so.
BLENDER_VENV ?= .venv-blender
$(BLENDER_VENV)/.installed:
	$(PYTHON) -m venv $(BLENDER_VENV)
	$(BLENDER_VENV)/bin/python -m pip install --quiet "bpy==5.0.1"
	touch $@

dcc-env: $(BLENDER_VENV)/.installed

bake: setup vdb-writer
	$(VENV)/bin/worldbake bake $(CONFIG)

plan: setup vdb-writer
	$(VENV)/bin/worldbake plan $(CONFIG)

# One worker per core (pytest-xdist): the suite is mostly Python and many small bakes.
test: setup vdb-writer
	$(PY) -m pytest -q -n auto --dist loadgroup

# Every benchmark in bench/, one after the other (minutes; not part of `make test`).
bench: setup vdb-writer
	@for b in bench/*.py; do m=$$(basename $$b .py); [ "$$m" = __init__ ] && continue; \
	  echo "== bench.$$m"; $(PY) -m bench.$$m || exit 1; done

# Regenerate the config reference in README.md from the stage declarations.
docs: setup
	$(PY) -c "import re,pathlib,pipeline.docs as d,pipeline.registry as r; p=pathlib.Path('README.md'); t=p.read_text(); b=t.index('<!-- BEGIN describe'); b=t.index('\n',b)+1; e=t.index('<!-- END describe'); p.write_text(t[:b]+d.describe(r.all_stages())+t[e:])"

clean:
	rm -rf build
