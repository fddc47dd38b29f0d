"""lie_dynamics.laws: each torque law against its formula written with the model's M, C and g;
the smooth friction compensation; the clamp (limits, inf, NaN, batches); and the one friction
shared by the streaming node and the trajectory fill."""
import math
import os
import warnings

import numpy as np
import pytest

from lie_dynamics import load_urdf
from lie_dynamics.laws import (COULOMB_VELOCITY_EPSILON, LAWS, MODES, EffortLimits, Friction, add_friction, clamp,
                               computed_torque_law, effort_limits, feedback, feedforward_law, friction_torque,
                               gravity_law, make_friction, pd_law, torque, uses_velocity)
from lie_dynamics.ros.core.compensator import Compensator
from lie_dynamics.ros.core.params import defaults
from lie_dynamics.trajectory import fill_trajectory_efforts
from core_cases import Clock, big_limits, fill_trajectory, make
from test_feedforward_core import point

TOL = 1e-9
ARM = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), 'config', 'arm7.urdf')


@pytest.fixture(scope='module')
def arm():
    """The bundled 7-DoF arm (its URDF has damping and friction on every joint)."""
    return load_urdf(ARM)


@pytest.fixture(scope='module')
def case(arm):
    rng = np.random.default_rng(3)
    n = arm.n
    q, qd, q_d, qd_d, qdd_d = rng.uniform(-1, 1, (5, n))
    kp, kd = rng.uniform(1, 50, n), rng.uniform(0.5, 5, n)
    fr = Friction(rng.uniform(0.1, 1, n), rng.uniform(0.1, 1, n), 0.07)
    return q, qd, (q_d, qd_d, qdd_d), kp, kd, fr


def mcg(model, q, qd):
    return model.mass_matrix(q), model.coriolis_matrix(q, qd), model.gravity(q)


def f(fr, v):
    return fr.viscous * v + fr.coulomb * np.tanh(v / fr.eps)


def close(a, b):
    np.testing.assert_allclose(a, b, atol=TOL, rtol=0)


def test_gravity_law(arm, case):
    q, qd, desired, kp, kd, fr = case
    M, C, g = mcg(arm, q, qd)
    close(gravity_law(arm, q), g)
    close(gravity_law(arm, q, qd), g)                                   # velocity terms off
    close(gravity_law(arm, q, qd, desired, kp, kd), g)                  # desired state and gains unused
    close(gravity_law(arm, q, qd, velocity_terms=True), C @ qd + g)
    close(gravity_law(arm, q, qd, friction=fr, velocity_terms=True), C @ qd + g + f(fr, qd))
    close(gravity_law(arm, q, qd, friction=fr), g + f(fr, qd))
    close(gravity_law(arm, q, None, friction=fr, velocity_terms=True), g)  # velocity unavailable: 0


def test_feedforward_law(arm, case):
    q, qd, desired, kp, kd, fr = case
    q_d, qd_d, qdd_d = desired
    Md, Cd, gd = mcg(arm, q_d, qd_d)
    ff = Md @ qdd_d + Cd @ qd_d + gd
    close(feedforward_law(arm, q, qd, desired), ff)
    close(feedforward_law(arm, q, qd, desired, kp, kd, fr), ff + f(fr, qd_d) + kp * (q_d - q) + kd * (qd_d - qd))
    close(feedforward_law(arm, q, qd, desired, kp, None, fr, velocity_terms=True), ff + f(fr, qd_d) + kp * (q_d - q))
    close(feedforward_law(arm, q, None, desired, None, kd), ff + kd * qd_d)   # unavailable velocity: 0


def test_computed_torque_law(arm, case):
    q, qd, desired, kp, kd, fr = case
    q_d, qd_d, qdd_d = desired
    M, C, g = mcg(arm, q, qd)
    v = qdd_d + kp * (q_d - q) + kd * (qd_d - qd)
    close(computed_torque_law(arm, q, qd, desired, kp, kd, fr), M @ v + C @ qd + g + f(fr, qd))
    close(computed_torque_law(arm, q, qd, desired), M @ qdd_d + C @ qd + g)   # C qd without velocity_terms
    close(computed_torque_law(arm, q, None, desired, kp, kd), M @ (qdd_d + kp * (q_d - q) + kd * qd_d) + g)


def test_pd_law(arm, case):
    q, qd, desired, kp, kd, fr = case
    q_d, qd_d, _ = desired
    close(pd_law(arm, q, qd, desired, kp, kd, fr, True), kp * (q_d - q) + kd * (qd_d - qd))   # no friction
    close(pd_law(arm, q, qd, desired, kp), kp * (q_d - q))
    np.testing.assert_array_equal(pd_law(arm, q, qd, desired), np.zeros(arm.n))


