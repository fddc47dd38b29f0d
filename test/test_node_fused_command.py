"""The fused command path (ros/core/fused.py, codegen/native_command.c) against the Python path:
two nodes in one process, one with it and one without (node.fused = None), fed the same
serialized joint_states and desired states. The command's and ~/commanded_efforts' bytes are
the same bit for bit, and so is what the core keeps (counters, q, stamp, result, law) for every
mode it covers, on the bundled arm and on a 30-joint tree with locked joints, clamped commands
included; and each case it does not cover (a layout change, a non-finite or an out-of-range
position, a ramp, a mode change, a stale desired state, an older stamp, no native kernel) is
declined, then decided by the Python path as without it."""
import re
import time

import numpy as np
import pytest

rclpy = pytest.importorskip('rclpy')

from rclpy.context import Context  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from rclpy.serialization import serialize_message  # noqa: E402
from sensor_msgs.msg import JointState  # noqa: E402
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint  # noqa: E402

from lie_dynamics import default_urdf_path, load_urdf  # noqa: E402
from lie_dynamics.codegen import native  # noqa: E402
from lie_dynamics.codegen.cache import use_native  # noqa: E402
from lie_dynamics.ros.core import fused as fused_module  # noqa: E402
from lie_dynamics.ros.core.cdr import joint_state_template  # noqa: E402
from lie_dynamics.ros.node import DynamicsNode  # noqa: E402
from robots import random_urdf  # noqa: E402

pytestmark = pytest.mark.skipif(native.module() is None, reason='no C compiler: the Python path only')

ARM_JOINTS = [f'joint{i}' for i in range(1, 8)]
T0 = 1_700_000_000 * 10 ** 9


class _Recorder:
    def __init__(self, sent, kind):
        self.sent, self.kind = sent, kind

    def publish(self, data):
        self.sent.append((self.kind, bytes(data)))

    def close(self):
        pass


@pytest.fixture(scope='module')
def ctx():
    c = Context()
    rclpy.init(context=c)
    yield c
    c.try_shutdown()


@pytest.fixture(scope='module')
def big(tmp_path_factory):
    """A 30-joint tree; 28 controlled, two locked (their values fed to the model)."""
    path = tmp_path_factory.mktemp('fused') / 'tree30.urdf'
    path.write_text(wide_limits(random_urdf(30, 30, tree=True, fixed_links=False, massless_links=False)))
    names = load_urdf(str(path)).joint_names
    return str(path), list(names), list(names[:14]) + list(names[16:])


