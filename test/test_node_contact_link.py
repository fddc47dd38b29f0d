"""The contact link and the external wrench from the dynamics node over real DDS (own domain,
conftest.py): joint_states whose efforts are Pinocchio's inverse dynamics minus J^T F of a push
on the tool (Pinocchio's LOCAL frame Jacobian), ~/contact/wrench, ~/contact/tool_wrench and
~/contact/link during and after it; the parameters' refusals."""
import math
import subprocess
import sys

import numpy as np
import pytest

rclpy = pytest.importorskip('rclpy')

from geometry_msgs.msg import WrenchStamped  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from sensor_msgs.msg import JointState  # noqa: E402
from std_msgs.msg import Bool, String  # noqa: E402

from lie_dynamics import default_urdf_path, load_urdf  # noqa: E402
from test_node import Harness, wait_until  # noqa: E402
from test_node_observer import HOME, JOINTS, T0_NS, send, start, stamp_ns  # noqa: E402
from oracle import Oracle  # noqa: E402


@pytest.fixture
def ros():
    h = Harness()
    h.ext, h.flags, h.wrench, h.tool, h.link = [], [], [], [], []
    h.t.create_subscription(WrenchStamped, '/dynamics_node/contact/wrench', h.wrench.append, 1000)
    h.t.create_subscription(WrenchStamped, '/dynamics_node/contact/tool_wrench', h.tool.append, 1000)
    h.t.create_subscription(String, '/dynamics_node/contact/link', lambda m: h.link.append(m.data), 1000)
    h.t.create_subscription(JointState, '/dynamics_node/external_torques', h.ext.append, 1000)
    h.t.create_subscription(Bool, '/dynamics_node/collision', lambda m: h.flags.append(m.data), 1000)
    yield h
    h.close()


@pytest.fixture(scope='module')
def oracle():
    return Oracle(open(default_urdf_path()).read(), joints=JOINTS)


def state(k, effort):
    """The arm held still at HOME (the push is then a constant external torque), stamped k ms."""
    msg = JointState(name=JOINTS, position=HOME.tolist(), velocity=[0.0] * 7, effort=[float(e) for e in effort])
    msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(T0_NS + k * 1_000_000, 10 ** 9)
    return msg


def vec(msg):
    w = msg.wrench
    return np.array([w.force.x, w.force.y, w.force.z, w.torque.x, w.torque.y, w.torque.z])


