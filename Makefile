# Two commands for a fresh machine: `make demo` (main job on the bundled arm) and `make test`.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: venv test bench demo clean

venv: $(STAMP)

$(STAMP): requirements.txt requirements-dev.txt
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --disable-pip-version-check -r requirements-dev.txt
	# the source tree on the venv's path, so `python -m lie_dynamics...` works from any folder
	$(PY) -c "import os, site; open(os.path.join(site.getsitepackages()[0], 'lie_dynamics_src.pth'), 'w').write(os.getcwd() + chr(10))"
	touch $(STAMP)

test: $(STAMP)
	$(PY) -m pytest -q -n 2 test

bench: $(STAMP)
	$(PY) -m bench $(ARGS)

demo: $(STAMP)
	$(PY) -m lie_dynamics.demo $(ARGS)

clean:
	rm -rf $(VENV) build install log .pytest_cache
