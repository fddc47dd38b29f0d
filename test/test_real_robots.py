"""Real vendor URDFs (example-robot-data): every file Pinocchio loads must load here, warnings
allowed, and agree with Pinocchio's RNEA, gravity and CRBA on random states."""
import glob
import os
import sys
import warnings

import numpy as np
import pinocchio as pin
import pytest

from lie_dynamics import load_urdf
from oracle import Oracle

ROOT = next(iter(glob.glob(os.path.join(sys.prefix, 'lib', 'python3*', 'site-packages', 'cmeel.prefix', 'share',
                                        'example-robot-data', 'robots'))), None)
FILES = sorted(glob.glob(os.path.join(ROOT, '**', '*.urdf'), recursive=True)) if ROOT else []
STATES = 3
TOL = 1e-9


def _pinocchio_loads(path):
    try:
        pin.buildModelFromUrdf(path)
    except Exception:  # urdfdom refuses it: so may we
        return False
    return True


def test_the_collection_is_installed():
    assert len(FILES) >= 60, 'example-robot-data is a test dependency (requirements-dev.txt)'


@pytest.mark.parametrize('path', FILES, ids=[os.path.relpath(f, ROOT) for f in FILES] if ROOT else [])
def test_vendor_urdf_loads_and_matches_pinocchio(path):
    if not _pinocchio_loads(path):
        pytest.skip('Pinocchio (urdfdom) refuses this file')
    with warnings.catch_warnings():
        warnings.simplefilter('ignore')  # physically odd inertias are warned about, not refused
        model = load_urdf(path)
    if model.n == 0:
        assert model.gravity(np.zeros(0)).shape == (0,)
        return
    with open(path, encoding='utf-8') as fh:
        oracle = Oracle(fh.read(), joints=model.joint_names)
    rng = np.random.default_rng(len(path))
    lo = np.where(np.isfinite(model.position_lower), model.position_lower, -np.pi)
    hi = np.where(np.isfinite(model.position_upper), model.position_upper, np.pi)
    q = rng.uniform(lo, hi, size=(STATES, model.n))
    qd = rng.normal(size=(STATES, model.n))
    qdd = rng.normal(size=(STATES, model.n))
    tau = model.inverse_dynamics(q, qd, qdd)
    g = model.gravity(q)
    M = model.mass_matrix(q)
    for k in range(STATES):
        for ours, ref in ((tau[k], oracle.rnea(q[k], qd[k], qdd[k])), (g[k], oracle.gravity(q[k])),
                          (M[k], oracle.crba(q[k]))):
            scale = max(1.0, np.max(np.abs(ref)))
            assert np.max(np.abs(ours - ref)) <= TOL * scale
