# Two commands for a fresh machine: `make demo` (main job on the bundled arm) and `make test`.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: venv test bench demo clean

venv: $(STAMP)

$(STAMP): requirements.txt requirements-dev.txt setup.py setup.cfg
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --disable-pip-version-check -r requirements-dev.txt
	# The package itself, editable: `python -m lie_dynamics...` from any folder, and the console
	# scripts (dynamics_node, sim_node, trajectory_source, demo, fill_trajectory, excitation_trajectory,
	# identify_dynamics) in .venv/bin.
	# --use-pep517: the legacy `setup.py develop` route would follow setup.cfg's [develop]
	# script_dir, which puts them where colcon installs them for `ros2 run` (lib/lie_dynamics).
	$(PY) -m pip install -q --disable-pip-version-check --no-deps --use-pep517 -e .
	rm -f $(VENV)/lib/python*/site-packages/lie_dynamics_src.pth  # the path file of earlier versions
	touch $(STAMP)

test: $(STAMP)
	$(PY) -m pytest -q -n 2 test

bench: $(STAMP)
	$(PY) -m bench $(ARGS)

demo: $(STAMP)
	$(PY) -m lie_dynamics.demo $(ARGS)

clean:
	rm -rf $(VENV) build install log .pytest_cache lie_dynamics.egg-info
