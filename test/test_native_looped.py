"""Looped native kernels (codegen/looped.py): the mass matrix, the ABA (and forward dynamics,
method='cholesky', which takes the looped ABA), the derivatives of inverse dynamics (with
wrenches, and the Coriolis matrix, their dtau/dqd half) and of forward dynamics rendered as
per-body steps looped in C, forced on small robots by THRESHOLDS looped_from = 1 so that they
compile in a fraction of a second. Checked against the Python kernels (the same model with the
native backend off), the straight-line native kernels and Pinocchio, single states and batches,
with payload, gravity, armature and locked-joint changes, and without recompiling for parameter
changes."""
import numpy as np
import pinocchio as pin
import pytest

from lie_dynamics.codegen import kernel, native, runtime
from lie_dynamics.codegen.traced import aba as t_aba
from lie_dynamics.codegen.traced import crba as t_crba
from lie_dynamics.codegen.traced import derivatives as t_der
from dyn_cases import (LoopedRobot, looped_from_one, payload_and_gravity, quiet_load as _load, rel_max as _rel,
                       uniform_states)
from oracle import Oracle
from robots import random_urdf

TOL = 1e-12
LIMITS = ('mass_matrix', 'aba', 'inverse_dynamics_derivatives', 'forward_dynamics_derivatives')
DERIVATIVES = (t_der.INVERSE_DYNAMICS_DERIVATIVES, t_der.INVERSE_DYNAMICS_DERIVATIVES_WRENCH, t_der.CORIOLIS,
               t_der.FORWARD_DYNAMICS_DERIVATIVES)

pytestmark = pytest.mark.skipif(native.module() is None, reason='no working C compiler')


@pytest.fixture(scope='module')
def looped_everywhere():
    """looped_from = 1 for the families with a looped form (restored after the module)."""
    yield from looped_from_one(LIMITS)


Robot = LoopedRobot   # M, ABA and derivatives looped (the fixture above)


# revolute, continuous and prismatic joints, fixed links merged into their parents
CASES = {'chain': lambda: random_urdf(31, 7), 'tree': lambda: random_urdf(32, 9, tree=True)}


@pytest.fixture(scope='module', params=list(CASES))
def robot(request, looped_everywhere):
    return Robot(CASES[request.param]())


_states = uniform_states


def _check_solve(got, want, ref, q, qd, tau):
    """A forward-dynamics result: its residual M qdd + h - tau (M, h of the Python twin) to TOL and
    the other result to eps cond(M), at least TOL (two correct solves differ by that much)."""
    M = ref.mass_matrix(q)
    assert _rel(M @ got + ref.inverse_dynamics(q, qd, np.zeros_like(q)), tau) <= TOL
    assert _rel(got, want) <= max(TOL, 1e-15 * np.linalg.cond(M))


