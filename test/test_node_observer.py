"""External torques and collisions from the dynamics node over real DDS (own domain, conftest.py):
joint_states whose efforts are Pinocchio's inverse dynamics minus a known external torque."""
import math
import subprocess
import sys

import numpy as np
import pytest

rclpy = pytest.importorskip('rclpy')

from rclpy.parameter import Parameter  # noqa: E402
from sensor_msgs.msg import JointState  # noqa: E402
from std_msgs.msg import Bool  # noqa: E402

from lie_dynamics import default_urdf_path  # noqa: E402
from oracle import Oracle  # noqa: E402
from test_node import Harness, wait_until  # noqa: E402

JOINTS = [f'joint{i}' for i in range(1, 8)]
DT = 1e-3
T0_NS = 1_700_000_000 * 10 ** 9   # wall-clock-like stamps: the observer must keep their resolution
HOME = np.array([0.0, -0.6, 0.0, 2.0, 0.0, 1.6, 0.8])


@pytest.fixture
def ros():
    h = Harness()
    h.ext, h.flags = [], []
    h.t.create_subscription(JointState, '/dynamics_node/external_torques', h.ext.append, 1000)
    h.t.create_subscription(Bool, '/dynamics_node/collision', lambda m: h.flags.append(m.data), 1000)
    yield h
    h.close()


@pytest.fixture(scope='module')
def oracle():
    return Oracle(open(default_urdf_path()).read(), joints=JOINTS)


def start(ros, **params):
    node = ros.start(urdf_path=default_urdf_path(), **params)
    wait_until(lambda: ros.t.count_publishers('/dynamics_node/external_torques') >= 1
               and ros.t.count_publishers('/dynamics_node/collision') >= 1, what='observer publishers')
    return node


def motion(k):
    a, w = np.linspace(0.2, 0.5, 7), np.linspace(1.0, 2.0, 7)
    t = k * DT
    return HOME + a * np.sin(w * t), a * w * np.cos(w * t), -a * w * w * np.sin(w * t)


def state(k, effort, velocity=None):
    q, qd, _ = motion(k)
    msg = JointState(name=JOINTS, position=q.tolist(), velocity=(qd if velocity is None else velocity).tolist(),
                     effort=[float(e) for e in effort])
    ns = T0_NS + k * 1_000_000
    msg.header.stamp.sec, msg.header.stamp.nanosec = ns // 10 ** 9, ns % 10 ** 9
    return msg


def send(ros, msg, expect_command=True):
    """Publish one joint_states message and wait until the node has taken it (best effort: a
    message lost while discovery completes is sent again)."""
    node = ros.node
    r0, n0 = node.core.count.received, len(ros.cmds)
    for _ in range(15):
        ros.js_pub.publish(msg)
        try:
            wait_until(lambda: node.core.count.received > r0 and (len(ros.cmds) > n0 or not expect_command),
                       timeout=2.0)
            return
        except AssertionError:
            continue
    raise AssertionError('joint_states not processed')


def efforts(oracle, k, ext=None):
    q, qd, qdd = motion(k)
    return oracle.rnea(q, qd, qdd) - (0.0 if ext is None else ext)  # the motors supply what the contact does not


def stamp_ns(msg):
    return msg.header.stamp.sec * 10 ** 9 + msg.header.stamp.nanosec


def test_external_torques_converge_to_a_step_and_collision_is_flagged(ros, oracle):
    gain, hold, thr = 100.0, 0.01, 3.0
    node = start(ros, **{'observer.gain': gain, 'collision.hold_time': hold, 'collision.threshold': [thr],
                         'diagnostics_period': 0.2})
    step = np.array([0.0, 8.0, 0.0, -5.0, 0.0, 1.0, 0.0])
    on, n = 150, 450
    for k in range(n):
        send(ros, state(k, efforts(oracle, k, step if k >= on else None)))
    wait_until(lambda: len(ros.ext) >= n and len(ros.flags) >= n, what='every estimate')
    assert len(ros.ext) == n and len(ros.flags) == n  # one per state, none for a re-sent one
    est = np.array([m.effort for m in ros.ext])
    stamps = [stamp_ns(m) for m in ros.ext]
    assert stamps == [T0_NS + k * 1_000_000 for k in range(n)]    # the input stamps
    assert list(ros.ext[-1].name) == JOINTS
    assert np.all(np.isfinite(est))
    assert np.abs(est[:on]).max() < 1e-6                          # free motion: no contact seen
    assert not any(ros.flags[:on])                                # no false alarm
    np.testing.assert_allclose(est[-1], step, atol=1e-6 * np.abs(step).max())
    cross = on + int(np.argmax(np.abs(est[on:]).max(axis=1) > thr))
    first = ros.flags.index(True)
    assert cross < first <= cross + round(hold / DT), (cross, first)   # within the hold time, not before
    assert all(ros.flags[first:])
    wait_until(lambda: ros.diag_values().get('collision_events') == '1', what='collision in the diagnostics')
    v = ros.diag_values()
    assert v['collision'] == 'True' and v['observer'] == 'running' and v['measured_effort'] == 'total'
    wait_until(lambda: any('collision' in line and 'joint2' in line for line in ros.logs), what='collision log')
    assert node.core.count.rejected == 0


