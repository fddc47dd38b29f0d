"""The dynamics node with real rclpy and DDS on localhost (own ROS_DOMAIN_ID, see conftest.py).

Each test starts the node in-process with its own Context and a SingleThreadedExecutor
spinning in a background thread, next to a tester node that plays robot_state_publisher,
joint_state_broadcaster and the effort controller. Torques are checked against Pinocchio.
"""
import math
import os
import re
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

rclpy = pytest.importorskip('rclpy')

from diagnostic_msgs.msg import DiagnosticArray  # noqa: E402
from rcl_interfaces.msg import Log  # noqa: E402
from rclpy.context import Context  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from rclpy.parameter_client import AsyncParameterClient  # noqa: E402
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy  # noqa: E402
from sensor_msgs.msg import JointState  # noqa: E402
from std_msgs.msg import Float64MultiArray, String  # noqa: E402
from std_srvs.srv import SetBool, Trigger  # noqa: E402

from lie_dynamics import load_urdf  # noqa: E402
from lie_dynamics.ros.node import DESCRIPTION_QOS, LOG_THROTTLE_S, DynamicsNode  # noqa: E402
from oracle import Oracle  # noqa: E402
from core_cases import big_limits  # noqa: E402
from robots import random_urdf, with_payload  # noqa: E402

ROSOUT_QOS = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)

TOL = 1e-9
CMD = '/effort_controller/commands'
TIMEOUT = 10.0
# A description loaded in the background (topic, parameter, reload) is built in a child process
# that starts cold with the first such load (a Python interpreter at a lower priority, numpy, the
# URDF parser's imports) and its kernels are generated before the swap: ~10 s beside two busy loops
# on a 2-core machine, which a test of what the node does with the model, or with its refusal, does
# not measure. Waits for the outcome of a node's first background load use this bound.
MODEL_TIMEOUT = 60.0


def throttled(logs, text, since):
    """(lines of the node that mention `text`, how many its throttle allows since `since`, a
    time.monotonic()): one per problem class every LOG_THROTTLE_S s, the first at once; a later
    one says how many were held back."""
    return sum(text in line for line in logs), 1 + int((time.monotonic() - since) / LOG_THROTTLE_S)


def wait_until(pred, timeout=TIMEOUT, what='condition'):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if pred():
            return
        time.sleep(0.002)
    raise AssertionError(f'timed out waiting for {what}')


