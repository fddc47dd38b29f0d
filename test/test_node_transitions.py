"""Safety of the dynamics node with real rclpy and DDS (harness of test_node.py): the watchdog
on the steady clock under use_sim_time, ramps on enable and disable, nothing published before
the first valid state, implausible and old states, the description-update policy."""
import os
import re
import time

import numpy as np
import pytest

rclpy = pytest.importorskip('rclpy')

from rosgraph_msgs.msg import Clock as ClockMsg  # noqa: E402
from sensor_msgs.msg import JointState  # noqa: E402
from std_msgs.msg import String  # noqa: E402
from std_srvs.srv import SetBool, Trigger  # noqa: E402

from lie_dynamics import load_urdf  # noqa: E402
from lie_dynamics.ros.node import JOINT_STATES_QOS  # noqa: E402
from test_node import MODEL_TIMEOUT, wait_until  # noqa: E402

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
ARM = open(os.path.join(ROOT, 'config', 'arm7.urdf')).read()
JOINTS = [f'joint{i}' for i in range(1, 8)]
Q = np.array([0.1, 0.5, -0.2, 1.2, 0.3, 0.8, 0.1])



def test_watchdog_runs_on_the_steady_clock_under_sim_time(ros):
    """use_sim_time with no /clock, then with a paused /clock: the stale action still comes, and
    so do the diagnostics."""
    node = ros.start(robot_description=ARM, use_sim_time=True, stale_timeout=0.2, diagnostics_period=0.1)
    g = load_urdf(ARM).gravity(Q)
    np.testing.assert_allclose(ros.send(JOINTS, Q), g, atol=1e-9)
    wait_until(lambda: len(ros.cmds) == 2, what='stale action without /clock')
    np.testing.assert_allclose(ros.cmds[1], g, atol=1e-9)
    wait_until(lambda: ros.diag_values().get('stale') == 'True', what='diagnostics without /clock')
    node.note_executor('events')   # run.py says which executor spins the node
    wait_until(lambda: ros.diag_values().get('executor') == 'events', what='executor in the diagnostics')
    clock = ros.t.create_publisher(ClockMsg, '/clock', 10)
    wait_until(lambda: clock.get_subscription_count() >= 1, what='/clock discovery')
    msg = ClockMsg()
    msg.clock.sec = 100
    clock.publish(msg)   # once: then /clock stays paused
    wait_until(lambda: node.get_clock().now().nanoseconds == 100 * 10 ** 9, what='sim time')
    np.testing.assert_allclose(ros.send(JOINTS, Q), g, atol=1e-9)
    wait_until(lambda: len(ros.cmds) == 4, what='stale action with a paused /clock')
    assert node.core.watchdog.stale_events == 2
    n = len(ros.diag_messages)
    wait_until(lambda: len(ros.diag_messages) > n + 2, what='diagnostics with a paused /clock')


