"""The looped native regressor (codegen/looped.py, traced/regressor.py looped_regressor), forced on
small robots by THRESHOLDS looped_from = 1 so that it compiles in a fraction of a second, and on
Talos reduced. Checked against the Python kernels (the same model with the native backend off),
the straight-line native kernel and Pinocchio's computeJointTorqueRegressor, single states and
batches, with gravity and locked-joint changes without recompiling, and its `out=` buffers."""
import glob
import os
import sys

import numpy as np
import pytest

from lie_dynamics.codegen import native, runtime
from lie_dynamics.codegen.traced import regressor as t_reg
from dyn_cases import (MOVED_GRAVITY, LoopedRobot, looped_from_one, payload_and_gravity, pin_body_permutation,
                       quiet_load as _load, rel_max as _rel, uniform_states)
from oracle import Oracle
from robots import random_urdf

TOL = 1e-12
PIN_TOL = 1e-10
SPEC = t_reg.REGRESSOR

pytestmark = pytest.mark.skipif(native.module() is None, reason='no working C compiler')

ROOT = next(iter(glob.glob(os.path.join(sys.prefix, 'lib', 'python3*', 'site-packages', 'cmeel.prefix', 'share',
                                        'example-robot-data', 'robots'))), None)


@pytest.fixture(scope='module')
def looped_everywhere():
    """looped_from = 1 for the regressor (restored after the module)."""
    yield from looped_from_one(('regressor',))


def _talos():
    if ROOT is None:
        pytest.skip('example-robot-data is not installed')
    with open(os.path.join(ROOT, 'talos_data/robots/talos_reduced.urdf'), encoding='utf-8') as fh:
        return fh.read()


Robot = LoopedRobot   # the regressor looped (the fixture above)


# revolute, continuous and prismatic joints with general axes, fixed links merged into their parents
CASES = {'chain': lambda: random_urdf(41, 7), 'tree': lambda: random_urdf(42, 9, tree=True), 'talos_reduced': _talos}


@pytest.fixture(scope='module', params=list(CASES))
def robot(request, looped_everywhere):
    return Robot(CASES[request.param]())


_states = uniform_states


def _pin(m, oracle, q, qd, qdd):
    perm = pin_body_permutation(m, oracle)
    return np.array([oracle.regressor(*s)[:, perm] for s in zip(q, qd, qdd, strict=True)])


def _check(m, ref, oracle, q, qd, qdd):
    """m's regressor on states (N, n) against the Python twin and Pinocchio, one state at a time
    and as one batch (the batch's rows equal the single calls)."""
    Y = m.regressor(q, qd, qdd)
    assert Y.shape == (len(q), m.n, 10 * m.nb)
    assert _rel(Y, ref.regressor(q, qd, qdd)) <= TOL
    assert _rel(Y, _pin(m, oracle, q, qd, qdd)) <= PIN_TOL
    for i in range(len(q)):
        assert np.array_equal(m.regressor(q[i], qd[i], qdd[i]), Y[i])
    assert _rel(Y @ m.inertial_parameters(), ref.inverse_dynamics(q, qd, qdd)) <= TOL


def test_looped_regressor_runs_and_agrees(robot):
    m, ref = robot.model, robot.ref
    assert runtime.looped(m, SPEC) and not runtime.looped(ref, SPEC)
    assert runtime.native(m, SPEC) is not None
    _check(m, ref, robot.oracle, *_states(m, 4, seed=1))


def test_threads_give_identical_results(robot):
    """A batch cut among threads (native.set_threads) equals the one-thread batch, bit for bit."""
    m = robot.model
    q, qd, qdd = _states(m, 2 * 64 + 3, seed=10)
    one = m.regressor(q, qd, qdd)
    previous = native.set_threads(2, min_rows=64)   # cut even this batch
    try:
        assert np.array_equal(runtime.native(m, SPEC)(q, qd, qdd), one)
    finally:
        native.set_threads(previous)


def test_out_buffers(robot):
    """The bound kernel's `out=` (the Model method has none): a good buffer is written and
    returned, a bad one declined (None), the kernel's own result unchanged."""
    m = robot.model
    q, qd, qdd = _states(m, 3, seed=2)
    fn = runtime.native(m, SPEC)
    want = m.regressor(q, qd, qdd)
    buf = np.full((3, m.n, 10 * m.nb), np.nan)
    assert fn(q, qd, qdd, buf) is buf and np.array_equal(buf, want)
    one = np.full((m.n, 10 * m.nb), np.nan)
    assert fn(q[0], qd[0], qdd[0], one) is one and np.array_equal(one, want[0])
    for bad in (np.empty((3, m.n, 10 * m.nb), np.float32), np.empty((3, m.n, 10 * m.nb + 1)),
                np.empty((m.n, 10 * m.nb))):
        assert fn(q, qd, qdd, bad) is None
    assert np.array_equal(m.regressor(q, qd, qdd), want)