class Pair:
    """The node with the fused path and the node without it, fed the same messages."""

    def __init__(self, ctx, urdf, names, joints, **params):
        self.names, self.joints = names, joints
        params = {**dict(urdf_path=urdf, joints=joints, stale_timeout=60.0, ramp_time=0.0, publish_joint_state=True,
                         desired_timeout=60.0), **params}
        self.nodes, self.sent = [], []
        for on in (True, False):
            node = DynamicsNode(f'fused_{"on" if on else "off"}_{id(self)}', context=ctx,
                                parameter_overrides=[Parameter(p, value=v) for p, v in params.items()])
            if not on:
                node.fused = None
            sent = []
            node.outputs._cmd_pub = _Recorder(sent, 'command')
            node.outputs._js_pub = _Recorder(sent, 'commanded_efforts')
            self.nodes.append(node)
            self.sent.append(sent)
        self.on, self.off = self.nodes
        m = self.on.core.model
        q = np.zeros(m.n)
        for node in self.nodes:   # the kernels built now: no state of the run falls to the reference
            node.core.model.gravity(q)
            node.core.model.inverse_dynamics(q, q, q)
        self.model = m
        self.rng = np.random.default_rng(3)
        self.k = 0

    def close(self):
        for node in self.nodes:
            node.destroy_node()

    def state(self, order=None, q=None, velocity=None, rclpy_bytes=False):
        """A serialized joint_states of a random state (controlled joints within their limits,
        locked joints at fixed values), names in `order` (default: the URDF's); its padding zeros
        (cdr.joint_state_template), or rclpy's (rclpy_bytes: not all defined, see
        test_node_output_cdr.py)."""
        m, rng = self.model, self.rng
        lo, hi = np.maximum(m.position_lower, -1.5), np.minimum(m.position_upper, 1.5)
        values = dict(zip(self.names, [0.1 * (k % 3) for k in range(len(self.names))], strict=True))
        values.update(zip(m.joint_names, rng.uniform(lo, hi) if q is None else q, strict=True))
        order = self.names if order is None else order
        n = len(order)
        pos = [values[j] for j in order]
        vel = rng.uniform(-1, 1, n) if velocity is None else np.asarray(velocity, dtype=float)
        eff = rng.uniform(-5, 5, n)
        stamp = T0 + self.k * 1_000_000
        self.k += 1
        if rclpy_bytes:
            msg = JointState(name=order, position=pos, velocity=vel.tolist(), effort=eff.tolist())
            msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(stamp, 10 ** 9)
            return bytes(serialize_message(msg))
        t, stamp_at, slots = joint_state_template(order)
        return t.fill(slots, (pos, vel, eff), stamp_at, stamp)

    def desired(self):
        n, rng = self.model.n, self.rng
        point = JointTrajectoryPoint(positions=rng.uniform(-0.5, 0.5, n).tolist(),
                                     velocities=rng.uniform(-1, 1, n).tolist(),
                                     accelerations=rng.uniform(-2, 2, n).tolist())
        buf = bytes(serialize_message(JointTrajectory(joint_names=self.joints, points=[point])))
        for node in self.nodes:
            node._on_desired(buf)

    def feed(self, buf):
        """Both nodes take buf; the same bytes out and the same state kept. Returns whether the
        fused path took it."""
        taken = self.on.fused.taken
        for node in self.nodes:
            node.on_joint_state(buf)
        a, b = self.sent
        assert a == b
        ca, cb = self.on.core, self.off.core
        for name in type(ca.count).__slots__:
            assert getattr(ca.count, name) == getattr(cb.count, name), name
        assert (ca.last_stamp, ca.law, ca.clamped) == (cb.last_stamp, cb.law, cb.clamped)
        assert (ca.last_cmd is None) == (cb.last_cmd is None)
        if ca.last_cmd is not None:
            assert ca.last_cmd.tobytes() == cb.last_cmd.tobytes()
        assert (ca.ramp.last is None) == (cb.ramp.last is None)
        if ca.ramp.last is not None:
            assert ca.ramp.last.tobytes() == cb.ramp.last.tobytes()
        assert (ca.last_q is None) == (cb.last_q is None)
        if ca.last_q is not None:
            assert ca.last_q.tobytes() == cb.last_q.tobytes()
        ra, rb = ca.result, cb.result
        assert (ra.stamp, ra.accepted, ra.reason, ra.why, ra.version) == (rb.stamp, rb.accepted, rb.reason, rb.why,
                                                                            rb.version)
        if ra.accepted:
            assert ra.q.tobytes() == rb.q.tobytes() and not ra.q.flags.writeable
            assert ra.velocity.tobytes() == rb.velocity.tobytes() and ra.effort.tobytes() == rb.effort.tobytes()
            assert list(ra.columns) == list(rb.columns)
        a.clear()
        b.clear()
        return self.on.fused.taken == taken + 1

    def set(self, **params):
        for node in self.nodes:
            assert all(r.successful for r in node.set_parameters([Parameter(k, value=v) for k, v in params.items()]))


@pytest.fixture
def arm(ctx):
    pairs = []

    def make(urdf=None, **params):
        pairs.append(Pair(ctx, urdf or default_urdf_path(), ARM_JOINTS, ARM_JOINTS, **params))
        return pairs[-1]
    yield make
    for p in pairs:
        p.close()


COVERED = [('gravity', {}), ('gravity', {'friction.viscous': [0.0], 'friction.coulomb': [0.0]}),
           ('feedforward', {'kp': [30.0], 'kd': [2.0]}), ('feedforward', {}),
           ('feedforward', {'kp': [30.0], 'friction.viscous': [0.0], 'friction.coulomb': [0.0]}),
           ('computed_torque', {'kp': [30.0], 'kd': [2.0]}),
           ('computed_torque', {'kd': [2.0], 'friction.viscous': [0.0]})]