class Harness:
    """Tester node + the node under test in one context, spun by one background thread."""

    def __init__(self):
        self.ctx = Context()
        rclpy.init(context=self.ctx)
        self.ex = SingleThreadedExecutor(context=self.ctx)
        t = self.t = rclpy.create_node('node_tester', context=self.ctx)
        self.desc_pub = t.create_publisher(String, 'robot_description', DESCRIPTION_QOS)
        self.js_pub = t.create_publisher(JointState, 'joint_states', 10)
        self.cmds, self.efforts, self.records = [], [], []
        self.diag = None
        self.diag_messages = []
        t.create_subscription(Float64MultiArray, CMD, lambda m: self.cmds.append(np.array(m.data)), 100)
        t.create_subscription(JointState, '/dynamics_node/commanded_efforts', self.efforts.append, 100)
        t.create_subscription(DiagnosticArray, '/diagnostics', self._on_diag, 10)
        # rosout's own QoS (transient local, keep 1000): a line logged before the match (a loaded
        # machine can take a second to discover the node's rosout publisher) still arrives.
        t.create_subscription(Log, '/rosout', self._on_log, ROSOUT_QOS)
        self.node = None
        self.spin_error = None
        self.closing = False
        self.ex.add_node(t)
        self.thread = threading.Thread(target=self._spin, daemon=True)
        self.thread.start()

    def _spin(self):
        try:
            self.ex.spin()
        except Exception as exc:  # executor shut down during close(), or a callback raised
            self.spin_error = exc
            if not self.closing:
                raise

    def _on_diag(self, msg):
        for st in msg.status:
            if st.name.startswith('dynamics_node'):
                self.diag = st
                self.diag_messages.append(st.message)

    def _on_log(self, msg):
        if msg.name == 'dynamics_node':
            self.records.append(msg)

    @property
    def logs(self):
        """The texts of the node's /rosout records so far."""
        return [r.msg for r in self.records]

    def diag_values(self):
        return {} if self.diag is None else {kv.key: kv.value for kv in self.diag.values}

    def diag_level(self):
        return None if self.diag is None else self.diag.level[0]

    def start(self, wait_model=True, params_file=None, features=None, **params):
        params.setdefault('stale_timeout', 60.0)
        if params_file is None:  # out of the way unless a test is about them (random URDF limits are narrow)
            params.setdefault('friction.viscous', [0.0])
            params.setdefault('friction.coulomb', [0.0])
            params.setdefault('ramp_time', 0.0)
            params.setdefault('position_margin', 1000.0)
        overrides = [Parameter(k, value=v) for k, v in params.items()]
        cli = ['--ros-args', '--params-file', str(params_file)] if params_file else None
        extra = {} if features is None else {'features': features}   # default: the node's FEATURES
        self.node = DynamicsNode(context=self.ctx, parameter_overrides=overrides, cli_args=cli, **extra)
        self.ex.add_node(self.node)
        wait_until(lambda: self.js_pub.get_subscription_count() >= 1 and self.t.count_publishers(CMD) >= 1,
                   what='discovery')
        if wait_model:
            wait_until(lambda: self.node.core.model is not None, timeout=MODEL_TIMEOUT, what='model')
        return self.node

    def publish(self, names, position, velocity=(), effort=()):
        self.js_pub.publish(JointState(name=list(names), position=[float(x) for x in position],
                                       velocity=[float(x) for x in velocity], effort=[float(x) for x in effort]))

    def send(self, names, position, velocity=(), effort=()):
        """Publish one joint_states message and return the command it produced."""
        n0 = len(self.cmds)
        self.publish(names, position, velocity, effort)
        wait_until(lambda: len(self.cmds) > n0, what='a command')
        assert len(self.cmds) == n0 + 1
        return self.cmds[n0]

    def publish_processed(self, names, position, velocity=(), effort=()):
        """Publish one joint_states message and wait until the node has taken it (joint_states
        keeps only the newest message: a second one sent at once could replace it)."""
        return self.publish_msg_processed(JointState(
            name=list(names), position=[float(x) for x in position], velocity=[float(x) for x in velocity],
            effort=[float(x) for x in effort]))

    def publish_msg_processed(self, msg):
        """publish_processed for a ready JointState message."""
        r0 = self.node.core.count.received
        # joint_states is best effort: right after start-up, while the reader's side of discovery
        # completes (seconds on a loaded machine), a message can be lost. Send it again then.
        for _ in range(15):
            self.js_pub.publish(msg)
            try:
                return wait_until(lambda: self.node.core.count.received > r0, timeout=2.0)
            except AssertionError:
                continue
        raise AssertionError('timed out waiting for joint_states processed')

    def send_rejected(self, good, names, position, velocity=(), effort=()):
        """Publish a bad message, then a good one: exactly one command (the good one's) must come."""
        n0, r0 = len(self.cmds), self.node.core.count.rejected
        self.publish_processed(names, position, velocity, effort)
        out = self.send(*good)
        assert len(self.cmds) == n0 + 1 and self.node.core.count.rejected == r0 + 1
        return out

    def set_params(self, **params):
        return self.node.set_parameters([Parameter(k, value=v) for k, v in params.items()])

    def call(self, srv_type, name, request):
        cli = self.t.create_client(srv_type, name)
        assert cli.wait_for_service(timeout_sec=TIMEOUT)
        fut = cli.call_async(request)
        wait_until(fut.done, what=f'service {name}')
        self.on_spin_thread(self.t.destroy_client, cli)
        return fut.result()

    def on_spin_thread(self, fn, *args):
        """Run fn(*args) on the executor's thread and return its result. Destroying an entity
        from this thread races the wait set the executor is building: it then raises
        InvalidHandle in the spin thread, and the tester stops receiving."""
        task = self.ex.create_task(fn, *args)
        wait_until(task.done, what=getattr(fn, '__name__', 'a task on the spin thread'))
        return task.result()

    def close(self):
        self.closing = True
        self.ex.shutdown(timeout_sec=2.0)
        self.thread.join(timeout=5.0)
        if self.node is not None:
            self.node.destroy_node()
        self.t.destroy_node()
        self.ctx.try_shutdown()