def test_bad_efforts_are_rejected_or_pause_the_observer(ros, oracle):
    node = start(ros, **{'observer.gain': 50.0, 'diagnostics_period': 0.1})
    ext = np.full(7, 2.0)
    k = 0
    for k in range(100):
        send(ros, state(k, efforts(oracle, k, ext)))
    wait_until(lambda: len(ros.ext) == 100, what='estimates')
    assert np.abs(np.array(ros.ext[-1].effort) - ext).max() < 0.05
    # wrong length: the whole message is rejected like other bad input (no command)
    rejected = node.core.count.rejected
    send(ros, state(100, [1.0] * 6), expect_command=False)
    assert node.core.count.rejected == rejected + 1
    # NaN effort: the command still goes out, the observer pauses and starts again
    bad = efforts(oracle, 101, ext)
    bad[4] = math.nan
    n_cmd, n_ext = len(ros.cmds), len(ros.ext)
    send(ros, state(101, bad))
    assert len(ros.cmds) == n_cmd + 1
    send(ros, state(102, efforts(oracle, 102, ext)))
    wait_until(lambda: len(ros.ext) == n_ext + 1, what='restarted estimate')
    assert stamp_ns(ros.ext[-1]) == T0_NS + 102 * 1_000_000       # nothing for the NaN one
    assert np.all(np.array(ros.ext[-1].effort) == 0.0)            # a new integral
    # absurd and infinite efforts, NaN velocities: never a non-finite value out, never a crash
    q_nan = motion(103)[1]
    q_nan[0] = math.nan
    for msg in (state(103, [1e308] * 7), state(104, [math.inf] * 7), state(105, efforts(oracle, 105), q_nan)):
        send(ros, msg)
    for k in range(106, 160):
        send(ros, state(k, efforts(oracle, k, ext)))
    wait_until(lambda: stamp_ns(ros.ext[-1]) == T0_NS + 159 * 1_000_000, what='estimates after the bad ones')
    assert all(np.all(np.isfinite(m.effort)) for m in ros.ext)
    assert all(np.all(np.isfinite(c)) for c in ros.cmds)
    assert np.abs(np.array(ros.ext[-1].effort) - ext).max() < 0.2
    wait_until(lambda: int(ros.diag_values().get('effort_unavailable_count', 0)) >= 2, what='count in diagnostics')
    assert int(ros.diag_values()['observer_resets']) >= 3
    wait_until(lambda: any('observer paused' in line for line in ros.logs), what='pause log')
    assert sum('observer paused' in line for line in ros.logs) <= 3   # throttled per problem class


def test_parameters_are_validated_and_the_observer_can_be_switched_off(ros, oracle):
    node = start(ros)
    for change, why in (({'collision.threshold': [1.0, 2.0]}, 'collision.threshold'),
                        ({'collision.threshold': [0.0]}, 'collision.threshold'),
                        ({'measured_effort': 'raw'}, 'measured_effort'), ({'observer.gain': 0.0}, 'observer.gain')):
        res = node.set_parameters_atomically([Parameter(k, value=v) for k, v in change.items()])
        assert not res.successful and why in res.reason, (change, res.reason)
    res = node.set_parameters_atomically([Parameter('collision.threshold', value=[5.0] * 7),
                                          Parameter('measured_effort', value='gravity_removed')])
    assert res.successful, res.reason
    for k in range(3):
        q = motion(k)[0]
        send(ros, state(k, efforts(oracle, k) - oracle.gravity(q)))
    wait_until(lambda: len(ros.ext) == 3, what='estimates')
    assert np.abs(np.array([m.effort for m in ros.ext])).max() < 1e-6
    assert all(r.successful for r in ros.set_params(**{'observer.enabled': False}))
    for k in range(3, 6):
        send(ros, state(k, efforts(oracle, k)))
    assert len(ros.ext) == 3 and node.contact_monitor.state == 'off'


def test_start_up_refuses_thresholds_that_do_not_fit_the_model():
    proc = subprocess.run([sys.executable, '-m', 'lie_dynamics.dynamics_node', '--ros-args', '-p',
                           f'urdf_path:={default_urdf_path()}', '-p', 'collision.threshold:=[1.0,2.0]'],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2, proc.stderr[-2000:]
    assert 'collision.threshold must have 1 or 7 values' in proc.stderr, proc.stderr[-2000:]