def test_gravity_and_payload_change_without_recompiling(robot):
    m, ref = robot.model, robot.ref
    q, qd, qdd = _states(m, 2, seed=3)
    _check(m, ref, robot.oracle, q, qd, qdd)
    before = native.compile_count()
    oracle = Oracle(robot.xml, joints=m.joint_names, gravity=MOVED_GRAVITY)
    with payload_and_gravity((m, ref)):
        _check(m, ref, oracle, q, qd, qdd)
    assert native.compile_count() == before


def test_locked_joints_change_without_recompiling(looped_everywhere):
    xml = random_urdf(43, 8)
    names = _load(xml).joint_names
    part = Robot(xml, joints=names[::2])
    m = part.model
    assert len(m.locked_joint_names) == len(names) - m.n and runtime.looped(m, SPEC)
    q, qd, qdd = _states(m, 2, seed=5)
    _check(m, part.ref, part.oracle, q, qd, qdd)
    compiled = native.compile_count()
    values = {j: 0.2 + 0.05 * k for k, j in enumerate(m.locked_joint_names)}
    for x in (m, part.ref):
        x.set_locked(values)
    _check(m, part.ref, Oracle(xml, joints=m.joint_names, locked=m.locked_values), q, qd, qdd)
    assert native.compile_count() == compiled


def test_looped_equals_straight_line(looped_everywhere):
    """The looped and the straight-line C forms of the same steps, one model each."""
    xml = random_urdf(44, 6, tree=True)
    m = _load(xml)
    T = runtime.THRESHOLDS
    saved = T['regressor']
    try:
        T['regressor'] = saved._replace(looped_from=None)
        straight = _load(xml)
        q, qd, qdd = _states(m, 3, seed=6)
        Y = straight.regressor(q, qd, qdd)
        assert not runtime.looped(straight, SPEC) and runtime.native(straight, SPEC) is not None
    finally:
        T['regressor'] = saved
    assert runtime.looped(m, SPEC)
    assert _rel(m.regressor(q, qd, qdd), Y) <= TOL


def test_mimic_joints_keep_todays_routes(looped_everywhere):
    """Mimic joints couple bodies: no looped form (looped.joints_of), the straight-line kernel runs."""
    xml = random_urdf(35, 6, mimic=True)
    m = _load(xml)
    assert t_reg.looped_regressor(runtime.frames(m)) is None
    assert not runtime.looped(m, SPEC) and runtime.native(m, SPEC) is not None
    ref = _load(xml)
    runtime.use_native(ref, False)
    q, qd, qdd = _states(m, 2, seed=7)
    assert _rel(m.regressor(q, qd, qdd), ref.regressor(q, qd, qdd)) <= TOL
    assert _rel(m.regressor(q, qd, qdd), _pin(m, Oracle(xml, joints=m.joint_names), q, qd, qdd)) <= PIN_TOL


def test_looped_from_counts_pairs_and_takes_over_above_the_caps():
    """The regressor's looped_from counts (body, ancestor) pairs; above the straight-line caps
    (native_max) the looped form runs whatever looped_from says."""
    T = runtime.THRESHOLDS
    saved = T['regressor']
    xml = random_urdf(37, 5)   # a chain: 15 pairs
    try:
        for limits, want in ((saved._replace(looped_from=15), True), (saved._replace(looped_from=16), False),
                             (saved._replace(looped_from=10 ** 6, compile_max=2, native_max=4), True)):
            T['regressor'] = limits
            runtime.clear()
            m = _load(xml)
            assert runtime.pairs(m) == 15
            assert runtime.looped(m, SPEC) == want, limits
            assert runtime.native(m, SPEC) is not None
            q, qd, qdd = _states(m, 2, seed=9)
            assert _rel(m.regressor(q, qd, qdd), _pin(m, Oracle(xml, joints=m.joint_names), q, qd, qdd)) <= PIN_TOL
    finally:
        T['regressor'] = saved
        runtime.clear()
