"""The node's serialized outputs (ros/outputs.py: the effort command, ~/commanded_efforts) and the
writers under them (cdr.multi_array_template, joint_state_template, Writer) byte for byte against
rclpy's serialize_message of the same message objects.

rclpy's bytes are not all defined: its alignment padding is whatever was in the buffer (seen:
'osi' after a frame_id's terminating zero) and its length is its size estimate, up to 8 bytes past
the message. So `same_bytes` compares every byte but the padding, which ours writes as zeros, and
the message read back from our bytes by rclpy must be the one serialized, bit for bit."""
import numpy as np
import pytest

pytest.importorskip('rclpy')
from rclpy.serialization import deserialize_message, serialize_message  # noqa: E402
from sensor_msgs.msg import JointState  # noqa: E402
from std_msgs.msg import Float64MultiArray, MultiArrayDimension  # noqa: E402

from lie_dynamics.ros.core.cdr import joint_state_template, multi_array_template, stamp_parts  # noqa: E402
from lie_dynamics.ros.outputs import Outputs  # noqa: E402

NAMES = [[], ['x'], ['joint1', 'j2é', 'a_longer_joint_name_3'], [f'arm_{k}_joint' for k in range(30)]]
STAMPS = [0, 1, 999_999_999, 1_700_000_000 * 10 ** 9 + 123_456_789, -1_500_000_000]


class _Publisher:
    """What Outputs asks of an rclpy publisher: its handle, held in use while it publishes raw bytes
    (interfaces.SerializedPublisher), recorded."""

    def __init__(self):
        self.sent = []
        self.handle, self.in_use = self, 0

    def __enter__(self):
        self.in_use += 1

    def __exit__(self, *exc):
        self.in_use -= 1

    def publish_raw(self, data):
        assert self.in_use == 1
        self.sent.append(data)


class _Clock:
    def now(self):
        return type('Now', (), {'nanoseconds': 42 * 10 ** 9 + 7})()


class _Node:
    """What Outputs asks of a node: publishers (recorded by topic) and the clock."""

    def __init__(self):
        self.publishers = {}

    def create_publisher(self, kind, name, qos, event_callbacks=None):
        return self.publishers.setdefault(name, _Publisher())

    def destroy_publisher(self, pub):
        self.publishers = {k: v for k, v in self.publishers.items() if v is not pub}

    def get_clock(self):
        return _Clock()


def same_bytes(ours, msg):
    """ours is msg's CDR: rclpy reads it back as msg (every field, floats by their bits), and
    rclpy's serialization of msg has the same bytes wherever ours is not a zero of padding."""
    theirs = bytes(serialize_message(msg))
    back = deserialize_message(ours, type(msg))
    for field in msg.get_fields_and_field_types():
        a, b = getattr(back, field), getattr(msg, field)
        if field in ('data', 'position', 'velocity', 'effort'):
            assert np.asarray(a, dtype=float).tobytes() == np.asarray(b, dtype=float).tobytes(), field
        else:
            assert a == b, field
    assert 0 <= len(theirs) - len(ours) <= 8, (len(theirs), len(ours))
    differ = [i for i in range(len(ours)) if ours[i] != theirs[i]]
    assert all(ours[i] == 0 for i in differ), differ
    return True


def _joint_state(names, effort, ns):
    msg = JointState(name=names, effort=effort.tolist())
    msg.header.stamp.sec, msg.header.stamp.nanosec = stamp_parts(ns)
    return msg


@pytest.mark.parametrize('names', NAMES)
def test_command_and_commanded_efforts_are_rclpys_bytes(names):
    """Outputs.command publishes bytes equal to serialize_message of the Float64MultiArray and
    of the JointState (stamp, names, efforts; no positions or velocities) it published before;
    the stamp of the input, or the clock's when there is none; a new layout is followed."""
    node = _Node()
    out = Outputs(node, 'effort_controller/commands')
    out.joint_state(True)
    cmd, js = node.publishers['effort_controller/commands'], node.publishers['~/commanded_efforts']
    rng = np.random.default_rng(len(names))
    for ns in STAMPS + [None]:
        tau = rng.normal(0.0, 50.0, len(names))
        tau[:1] = [-0.0] if ns == 0 else tau[:1]   # a negative zero keeps its sign bit
        out.command(tau, names, ns)
        assert isinstance(cmd.sent[-1], bytes) and isinstance(js.sent[-1], bytes)
        assert same_bytes(cmd.sent[-1], Float64MultiArray(data=tau.tolist()))
        assert same_bytes(js.sent[-1], _joint_state(names, tau, 42 * 10 ** 9 + 7 if ns is None else ns))
    other = names + ['extra']   # another layout: other names and length
    tau = rng.normal(size=len(other))
    out.command(tau, other, 5)
    assert same_bytes(cmd.sent[-1], Float64MultiArray(data=tau.tolist()))
    assert same_bytes(js.sent[-1], _joint_state(other, tau, 5))
    out.joint_state(False)   # off: the command alone, the other publisher released and destroyed
    out.command(tau, other, 6)
    assert len(cmd.sent) == len(js.sent) + 1 and '~/commanded_efforts' not in node.publishers and js.in_use == 0
    out.close()   # before the node goes: the command's handle released, once
    out.close()
    assert cmd.in_use == 0


def test_multi_array_with_a_layout_is_rclpys_bytes():
    """The layout rows and data_offset of cdr.multi_array_template (the dynamics topics' matrices)."""
    rng = np.random.default_rng(3)
    for rows, cols in ((6, 7), (1, 1), (3, 0), (30, 30)):
        A = rng.normal(size=(rows, cols))
        dims = (('rows: a,b', rows, rows * cols), ('cols: é', cols, cols))
        t, slots = multi_array_template(rows * cols, dims)
        msg = Float64MultiArray(data=A.ravel().tolist())
        msg.layout.dim = [MultiArrayDimension(label=a, size=b, stride=c) for a, b, c in dims]
        assert same_bytes(t.writer(slots).message((A.ravel(),)), msg)
        assert t.fill(slots, (A.ravel(),)) == t.writer(slots).message((A.ravel(),))


@pytest.mark.parametrize('names', NAMES)
def test_joint_state_template_is_rclpys_bytes(names):
    """joint_state_template with its three arrays, through Writer and fill."""
    n = len(names)
    q, qd, e = np.random.default_rng(n).normal(size=(3, n))
    t, stamp_at, slots = joint_state_template(names)
    for ns in STAMPS:
        msg = JointState(name=names, position=q.tolist(), velocity=qd.tolist(), effort=e.tolist())
        msg.header.stamp.sec, msg.header.stamp.nanosec = stamp_parts(ns)
        assert same_bytes(t.writer(slots, stamp_at).message((q, qd, e), ns), msg)
        assert t.fill(slots, (q, qd, e), stamp_at, ns) == t.writer(slots, stamp_at).message((q, qd, e), ns)
