"""Feedforward / computed-torque / PD laws, the desired-state stream and trajectory effort fill
in the node's decision logic without ROS (lie_dynamics.ros.core.compensator), checked against Pinocchio."""
import math
from types import SimpleNamespace as NS

import numpy as np
import pytest

from lie_dynamics import load_urdf
from lie_dynamics.ros.core.compensator import OK, WARN, Compensator
from lie_dynamics.ros.core.params import check_value
from lie_dynamics.ros.trajectories.fill import TrajectoryInput
from lie_dynamics.ros.trajectories.trajectory_msgs import set_point_efforts, trajectory_arrays, trajectory_message
from oracle import Oracle
from core_cases import Clock, big_limits, fill_trajectory, make
from robots import random_urdf

TOL = 1e-9


@pytest.fixture(scope='module')
def chain():
    """5 revolute joints; joints[1] is not controlled (locked, fed by joint_states)."""
    xml = big_limits(random_urdf(33, 5, joint_types=('revolute',), mimic=False))
    names = load_urdf(xml).joint_names
    return xml, [names[0]] + names[2:], names[1]


def point(q=(), qd=(), qdd=(), t=0.0):
    sec = int(t)
    return NS(positions=list(q), velocities=list(qd), accelerations=list(qdd), effort=[],
              time_from_start=NS(sec=sec, nanosec=int(round((t - sec) * 1e9))))


def states(n, seed):
    rng = np.random.default_rng(seed)
    return [rng.uniform(-1.5, 1.5, n) for _ in range(5)]


def test_feedforward_is_inverse_dynamics_at_the_desired_state(chain):
    xml, ctrl, locked = chain
    n = len(ctrl)
    c = make(xml, ctrl, mode='feedforward')
    q, qd, q_d, qd_d, qdd_d = states(n, 1)
    names = ['unrelated', locked] + ctrl[::-1]   # any order; other names are ignored
    assert c.on_desired(names, [point([9.0, 9.0] + q_d[::-1].tolist(), [0.0, 0.0] + qd_d[::-1].tolist(),
                                      [0.0, 0.0] + qdd_d[::-1].tolist())])
    tau = c.on_joint_state(ctrl + [locked], list(q) + [0.4], list(qd) + [0.0])
    ref = Oracle(xml, joints=ctrl, locked={locked: 0.4}).rnea(q_d, qd_d, qdd_d)   # locked: measured value
    np.testing.assert_allclose(tau, ref, atol=TOL, rtol=0)
    assert c.law == 'feedforward' and not c.desired_fallback
    # velocities / accelerations absent: zeros
    assert c.on_desired(ctrl, [point(q_d)])
    tau = c.on_joint_state(ctrl + [locked], list(q) + [0.4])
    np.testing.assert_allclose(tau, Oracle(xml, joints=ctrl, locked={locked: 0.4}).gravity(q_d), atol=TOL, rtol=0)
    # gravity_scale scales the g term only
    assert c.on_desired(ctrl, [point(q_d, qd_d, qdd_d)])
    c.update({'gravity_scale': 0.25})
    tau = c.on_joint_state(ctrl + [locked], list(q) + [0.4])
    o = Oracle(xml, joints=ctrl, locked={locked: 0.4}, gravity=(0.0, 0.0, -9.81 * 0.25))
    np.testing.assert_allclose(tau, o.rnea(q_d, qd_d, qdd_d), atol=TOL, rtol=0)