def wide_limits(xml):
    """The robot with every effort limit 10^4 times its own: random desired states far from the
    measured one, and random trees' gravity, are then never clamped (the clamp has its own test)."""
    return re.sub(r'effort="([^"]*)"', lambda m: f'effort="{float(m.group(1)) * 1e4!r}"', xml)


@pytest.fixture(scope='module')
def wide_arm(tmp_path_factory):
    path = tmp_path_factory.mktemp('fused') / 'arm7_wide.urdf'
    with open(default_urdf_path(), encoding='utf-8') as fh:
        path.write_text(wide_limits(fh.read()))
    return str(path)


@pytest.mark.parametrize('mode,params', COVERED)
def test_the_same_bytes_on_the_arm(arm, wide_arm, mode, params):
    """Every state after the first two (a new layout, then the layout repeated) is taken and gives
    the Python path's bytes."""
    p = arm(urdf=wide_arm, mode=mode, **params)
    if mode != 'gravity':
        p.desired()
    took = [p.feed(p.state(order=ARM_JOINTS[::-1])) for _ in range(30)]
    assert took == [False, False] + [True] * 28
    if mode != 'gravity':   # a new desired state before every state: handed to the Command, the same bytes
        made = []
        make = p.on.fused._make
        p.on.fused._make = lambda *args: made.append(1) or make(*args)
        for _ in range(5):
            p.desired()
            assert p.feed(p.state(order=ARM_JOINTS[::-1]))
        assert not made


@pytest.mark.parametrize('mode', ['gravity', 'feedforward', 'computed_torque'])
def test_the_same_bytes_on_a_30_joint_tree_with_locked_joints(ctx, big, mode):
    urdf, names, joints = big
    p = Pair(ctx, urdf, names, joints, mode=mode, kp=[20.0], kd=[1.0])
    try:
        if mode != 'gravity':
            p.desired()
        took = [p.feed(p.state()) for _ in range(20)]
        assert took == [False, False] + [True] * 18
    finally:
        p.close()


def test_each_unusual_state_is_declined_and_decided_by_the_python_path(arm):
    p = arm()
    assert [p.feed(p.state()) for _ in range(3)] == [False, False, True]
    # a layout change: the new layout's first two states by the Python path, then taken again
    assert [p.feed(p.state(order=ARM_JOINTS[::-1])) for _ in range(4)] == [False, False, True, True]
    q = np.zeros(7)
    q[2] = np.nan   # non-finite position: refused by the Python path
    assert not p.feed(p.state(order=ARM_JOINTS[::-1], q=q))
    assert p.on.core.result.reason == 'nonfinite'
    q[2] = 100.0    # outside its range
    assert not p.feed(p.state(order=ARM_JOINTS[::-1], q=q))
    assert p.on.core.result.reason == 'implausible'
    assert p.feed(p.state(order=ARM_JOINTS[::-1]))
    # a non-finite velocity: used by the friction law, counted unavailable by the Python path
    assert not p.feed(p.state(order=ARM_JOINTS[::-1], velocity=[np.nan] * 7))
    assert p.on.core.count.velocity_unavailable == 1
    # an older stamp: refused by the Python path
    p.k -= 5
    assert not p.feed(p.state(order=ARM_JOINTS[::-1]))
    assert p.on.core.result.reason == 'old'
    p.k += 10
    assert p.feed(p.state(order=ARM_JOINTS[::-1]))



def test_a_layout_that_never_repeats_makes_no_fused_command(arm):
    """A publisher whose padding bytes change from message to message (rclpy's serialize_message
    leaves them undefined) never repeats its layout: the decoder walks every message, and no fused
    command is made for one (it would be made for nothing at every message)."""
    p = arm()
    made = []
    make = p.on.fused._make
    p.on.fused._make = lambda *args: made.append(1) or make(*args)
    took = []
    for k in range(10):
        buf = bytearray(p.state())
        buf[17] = k + 1   # the padding after the empty frame_id
        took.append(p.feed(bytes(buf)))
    assert not any(took) and not made
    assert [p.feed(p.state()) for _ in range(3)] == [False, False, True] and made == [1]


