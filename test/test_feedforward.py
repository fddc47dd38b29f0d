"""Feedforward modes, the desired-state stream and the trajectory effort fill of the dynamics
node with real rclpy and DDS on localhost (harness of test_node.py), checked against Pinocchio."""
import math
import os
import time

import numpy as np
import pytest

rclpy = pytest.importorskip('rclpy')

from std_msgs.msg import String  # noqa: E402
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint  # noqa: E402

from lie_dynamics import load_urdf  # noqa: E402
from lie_dynamics.ros.trajectories.trajectory_msgs import trajectory_arrays, trajectory_message  # noqa: E402
from oracle import Oracle  # noqa: E402
from robots import random_urdf  # noqa: E402
from test_node import MODEL_TIMEOUT, TOL, Harness, big_limits, throttled, wait_until  # noqa: E402

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
DESIRED = '/dynamics_node/desired'


class FFHarness(Harness):
    """Adds a desired-state publisher and a planner / joint_trajectory_controller stand-in."""

    def __init__(self):
        super().__init__()
        self.des_pub = self.t.create_publisher(JointTrajectory, DESIRED, 10)
        self.traj_pub = self.t.create_publisher(JointTrajectory, '/dynamics_node/trajectory_in', 10)
        self.trajs = []
        self.t.create_subscription(JointTrajectory, '/dynamics_node/trajectory_out', self.trajs.append, 10)

    def start(self, **kw):
        node = super().start(**kw)
        wait_until(lambda: self.des_pub.get_subscription_count() >= 1 and self.traj_pub.get_subscription_count() >= 1
                   and self.t.count_publishers('/dynamics_node/trajectory_out') >= 1, what='discovery')
        return node

    def desire(self, names, q, qd=(), qdd=(), points=1, accepted=True):
        """Publish one desired-state message and wait until the node has processed it."""
        core = self.node.core
        r0, a0 = core.count.desired_received, core.count.desired_accepted
        pt = JointTrajectoryPoint(positions=[float(x) for x in q], velocities=[float(x) for x in qd],
                                  accelerations=[float(x) for x in qdd])
        self.des_pub.publish(JointTrajectory(joint_names=list(names), points=[pt] * points))
        wait_until(lambda: core.count.desired_received > r0, what='desired state processed')
        assert (core.count.desired_accepted == a0 + 1) == accepted

    def log_count(self, text):
        return sum(text in line for line in self.logs)


@pytest.fixture
def ros():
    h = FFHarness()
    yield h
    h.close()


@pytest.fixture(scope='module')
def chain():
    xml = big_limits(random_urdf(44, 5, joint_types=('revolute',)))
    names = load_urdf(xml).joint_names
    return xml, [names[0]] + names[2:], names[1]


