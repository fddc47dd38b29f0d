"""Stability claims that matter to users, as regression tests (bench/stability.py maps them in full).

References are the same quantities in numpy.longdouble (bench/reference.py, 80-bit on x86-64).
Bounds are the measured values times a margin of about 10 (stated per test).
"""
import numpy as np
import pytest

from bench import common, reference
from bench.common import rel_err
from bench.reference import LD, Generic
from lie_dynamics import InertiaWarning, load_urdf, spatial as se3
from lie_dynamics.sim.demo import HOME
from lie_dynamics.sim.integrators import STEPPERS, lie_midpoint
from lie_dynamics.sim.arm import ArmSim

PI_LD = np.longdouble('3.14159265358979323846264338327950288')
pytestmark = pytest.mark.skipif(np.finfo(np.longdouble).eps > 1e-18,
                                reason='needs an extended-precision numpy.longdouble (x86-64)')


def _axes(k=50, seed=0):
    rng = np.random.default_rng(seed)
    u = rng.normal(size=(k, 3))
    v = rng.normal(size=(k, 3))
    return ((u / np.linalg.norm(u, axis=1, keepdims=True)).astype(LD),
            (v / np.linalg.norm(v, axis=1, keepdims=True)).astype(LD))


# ---------------------------------------------------------------- exp / log
@pytest.mark.parametrize('theta', [LD('1e-12'), PI_LD - LD('1e-9'), LD('1e-2') * (1 - LD('1e-12')), LD('1e-2')],
                         ids=['1e-12', 'pi-1e-9', 'below-series-switch', 'series-switch'])
def test_exp_log_full_precision_near_singular_angles(theta):
    """exp/log of SO(3) and SE(3) to 1e-14 at theta = 1e-12 and pi - 1e-9 (measured: <= 1e-15; the
    textbook closed forms give NaN at 1e-12 and 1e-7 relative error at pi - 1e-9)."""
    u, v = _axes()
    w = theta * u
    T = reference.exp6_ld(w, v)
    Tin = T.astype(float)
    assert np.max(rel_err(se3.exp3(w.astype(float)), T[:, :3, :3], axis=(1, 2))) < 1e-14
    assert np.max(rel_err(se3.exp6(np.concatenate([w, v], 1).astype(float)), T, axis=(1, 2))) < 1e-14
    assert np.max(rel_err(se3.log3(Tin[:, :3, :3]), w, axis=1)) < 1e-14
    assert np.max(rel_err(se3.log6(Tin), np.concatenate([w, v], 1), axis=1)) < 1e-14


def test_exp_log_exact_at_zero():
    assert np.array_equal(se3.exp3(np.zeros(3)), np.eye(3))
    assert np.array_equal(se3.exp6(np.zeros(6)), np.eye(4))
    assert np.array_equal(se3.log3(np.eye(3)), np.zeros(3))
    assert np.array_equal(se3.log6(np.eye(4)), np.zeros(6))


# ---------------------------------------------------------------- long chains
@pytest.fixture(scope='module')
def chain200():
    xml = common.robot_urdf(200, seed=1200)
    model = load_urdf(xml)
    q, qd, qdd = common.random_states(model, 4, seed=200)
    return model, (q, qd, qdd), Generic(model, LD).inverse_dynamics(q, qd, qdd)


def test_rnea_float64_error_on_200_joint_chain(chain200):
    """Float64 RNEA on a random 200-joint chain stays within 2e-13 (1000 ulps) of the longdouble
    result, relative to the largest torque (measured: 3e-14 on the single-state path, which is the
    vectorised root-frame form at this size, 1.4e-14 in the batched kernels; error grows ~n)."""
    model, (q, qd, qdd), ref = chain200
    single = np.array([model.inverse_dynamics(q[i], qd[i], qdd[i]) for i in range(len(q))])
    assert np.max(rel_err(single, ref, axis=1)) < 2e-13
    batch = model.inverse_dynamics(*(np.resize(a, (64, model.n)) for a in (q, qd, qdd)))[:len(q)]
    assert np.max(rel_err(batch, ref, axis=1)) < 2e-13


def test_generic_reference_agrees_with_the_library(chain200):
    """The longdouble reference is the same algorithm as the library (sanity check of the oracle)."""
    model, (q, qd, qdd), ref = chain200
    assert np.max(rel_err(model.inverse_dynamics(q, qd, qdd), ref, axis=1)) < 1e-13
    assert Generic(model, np.float32).inverse_dynamics(q, qd, qdd).dtype == np.float32


# ---------------------------------------------------------------- forward dynamics
def _fd_errors(xml, S=3):
    model = load_urdf(xml)
    q, qd, qdd0 = common.random_states(model, S, seed=3)
    tau = model.inverse_dynamics(q, qd, qdd0)
    with np.errstate(all='ignore'):   # the reference divides by zero where M is singular
        ref = Generic(model, LD).forward_dynamics(q, qd, tau)
    out = {}
    for method in ('cholesky', 'aba'):
        try:
            out[method] = float(np.max(rel_err(model.forward_dynamics(q, qd, tau, method=method), ref, axis=1)))
        except ValueError as exc:
            out[method] = exc
    return out