def test_feedforward_with_pd_and_friction_at_the_desired_velocity(chain):
    xml, ctrl, locked = chain
    n = len(ctrl)
    kp, kd = np.linspace(10, 50, n), np.linspace(1, 3, n)
    c = make(xml, ctrl, mode='feedforward', kp=kp.tolist(), kd=kd.tolist(),
             **{'friction.viscous': [0.3], 'friction.coulomb': [0.2]})
    q, qd, q_d, qd_d, qdd_d = states(n, 2)
    c.on_desired(ctrl, [point(q_d, qd_d, qdd_d)])
    tau = c.on_joint_state(ctrl, q, qd)
    eps = c.settings['friction.coulomb_velocity_epsilon']
    ref = (Oracle(xml, joints=ctrl).rnea(q_d, qd_d, qdd_d) + 0.3 * qd_d + 0.2 * np.tanh(qd_d / eps)
           + kp * (q_d - q) + kd * (qd_d - qd))
    np.testing.assert_allclose(tau, ref, atol=TOL, rtol=0)
    # NaN measured velocity of one joint: used as 0 in the D term
    qd_nan = qd.copy()
    qd_nan[2] = math.nan
    tau = c.on_joint_state(ctrl, q, qd_nan)
    np.testing.assert_allclose(tau[2], ref[2] + kd[2] * qd[2], atol=TOL, rtol=0)
    assert c.count.velocity_unavailable == 1


def test_computed_torque_law(chain):
    xml, ctrl, locked = chain
    n = len(ctrl)
    kp, kd = np.full(n, 100.0), np.linspace(5, 20, n)
    c = make(xml, ctrl, mode='computed_torque', kp=[100.0], kd=kd.tolist())
    q, qd, q_d, qd_d, qdd_d = states(n, 3)
    c.on_desired(ctrl, [point(q_d, qd_d, qdd_d)])
    tau = c.on_joint_state(ctrl + [locked], list(q) + [-0.3], list(qd) + [0.0])
    o = Oracle(xml, joints=ctrl, locked={locked: -0.3})
    ref = o.crba(q) @ (qdd_d + kp * (q_d - q) + kd * (qd_d - qd)) + o.rnea(q, qd, np.zeros(n))
    np.testing.assert_allclose(tau, ref, atol=TOL, rtol=0)
    # computed torque always has C(q, qd) qd, also without include_velocity_terms, and friction at qd
    c.update({'friction.viscous': [0.5]})
    tau = c.on_joint_state(ctrl + [locked], list(q) + [-0.3], list(qd) + [0.0])
    np.testing.assert_allclose(tau, ref + 0.5 * qd, atol=TOL, rtol=0)


def test_pd_law_has_no_model_terms(chain):
    xml, ctrl, locked = chain
    n = len(ctrl)
    c = make(xml, ctrl, mode='pd', kp=np.arange(1.0, n + 1).tolist(), kd=[2.0],
             **{'friction.viscous': [0.5]}, gravity_scale=1.0)
    q, qd, q_d, qd_d, _ = states(n, 4)
    c.on_desired(ctrl, [point(q_d, qd_d)])
    tau = c.on_joint_state(ctrl, q, qd)
    np.testing.assert_allclose(tau, np.arange(1.0, n + 1) * (q_d - q) + 2.0 * (qd_d - qd), atol=TOL, rtol=0)
    c.update({'kp': [0.0], 'kd': []})
    np.testing.assert_array_equal(c.on_joint_state(ctrl, q, qd), np.zeros(n))