@pytest.fixture(scope='module')
def chain():
    """5 revolute joints; the second one is not controlled, so it is locked and moves via joint_states."""
    xml = big_limits(random_urdf(21, 5, joint_types=('revolute',)))
    names = load_urdf(xml).joint_names
    return xml, [names[0]] + names[2:], names[1]


def test_gravity_compensation_matches_pinocchio(ros, chain):
    """Latched description before start; streamed joint_states with a moving locked joint;
    gravity parameter change; payload at run time (parameter service); clamp."""
    xml, ctrl, locked = chain
    ros.desc_pub.publish(String(data=xml))  # transient local: the node starts later
    node = ros.start(joints=ctrl, diagnostics_period=0.2)
    rng = np.random.default_rng(0)
    names = [locked, 'some_other_joint'] + ctrl[::-1]   # arbitrary order and extra joints
    sent = [(rng.uniform(-2, 2, len(ctrl)), rng.uniform(-1.5, 1.5)) for _ in range(40)]
    for q, ql in sent:  # one at a time: joint_states keeps only the newest message (depth 1)
        ros.send(names, [ql, 0.5] + q[::-1].tolist())
    time.sleep(0.05)
    assert len(ros.cmds) == len(sent)  # one command per accepted message
    for (q, ql), tau in zip(sent, ros.cmds, strict=True):
        np.testing.assert_allclose(tau, Oracle(xml, joints=ctrl, locked={locked: ql}).gravity(q), atol=TOL, rtol=0)
    q, ql = sent[-1]
    names = ctrl + [locked]

    # wall mount: gravity along -y
    assert all(r.successful for r in ros.set_params(gravity=[0.0, -9.81, 0.0]))
    tau = ros.send(names, list(q) + [ql])
    ref = Oracle(xml, joints=ctrl, locked={locked: ql}, gravity=(0.0, -9.81, 0.0)).gravity(q)
    np.testing.assert_allclose(tau, ref, atol=TOL, rtol=0)

    # payload at run time, through the parameter services (as `ros2 param set` does)
    link = [k for k, (b, _) in node.core.model.link_frames.items() if b == node.core.model.nb - 1][0]
    client = AsyncParameterClient(ros.t, 'dynamics_node')
    assert client.wait_for_services(timeout_sec=TIMEOUT)
    inertia = [0.01, 0.001, 0.0, 0.02, 0.0, 0.015]
    fut = client.set_parameters_atomically([
        Parameter('payload.link', value=link), Parameter('payload.mass', value=1.7),
        Parameter('payload.com', value=[0.05, -0.02, 0.1]), Parameter('payload.inertia', value=inertia)])
    wait_until(fut.done, what='set_parameters')
    assert fut.result().result.successful, fut.result().result.reason
    tau = ros.send(names, list(q) + [ql])
    xml_p = with_payload(xml, link, 1.7, [0.05, -0.02, 0.1], inertia)
    ref = Oracle(xml_p, joints=ctrl, locked={locked: ql}, gravity=(0.0, -9.81, 0.0)).gravity(q)
    np.testing.assert_allclose(tau, ref, atol=TOL, rtol=0)

    # clamp: effort limits scaled down far below the gravity torques
    limit = 1e6 * 2e-6
    assert all(r.successful for r in ros.set_params(effort_limit_scale=2e-6))
    tau = ros.send(names, list(q) + [ql])
    assert np.any(np.abs(ref) > limit)
    np.testing.assert_allclose(tau, np.clip(ref, -limit, limit), atol=TOL, rtol=0)
    assert np.all(np.abs(tau) <= limit)
    wait_until(lambda: any('clamped' in line for line in ros.logs), what='clamp log')
    wait_until(lambda: int(ros.diag_values().get('clamp_count', 0)) >= 1, what='clamp diag')
    v = ros.diag_values()
    assert v['model_name'] == 'random_21_5' and v['joint_count'] == str(len(ctrl))
    assert v['locked_joints'] == locked