def _wrenches(m, N, seed):
    """Body wrenches on two links, one per state."""
    rng = np.random.default_rng(seed)
    links = [nm for nm, (b, _) in m.link_frames.items() if b >= 0]
    return {links[-1]: rng.uniform(-2, 2, (N, 6)), links[len(links) // 2]: rng.uniform(-2, 2, (N, 6))}


def _pin_aba_derivatives(oracle, q, qd, tau):
    E = oracle.E
    dq, dv, Minv = pin.computeABADerivatives(oracle.model, oracle.data, oracle.pin_q(q), oracle.pin_v(qd), E @ tau)
    Minv = np.triu(Minv) + np.triu(Minv, 1).T
    return E.T @ dq @ E, E.T @ dv @ E, E.T @ Minv @ E


def _check_fd_derivatives(m, ref, oracle, q, qd, qdd):
    """The looped forward-dynamics derivatives against the Python twin and Pinocchio (where its model
    has our joints: locked joints move in Pinocchio's), one state at a time and as one batch:
    solves with M, to eps cond(M) (at least TOL)."""
    tau = ref.inverse_dynamics(q, qd, qdd)
    D = m.forward_dynamics_derivatives(q, qd, tau)
    for i in range(len(q)):
        s = (q[i], qd[i], tau[i])
        d = m.forward_dynamics_derivatives(*s)
        tol = max(TOL, 1e-15 * np.linalg.cond(ref.mass_matrix(q[i])))
        peers = _pin_aba_derivatives(oracle, *s) if oracle.E.shape[0] == m.n else (None,) * 3
        for k, (want, peer) in enumerate(zip(ref.forward_dynamics_derivatives(*s), peers, strict=True)):
            assert np.array_equal(D[k][i], d[k])
            assert _rel(d[k], want) <= tol
            if peer is not None:
                assert _rel(d[k], peer) <= max(tol, 1e-10)


def _check_derivatives(m, ref, oracle, q, qd, qdd):
    """The looped derivative kernels (ID derivatives, with wrenches, the Coriolis matrix, forward
    dynamics) against the Python twin and Pinocchio, one state at a time and as one batch."""
    _check_fd_derivatives(m, ref, oracle, q, qd, qdd)
    D = m.inverse_dynamics_derivatives(q, qd, qdd)
    C = m.coriolis_matrix(q, qd, method='recursive')
    w = _wrenches(m, len(q), seed=len(q))
    W, Wref = m.inverse_dynamics_derivatives(q, qd, qdd, w), ref.inverse_dynamics_derivatives(q, qd, qdd, w)
    assert _rel(W[0], D[0]) > 1e-6   # the wrenches enter dtau/dq
    for i in range(len(q)):
        d = m.inverse_dynamics_derivatives(q[i], qd[i], qdd[i])
        for k in range(2):
            assert np.array_equal(D[k][i], d[k])
            assert _rel(d[k], ref.inverse_dynamics_derivatives(q[i], qd[i], qdd[i])[k]) <= TOL
            assert _rel(d[k], oracle.rnea_derivatives(q[i], qd[i], qdd[i])[k]) <= TOL
            assert _rel(W[k][i], Wref[k][i]) <= TOL
        c = m.coriolis_matrix(q[i], qd[i], method='recursive')
        assert np.array_equal(C[i], c)
        assert _rel(c, ref.coriolis_matrix(q[i], qd[i], method='recursive')) <= TOL
        assert _rel(c, oracle.coriolis_matrix(q[i], qd[i])) <= TOL


def _check_all(m, ref, oracle, q, qd, qdd):
    """Every looped family of m on states (N, n) against the Python twin and Pinocchio, one state
    at a time and as one batch (the batch's rows equal the single calls)."""
    tau = ref.inverse_dynamics(q, qd, qdd)
    M = m.mass_matrix(q)
    A = m.forward_dynamics(q, qd, tau, method='aba')
    C = m.forward_dynamics(q, qd, tau)
    _check_derivatives(m, ref, oracle, q, qd, qdd)
    for i in range(len(q)):
        s = (q[i], qd[i], tau[i])
        Mi = m.mass_matrix(q[i])
        assert np.array_equal(M[i], Mi)
        assert _rel(Mi, ref.mass_matrix(q[i])) <= TOL
        assert _rel(Mi, oracle.crba(q[i])) <= TOL
        a = m.forward_dynamics(*s, method='aba')
        assert np.array_equal(A[i], a)
        assert np.array_equal(C[i], m.forward_dynamics(*s))
        for got in (a, C[i]):
            _check_solve(got, ref.forward_dynamics(*s, method='aba'), ref, *s)
            _check_solve(got, oracle.aba(*s), ref, *s)


def test_looped_kernels_run_and_agree(robot):
    m, ref = robot.model, robot.ref
    for spec in (t_crba.MASS_MATRIX, t_aba.spec(m)) + DERIVATIVES:
        assert runtime.looped(m, spec) and not runtime.looped(ref, spec)
        assert runtime.native(m, spec) is not None
    _check_all(m, ref, robot.oracle, *_states(m, 4, seed=1))


def test_out_buffers(robot):
    m, ref = robot.model, robot.ref
    q, qd, qdd = _states(m, 3, seed=2)
    buf = np.empty((3, m.n, m.n))
    assert m.mass_matrix(q, out=buf) is buf
    assert _rel(buf, ref.mass_matrix(q)) <= TOL
    tau = ref.inverse_dynamics(q, qd, qdd)
    one = np.empty(m.n)
    assert m.forward_dynamics(q[0], qd[0], tau[0], method='aba', out=one) is one
    assert np.array_equal(one, m.forward_dynamics(q[0], qd[0], tau[0], method='aba'))
    with pytest.raises(ValueError, match='out must be'):
        m.mass_matrix(q[0], out=np.empty((m.n, m.n + 1)))


def test_parameters_change_without_recompiling(robot):
    m, ref = robot.model, robot.ref
    q, qd, qdd = _states(m, 2, seed=3)
    _check_all(m, ref, robot.oracle, q, qd, qdd)
    before = native.compile_count()
    with payload_and_gravity((m, ref)):
        tau = ref.inverse_dynamics(q, qd, qdd)
        for i in range(len(q)):
            assert _rel(m.mass_matrix(q[i]), ref.mass_matrix(q[i])) <= TOL
            for k in range(2):
                assert _rel(m.inverse_dynamics_derivatives(q[i], qd[i], qdd[i])[k],
                            ref.inverse_dynamics_derivatives(q[i], qd[i], qdd[i])[k]) <= TOL
            assert _rel(m.coriolis_matrix(q[i], qd[i], method='recursive'),
                        ref.coriolis_matrix(q[i], qd[i], method='recursive')) <= TOL
            s = (q[i], qd[i], tau[i])
            tol = max(TOL, 1e-15 * np.linalg.cond(ref.mass_matrix(q[i])))
            for got, want in zip(m.forward_dynamics_derivatives(*s), ref.forward_dynamics_derivatives(*s), strict=True):
                assert _rel(got, want) <= tol
            for method in ('aba', 'cholesky'):
                s = (q[i], qd[i], tau[i])
                _check_solve(m.forward_dynamics(*s, method=method), ref.forward_dynamics(*s, method='aba'), ref, *s)
    assert native.compile_count() == before


def test_armature(robot):
    """The armature: a parameter of the looped M, the ABA's other variant (one more kernel)."""
    m, ref = robot.model, robot.ref
    q, qd, qdd = _states(m, 2, seed=4)
    arm = np.linspace(0.05, 0.3, m.n)
    try:
        for x in (m, ref):
            x.set_armature(arm)
        assert runtime.looped(m, t_aba.spec(m)) and t_aba.spec(m) is t_aba.ABA
        tau = ref.inverse_dynamics(q, qd, qdd)
        for i in range(len(q)):
            assert _rel(m.mass_matrix(q[i]), ref.mass_matrix(q[i])) <= TOL
            s = (q[i], qd[i], tau[i])
            _check_solve(m.forward_dynamics(*s, method='aba'), ref.forward_dynamics(*s, method='aba'), ref, *s)
            tol = max(TOL, 1e-15 * np.linalg.cond(ref.mass_matrix(q[i])))
            for got, want in zip(m.forward_dynamics_derivatives(*s), ref.forward_dynamics_derivatives(*s), strict=True):
                assert _rel(got, want) <= tol
    finally:
        for x in (m, ref):
            x.set_armature(np.zeros(m.n))


def test_locked_joints_change_without_recompiling(looped_everywhere):
    xml = random_urdf(33, 8)
    names = _load(xml).joint_names
    part = Robot(xml, joints=names[::2])
    m = part.model
    assert len(m.locked_joint_names) == len(names) - m.n
    q, qd, qdd = _states(m, 2, seed=5)
    _check_all(m, part.ref, part.oracle, q, qd, qdd)
    compiled = native.compile_count()
    values = {j: 0.2 + 0.05 * k for k, j in enumerate(m.locked_joint_names)}
    for x in (m, part.ref):
        x.set_locked(values)
    oracle = Oracle(xml, joints=m.joint_names, locked=m.locked_values)
    _check_all(m, part.ref, oracle, q, qd, qdd)
    assert native.compile_count() == compiled


def test_looped_equals_straight_line(looped_everywhere):
    """The looped and the straight-line C forms of the same traces, one model each."""
    xml = random_urdf(34, 6, tree=True)
    m = _load(xml)
    T = runtime.THRESHOLDS
    saved = {k: T[k] for k in LIMITS}
    try:
        for k in LIMITS:
            T[k] = T[k]._replace(looped_from=None)
        straight = _load(xml)
        q, qd, qdd = _states(m, 3, seed=6)
        tau = straight.inverse_dynamics(q, qd, qdd)
        M, A = straight.mass_matrix(q), straight.forward_dynamics(q, qd, tau, method='aba')
        D = straight.inverse_dynamics_derivatives(q, qd, qdd)
        C = straight.coriolis_matrix(q, qd, method='recursive')
        assert not runtime.looped(straight, t_crba.MASS_MATRIX)
        assert not any(runtime.looped(straight, s) for s in DERIVATIVES)
    finally:
        T.update(saved)
    assert runtime.looped(m, t_crba.MASS_MATRIX)
    assert _rel(m.mass_matrix(q), M) <= TOL
    for got, want in zip(m.inverse_dynamics_derivatives(q, qd, qdd), D, strict=True):
        assert _rel(got, want) <= TOL
    assert _rel(m.coriolis_matrix(q, qd, method='recursive'), C) <= TOL
    assert _rel(m.forward_dynamics(q, qd, tau, method='aba'), A) <= max(TOL, 1e-15 * max(
        np.linalg.cond(x) for x in M))


def test_mimic_joints_keep_todays_routes(looped_everywhere):
    """Mimic joints couple bodies: no looped form (looped.joints_of), the straight-line kernel runs."""
    xml = random_urdf(35, 6, mimic=True)
    m = _load(xml)
    assert not t_aba.supports(m)   # a mimic joint was drawn
    assert not runtime.looped(m, t_crba.MASS_MATRIX)
    assert not any(runtime.looped(m, s) for s in DERIVATIVES)
    assert all(s.looped(runtime.frames(m)) is None for s in DERIVATIVES)
    ref = _load(xml)
    runtime.use_native(ref, False)
    q = _states(m, 1, seed=7)[0][0]
    assert _rel(m.mass_matrix(q), ref.mass_matrix(q)) <= TOL
    assert _rel(m.mass_matrix(q), Oracle(xml, joints=m.joint_names).crba(q)) <= TOL
    for got, want in zip(m.inverse_dynamics_derivatives(q, q, q), ref.inverse_dynamics_derivatives(q, q, q),
                         strict=True):
        assert _rel(got, want) <= TOL


def test_looped_kernels_load_from_the_disk_cache(looped_everywhere):
    """A second process (here: the runtime cleared) loads the looped library without compiling or
    rendering it again; its key differs from the straight-line kernel's (another name)."""
    xml = random_urdf(36, 5)
    q = _states(_load(xml), 1, seed=8)[0][0]
    m = _load(xml)
    first = m.mass_matrix(q), m.coriolis_matrix(q, q, method='recursive')
    runtime.clear()
    compiled, rendered = native.compile_count(), kernel.builds()
    m = _load(xml)
    assert np.array_equal(m.mass_matrix(q), first[0])
    assert np.array_equal(m.coriolis_matrix(q, q, method='recursive'), first[1])
    assert native.compile_count() == compiled and kernel.builds() == rendered
    assert runtime.looped(m, t_crba.MASS_MATRIX) and runtime.looped(m, t_der.CORIOLIS)


def test_looped_from_counts_pairs_and_takes_over_above_the_caps():
    """The mass matrix's looped_from counts (body, ancestor) pairs; above the straight-line caps
    the looped form runs whatever looped_from says."""
    T = runtime.THRESHOLDS
    saved = T['mass_matrix']
    xml = random_urdf(37, 5)   # a chain: 15 pairs
    try:
        for limits, want in ((saved._replace(looped_from=15), True), (saved._replace(looped_from=16), False),
                             (saved._replace(looped_from=10 ** 6, compile_max=2, native_max=4), True)):
            T['mass_matrix'] = limits
            m = _load(xml)
            assert runtime.pairs(m) == 15
            assert runtime.looped(m, t_crba.MASS_MATRIX) == want, limits
            q = _states(m, 1, seed=9)[0][0]
            assert _rel(m.mass_matrix(q), Oracle(xml, joints=m.joint_names).crba(q)) <= TOL
    finally:
        T['mass_matrix'] = saved
        runtime.clear()


def test_forward_dynamics_derivatives_decline_a_singular_mass_matrix(looped_everywhere):
    """A massless tip (M singular): the looped kernel's pivots (M = L^T D L) fail the test, state by
    state and in batches, and the reference names the problem."""
    from test_forward_dynamics import MASSLESS_TIP
    m = _load(MASSLESS_TIP)
    assert runtime.looped(m, t_der.FORWARD_DYNAMICS_DERIVATIVES)
    z = np.zeros(2)
    assert runtime.native(m, t_der.FORWARD_DYNAMICS_DERIVATIVES)(np.array([0.1, 0.2]), z, z) is None
    with pytest.raises(ValueError, match='mass matrix is not positive definite'):
        m.forward_dynamics_derivatives(np.array([0.1, 0.2]), z, z)
    for N in (3, 60):
        with pytest.raises(ValueError, match='mass matrix is not positive definite at state 0'):
            m.forward_dynamics_derivatives(np.zeros((N, 2)), np.zeros((N, 2)), np.zeros((N, 2)))


def test_derivative_kernels_out_buffers(robot):
    """The bound looped derivative kernels write into a good `out` (single states and batches) what
    they return otherwise, and decline a bad one (None: the validating path then names it)."""
    m = robot.model
    q, qd, qdd = _states(m, 3, seed=10)
    tau = robot.ref.inverse_dynamics(q, qd, qdd)
    for spec, args in ((t_der.INVERSE_DYNAMICS_DERIVATIVES, (q, qd, qdd)), (t_der.CORIOLIS, (q, qd)),
                       (t_der.FORWARD_DYNAMICS_DERIVATIVES, (q, qd, tau))):
        fn = runtime.native(m, spec)
        for a in ([x[0] for x in args], list(args)):
            want = fn(*a)
            buf = np.full(want.shape, np.nan)
            assert fn(*a, buf) is buf and np.array_equal(buf, want), spec.name
            for bad in (np.empty(want.shape, np.float32), np.empty(want.shape[:-1] + (want.shape[-1] + 1,))):
                assert fn(*a, bad) is None


def test_talos_reduced_derivatives(looped_everywhere):
    """Every looped derivative family on a real humanoid (Talos reduced, 32 bodies, example-robot-data)
    against the Python kernels and Pinocchio, single states and a batch."""
    from dyn_cases import ERD_ROBOTS
    if ERD_ROBOTS is None:
        pytest.skip('example-robot-data is not installed')
    with open(f'{ERD_ROBOTS}/talos_data/robots/talos_reduced.urdf', encoding='utf-8') as fh:
        talos = Robot(fh.read())
    m = talos.model
    assert m.nb >= 30 and all(runtime.looped(m, s) for s in DERIVATIVES)
    _check_derivatives(m, talos.ref, talos.oracle, *_states(m, 2, seed=11))