def test_mode_switch_stale_desired_fallback_and_recovery(chain):
    xml, ctrl, locked = chain
    n = len(ctrl)
    clock = Clock()
    c = make(xml, ctrl, clock=clock, desired_timeout=0.05, include_velocity_terms=True)
    o = Oracle(xml, joints=ctrl)
    q, qd, q_d, qd_d, qdd_d = states(n, 5)
    gravity_law = o.rnea(q, qd, np.zeros(n))   # the gravity mode, with include_velocity_terms
    np.testing.assert_allclose(c.on_joint_state(ctrl, q, qd), gravity_law, atol=TOL, rtol=0)
    c.update({'mode': 'feedforward'})
    assert ('info', 'mode', 'mode: feedforward') in c.events
    c.events.clear()
    # no desired state yet: gravity at the measured state, said once
    for _ in range(3):
        np.testing.assert_allclose(c.on_joint_state(ctrl, q, qd), gravity_law, atol=TOL, rtol=0)
    assert [e[1] for e in c.events] == ['desired:none'] and 'no desired state received yet' in c.events[0][2]
    assert c.count.fallback_events == 1 and c.law == 'gravity (fallback)'
    level, msg, values = c.diagnostics()
    assert level == WARN and 'gravity fallback' in msg and dict(values)['control_law'] == 'gravity (fallback)'
    c.events.clear()
    c.on_desired(ctrl, [point(q_d, qd_d, qdd_d)])
    np.testing.assert_allclose(c.on_joint_state(ctrl, q, qd), o.rnea(q_d, qd_d, qdd_d), atol=TOL, rtol=0)
    assert [e[1] for e in c.events] == ['desired:resumed']
    assert c.diagnostics()[:2] == (OK, 'feedforward')
    c.events.clear()
    clock.t += 0.04
    np.testing.assert_allclose(c.on_joint_state(ctrl, q, qd), o.rnea(q_d, qd_d, qdd_d), atol=TOL, rtol=0)
    clock.t += 0.02   # 0.06 s > desired_timeout
    np.testing.assert_allclose(c.on_joint_state(ctrl, q, qd), gravity_law, atol=TOL, rtol=0)
    assert [e[1] for e in c.events] == ['desired:stale'] and 'for 0.060 s' in c.events[0][2]
    assert c.count.fallback_events == 2
    # switching at run time; the joint_states watchdog is unchanged (gravity at the last state)
    c.on_desired(ctrl, [point(q_d, qd_d, qdd_d)])
    c.update({'mode': 'gravity'})
    np.testing.assert_allclose(c.on_joint_state(ctrl, q, qd), gravity_law, atol=TOL, rtol=0)
    c.update({'mode': 'pd', 'kp': [3.0]})
    np.testing.assert_allclose(c.on_joint_state(ctrl, q, qd), 3.0 * (q_d - q), atol=TOL, rtol=0)
    clock.t += 1.0
    np.testing.assert_allclose(c.tick(), o.gravity(q), atol=TOL, rtol=0)
    # disabled: still tracked, nothing published
    c.update({'enabled': False})
    assert c.on_joint_state(ctrl, q, qd) is None


def test_output_is_clamped_in_every_mode(chain):
    xml, ctrl, locked = chain
    xml = big_limits(xml, '2.0')
    n = len(ctrl)
    c = make(xml, ctrl, mode='pd', kp=[1000.0], effort_limit_scale=0.5)
    c.on_desired(ctrl, [point(np.ones(n))])
    np.testing.assert_allclose(c.on_joint_state(ctrl, -np.ones(n)), np.ones(n), atol=TOL)
    assert c.count.clamp_count == 1
    c.update({'mode': 'feedforward', 'kp': [0.0]})
    c.on_desired(ctrl, [point(np.ones(n), np.zeros(n), np.full(n, 1e4))])
    tau = c.on_joint_state(ctrl, np.zeros(n))
    assert np.all(np.abs(tau) <= 1.0) and c.count.clamp_count == 2
    c.model.inverse_dynamics = lambda *a, **kw: np.full(n, math.nan)
    assert c.on_joint_state(ctrl, np.zeros(n)) is None and 'non-finite torque' in c.last_error