def test_bad_joint_states_are_rejected_and_logged_once(ros, chain):
    xml, ctrl, locked = chain
    ros.desc_pub.publish(String(data=xml))
    ros.start(joints=ctrl)
    n = len(ctrl)
    q = np.linspace(-1, 1, n)
    good = (ctrl, q)
    ref = Oracle(xml, joints=ctrl).gravity(q)
    cases = {
        'lengths differ': [(ctrl, q[:-1]), (ctrl, q, [0.0]), (ctrl, q, [], [0.0] * (n + 1))],
        'duplicate': [(ctrl + [ctrl[0]], list(q) + [0.0])] * 3,
        'non-finite': [(ctrl, list(q[:-1]) + [math.nan]), (ctrl, list(q[:-1]) + [math.inf]),
                       (ctrl + [locked], list(q) + [math.nan])],
        'missing controlled': [(ctrl[1:], q[1:])],
    }
    t0 = time.monotonic()
    for msgs in cases.values():
        for bad in msgs:
            tau = ros.send_rejected(good, *bad)
            np.testing.assert_allclose(tau, ref, atol=TOL, rtol=0)
    # one throttled log line per problem although several messages were bad (within LOG_THROTTLE_S)
    wait_until(lambda: all(any(p in line for line in ros.logs) for p in cases), what='rejection logs')
    time.sleep(0.1)
    for problem in cases:
        n, most = throttled(ros.logs, problem, t0)
        assert 1 <= n <= most, (problem, most, ros.logs)
    assert ros.node.core.count.rejected == sum(len(m) for m in cases.values())


def test_nan_velocity_velocity_terms_and_joint_state_output(ros, chain):
    xml, ctrl, locked = chain
    ros.desc_pub.publish(String(data=xml))
    ros.start(joints=ctrl, include_velocity_terms=True, publish_joint_state=True)
    wait_until(lambda: ros.t.count_publishers('/dynamics_node/commanded_efforts') >= 1, what='efforts pub')
    n = len(ctrl)
    rng = np.random.default_rng(3)
    q, qd = rng.uniform(-1, 1, n), rng.uniform(-2, 2, n)
    o = Oracle(xml, joints=ctrl)
    tau = ros.send(ctrl, q, qd, [0.0] * n)
    np.testing.assert_allclose(tau, o.rnea(q, qd, np.zeros(n)), atol=TOL, rtol=0)
    qd[2] = math.nan   # joint_state_broadcaster sends NaN for a missing velocity interface
    tau = ros.send(ctrl, q, qd)
    qd[2] = 0.0
    np.testing.assert_allclose(tau, o.rnea(q, qd, np.zeros(n)), atol=TOL, rtol=0)
    assert np.all(np.isfinite(tau))
    wait_until(lambda: len(ros.efforts) >= 2, what='JointState output')
    assert list(ros.efforts[-1].name) == ctrl
    np.testing.assert_array_equal(np.array(ros.efforts[-1].effort), tau)


def test_stale_input_hold_zero_and_recovery(ros, chain):
    xml, ctrl, locked = chain
    ros.desc_pub.publish(String(data=xml))
    ros.start(joints=ctrl, include_velocity_terms=True, stale_timeout=0.25, diagnostics_period=0.1)
    n = len(ctrl)
    q, qd = np.full(n, 0.3), np.full(n, 1.5)
    o = Oracle(xml, joints=ctrl)
    t0 = time.monotonic()
    tau = ros.send(ctrl, q, qd)
    np.testing.assert_allclose(tau, o.rnea(q, qd, np.zeros(n)), atol=TOL, rtol=0)
    wait_until(lambda: len(ros.cmds) == 2, timeout=3.0, what='stale command')
    assert time.monotonic() - t0 >= 0.25
    np.testing.assert_allclose(ros.cmds[1], o.gravity(q), atol=TOL, rtol=0)   # velocity terms dropped
    wait_until(lambda: ros.diag_values().get('stale') == 'True' and ros.diag_level() == 1, what='stale diag')
    time.sleep(0.3)
    assert len(ros.cmds) == 2   # applied once, not repeated
    tau = ros.send(ctrl, q, qd)  # recovery
    np.testing.assert_allclose(tau, o.rnea(q, qd, np.zeros(n)), atol=TOL, rtol=0)
    wait_until(lambda: ros.diag_values().get('stale') == 'False', what='recovered diag')
    assert all(r.successful for r in ros.set_params(stale_action='zero'))
    wait_until(lambda: len(ros.cmds) == 4, timeout=3.0, what='zero stale command')
    np.testing.assert_array_equal(ros.cmds[3], np.zeros(n))
    assert ros.node.core.watchdog.stale_events == 2
    assert any('compensation resumed' in line for line in ros.logs)