def test_dispatch_and_velocity_use(arm, case):
    q, qd, desired, kp, kd, fr = case
    assert set(LAWS) == set(MODES)
    for mode in MODES:
        np.testing.assert_array_equal(torque(mode, arm, q, qd, desired, kp, kd, fr, True),
                                      LAWS[mode](arm, q, qd, desired, kp, kd, fr, True))
    assert not uses_velocity('gravity') and uses_velocity('gravity', velocity_terms=True)
    assert uses_velocity('gravity', friction=fr) and not uses_velocity('gravity', kd=kd)
    assert uses_velocity('computed_torque')
    for mode in ('feedforward', 'pd'):
        assert uses_velocity(mode, kd=kd) and not uses_velocity(mode, friction=fr, velocity_terms=True)


def test_friction_is_smooth_tanh():
    v = np.array([-1.0, -0.05, -0.01, 0.0, 1e-6, 0.01, 0.05, 1.0])
    out = friction_torque(v, 0.5, 0.3)
    np.testing.assert_allclose(out, 0.5 * v + 0.3 * np.tanh(v / COULOMB_VELOCITY_EPSILON), rtol=0, atol=1e-15)
    assert out[3] == 0.0 and 0 < out[4] < 1e-5    # continuous through rest, not sign(v)
    np.testing.assert_allclose(friction_torque(v, None, 0.3, eps=0.5), 0.3 * np.tanh(v / 0.5), rtol=0, atol=1e-15)
    np.testing.assert_array_equal(friction_torque(v), np.zeros_like(v))
    # a batch (N, n) with per-joint coefficients
    V = np.outer([-0.2, 0.0, 0.3], [1.0, 2.0])
    b, fc = np.array([0.1, 0.2]), np.array([1.0, 3.0])
    np.testing.assert_allclose(friction_torque(V, b, fc, 0.1), b * V + fc * np.tanh(V / 0.1), rtol=0, atol=1e-15)
    tau = np.ones(2)
    assert add_friction(tau, V[0], None) is tau and add_friction(tau, None, Friction(b, fc)) is tau
    close(add_friction(tau, V[2], Friction(b, fc, 0.1)), tau + friction_torque(V[2], b, fc, 0.1))
    assert make_friction([0.0, 0.0], [0.0, 0.0]) is None and make_friction() is None
    fr = make_friction([0.1, 0.0], None, 0.2)
    assert fr.coulomb is None and fr.eps == 0.2 and fr.viscous.tolist() == [0.1, 0.0]


def test_clamp_limits_inf_and_nan():
    lim = effort_limits([1.0, 2.0, math.inf], 0.5)
    assert isinstance(lim, EffortLimits) and lim.limit.tolist() == [0.5, 1.0, math.inf]
    tau = np.array([0.4, -1.0, 1e300])
    out, over = clamp(tau, lim)
    assert out is tau and over is None                                    # within: untouched
    out, over = clamp(np.array([0.7, -3.0, 5.0]), lim)
    assert out.tolist() == [0.5, -1.0, 5.0] and over.tolist() == [True, True, False]
    out, over = clamp(np.array([-math.inf, 0.0, 0.0]), lim)               # inf with a finite limit: clipped
    assert out.tolist() == [-0.5, 0.0, 0.0] and over.tolist() == [True, False, False]
    out, over = clamp(np.array([0.0, 0.0, math.inf]), lim)                # inf without a limit: never out
    assert out is None and over is None
    out, over = clamp(np.array([math.nan, 0.0, 0.0]), lim)                # NaN: never out
    assert out is None and over is None
    out, over = clamp(np.array([math.nan, 5.0, 0.0]), lim)                # ... also when another joint clamps
    assert out is None and over.tolist() == [False, True, False]
    # scale 0: every limited joint clamped to 0; a missing limit stays unlimited (inf * 0)
    zero = effort_limits([1.0, math.inf], 0.0)
    assert zero.limit.tolist() == [0.0, math.inf]
    out, over = clamp(np.array([0.3, -7.0]), zero)
    assert out.tolist() == [0.0, -7.0] and over.tolist() == [True, False]
    # a batch (N, n) and plain per-joint limits
    T = np.array([[0.2, 3.0], [-2.0, 0.1], [0.0, 0.0]])
    out, over = clamp(T, [1.0, 1.0])
    assert out.tolist() == [[0.2, 1.0], [-1.0, 0.1], [0.0, 0.0]]
    assert over.tolist() == [[False, True], [True, False], [False, False]]