def test_bad_desired_states_are_rejected_and_keep_the_last_good_one(chain):
    xml, ctrl, locked = chain
    n = len(ctrl)
    clock = Clock()
    c = make(xml, ctrl, clock=clock, mode='feedforward', desired_timeout=1.0)
    q_d = np.linspace(-1, 1, n)
    assert c.on_desired(ctrl, [point(q_d)])
    t_good = c.desired_time
    good = c.on_joint_state(ctrl, np.zeros(n))
    cases = [
        ('points', ctrl, []),
        ('points', ctrl, [point(q_d), point(q_d)]),
        ('length', ctrl, [point(q_d[:-1])]),
        ('length', ctrl, [point(q_d, [0.0])]),
        ('length', ctrl, [point(q_d, (), np.zeros(n + 1))]),
        ('duplicate', ctrl + [ctrl[0]], [point(list(q_d) + [0.0])]),
        ('missing', ctrl[1:], [point(q_d[1:])]),
        ('missing', ['a' + j for j in ctrl], [point(q_d)]),
        ('nonfinite', ctrl, [point(list(q_d[:-1]) + [math.nan])]),
        ('nonfinite', ctrl, [point(q_d, np.full(n, math.inf))]),
        ('nonfinite', ctrl, [point(q_d, (), [math.nan] + [0.0] * (n - 1))]),
    ]
    for k, (kind, names, points) in enumerate(cases):
        c.events.clear()
        clock.t += 0.01
        assert not c.on_desired(names, points), kind
        assert [e[1] for e in c.events] == ['desired:' + kind]
        assert c.count.desired_rejected == k + 1
    c.events.clear()
    c.on_desired(['a' + j for j in ctrl], [point(q_d)])
    text = c.events[0][2]
    assert ctrl[0] in text and 'a' + ctrl[0] in text   # names the missing and the unexpected joints
    # a non-finite value of a joint that is not controlled is not used
    assert c.on_desired(ctrl + ['other'], [point(list(q_d) + [math.nan])])
    assert c.desired_time > t_good
    c.desired_time = t_good
    np.testing.assert_array_equal(c.on_joint_state(ctrl, np.zeros(n)), good)   # last good one in use
    assert c.diagnostics()[0] == WARN   # rejections in the window


def test_gain_and_mode_parameters():
    for name, value in [('mode', 'impedance'), ('kp', [-1.0]), ('kd', [math.nan]), ('desired_timeout', 0.0),
                        ('desired_topic', ' ')]:
        with pytest.raises(ValueError):
            check_value(name, value)
    assert check_value('kp', [1, 2]) == [1.0, 2.0]
    with pytest.raises(ValueError, match='kp must have 1 or 3'):
        Compensator({'joints': ['a', 'b', 'c'], 'kp': [1.0, 2.0]})
    xml = random_urdf(5, 3, joint_types=('revolute',))
    c = Compensator({'kd': [1.0, 2.0]})   # no joints yet: checked when the model comes
    with pytest.raises(ValueError, match='kd must have 1 or 3'):
        c.set_model(load_urdf(xml))
    c = Compensator()
    c.set_model(load_urdf(xml))
    with pytest.raises(ValueError, match='kp'):
        c.update({'mode': 'pd', 'kp': [1.0, 2.0]})
    assert c.settings['mode'] == 'gravity'   # atomic: nothing applied


# ---------------------------------------------------------------- trajectories

@pytest.fixture(scope='module')
def arm():
    import os
    with open(os.path.join(os.path.dirname(__file__), '..', 'config', 'arm7.urdf')) as fh:
        xml = fh.read()
    joints = [f'joint{i}' for i in range(1, 8)]
    return xml, joints, Oracle(xml, joints=joints)


def smooth(N, n=7, T=2.0):
    t = np.linspace(0, T, N)
    w = 2 * np.pi / T * np.arange(1, n + 1) / 4
    return t, 0.3 * np.sin(np.outer(t, w)), 0.3 * np.cos(np.outer(t, w)) * w, -0.3 * np.sin(np.outer(t, w)) * w ** 2