def test_bad_description_keeps_previous_model(ros, chain):
    xml, ctrl, locked = chain
    ros.desc_pub.publish(String(data=xml))
    node = ros.start(joints=ctrl, diagnostics_period=0.1)
    q = np.linspace(-0.5, 0.5, len(ctrl))
    names = ctrl + [locked]
    ref = Oracle(xml, joints=ctrl, locked={locked: 0.2}).gravity(q)
    np.testing.assert_allclose(ros.send(names, list(q) + [0.2]), ref, atol=TOL, rtol=0)
    # a floating joint below the controlled ones (above them it is taken as fixed, as kdl_parser does)
    tip = re.search(rf'<joint name="{ctrl[-1]}".*?<child link="([^"]+)"', xml, re.DOTALL).group(1)
    floating = xml.replace('</robot>', '<link name="free_body"><inertial><mass value="1"/><inertia ixx="0.01" '
                                       'ixy="0" ixz="0" iyy="0.01" iyz="0" izz="0.01"/></inertial></link>'
                                       '<joint name="float_j" type="floating">'
                                       f'<parent link="{tip}"/><child link="free_body"/></joint></robot>')
    bad = {
        'malformed': '<robot name="x"><link name="a"></robot',
        'floating': floating,
        ctrl[0]: xml.replace(f'"{ctrl[0]}"', '"renamed_joint"'),
        'not URDF': 'just some text',
    }
    for why, text in bad.items():
        node.core.description_error = ''
        ros.desc_pub.publish(String(data=text))
        wait_until(lambda: node.core.description_error != '', what=f'rejection of {why}')
        assert why in node.core.description_error, node.core.description_error
        np.testing.assert_allclose(ros.send(names, list(q) + [0.2]), ref, atol=TOL, rtol=0)
    wait_until(lambda: ros.diag_values().get('description_error') and ros.diag_level() == 1,
               what='diagnostics')
    assert 'previous model kept' in ros.diag.message
    # a good update replaces the model; locked values survive the swap
    heavier = re.sub(r'<mass value="([^"]*)"', lambda m: f'<mass value="{3 * float(m.group(1))!r}"', xml)
    ros.desc_pub.publish(String(data=heavier))
    wait_until(lambda: node.core.description_error == '', what='model update')
    ref = Oracle(heavier, joints=ctrl, locked={locked: 0.2}).gravity(q)
    np.testing.assert_allclose(ros.send(ctrl, q), ref, atol=TOL, rtol=0)


