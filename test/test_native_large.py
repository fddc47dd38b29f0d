"""Native kernels on large robots (THRESHOLDS native_max, above the Python kernels' compile_max):
every family native on PR2, Talos reduced and random trees of 32 and 64 bodies, equal to
Pinocchio and to the vectorised numpy reference (the Python implementation these sizes had
before); payload, gravity and locked-joint changes without recompiling. One module-scoped model
per robot: each kernel is compiled once for the whole file."""
import glob
import os
import sys

import numpy as np
import pytest

from lie_dynamics.codegen import native, runtime
from lie_dynamics.codegen.traced import aba as t_aba
from lie_dynamics.codegen.traced import cholesky as t_chol
from lie_dynamics.codegen.traced import crba as t_crba
from lie_dynamics.codegen.traced import derivatives as t_der
from lie_dynamics.codegen.traced import regressor as t_reg
from lie_dynamics.codegen.traced import rnea as t_rnea
from dyn_cases import payload_and_gravity, quiet_load as _load, rel_max as _rel
from oracle import Oracle
from robots import random_urdf

ROOT = next(iter(glob.glob(os.path.join(sys.prefix, 'lib', 'python3*', 'site-packages', 'cmeel.prefix', 'share',
                                        'example-robot-data', 'robots'))), None)
REAL = {'pr2': 'pr2_description/urdf/pr2.urdf', 'talos_reduced': 'talos_data/robots/talos_reduced.urdf'}
TOL = 1e-12
SPECS = [t_rnea.INVERSE_DYNAMICS, t_rnea.GRAVITY, t_rnea.CORIOLIS_TERM, t_crba.MASS_MATRIX, t_chol.FORWARD_DYNAMICS,
         t_aba.ABA, t_der.INVERSE_DYNAMICS_DERIVATIVES, t_der.CORIOLIS,
         t_der.FORWARD_DYNAMICS_DERIVATIVES, t_reg.REGRESSOR]

pytestmark = pytest.mark.skipif(native.module() is None, reason='no working C compiler')


def _xml(name):
    if name in REAL:
        if ROOT is None:
            pytest.skip('example-robot-data is not installed')
        with open(os.path.join(ROOT, REAL[name]), encoding='utf-8') as fh:
            return fh.read()
    n = int(name[len('tree'):])
    return random_urdf(100 + n, n, tree=True)


# Forward dynamics is a solve with M: two correct algorithms differ by up to ~eps cond(M) (the
# 64-body tree: 1.7e-12 between the kernel and the vectorised reference). Its results are checked
# to TOL by their residual (M qdd + h = tau, M and h from the reference) and against the
# reference and Pinocchio to eps cond(M), at least TOL.
SOLVES = ('forward_dynamics', 'aba')


def _check(fam, got, want, ref, s, what):
    if fam not in SOLVES:
        for g, w in zip(*(x if isinstance(x, tuple) else (x,) for x in (got, want)), strict=True):
            assert _rel(g, w) <= TOL, (fam, what)
        return
    q, qd, _, tau = s
    M = ref.mass_matrix(q)
    assert _rel(M @ got + ref.inverse_dynamics(q, qd, np.zeros_like(q)), tau) <= TOL, (fam, what, 'residual')
    assert _rel(got, want) <= max(TOL, 1e-15 * np.linalg.cond(M)), (fam, what)


def _states(model, N, seed):
    rng = np.random.default_rng(seed)
    return [np.ascontiguousarray(x) for x in rng.uniform(-1, 1, (3, N, model.n))]


class Robot:
    """A model with its native kernels, its reference twin (native off: above compile_max, the
    vectorised numpy reference) and Pinocchio."""

    def __init__(self, name):
        self.xml = _xml(name)
        self.model = _load(self.xml)
        self.ref = _load(self.xml)
        runtime.use_native(self.ref, False)
        self.oracle = Oracle(self.xml, joints=self.model.joint_names)


@pytest.fixture(scope='module', params=['pr2', 'talos_reduced', 'tree32', 'tree64'])
def robot(request):
    yield Robot(request.param)
    runtime.clear()