def test_trajectory_efforts_match_pinocchio_in_message_order(arm):
    xml, joints, o = arm
    c = Compensator({'friction.viscous': [0.0], 'friction.coulomb': [0.0]})
    c.set_model(load_urdf(xml))
    t, q, qd, qdd = smooth(60)
    perm = [3, 0, 6, 1, 5, 2, 4]
    names = [joints[i] for i in perm] + ['gripper_finger']
    pad = np.full((len(t), 1), 0.01)
    msg = trajectory_message(names, t, np.hstack([q[:, perm], pad]), np.hstack([qd[:, perm], pad]),
                             np.hstack([qdd[:, perm], pad]))
    eff = fill_trajectory(c, msg.joint_names, msg.points)
    ref = np.array([o.rnea(*s) for s in zip(q, qd, qdd, strict=True)])
    np.testing.assert_allclose(eff[:, :7], ref[:, perm], atol=TOL, rtol=0)
    np.testing.assert_array_equal(eff[:, 7], 0.0)   # not a controlled joint
    set_point_efforts(msg.points, eff)
    assert list(msg.points[5].effort) == eff[5].tolist()
    # no accelerations: derived from the velocities (trajectory.py), efforts at the derived values
    msg = trajectory_message(joints, t, q, qd)
    eff = fill_trajectory(c, msg.joint_names, msg.points)
    arrays = trajectory_arrays(joints, msg.points)
    assert arrays['accelerations'] is None
    qdd_fd = np.gradient(qd, arrays['time_from_start'], axis=0, edge_order=2)   # times as sent (ns)
    np.testing.assert_allclose(eff, [o.rnea(*s) for s in zip(q, qd, qdd_fd, strict=True)], atol=TOL, rtol=0)
    # friction at the point velocity; clamp to the limits
    c.update({'friction.viscous': [0.4], 'effort_limit_scale': 0.05})
    eff = fill_trajectory(c, msg.joint_names, msg.points)
    lim = 0.05 * c.model.effort_limits
    ref = np.array([o.rnea(*s) for s in zip(q, qd, qdd_fd, strict=True)])
    np.testing.assert_allclose(eff, np.clip(ref + 0.4 * qd, -lim, lim), atol=TOL, rtol=0)
    assert any(e[1] == 'trajectory:clamp' for e in c.events)
    assert c.count.trajectories_filled == 3


def test_bad_trajectories_are_rejected_with_a_reason(arm):
    xml, joints, o = arm
    c = Compensator()
    assert fill_trajectory(c, joints, [point(np.zeros(7))]) is None and 'no robot model' in c.last_error
    c.set_model(load_urdf(xml))
    t, q, qd, qdd = smooth(5)
    pts = lambda: [point(a, b, t=s) for s, a, b in zip(t, q, qd, strict=True)]   # noqa: E731
    cases = {
        'no points': (joints, []),
        'point 2 has 6 positions': (joints, pts()[:2] + [point(q[2][:6], qd[2], t=t[2])] + pts()[3:]),
        'velocities given for some points only': (joints, pts()[:3] + [point(q[3], t=t[3])] + pts()[4:]),
        'point 1 has 3 accelerations': (joints, [pts()[0], point(q[1], qd[1], [0.0] * 3, t=t[1])] + pts()[2:]),
        'times must increase strictly': (joints, pts()[:2] + [point(q[2], qd[2], t=t[1])] + pts()[3:]),
        'trajectory rejected: duplicate joint names': (joints[:6] + [joints[0]], pts()),
        "trajectory rejected: missing controlled joints ['joint7']": (joints[:6] + ['finger'], pts()),
        'non-finite value at point 4': (joints, pts()[:4] + [point(list(q[4][:6]) + [math.inf], qd[4], t=t[4])]),
    }
    for k, (why, (names, points)) in enumerate(cases.items()):
        c.events.clear()
        assert fill_trajectory(c, names, points) is None, why
        assert len(c.events) == 1 and why in c.events[0][2], (why, c.events)
        assert c.count.trajectories_rejected == k + 2
    c.update({'enabled': False})
    assert fill_trajectory(c, joints, pts()) is None and 'disabled' in c.last_error
    c.update({'enabled': True})
    assert fill_trajectory(c, joints, pts()) is not None


def test_a_fill_lost_with_its_process_is_not_said_to_be_unpublished():
    c = Compensator()
    side = TrajectoryInput(c)
    side.done('bad header')
    assert c.events[-1][2].endswith('(nothing published)') and c.count.trajectories_rejected == 1
    # the trajectory process died between its fill and its report: the node cannot know which
    side.done('trajectory process exited with status -9 while filling', kind='process')
    assert 'may have published it' in c.events[-1][2] and 'nothing published' not in c.events[-1][2]
    assert c.events[-1][1] == 'trajectory:process' and c.count.trajectories_rejected == 2