def test_services_enable_and_reload(ros, chain, tmp_path):
    xml, ctrl, locked = chain
    path = tmp_path / 'robot.urdf'
    path.write_text(xml)
    ros.start(joints=ctrl, urdf_path=str(path))
    q = np.linspace(0.1, 0.9, len(ctrl))
    ref = Oracle(xml, joints=ctrl).gravity(q)
    np.testing.assert_allclose(ros.send(ctrl, q), ref, atol=TOL, rtol=0)

    res = ros.call(SetBool, '/dynamics_node/set_enabled', SetBool.Request(data=False))
    assert res.success
    wait_until(lambda: len(ros.cmds) == 2, what='zero command on disable')
    np.testing.assert_array_equal(ros.cmds[1], np.zeros(len(ctrl)))
    assert ros.node.get_parameter('enabled').value is False
    n0 = ros.node.core.count.accepted
    ros.publish(ctrl, q)
    wait_until(lambda: ros.node.core.count.accepted == n0 + 1, what='disabled message processed')
    assert len(ros.cmds) == 2  # silent while disabled
    assert ros.call(SetBool, '/dynamics_node/set_enabled', SetBool.Request(data=True)).success
    np.testing.assert_allclose(ros.send(ctrl, q), ref, atol=TOL, rtol=0)

    # the reload runs in the background: answered at once, the new model swaps in when ready
    heavier = re.sub(r'<mass value="([^"]*)"', lambda m: f'<mass value="{2 * float(m.group(1))!r}"', xml)
    path.write_text(heavier)
    model = ros.node.core.model
    res = ros.call(Trigger, '/dynamics_node/reload_model', Trigger.Request())
    assert res.success and 'loading' in res.message, res.message
    wait_until(lambda: ros.node.core.model is not model, timeout=MODEL_TIMEOUT, what='reloaded model')
    np.testing.assert_allclose(ros.send(ctrl, q), Oracle(heavier, joints=ctrl).gravity(q), atol=TOL, rtol=0)
    path.write_text('<robot name="broken"><link name=')
    res = ros.call(Trigger, '/dynamics_node/reload_model', Trigger.Request())
    assert res.success, res.message  # started; the failure is reported by the log and the diagnostics
    wait_until(lambda: 'malformed' in ros.node.core.description_error, what='reload failure')
    np.testing.assert_allclose(ros.send(ctrl, q), Oracle(heavier, joints=ctrl).gravity(q), atol=TOL, rtol=0)
    path.unlink()  # refused at once: nothing to read
    res = ros.call(Trigger, '/dynamics_node/reload_model', Trigger.Request())
    assert not res.success and 'not found' in res.message


def test_no_model_publishes_nothing_and_parameter_validation(ros, chain):
    xml, ctrl, locked = chain
    volatile = ros.t.create_publisher(String, 'robot_description', 10)   # a common mistake
    node = ros.start(wait_model=False, joints=ctrl, diagnostics_period=0.1)
    wait_until(lambda: any('volatile durability' in line and 'node_tester' in line for line in ros.logs),
               what='incompatible publisher warning')
    ros.on_spin_thread(ros.t.destroy_publisher, volatile)
    q = np.zeros(len(ctrl))
    for _ in range(3):
        ros.publish_processed(ctrl, q)
    wait_until(lambda: any('no robot model' in line for line in ros.logs), what='no-model log')
    assert ros.cmds == []
    ros.desc_pub.publish(String(data=xml))
    wait_until(lambda: node.core.model is not None, timeout=MODEL_TIMEOUT, what='model')
    np.testing.assert_allclose(ros.send(ctrl, q), Oracle(xml, joints=ctrl).gravity(q), atol=TOL, rtol=0)
    assert sum('no robot model' in line for line in ros.logs) == 1   # said once

    rejected = [dict(gravity_scale=1.5), dict(gravity=[0.0, -9.81]), dict(stale_action='freeze'),
                dict(joints=['a']), dict(command_topic='/x'), dict(payload__link='no_such_link'),
                dict(**{'friction.viscous': [0.1, 0.2]}), dict(**{'payload.mass': 2.0}),
                dict(urdf_path='/nonexistent.urdf')]
    for change in rejected:
        change = {k.replace('__', '.'): v for k, v in change.items()}
        change.setdefault('payload.mass', 2.0) if 'payload.link' in change else None
        res = node.set_parameters_atomically([Parameter(k, value=v) for k, v in change.items()])
        assert not res.successful, change
    np.testing.assert_allclose(ros.send(ctrl, q), Oracle(xml, joints=ctrl).gravity(q), atol=TOL, rtol=0)