def test_a_push_on_the_tool_is_isolated_and_its_wrench_published(ros, oracle):
    thr = [3.0, 3.0, 3.0, 3.0, 0.5, 0.5, 0.5]   # scaled with the effort limits (87 and 12 N m)
    start(ros, **{'observer.gain': 100.0, 'collision.hold_time': 0.005, 'collision.threshold': thr,
                  'contact.wrench_frame': 'tool0', 'diagnostics_period': 0.1})
    wait_until(lambda: ros.t.count_publishers('/dynamics_node/contact/tool_wrench') >= 1, what='contact publishers')
    F = np.array([12.0, -20.0, 8.0, 0.64, -0.08, -1.16])   # 12, -20, 8 N at (4, 3, 2) cm in tool0
    model = load_urdf(default_urdf_path())

    pushed = oracle.frame_jacobian(HOME, 'tool0', 'local').T @ F
    g = oracle.gravity(HOME)   # the motors hold the arm against gravity and the push
    on, off, n = 50, 200, 300
    for k in range(off):
        send(ros, state(k, g - (pushed if k >= on else 0.0)))
    wait_until(lambda: len(ros.tool) >= off and ros.link == ['link7'], what='the link isolated')
    wait_until(lambda: ros.diag_values().get('contact_link') == 'link7', what='the link in the diagnostics')
    v = ros.diag_values()
    assert v['contact_isolation'] == 'isolated' and v['contact_wrench_rank'] == '6'
    assert v['contact_tool_wrench_rank'] == '6' and v['contact_wrench_frame'] == 'tool0'
    # one line: the collision and the link
    wait_until(lambda: any('beyond collision.threshold' in line and "contact link 'link7': force" in line
                           for line in ros.logs), what='the log line')
    wait_until(lambda: ros.diag is not None and "collision at link 'link7'" in ros.diag.message,
               what='the link in the diagnostics message')
    # the tool wrench: every sample, the input stamps, F once the residual has settled
    assert [stamp_ns(m) for m in ros.tool] == [T0_NS + k * 1_000_000 for k in range(off)]
    assert all(m.header.frame_id == 'tool0' for m in ros.tool)
    # (the time mean over the settled stretch, the observer's lag corrected: the trapezoid's error on the rise's tail)
    lag = 2e-5 * np.abs(F).max()
    np.testing.assert_allclose(vec(ros.tool[-1]), F, atol=lag)
    assert np.abs(vec(ros.tool[on - 1])).max() < 1e-6
    # the link's wrench: only while the flag is up and after the residual settled, at link7's origin
    first = ros.flags.index(True)
    assert ros.wrench and all(m.header.frame_id == 'link7' for m in ros.wrench)
    assert stamp_ns(ros.wrench[0]) > T0_NS + first * 1_000_000    # not on the rising residual
    np.testing.assert_allclose(model.jacobian(HOME, 'link7', 'local').T @ vec(ros.wrench[-1]), pushed,
                               atol=lag)
    # a non-finite effort: nothing published for it, the observer and the isolation start anew
    bad = g - pushed
    bad[2] = math.nan
    n_tool = len(ros.tool)
    send(ros, state(off, bad))
    for k in range(off + 1, n):
        send(ros, state(k, g))   # released
    wait_until(lambda: len(ros.tool) >= n - 1 and len(ros.link) >= 2, what='after the release')
    assert T0_NS + off * 1_000_000 not in [stamp_ns(m) for m in ros.tool[n_tool:]]
    assert ros.link[:2] == ['link7', '']
    wait_until(lambda: np.abs(vec(ros.wrench[-1])).max() == 0.0, what='the zero wrench')
    zero = ros.wrench[-1]
    assert zero.header.frame_id == 'link7' and stamp_ns(zero) == T0_NS + (off + 1) * 1_000_000
    assert all(np.all(np.isfinite(vec(m))) for m in ros.wrench + ros.tool)
    assert not ros.flags[-1] and ros.link[-1] == ''


def test_contact_parameters_are_validated(ros):
    node = start(ros)
    for change, why in (({'contact.wrench_frame': 'tool'}, "did you mean 'tool0'"),
                        ({'contact.wrench_frame': 'base_link'}, 'fixed to the root'),
                        ({'contact.rcond': 0.0}, 'contact.rcond'), ({'contact.rcond': -1.0}, 'contact.rcond'),
                        ({'contact.rcond': math.nan}, 'contact.rcond'), ({'contact.rcond': math.inf}, 'contact.rcond'),
                        ({'contact.strict_below': -1.0}, 'contact.strict_below'),
                        ({'contact.strict_below': math.nan}, 'contact.strict_below'),
                        ({'contact.strict_below': math.inf}, 'contact.strict_below')):
        res = node.set_parameters_atomically([Parameter(k, value=v) for k, v in change.items()])
        assert not res.successful and why in res.reason, (change, res.reason)
    assert node.get_parameter('contact.strict_below').value == 2.0   # kept after the refusals (the default)
    res = node.set_parameters_atomically([Parameter('contact.wrench_frame', value='flange'),
                                          Parameter('contact.rcond', value=0.01),
                                          Parameter('contact.strict_below', value=0.0)])
    assert res.successful, res.reason


def test_start_up_refuses_a_wrench_frame_no_joint_moves():
    proc = subprocess.run([sys.executable, '-m', 'lie_dynamics.dynamics_node', '--ros-args', '-p',
                           f'urdf_path:={default_urdf_path()}', '-p', 'contact.wrench_frame:=base_link'],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2, proc.stderr[-2000:]
    assert "link 'base_link' moves with no controlled joint" in proc.stderr, proc.stderr[-2000:]
