# worldbake: two commands from a fresh machine: `make bake`, then `make test`.
PYTHON ?= python3
VENV   ?= .venv
PY      = $(VENV)/bin/python
CONFIG ?= configs/default.toml

.PHONY: setup bake plan test bench docs clean dcc-env
.DELETE_ON_ERROR:

# The virtual environment, rebuilt when pyproject.toml changes.
$(VENV)/.installed: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[test,bench]'
	touch $@

setup: $(VENV)/.installed

# Blender as a Python module for tests/dcc (a real USD client): its own environment, since bpy 5.0 needs
# numpy<2 and the project numpy>=2. The wheel is about 370 MB; without it tests/dcc skip and say so.
BLENDER_VENV ?= .venv-blender
$(BLENDER_VENV)/.installed:
	$(PYTHON) -m venv $(BLENDER_VENV)
	$(BLENDER_VENV)/bin/python -m pip install --quiet "bpy==5.0.1"
	touch $@

dcc-env: $(BLENDER_VENV)/.installed

bake: setup
	$(VENV)/bin/worldbake bake $(CONFIG)

plan: setup
	$(VENV)/bin/worldbake plan $(CONFIG)

# One worker per core (pytest-xdist): the suite is mostly Python and many small bakes.
test: setup
	$(PY) -m pytest -q -n auto --dist loadgroup

# Every benchmark in bench/, one after the other (minutes; not part of `make test`).
bench: setup
	@for b in bench/*.py; do m=$$(basename $$b .py); [ "$$m" = __init__ ] && continue; \
	  echo "== bench.$$m"; $(PY) -m bench.$$m || exit 1; done

# Regenerate the config reference in README.md from the stage declarations.
docs: setup
	$(PY) -c "import re,pathlib,pipeline.docs as d,pipeline.registry as r; p=pathlib.Path('README.md'); t=p.read_text(); b=t.index('<!-- BEGIN describe'); b=t.index('\n',b)+1; e=t.index('<!-- END describe'); p.write_text(t[:b]+d.describe(r.all_stages())+t[e:])"

clean:
	rm -rf build