def _family_calls(m, q, qd, qdd, tau):
    """Every family through the Model's methods (ABA only without mimic joints: PR2 has them)."""
    calls = {'inverse_dynamics': lambda: m.inverse_dynamics(q, qd, qdd), 'gravity': lambda: m.gravity(q),
             'coriolis_term': lambda: m.coriolis_term(q, qd),
            'mass_matrix': lambda: m.mass_matrix(q), 'forward_dynamics': lambda: m.forward_dynamics(q, qd, tau),
            'aba': lambda: m.forward_dynamics(q, qd, tau, method='aba'),
            'inverse_dynamics_derivatives': lambda: m.inverse_dynamics_derivatives(q, qd, qdd),
            'coriolis': lambda: m.coriolis_matrix(q, qd, method='recursive'),
            'forward_dynamics_derivatives': lambda: m.forward_dynamics_derivatives(q, qd, tau),
            'regressor': lambda: m.regressor(q, qd, qdd)}
    if not t_aba.supports(m):
        del calls['aba']
    return calls


def _oracle_calls(o, q, qd, qdd, tau):
    return {'inverse_dynamics': lambda: o.rnea(q, qd, qdd), 'gravity': lambda: o.gravity(q),
            'coriolis_term': lambda: o.coriolis_matrix(q, qd) @ qd,
            'mass_matrix': lambda: o.crba(q), 'forward_dynamics': lambda: o.aba(q, qd, tau),
            'aba': lambda: o.aba(q, qd, tau),
            'inverse_dynamics_derivatives': lambda: o.rnea_derivatives(q, qd, qdd),
            'coriolis': lambda: o.coriolis_matrix(q, qd)}


def _sized(model, spec):
    t = runtime.THRESHOLDS[spec.limits]
    return (runtime.pairs(model) if t.size == 'pairs' else model.nb) <= runtime.native_max(t)


def test_every_family_native_equals_pinocchio_and_the_reference(robot):
    m, ref, o = robot.model, robot.ref, robot.oracle
    q, qd, qdd = _states(m, 3, seed=5)
    tau = m.inverse_dynamics(q, qd, qdd)
    for spec in SPECS:
        want = (_sized(m, spec) or runtime.looped(m, spec)) and not (spec is t_aba.ABA and not t_aba.supports(m))
        assert (runtime.native(m, spec) is not None) == want, spec.name
    assert runtime.native(m, t_rnea.INVERSE_DYNAMICS) is not None and runtime.native(m, t_crba.MASS_MATRIX) is not None
    for i in range(len(q)):
        s = (q[i], qd[i], qdd[i], tau[i])
        ours, theirs, peer = _family_calls(m, *s), _family_calls(ref, *s), _oracle_calls(o, *s)
        for fam, f in ours.items():
            got = f()
            _check(fam, got, theirs[fam](), ref, s, (i, 'reference'))
            if fam in peer:
                _check(fam, got, peer[fam](), ref, s, (i, 'pinocchio'))
        # batches through the same kernels: the rows of the single states
        if i == 0:
            batch = m.mass_matrix(q)
            assert _rel(batch[0], m.mass_matrix(q[0])) == 0.0


def test_parameters_change_without_recompiling(robot):
    m, ref = robot.model, robot.ref
    q, qd, qdd = _states(m, 2, seed=6)
    tau = m.inverse_dynamics(q, qd, qdd)
    for f in _family_calls(m, q, qd, qdd, tau).values():
        f()
    before = native.compile_count()
    with payload_and_gravity((m, ref)):
        for i in range(len(q)):
            s = (q[i], qd[i], qdd[i], tau[i])
            ours, theirs = _family_calls(m, *s), _family_calls(ref, *s)
            for fam, f in ours.items():
                _check(fam, f(), theirs[fam](), ref, s, (i, 'payload and gravity'))
    assert native.compile_count() == before


def test_locked_joints_change_without_recompiling(robot):
    part = _load(robot.xml, joints=robot.model.joint_names[::2])
    q, qd, qdd = _states(part, 2, seed=7)
    part.inverse_dynamics(q[0], qd[0], qdd[0])
    part.mass_matrix(q[0])
    compiled = native.compile_count()
    part.set_locked({j: 0.2 + 0.05 * k for k, j in enumerate(part.locked_joint_names)})
    oracle = Oracle(robot.xml, joints=part.joint_names, locked=part.locked_values)
    for i in range(2):
        assert _rel(part.inverse_dynamics(q[i], qd[i], qdd[i]), oracle.rnea(q[i], qd[i], qdd[i])) <= TOL
        assert _rel(part.mass_matrix(q[i]), oracle.crba(q[i])) <= TOL
    assert native.compile_count() == compiled