@pytest.mark.parametrize('mode', MODES)
def test_absurd_gains_give_limited_or_no_torque_without_numpy_warnings(arm, mode):
    """kp = kd = friction = 1e308: products overflow to +-inf (or NaN) silently; the node publishes
    the limit or nothing, never a non-finite or over-limit value, and numpy says nothing on stderr."""
    with open(ARM) as fh:
        xml = fh.read()
    ctrl = list(arm.joint_names)
    huge = [1e308]
    with warnings.catch_warnings():
        warnings.simplefilter('error')   # a numpy RuntimeWarning would raise here
        c = make(xml, ctrl, mode=mode, kp=huge, kd=huge, include_velocity_terms=True,
                 **{'friction.viscous': huge, 'friction.coulomb': huge})
        assert c.on_desired(ctrl, [point(np.full(arm.n, 2.0), np.full(arm.n, -3.0))])
        lim = arm.effort_limits
        answered = 0
        for q, qd in ((np.zeros(arm.n), np.full(arm.n, 3.0)), (np.full(arm.n, -1.0), np.zeros(arm.n)),
                      (np.zeros(arm.n), np.full(arm.n, -5.0)), (np.zeros(arm.n), np.full(arm.n, 1e308))):
            tau = c.on_joint_state(ctrl, q, qd)
            if tau is not None:
                answered += 1
                assert np.all(np.isfinite(tau)) and np.all(np.abs(tau) <= lim), tau
        assert answered < 4   # the NaN cases (inf - inf) are refused
        # the library functions themselves
        e = feedback(np.zeros(2), np.zeros(2), (np.full(2, 2.0), np.full(2, -2.0)), np.full(2, 1e308), None)
        assert np.all(np.isinf(e))
        assert np.all(np.isinf(friction_torque(np.array([1e308, -1e308]), 2.0, 1.0)))


def test_trajectory_fill_and_streaming_node_use_the_same_friction(arm):
    """Coulomb friction is fc*tanh(v/eps) both in the streamed commands and in trajectory efforts
    (fill_trajectory_efforts(friction=True), and the node's ~/trajectory_in path)."""
    xml = big_limits(open(ARM).read())
    model = load_urdf(xml)
    n = model.n
    q = np.linspace(-0.6, 0.6, n)
    v = np.array([0.01, -0.02, 0.03, 0.005, -0.04, 0.1, -0.001])   # small: tanh and sign differ
    for eps in (defaults()['friction.coulomb_velocity_epsilon'], 0.2):
        ref = model.damping * v + model.friction * np.tanh(v / eps)
        assert not np.allclose(ref, model.damping * v + model.friction * np.sign(v))
        c = Compensator({'friction.coulomb_velocity_epsilon': eps}, clock=Clock())   # friction from the URDF
        c.set_model(load_urdf(xml))
        streamed = c.on_joint_state(model.joint_names, q, v) - model.gravity(q)
        traj = {'positions': q[None], 'velocities': v[None], 'accelerations': np.zeros((1, n))}
        filled = fill_trajectory_efforts(model, traj, friction=True, eps=eps)['efforts'][0]
        filled -= model.inverse_dynamics(q, v, np.zeros(n))
        close(streamed, ref)
        close(filled, ref)
        point = type('Point', (), dict(positions=list(q), velocities=list(v), accelerations=[0.0] * n, effort=[],
                                       time_from_start=type('T', (), dict(sec=0, nanosec=0))))
        node_traj = fill_trajectory(c, model.joint_names, [point])[0] - model.inverse_dynamics(q, v, np.zeros(n))
        close(node_traj, ref)
    with pytest.raises(ValueError, match='eps'):
        fill_trajectory_efforts(model, traj, friction=True, eps=0.0)


def test_stale_action_is_clamped_and_counted_like_commands():
    """The stale action goes through the same clamp as the streamed command (and is counted)."""
    xml = big_limits(open(ARM).read(), '2.0')
    joints = [f'joint{i}' for i in range(1, 8)]
    clock = Clock()
    c = make(xml, joints, clock=clock, effort_limit_scale=0.5, stale_timeout=0.1)
    q = np.full(7, 0.7)
    tau = c.on_joint_state(joints, q)
    g = c.model.gravity(q)
    assert np.any(np.abs(g) > 1.0)
    close(tau, np.clip(g, -1.0, 1.0))
    assert c.count.clamp_count == 1
    clock.t += 1.0
    close(c.tick(), np.clip(g, -1.0, 1.0))
    assert c.count.clamp_count == 2 and [e[1] for e in c.events].count('clamp') == 2
