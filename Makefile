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
	touch $(STAMP)

test: $(STAMP)
	$(PY) -m pytest -q -n 2 test

bench: $(STAMP)
	$(PY) -m bench $(ARGS)

demo: $(STAMP)
	$(PY) -m lie_dynamics.demo $(ARGS)

clean:
	rm -rf $(VENV) build install log .pytest_cache