def test_parameter_change_is_validated_whole_then_applied(ros, chain):
    """on_set validates the whole change (a new description is built but not made current);
    post_set applies it: a bad setting next to a good description rejects both."""
    xml, ctrl, locked = chain
    node = ros.start(joints=ctrl, robot_description=xml, publish_joint_state=False)
    model = node.core.model
    q = np.linspace(-0.5, 0.5, len(ctrl))
    heavier = re.sub(r'<mass value="([^"]*)"', lambda m: f'<mass value="{3 * float(m.group(1))!r}"', xml)
    res = node.set_parameters_atomically([Parameter('robot_description', value=heavier),
                                          Parameter('kp', value=[1.0, 2.0])])
    assert not res.successful and 'kp' in res.reason
    assert node.core.model is model and node.get_parameter('robot_description').value == xml
    np.testing.assert_allclose(ros.send(ctrl, q), Oracle(xml, joints=ctrl).gravity(q), atol=TOL, rtol=0)
    # accepted: the new model, the setting and the new publisher all come with the set
    res = node.set_parameters_atomically([Parameter('robot_description', value=heavier),
                                          Parameter('gravity_scale', value=0.5),
                                          Parameter('publish_joint_state', value=True)])
    assert res.successful, res.reason
    assert node.core.settings['gravity_scale'] == 0.5   # at once; the model when loaded (background)
    wait_until(lambda: node.core.model is not model, timeout=MODEL_TIMEOUT, what='new model')
    wait_until(lambda: ros.t.count_publishers('/dynamics_node/commanded_efforts') == 1, what='joint state publisher')
    ref = Oracle(heavier, joints=ctrl, gravity=(0.0, 0.0, -9.81 * 0.5)).gravity(q)
    np.testing.assert_allclose(ros.send(ctrl, q), ref, atol=TOL, rtol=0)
    wait_until(lambda: len(ros.efforts) >= 1, what='commanded_efforts')
    np.testing.assert_allclose(np.array(ros.efforts[-1].effort), ref, atol=TOL, rtol=0)
    assert all(r.successful for r in ros.set_params(publish_joint_state=False))
    wait_until(lambda: ros.t.count_publishers('/dynamics_node/commanded_efforts') == 0, what='publisher gone')

# Link `tip` breaks the triangle inequality of its inertia (0.001 + 0.001 < 0.01 kg m^2).
BAD_INERTIA = (
    '<robot name="bad_inertia"><link name="base_link"/>'
    '<link name="arm"><inertial><origin xyz="0 0 0.1"/><mass value="1"/>'
    '<inertia ixx="0.01" ixy="0" ixz="0" iyy="0.01" iyz="0" izz="0.005"/></inertial></link>'
    '<joint name="j1" type="revolute"><parent link="base_link"/><child link="arm"/><axis xyz="0 1 0"/>'
    '<limit effort="100" velocity="1" lower="-3" upper="3"/></joint>'
    '<link name="tip"><inertial><mass value="0.05"/>'
    '<inertia ixx="0.001" ixy="0" ixz="0" iyy="0.001" iyz="0" izz="0.01"/></inertial></link>'
    '<joint name="j2" type="revolute"><parent link="arm"/><child link="tip"/><origin xyz="0 0 0.2"/>'
    '<axis xyz="0 1 0"/><limit effort="100" velocity="1" lower="-3" upper="3"/></joint></robot>')


def test_log_lines_reach_rosout_with_their_level_and_call_site_and_the_logger_level_applies(ros, chain):
    """The node's log lines (Outputs.log_line, through rclpy's C logging call) arrive on /rosout
    as rclpy's logger would send them, and a level set for the node's logger still filters."""
    from rclpy.logging import LoggingSeverity

    from lie_dynamics.ros import outputs
    node = ros.start(wait_model=False)
    for severity in ('info', 'warn', 'error'):
        node.outputs.log_line(severity, f'probe line {severity}')
    wait_until(lambda: sum(r.msg.startswith('probe line') for r in ros.records) == 3, what='probe lines')
    got = {r.msg: r for r in ros.records if r.msg.startswith('probe line')}
    assert {k: r.level for k, r in got.items()} == {'probe line info': Log.INFO, 'probe line warn': Log.WARN,
                                                    'probe line error': Log.ERROR}
    for r in got.values():
        assert (r.function, os.path.basename(r.file), r.line) == (
            'log_line', 'outputs.py', outputs.Outputs.log_line.__code__.co_firstlineno)
    node.get_logger().set_level(LoggingSeverity.ERROR)
    try:
        node.outputs.log_line('warn', 'filtered warn')
        node.outputs.log_line('error', 'kept error')
        wait_until(lambda: 'kept error' in ros.logs, what='the error line')
        assert 'filtered warn' not in ros.logs   # published before the error line: it would be here
    finally:
        node.get_logger().set_level(LoggingSeverity.INFO)