def test_modes_fallback_and_run_time_switch(ros, chain):
    xml, ctrl, locked = chain
    n = len(ctrl)
    ros.desc_pub.publish(String(data=xml))
    ros.start(joints=ctrl, mode='feedforward', desired_timeout=0.4, diagnostics_period=0.1)
    rng = np.random.default_rng(5)
    q, qd, q_d, qd_d, qdd_d = (rng.uniform(-1.5, 1.5, n) for _ in range(5))
    ql = 0.3
    js = (ctrl + [locked], list(q) + [ql], list(qd) + [0.0])
    o = Oracle(xml, joints=ctrl, locked={locked: ql})
    gravity = o.gravity(q)

    # no desired state yet: gravity compensation at the measured state, said once and in diagnostics
    np.testing.assert_allclose(ros.send(*js), gravity, atol=TOL, rtol=0)
    np.testing.assert_allclose(ros.send(*js), gravity, atol=TOL, rtol=0)
    wait_until(lambda: ros.diag is not None and 'gravity fallback' in ros.diag.message and ros.diag_level() == 1,
               what='fallback diagnostics')
    wait_until(lambda: ros.log_count('no desired state received yet') == 1, what='fallback log')

    # feedforward, kp = kd = 0: inverse dynamics at the desired state (names in any order)
    ros.desire(['other'] + ctrl[::-1], [5.0] + q_d[::-1].tolist(), [0.0] + qd_d[::-1].tolist(),
               [0.0] + qdd_d[::-1].tolist())
    np.testing.assert_allclose(ros.send(*js), o.rnea(q_d, qd_d, qdd_d), atol=TOL, rtol=0)
    wait_until(lambda: ros.log_count('fresh again: mode feedforward resumed') == 1, what='recovery log')
    wait_until(lambda: ros.diag.message == 'feedforward' and ros.diag_values().get('control_law') == 'feedforward',
               what='diagnostics after recovery')

    kp, kd = np.linspace(20.0, 60.0, n), np.linspace(1.0, 4.0, n)
    e, de = q_d - q, qd_d - qd
    expected = {
        'computed_torque': o.crba(q) @ (qdd_d + kp * e + kd * de) + o.rnea(q, qd, np.zeros(n)),
        'pd': kp * e + kd * de,
        'feedforward': o.rnea(q_d, qd_d, qdd_d) + kp * e + kd * de,
    }
    for mode, ref in expected.items():   # switched at run time, one parameter call
        assert all(r.successful for r in ros.set_params(mode=mode, kp=kp.tolist(), kd=kd.tolist()))
        ros.desire(ctrl, q_d, qd_d, qdd_d)
        np.testing.assert_allclose(ros.send(*js), ref, atol=TOL, rtol=0, err_msg=mode)
    assert ros.node.get_parameter('mode').value == 'feedforward'
    for bad in (dict(mode='impedance'), dict(kp=[1.0, 2.0]), dict(kd=[-1.0]), dict(desired_timeout=0.0)):
        assert not ros.set_params(**bad)[0].successful, bad

    # the stream stops: gravity fallback after desired_timeout, then recovery
    time.sleep(0.45)
    np.testing.assert_allclose(ros.send(*js), gravity, atol=TOL, rtol=0)
    wait_until(lambda: any('no valid desired state on /dynamics_node/desired for' in line for line in ros.logs),
               what='stale log')
    wait_until(lambda: 'desired state stale: gravity fallback' in ros.diag.message, what='stale diagnostics')
    ros.desire(ctrl, q_d, qd_d, qdd_d)
    np.testing.assert_allclose(ros.send(*js), expected['feedforward'], atol=TOL, rtol=0)
    assert ros.node.core.count.fallback_events == 2


def test_bad_desired_messages_are_rejected_and_logged_once(ros, chain):
    xml, ctrl, locked = chain
    n = len(ctrl)
    ros.desc_pub.publish(String(data=xml))
    ros.start(joints=ctrl, mode='feedforward', desired_timeout=30.0)
    q_d = np.linspace(-0.8, 0.8, n)
    ros.desire(ctrl, q_d, np.ones(n))
    ref = Oracle(xml, joints=ctrl).rnea(q_d, np.ones(n), np.zeros(n))
    np.testing.assert_allclose(ros.send(ctrl, np.zeros(n)), ref, atol=TOL, rtol=0)
    cases = {
        'takes exactly one': [dict(points=0), dict(points=2)],
        'array lengths differ': [dict(q=q_d[:-1]), dict(qd=[1.0])],
        'duplicate joint names': [dict(names=ctrl + [ctrl[0]], q=list(q_d) + [0.0])] * 2,
        'missing controlled joints': [dict(names=ctrl[1:], q=q_d[1:])],
        'non-finite': [dict(q=list(q_d[:-1]) + [math.nan]), dict(qdd=[math.inf] * n)],
    }
    t0 = time.monotonic()
    for msgs in cases.values():
        for m in msgs:
            ros.desire(m.get('names', ctrl), m.get('q', q_d), m.get('qd', ()), m.get('qdd', ()),
                       points=m.get('points', 1), accepted=False)
            # the last valid desired state is still in use
            np.testing.assert_allclose(ros.send(ctrl, np.zeros(n)), ref, atol=TOL, rtol=0)
    wait_until(lambda: all(ros.log_count(p) for p in cases), what='rejection logs')
    time.sleep(0.1)
    for problem in cases:   # one line per problem within LOG_THROTTLE_S
        n, most = throttled(ros.logs, problem, t0)
        assert 1 <= n <= most, (problem, most, ros.logs)
    assert ros.node.core.count.desired_rejected == sum(len(m) for m in cases.values())