def test_ramps_on_disable_and_enable(ros):
    ros.start(robot_description=ARM, ramp_time=0.4)
    g = load_urdf(ARM).gravity(Q)
    np.testing.assert_allclose(ros.send(JOINTS, Q), g, atol=1e-9)   # start-up: no ramp
    assert ros.call(SetBool, '/dynamics_node/set_enabled', SetBool.Request(data=False)).success
    levels = []
    while True:   # the command ramps down with the input, then stops
        n0 = len(ros.cmds)
        ros.publish_processed(JOINTS, Q)
        time.sleep(0.01)
        if len(ros.cmds) == n0:
            break
        levels.append(float(ros.cmds[-1] @ g / (g @ g)))
        np.testing.assert_allclose(ros.cmds[-1], levels[-1] * g, atol=1e-9)
    assert len(levels) >= 3 and levels[-1] == 0.0 and np.all(np.diff(levels) <= 1e-12), levels
    assert 0 < levels[len(levels) // 2] < 1
    n0 = len(ros.cmds)
    ros.publish_processed(JOINTS, Q)
    assert len(ros.cmds) == n0   # silent
    assert ros.call(SetBool, '/dynamics_node/set_enabled', SetBool.Request(data=True)).success
    levels = [float(ros.send(JOINTS, Q) @ g / (g @ g))]
    while levels[-1] < 1.0:
        time.sleep(0.01)
        levels.append(float(ros.send(JOINTS, Q) @ g / (g @ g)))
    assert levels[0] == 0.0 and len(levels) >= 3 and np.all(np.diff(levels) >= -1e-12), levels
    np.testing.assert_allclose(ros.cmds[-1], g, atol=1e-9)


def test_nothing_before_the_first_valid_state_and_bad_states(ros):
    node = ros.start(robot_description=ARM, position_margin=0.5)
    assert JOINT_STATES_QOS.depth == 1   # only the newest state is kept
    assert ros.call(SetBool, '/dynamics_node/set_enabled', SetBool.Request(data=False)).success
    assert ros.call(SetBool, '/dynamics_node/set_enabled', SetBool.Request(data=True)).success
    ros.publish_processed(JOINTS, [1e308] * 7)   # finite but absurd: rejected, nothing published
    lim = load_urdf(ARM).position_upper
    ros.publish_processed(JOINTS, lim + 0.6)     # beyond the limits + position_margin 0.5
    time.sleep(0.2)
    assert ros.cmds == [] and node.core.count.rejected == 2
    assert 'implausible' in node.core.last_error
    np.testing.assert_allclose(ros.send(JOINTS, lim + 0.4), load_urdf(ARM).gravity(lim + 0.4), atol=1e-9)

    def stamped(sec):
        m = JointState(name=JOINTS, position=Q.tolist())
        m.header.stamp.sec = sec
        return m
    n0 = len(ros.cmds)
    ros.js_pub.publish(stamped(20))
    wait_until(lambda: len(ros.cmds) == n0 + 1, what='stamped state')
    r0 = node.core.count.rejected
    ros.js_pub.publish(stamped(10))   # older than the last accepted one: refused
    wait_until(lambda: node.core.count.rejected == r0 + 1, what='old state refused')
    assert len(ros.cmds) == n0 + 1 and 'older' in node.core.last_error


def test_description_update_policy(ros):
    node = ros.start(robot_description=ARM, diagnostics_period=0.1)
    g = load_urdf(ARM).gravity(Q)
    # another robot with the same joint names and 1000 N m limits: refused by default
    other = re.sub(r'effort="[^"]*"', 'effort="1000"', ARM.replace('name="lie_arm7"', 'name="other_arm"'))
    assert 'other_arm' in other
    ros.desc_pub.publish(String(data=heavier(other)))
    wait_until(lambda: 'other_arm' in node.core.description_error, timeout=MODEL_TIMEOUT, what='refusal')
    assert 'same_robot' in node.core.description_error and node.core.model.name == 'lie_arm7'
    np.testing.assert_allclose(ros.send(JOINTS, Q), g, atol=1e-9)
    wait_until(lambda: ros.diag_values().get('description_update') == 'same_robot', what='diagnostics')
    # the same robot with other masses and limits: accepted, the changes logged
    same = re.sub(r'effort="[^"]*"', 'effort="90"', heavier(ARM))
    ros.desc_pub.publish(String(data=same))
    wait_until(lambda: node.core.description_error == '' and node.core.model.effort_limits[0] == 90,
               what='same robot accepted')
    wait_until(lambda: any('effort limits changed' in line for line in ros.logs), what='change log')
    wait_until(lambda: any('masses changed' in line for line in ros.logs), what='mass change log')
    # any: another robot too
    assert all(r.successful for r in ros.set_params(description_update='any'))
    ros.desc_pub.publish(String(data=other))
    wait_until(lambda: node.core.model.name == 'other_arm', what='other robot accepted')
    # none: nothing replaces the model, and reloads are refused at once
    assert all(r.successful for r in ros.set_params(description_update='none'))
    res = ros.call(Trigger, '/dynamics_node/reload_model', Trigger.Request())
    assert not res.success and "'none'" in res.message
    assert not ros.set_params(robot_description=ARM)[0].successful
    assert not ros.set_params(inertia_policy='repair')[0].successful
    ros.desc_pub.publish(String(data=ARM))
    wait_until(lambda: "'none'" in node.core.description_error, what='update refused')
    assert node.core.model.name == 'other_arm'


def heavier(xml):
    return re.sub(r'<mass value="([^"]*)"', lambda m: f'<mass value="{1.5 * float(m.group(1))!r}"', xml)