@pytest.mark.parametrize('tilt', [0.0, 1e-7, 1e-6])
def test_forward_dynamics_raises_when_mass_matrix_is_numerically_singular(tilt):
    """Two (nearly) coaxial joints with a massless link between: M singular or cond > 1e13.
    Both methods raise ValueError (an explicit inverse returns 1e-3 errors here, silently)."""
    for method, res in _fd_errors(common.near_coaxial_urdf(tilt)).items():
        assert isinstance(res, ValueError), (method, res)
        assert 'moves no mass' in str(res)


def test_forward_dynamics_massless_distal_link_raises():
    xml = common.scale_chain_masses(common.arm_xml(), 0.0)
    with pytest.warns(InertiaWarning, match='massless moving body'):   # load_urdf says so first
        errors = _fd_errors(xml)
    for method, res in errors.items():
        assert isinstance(res, ValueError), (method, res)


def test_forward_dynamics_never_returns_large_errors_silently():
    """Scanning the tilt down to singular: whatever is returned (not raised) is within 1e-3
    (measured worst 9e-5, at cond(M) ~ 1e12 just before the methods start raising)."""
    for tilt in 10.0 ** -np.arange(1, 8.5, 0.5):
        for method, res in _fd_errors(common.near_coaxial_urdf(tilt), S=2).items():
            assert isinstance(res, ValueError) or res < 1e-3, (tilt, method, res)


@pytest.mark.parametrize('method', ['cholesky', 'aba'])
def test_forward_dynamics_accurate_with_mass_ratio_1e_minus_10(method):
    """Masses graded 1 : 1e-10 along the arm (cond(M) ~ 4e10): ill-conditioned by scale only, so
    both methods stay at ~1e-13 (bound 1e-12)."""
    res = _fd_errors(common.scale_chain_masses(common.arm_xml(), 1e-10))[method]
    assert not isinstance(res, Exception) and res < 1e-12


@pytest.mark.parametrize('method', ['cholesky', 'aba'])
@pytest.mark.parametrize('ratio, massless', [(1e-13, False), (1e-30, True)])
def test_forward_dynamics_graded_masses_are_not_rejected(method, ratio, massless):
    """Scale alone (cond(M) far past 1e12) is no reason to refuse: each Cholesky pivot is judged
    against its own diagonal entry, so only near-dependent joints raise."""
    xml = common.scale_chain_masses(common.arm_xml(), ratio)
    if massless:   # the distal subtree is below 1e-12 of the inertia scale (Model.massless_joints): load_urdf warns
        with pytest.warns(InertiaWarning, match='massless moving body'):
            res = _fd_errors(xml)[method]
    else:
        res = _fd_errors(xml)[method]
    assert not isinstance(res, Exception), res
    assert res < 1e-10


# ---------------------------------------------------------------- derivatives
def test_analytic_derivatives_exact_to_rounding():
    """dtau/dq, dtau/dqd to 1e-13 of a longdouble complex-step reference (measured ~1e-15;
    the best central difference reaches ~1e-10)."""
    model = load_urdf(common.arm_xml())
    q, qd, qdd = common.random_states(model, 4, seed=4)
    dq, dv = Generic(model, np.clongdouble).derivatives(q, qd, qdd)
    a, b = model.inverse_dynamics_derivatives(q, qd, qdd)
    assert np.max(rel_err(np.concatenate([a, b], 1).reshape(4, -1), np.concatenate([dq, dv], 1).reshape(4, -1),
                          axis=1)) < 1e-13


# ---------------------------------------------------------------- integrators
@pytest.fixture(scope='module')
def arm():
    return load_urdf(common.arm_xml())


def test_lie_midpoint_is_time_reversible(arm):
    """The implicit midpoint rule is symmetric: 40 steps forward and 40 back return to the start."""
    q0, qd0 = np.array(HOME), np.linspace(-1, 1, arm.n)
    q, qd = q0, qd0
    for dt in (5e-3, -5e-3):
        for _ in range(40):
            q, qd = lie_midpoint(arm, q, qd, dt)
    assert np.max(np.abs(q - q0)) < 1e-11 and np.max(np.abs(qd - qd0)) < 1e-10


def test_lie_midpoint_energy_error_far_below_semi_implicit_euler(arm):
    """0.3 s of free fall at dt = 5 ms (no damping): the symplectic midpoint's energy error is
    3.6e-3 J, the sim's default semi-implicit Euler 0.6 J (bounds: 0.05 J and 10x apart)."""
    err = {}
    for name in ('semi_implicit_euler', 'lie_midpoint'):
        sim = ArmSim(arm, dt=5e-3, q0=HOME, qd0=np.linspace(-1, 1, arm.n), damping=False, limits=False,
                     integrator=name)
        e0, worst = sim.energy(), 0.0
        for _ in range(60):
            sim.step()
            worst = max(worst, abs(sim.energy() - e0))
        err[name] = worst
    assert err['lie_midpoint'] < 0.05
    assert err['semi_implicit_euler'] > 10 * err['lie_midpoint']


def test_sim_integrator_option(arm):
    assert set(STEPPERS) == {'explicit_euler', 'semi_implicit_euler', 'rk4', 'lie_midpoint'}
    with pytest.raises(ValueError, match='unknown integrator'):
        ArmSim(arm, integrator='leapfrog')
    sim = ArmSim(arm, dt=1e-3, q0=HOME, integrator='rk4')
    sim.step(3)
    assert np.all(np.isfinite(sim.q)) and sim.t == pytest.approx(3e-3)