def test_clamped_commands_are_fused_and_the_ramp_is_the_python_paths(arm):
    """A clamped command (every joint, or some) is the fused path's too: the same bytes, the same
    count, names and log line; the ramp stays the Python path's."""
    p = arm()
    said = ([], [])
    for node, lines in zip(p.nodes, said, strict=True):   # the core's log lines, as queued
        event = node.core.event
        node.core.event = lambda *a, event=event, lines=lines: lines.append(a) or event(*a)
    assert [p.feed(p.state()) for _ in range(3)] == [False, False, True]
    p.set(effort_limit_scale=1e-3)   # every command clamped
    assert all(p.feed(p.state()) for _ in range(3))   # (new settings: a new Command, at once)
    assert p.on.core.count.clamp_count == 3 and p.on.core.clamped == ARM_JOINTS
    clamp_lines = [[a for a in lines if a[1] == 'clamp'] for lines in said]
    assert len(clamp_lines[0]) == 3 and clamp_lines[0] == clamp_lines[1]
    g = np.abs(p.on.core.model.gravity(np.zeros(7)))
    p.set(effort_limit_scale=float(np.median(g[g > 0] / p.on.core.model.effort_limits[g > 0])))
    took = [p.feed(p.state(q=np.zeros(7))) for _ in range(3)]   # some joints clamped, the others not
    assert all(took) and 0 < len(p.on.core.clamped) < 7
    assert p.on.core.count.clamp_count == 6
    p.set(effort_limit_scale=1.0)
    assert p.feed(p.state()) and p.on.core.clamped is None
    p.set(ramp_time=0.5)
    p.set(gravity_scale=0.99)   # a blend under way, shaped by the Python path
    assert not p.feed(p.state())
    assert not p.on.core.ramp.idle


def test_a_mode_it_does_not_cover_and_a_fallback_are_declined(arm, wide_arm):
    p = arm(urdf=wide_arm, mode='feedforward', desired_timeout=0.5)
    p.desired()
    assert [p.feed(p.state()) for _ in range(3)] == [False, False, True]
    p.set(mode='pd')
    assert not any(p.feed(p.state()) for _ in range(2))
    p.set(mode='feedforward')
    p.desired()
    assert p.feed(p.state())
    time.sleep(0.7)   # the desired state goes stale: gravity instead, said by the Python path
    assert not p.feed(p.state())
    assert p.on.core.law == 'gravity (fallback)'
    p.desired()   # fresh again: the Python path says so once, then the fused path
    assert [p.feed(p.state()) for _ in range(2)] == [False, True]


def test_without_a_native_kernel_the_python_path(arm, monkeypatch):
    p = arm()
    assert [p.feed(p.state()) for _ in range(3)] == [False, False, True]
    for node in p.nodes:   # this model's kernels: the Python ones (built now, not deferred)
        use_native(node.core.model, False)
    native.invalidate()
    for node in p.nodes:
        node.core.model.gravity(np.zeros(7))
    assert not any(p.feed(p.state()) for _ in range(3))
    for node in p.nodes:
        use_native(node.core.model, True)
    native.invalidate()
    assert p.feed(p.state())
    monkeypatch.setattr(fused_module.native, 'module', lambda: None)   # no C compiler
    p.set(kp=[1.0])   # a new key: the fused command is made again, without the backend
    assert not any(p.feed(p.state()) for _ in range(3))



def test_switched_off_there_is_none(ctx, monkeypatch):
    """LIE_DYNAMICS_FUSED_COMMAND=0 (node.FUSED_COMMAND): no fused path, the Python path for every state."""
    from lie_dynamics.ros import node as node_module
    monkeypatch.setattr(node_module, 'FUSED_COMMAND', False)
    node = DynamicsNode('fused_switched_off', context=ctx,
                        parameter_overrides=[Parameter('urdf_path', value=default_urdf_path())])
    try:
        assert node.fused is None
    finally:
        node.destroy_node()
