"""Shared robots, random states and comparison helpers for the Lagrangian/derivative tests."""
import contextlib
import functools
import glob
import os
import sys
import warnings

import numpy as np
import pytest

from lie_dynamics import default_urdf_path, load_urdf
from oracle import Oracle
from robots import NAMED_CASES, named_urdf

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
ARM = os.path.join(ROOT, 'config', 'arm7.urdf')
CASES = list(NAMED_CASES) + ['arm7']
N_STATES = 100


@functools.lru_cache(maxsize=None)
def xml_of(name):
    if name == 'arm7':
        with open(ARM, encoding='utf-8') as fh:
            return fh.read()
    return named_urdf(name)


@functools.lru_cache(maxsize=None)
def case(name):
    """(model, oracle) for a named robot, joints in the same order."""
    xml = xml_of(name)
    model = load_urdf(xml)
    return model, Oracle(xml, joints=model.joint_names)


def states(model, N=N_STATES, seed=0):
    """N random (q, qd, qdd): angles over a full turn, prismatic within +-0.5 m."""
    rng = np.random.default_rng(seed)
    span = np.array([0.5 if t == 'prismatic' else np.pi for t in model.joint_types])
    q = rng.uniform(-1, 1, size=(N, model.n)) * span
    qd = rng.normal(size=(N, model.n))
    qdd = rng.normal(size=(N, model.n))
    return q, qd, qdd


def rel_err(a, b, floor=1e-6):
    """max |a - b| / max(|b|, floor) per state (leading axis), worst state."""
    a, b = np.asarray(a), np.asarray(b)
    axes = tuple(range(1, a.ndim))
    num = np.max(np.abs(a - b), axis=axes)
    den = np.maximum(np.max(np.abs(b), axis=axes), floor)
    return float(np.max(num / den))


def oracle_stack(fn, *args):
    return np.array([fn(*row) for row in zip(*args)])


def pin_body_permutation(model, oracle):
    """Column permutation from Pinocchio's dynamic parameters to ours."""
    names = oracle.body_names()
    return np.concatenate([np.arange(10) + 10 * names.index(b) for b in model.body_joint_names])


def quiet_load(xml, **kw):
    """load_urdf without its warnings (vendor inertias are warned about)."""
    with warnings.catch_warnings():
        warnings.simplefilter('ignore')
        return load_urdf(xml, **kw)


def rel_max(a, b):
    """max |a - b| over every entry, relative to max(1, max |b|)."""
    a, b = np.asarray(a), np.asarray(b)
    return float(np.max(np.abs(a - b)) / max(1.0, float(np.max(np.abs(b)))))


# example-robot-data's robots folder in this environment (its cmeel prefix), or None
ERD_ROBOTS = next(iter(glob.glob(os.path.join(sys.prefix, 'lib', 'python3*', 'site-packages', 'cmeel.prefix',
                                              'share', 'example-robot-data', 'robots'))), None)


def case_urdf(name):
    """The URDF text of a test robot: 'arm7' (the bundled arm), a path below example-robot-data's
    robots folder (skipped when it is not installed), else a named case of robots.named_urdf."""
    if name == 'arm7':
        path = default_urdf_path()
    elif '/' in name:
        if ERD_ROBOTS is None:
            pytest.skip('example-robot-data is not installed')
        path = os.path.join(ERD_ROBOTS, name)
    else:
        return named_urdf(name)
    with open(path, encoding='utf-8') as fh:
        return fh.read()


def looped_from_one(limits):
    """A generator for a module-scoped fixture: THRESHOLDS looped_from = 1 for the families
    `limits` (their looped native kernels on small robots, which compile in a fraction of a
    second), restored afterwards; the runtime's caches cleared both times."""
    from lie_dynamics.codegen import runtime
    T = runtime.THRESHOLDS
    saved = {k: T[k] for k in limits}
    for k in limits:
        T[k] = T[k]._replace(looped_from=1)
    runtime.clear()
    yield
    T.update(saved)
    runtime.clear()


class LoopedRobot:
    """A model (loaded from xml with kw), its Python twin (the native backend off) and Pinocchio."""

    def __init__(self, xml, **kw):
        from lie_dynamics.codegen import runtime
        self.xml = xml
        self.model = quiet_load(xml, **kw)
        self.ref = quiet_load(xml, **kw)
        runtime.use_native(self.ref, False)
        self.oracle = Oracle(xml, joints=self.model.joint_names, locked=self.model.locked_values)


def uniform_states(model, N, seed):
    """[q, qd, qdd], each (N, n) C-contiguous, uniform in [-1, 1]."""
    rng = np.random.default_rng(seed)
    return [np.ascontiguousarray(x) for x in rng.uniform(-1, 1, (3, N, model.n))]


MOVED_GRAVITY = (0.5, -1.0, -9.0)


@contextlib.contextmanager
def payload_and_gravity(models):
    """On each model: a 1.5 kg payload on the last link with a body and gravity MOVED_GRAVITY,
    then restored (no payload, standard gravity). Yields that link's name. For the tests that a
    parameter change reaches a compiled kernel without compiling again."""
    m = models[0]
    link = [nm for nm, (b, _) in m.link_frames.items() if b >= 0][-1]
    try:
        for x in models:
            x.set_payload(link, 1.5, [0.05, 0.0, 0.1], [0.01, 0.0, 0.0, 0.02, 0.0, 0.03])
            x.set_gravity(list(MOVED_GRAVITY))
        yield link
    finally:
        for x in models:
            x.clear_payload()
            x.set_gravity([0.0, 0.0, -9.81])