def test_inertia_policy_strict_refuses_then_warn_loads(ros):
    # at start-up a description the policy refuses is a configuration that cannot work: no node
    with pytest.raises(ValueError, match='tip'):
        DynamicsNode(context=ros.ctx, parameter_overrides=[Parameter('robot_description', value=BAD_INERTIA),
                                                           Parameter('inertia_policy', value='strict')])
    node = ros.start(wait_model=False, inertia_policy='strict', diagnostics_period=0.1)
    ros.desc_pub.publish(String(data=BAD_INERTIA))   # later, from the topic: refused, the node keeps running
    wait_until(lambda: ros.diag_level() == 2 and 'tip' in ros.diag_values().get('description_error', ''),
               timeout=MODEL_TIMEOUT, what='strict refusal in the diagnostics')
    assert node.core.model is None
    # the policy change reloads the refused description (in the background)
    assert all(r.successful for r in ros.set_params(inertia_policy='warn'))
    wait_until(lambda: node.core.model is not None, what='reload under the new policy')
    assert node.core.model.name == 'bad_inertia'
    wait_until(lambda: ros.diag_values().get('inertia_warnings') == '1', what='inertia diagnostics')
    wait_until(lambda: any('tip' in line and 'triangle inequality' in line for line in ros.logs),
               what='inertia log line')
    # strict while that model runs: refused, model and policy stay
    res = ros.set_params(inertia_policy='strict')[0]
    assert not res.successful and 'tip' in res.reason
    assert node.get_parameter('inertia_policy').value == 'warn' and node.core.model.name == 'bad_inertia'


def test_shipped_wall_mount_config(ros):
    """config/wall_mount_payload.yaml: gravity along -x, velocity terms, 1.5 kg on tool0, 0.9 x limits."""
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    node = ros.start(params_file=os.path.join(root, 'config', 'wall_mount_payload.yaml'))
    xml = open(os.path.join(root, 'config', 'arm7.urdf')).read()
    joints = [f'joint{i}' for i in range(1, 8)]
    assert node.core.layout == joints and node.core.model.name == 'lie_arm7'
    xml_p = with_payload(xml, 'tool0', 1.5, [0.0, 0.0, 0.06], [0.004, 0.0, 0.0, 0.004, 0.0, 0.002])
    o = Oracle(xml_p, joints=joints, gravity=(-9.81, 0.0, 0.0))
    model = load_urdf(xml)
    lim = 0.9 * model.effort_limits
    rng = np.random.default_rng(7)
    for _ in range(5):  # within the joint limits: the shipped config checks positions against them
        q, qd = rng.uniform(model.position_lower, model.position_upper), rng.uniform(-1, 1, 7)
        tau = ros.send(joints, q, qd)
        np.testing.assert_allclose(tau, np.clip(o.rnea(q, qd, np.zeros(7)), -lim, lim), atol=TOL, rtol=0)


@pytest.mark.parametrize('params, reason', [
    (['stale_action:=freeze'], 'stale_action'),
    (['urdf_path:=/nonexistent.urdf'], 'not found'),                    # a launch-file typo
    (['robot_description:=<robot name="x"><link'], 'malformed'),
    (['robot_description:=not xml', 'urdf_path:=config/arm7.urdf'], 'not URDF XML'),  # no silent fallback
    (['urdf_path:=config/arm7.urdf', 'joints:=[joint1,nope]'], "unknown joint 'nope'"),
])
def test_module_entry_point_rejects_bad_configuration(params, reason):
    """A start-up value that cannot work ends the process: one line on stderr, exit status 2."""
    args = [a for p in params for a in ('-p', p)]
    proc = subprocess.run([sys.executable, '-m', 'lie_dynamics.dynamics_node', '--ros-args', *args],
                          capture_output=True, text=True, timeout=60,
                          cwd=os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    assert proc.returncode == 2, proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1 and reason in proc.stderr, proc.stderr
    assert proc.stderr.startswith('dynamics_node: invalid configuration: ')