def test_trajectory_fill_with_the_shipped_feedforward_config(ros):
    node = ros.start(params_file=os.path.join(ROOT, 'config', 'arm7_feedforward.yaml'))
    joints = [f'joint{i}' for i in range(1, 8)]
    s = node.core.settings
    assert s['mode'] == 'feedforward' and node.core.layout == joints and len(s['kp']) == 7
    xml = open(os.path.join(ROOT, 'config', 'arm7.urdf')).read()
    o = Oracle(xml, joints=joints)
    kp, kd = np.array(s['kp']), np.array(s['kd'])
    rng = np.random.default_rng(9)
    q, qd, q_d, qd_d, qdd_d = (rng.uniform(-0.5, 0.5, 7) for _ in range(5))
    ros.desire(joints, q_d, qd_d, qdd_d)
    ref = o.rnea(q_d, qd_d, qdd_d) + kp * (q_d - q) + kd * (qd_d - qd)
    np.testing.assert_allclose(ros.send(joints, q, qd), ref, atol=TOL, rtol=0)

    # a planner's trajectory: message joint order kept, efforts per point, 0 for other joints
    N = 200
    t = np.linspace(0.0, 4.0, N)
    w = np.arange(1, 8) * 0.3
    Q, QD, QDD = 0.4 * np.sin(np.outer(t, w)), 0.4 * np.cos(np.outer(t, w)) * w, -0.4 * np.sin(np.outer(t, w)) * w ** 2
    perm = [6, 2, 0, 4, 1, 5, 3]
    names = [joints[i] for i in perm] + ['gripper']
    pad = np.zeros((N, 1))
    msg = trajectory_message(names, t, np.hstack([Q[:, perm], pad]), np.hstack([QD[:, perm], pad]),
                             np.hstack([QDD[:, perm], pad]))
    msg.header.frame_id = 'keep_me'
    ros.traj_pub.publish(msg)
    # the node's trajectory process may still be starting (a cold interpreter: ~10 s beside busy loops)
    wait_until(lambda: len(ros.trajs) == 1, timeout=MODEL_TIMEOUT, what='filled trajectory')
    out = ros.trajs[0]
    assert list(out.joint_names) == names and out.header.frame_id == 'keep_me' and len(out.points) == N
    arr = trajectory_arrays(out.joint_names, out.points)
    np.testing.assert_array_equal(arr['positions'], np.hstack([Q[:, perm], pad]))
    eff = np.array([p.effort for p in out.points])
    ref = np.array([o.rnea(*x) for x in zip(Q, QD, QDD, strict=True)])
    np.testing.assert_allclose(eff[:, :7], ref[:, perm], atol=TOL, rtol=0)
    np.testing.assert_array_equal(eff[:, 7], 0.0)

    # no accelerations: derived from velocities and time_from_start
    ros.traj_pub.publish(trajectory_message(joints, t, Q, QD))
    wait_until(lambda: len(ros.trajs) == 2, what='second trajectory')
    ts = trajectory_arrays(joints, ros.trajs[1].points)['time_from_start']
    QDD_fd = np.gradient(QD, ts, axis=0, edge_order=2)
    np.testing.assert_allclose(np.array([p.effort for p in ros.trajs[1].points]),
                               [o.rnea(*x) for x in zip(Q, QD, QDD_fd, strict=True)], atol=TOL, rtol=0)

    # bad trajectories: nothing published, one log line each
    def bad(**change):
        m = trajectory_message(joints, t[:5], Q[:5], QD[:5])
        for k, v in change.items():
            v(m) if callable(v) else setattr(m, k, v)
        return m
    cases = {
        'trajectory has no points': bad(points=[]),
        'point 3 has 6 positions': bad(p=lambda m: setattr(m.points[3], 'positions', [0.0] * 6)),
        'velocities given for some points only': bad(p=lambda m: setattr(m.points[2], 'velocities', [])),
        'times must increase strictly': bad(p=lambda m: setattr(m.points[4], 'time_from_start',
                                                                m.points[3].time_from_start)),
        'trajectory rejected: duplicate joint names': bad(joint_names=joints[:6] + ['joint1']),
        "trajectory rejected: missing controlled joints ['joint7']": bad(joint_names=joints[:6] + ['finger']),
        'non-finite value at point 1': bad(p=lambda m: setattr(m.points[1], 'positions', [math.nan] * 7)),
    }
    for why, m in cases.items():
        r0 = node.core.count.trajectories_rejected
        ros.traj_pub.publish(m)
        wait_until(lambda r0=r0: node.core.count.trajectories_rejected == r0 + 1, what=why)
    ros.traj_pub.publish(trajectory_message(joints, t[:3], Q[:3], QD[:3], QDD[:3]))
    wait_until(lambda: len(ros.trajs) == 3, what='good trajectory after the bad ones')
    wait_until(lambda: all(ros.log_count(why) for why in cases), what='trajectory rejection logs')
    time.sleep(0.05)
    assert len(ros.trajs) == 3
    for why in cases:
        assert ros.log_count(why) == 1, (why, ros.logs)
    assert len(ros.trajs[2].points) == 3
