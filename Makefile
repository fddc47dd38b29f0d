# Two commands for a fresh machine: `make demo` (main job on the bundled arm) and `make test`.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: venv test test-numpy1 bench demo clean

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

# The suite on Ubuntu 24.04's numpy (1.26, what a ROS Jazzy user has) in its own .venv-numpy1.
# Pinocchio's wheels declare numpy >= 2 (a packaging bound: they run on 1.26), so numpy is
# replaced after the install instead of constrained in it.
NUMPY1 := .venv-numpy1
test-numpy1:
	test -x $(NUMPY1)/bin/python || $(PYTHON) -m venv $(NUMPY1)
	$(NUMPY1)/bin/python -m pip install -q --disable-pip-version-check -r requirements-dev.txt
	$(NUMPY1)/bin/python -m pip install -q --disable-pip-version-check --no-deps numpy==1.26.4
	$(NUMPY1)/bin/python -m pip install -q --disable-pip-version-check --no-deps --use-pep517 -e .
	rm -f $(NUMPY1)/lib/python*/site-packages/lie_dynamics_src.pth
	$(NUMPY1)/bin/python -c "import numpy; assert numpy.__version__ == '1.26.4', numpy.__version__"
	$(NUMPY1)/bin/python -m pytest -q -n 2 test

bench: $(STAMP)
	$(PY) -m bench $(ARGS)

demo: $(STAMP)
	$(PY) -m lie_dynamics.demo $(ARGS)

clean:
	rm -rf $(VENV) $(NUMPY1) build install log .pytest_cache lie_dynamics.egg-info
