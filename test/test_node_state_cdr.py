"""The serialized joint_states and desired-state readers (lie_dynamics.ros.core.cdr) against rclpy's
deserialization: bit-identical values for valid messages (random and edge cases), the same
accept/refuse outcome for damaged ones, and a node flooded with garbage on both topics that
logs a bounded number of lines and keeps answering the valid states in between."""
import os
import random
import struct
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

rclpy = pytest.importorskip('rclpy')

from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.qos import QoSProfile, ReliabilityPolicy  # noqa: E402
from rclpy.serialization import deserialize_message, serialize_message  # noqa: E402
from sensor_msgs.msg import JointState  # noqa: E402
from std_msgs.msg import Float64MultiArray  # noqa: E402
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint  # noqa: E402

from lie_dynamics import load_urdf  # noqa: E402
from lie_dynamics.ros.core import cdr  # noqa: E402
from lie_dynamics.ros.core.compensator import Compensator  # noqa: E402

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
ARM_PATH = os.path.join(ROOT, 'config', 'arm7.urdf')
JOINTS = [f'joint{i}' for i in range(1, 8)]
Q = np.array([0.1, 0.5, -0.2, 1.2, 0.3, 0.8, 0.1])
NAN = float('nan')


def _name(rng):
    return ''.join(rng.choice(['a', 'b', 'é', 'ß', '日', '\U0001F600', '_', '1']) for _ in range(rng.randint(0, 6)))


def _values(rng, n):
    return [rng.choice([0.0, -0.0, 1.5, NAN, float('inf'), -1e308, 5e-324, rng.uniform(-10, 10)]) for _ in range(n)]


def _count(rng, k):
    return k if rng.random() < 0.7 else rng.choice([0, rng.randint(0, 5)])


def random_joint_state(rng):
    k = rng.randint(0, 5)
    m = JointState(name=[_name(rng) for _ in range(_count(rng, k))], position=_values(rng, _count(rng, k)),
                   velocity=_values(rng, _count(rng, k)), effort=_values(rng, _count(rng, k)))
    m.header.frame_id = _name(rng)
    m.header.stamp.sec, m.header.stamp.nanosec = rng.randint(-2**31, 2**31 - 1), rng.randint(0, 2**32 - 1)
    return m


def random_trajectory(rng):
    k = rng.randint(0, 4)
    points = [JointTrajectoryPoint(positions=_values(rng, _count(rng, k)), velocities=_values(rng, _count(rng, k)),
                                   accelerations=_values(rng, _count(rng, k)), effort=_values(rng, _count(rng, k)))
              for _ in range(rng.choice([1, 1, 1, 0, 2, 3]))]
    for p in points:
        p.time_from_start.sec, p.time_from_start.nanosec = rng.randint(-5, 5), rng.randint(0, 10**9 - 1)
    m = JointTrajectory(joint_names=[_name(rng) for _ in range(_count(rng, k))], points=points)
    m.header.frame_id = _name(rng)
    return m


def damaged(rng, buf):
    """buf with 1-3 random cuts, byte changes, appended bytes or replaced uint32 counts."""
    b = bytearray(buf)
    for _ in range(rng.randint(1, 3)):
        op = rng.random()
        if op < 0.3 and len(b) > 4:
            del b[rng.randrange(4, len(b)):]
        elif op < 0.7 and len(b) > 4:
            b[rng.randrange(4, len(b))] = rng.choice([0, 1, 2, 0xff, 0x7f, rng.randrange(256)])
        elif op < 0.85:
            b += bytes(rng.randrange(256) for _ in range(rng.randint(1, 9)))
        elif len(b) > 8:
            j = 4 + (rng.randrange(0, len(b) - 8) & ~3)
            b[j:j + 4] = rng.choice([0, 1, 2**31, 2**32 - 1, rng.randint(0, 50)]).to_bytes(4, 'little')
    return bytes(b)


def bits(a):
    return np.asarray(a, dtype=float).tobytes()


def rclpy_or_none(buf, kind, capfd):
    """rclpy's reading of buf, or None when it refuses it. A sequence count beyond the buffer
    inside a point makes rclpy's type support print "sequence size exceeds remaining buffer"
    and yet return a message, with zeros it made up: malformed too (cdr.py refuses it)."""
    capfd.readouterr()
    try:
        msg = deserialize_message(buf, kind)
    except Exception:  # noqa: BLE001 - rclpy's refusal (RMWError and kin): the oracle says "malformed"
        msg = None
    return None if 'exceeds remaining buffer' in capfd.readouterr().err else msg


def check_joint_state(decoder, buf, capfd):
    """Both readers agree on buf: both refuse, or the same values bit for bit. Returns accepted?"""
    ref = rclpy_or_none(buf, JointState, capfd)
    try:
        s = decoder.read(buf)
    except ValueError:
        assert ref is None, f'refused a message rclpy reads: {buf.hex()}'
        return False
    assert ref is not None, f'read a message rclpy refuses: {buf.hex()}'
    assert list(s.names) == list(ref.name), buf.hex()
    assert s.stamp == ref.header.stamp.sec * 1_000_000_000 + ref.header.stamp.nanosec
    for mine, theirs in ((s.position, ref.position), (s.velocity, ref.velocity), (s.effort, ref.effort)):
        assert bits(mine) == bits(theirs), buf.hex()
        assert not mine.flags.writeable
    return True


def check_trajectory(buf, capfd):
    ref = rclpy_or_none(buf, JointTrajectory, capfd)
    try:
        names, points = cdr.read_joint_trajectory(buf)
    except ValueError:
        assert ref is None, f'refused a message rclpy reads: {buf.hex()}'
        return False
    assert ref is not None, f'read a message rclpy refuses: {buf.hex()}'
    assert names == list(ref.joint_names) and len(points) == len(ref.points)
    for p, r in zip(points, ref.points, strict=True):
        for f in ('positions', 'velocities', 'accelerations'):
            assert bits(getattr(p, f)) == bits(getattr(r, f)), buf.hex()
    one = cdr.read_joint_trajectory(buf, one=True)   # the node's reading: the same, or only the count
    assert one[0] == names and (one[1] == range(len(points)) if len(points) != 1 else
                                all(bits(a) == bits(b) for a, b in zip(one[1][0], points[0], strict=True)))
    return True


def test_joint_states_read_bit_identical_to_rclpy(capfd):
    rng = random.Random(20240522)
    decoder = cdr.JointStateDecoder()
    outcomes = {True: 0, False: 0}
    for _ in range(1500):
        buf = bytes(serialize_message(random_joint_state(rng)))
        assert check_joint_state(decoder, buf, capfd)
        outcomes[check_joint_state(decoder, damaged(rng, buf), capfd)] += 1
        assert check_joint_state(decoder, buf, capfd)   # after a damaged one: the names cache holds no stale list
    assert min(outcomes.values()) > 300, outcomes   # damage covers both outcomes


def test_joint_states_stream_read_bit_identical_to_rclpy(capfd, monkeypatch):
    """A stream keeps its layout (the decoder then reads the arrays where the last message had
    them): every message still reads as rclpy reads it, also one of the same length whose names,
    frame_id or array counts differ, and one damaged in between."""
    import lie_dynamics.cdr as core_cdr
    walked = []   # the messages read from the start (a Buffer made): the others took the last layout
    monkeypatch.setattr(core_cdr, 'Buffer', lambda *a: walked.append(1) or cdr.Buffer(*a))
    rng = random.Random(20261127)
    decoder = cdr.JointStateDecoder()
    layouts = [(JOINTS, 'base', 7, 7), (JOINTS, 'base', 7, 0), (JOINTS, 'base', 0, 7), (JOINTS, 'esab', 7, 7),
               ([j[::-1] for j in JOINTS], 'base', 7, 7), (JOINTS, '', 7, 7), (['a', 'b'], 'base', 2, 2)]
    changes, last = 0, None
    for k in range(600):
        layout = layouts[0 if rng.random() < 0.6 else rng.randrange(len(layouts))]
        names, frame, nv, ne = layout
        n = len(names)
        m = JointState(name=names, position=_values(rng, n), velocity=_values(rng, nv), effort=_values(rng, ne))
        m.header.frame_id = frame
        m.header.stamp.sec, m.header.stamp.nanosec = rng.randint(-2**31, 2**31 - 1), rng.randint(0, 2**32 - 1)
        buf = bytes(serialize_message(m))
        assert check_joint_state(decoder, buf, capfd)
        changes += layout != last
        last = layout
        if k % 50 == 49:
            check_joint_state(decoder, damaged(rng, buf), capfd)
            last = None
    # read from the start: when the layout changed (or after a damaged message), and the damaged ones
    assert len(walked) <= changes + 12 and changes < 400


def test_desired_states_read_bit_identical_to_rclpy(capfd):
    rng = random.Random(77)
    outcomes = {True: 0, False: 0}
    for _ in range(1000):
        buf = bytes(serialize_message(random_trajectory(rng)))
        assert check_trajectory(buf, capfd)
        outcomes[check_trajectory(damaged(rng, buf), capfd)] += 1
    assert min(outcomes.values()) > 200, outcomes


def test_edge_cases(capfd):
    decoder = cdr.JointStateDecoder()
    empty = bytes(serialize_message(JointState()))
    s = decoder.read(empty)
    assert s.names == () and s.stamp == 0 and all(len(a) == 0 for a in s[2:])
    # joint_state_broadcaster without velocity/effort interfaces: NaN
    m = JointState(name=JOINTS, position=Q.tolist(), velocity=[NAN] * 7, effort=[NAN] * 7)
    buf = bytes(serialize_message(m))
    assert check_joint_state(decoder, buf, capfd)
    first = decoder.read(buf).names
    assert decoder.read(buf).names is first   # the same names: decoded once
    assert check_joint_state(decoder, bytes(serialize_message(JointState(name=['ä', '日本', '\U0001F916'],
                                                                          position=[1.0, 2.0, 3.0]))), capfd)
    for cut in range(len(buf)):   # every truncation: refused with ValueError, as rclpy refuses it
        assert not check_joint_state(decoder, buf[:cut], capfd)
    with pytest.raises(cdr.Unsupported):
        decoder.read(b'\x00\x07\x00\x00' + buf[4:])   # XCDR2: refused, never handed to rclpy
    # big endian (another machine's byte order), written by hand
    be = bytearray(b'\x00\x00\x00\x00' + struct.pack('>iII', -3, 7, 2) + b'x\0\0\0' + struct.pack('>I', 2))
    for name in ('j1', 'jé'):
        raw = name.encode() + b'\0'
        be += struct.pack('>I', len(raw)) + raw
        be += b'\0' * (-len(be) % 4)
    for values in ([1.5, NAN], [], [2.0, -0.0]):
        be += struct.pack('>I', len(values))
        if values:
            be += b'\0' * (-(len(be) - 4) % 8) + struct.pack(f'>{len(values)}d', *values)
    s = decoder.read(bytes(be))
    assert s.names == ('j1', 'jé') and s.stamp == -3 * 10**9 + 7
    assert bits(s.position) == bits([1.5, NAN]) and len(s.velocity) == 0 and bits(s.effort) == bits([2.0, -0.0])


def test_the_core_refuses_what_it_refused_before():
    """Samples meet the same checks as messages did: lengths that differ, NaN positions."""
    core = Compensator({'position_margin': 1000.0, 'friction.viscous': [0.0], 'friction.coulomb': [0.0]})
    core.load(ARM_PATH)
    decoder = cdr.JointStateDecoder()

    def sample(**fields):
        return decoder.read(bytes(serialize_message(JointState(name=JOINTS, **fields))))
    g = load_urdf(ARM_PATH).gravity(Q)
    np.testing.assert_allclose(core.on_sample(sample(position=Q.tolist(), velocity=[NAN] * 7)), g, atol=1e-12)
    for bad in (dict(position=Q.tolist()[:6]), dict(position=Q.tolist(), velocity=[0.0] * 3),
                dict(position=Q.tolist(), effort=[0.0] * 8)):
        assert core.on_sample(sample(**bad)) is None and core.events[-1][1] == 'reject:length'
    assert core.on_sample(sample(position=[NAN] + Q.tolist()[1:])) is None and core.events[-1][1] == 'reject:nonfinite'
    assert core.refuse_malformed('joint_states', 'serialized joint_states is truncated') is None
    assert core.events[-1][1] == 'reject:malformed' and core.count.rejected == 5 and core.count.accepted == 1


# ------------------------------------------------------------------ the node, flooded
FLOOD_S = 2.0
FLOOD_HZ = 1000


def _garbage(rng, desired):
    """Serialized messages that are not valid: a sequence count beyond the buffer (what makes
    rclpy's deserializer print "sequence size exceeds remaining buffer"), truncated, a foreign
    encoding, random bytes. Made from joints the node does not control: the transport may hand
    a truncated message over in a reused buffer, its missing tail filled from an earlier message
    (seen with rmw_fastrtps across processes), which would make it whole again."""
    if desired:
        good = bytes(serialize_message(JointTrajectory(joint_names=['x0', 'x1'], points=[
            JointTrajectoryPoint(positions=[1.0, 2.0], velocities=[0.0, 0.0])])))
        count = good.find(struct.pack('<dd', 1.0, 2.0)) + 16   # the velocities count
    else:
        good = bytes(serialize_message(JointState(name=[f'x{i}' for i in range(7)], position=Q.tolist())))
        count = good.rfind((7).to_bytes(4, 'little'))           # the positions count
    kind = rng.randrange(5)
    if kind < 2:
        return good[:count] + (2**30 + rng.randrange(2**20)).to_bytes(4, 'little') + good[count + 4:]
    if kind == 2:
        return good[:rng.randrange(5, count)]   # cut before the end of the data (not the padding)
    if kind == 3:
        return b'\x00\x07\x00\x00' + good[4:]
    return bytes(rng.randrange(256) for _ in range(rng.randint(8, 64)))


def test_garbage_flood_is_logged_bounded_and_valid_states_answered(tmp_path):
    """Garbage on joint_states and the desired topic at 1 kHz for 2 s with valid states in
    between: at most 5 log lines per second from the node (its whole stderr, where rclpy's
    deserializer would print every failure), and every command is the valid states' gravity."""
    ns = '/cdr_flood'
    env = dict(os.environ, ROS_LOG_DIR=str(tmp_path))
    cmd = [sys.executable, '-m', 'lie_dynamics.dynamics_node', '--ros-args', '-p', f'urdf_path:={ARM_PATH}',
           '-p', f'command_topic:={ns}/commands', '-p', f'desired_topic:={ns}/desired', '-p', 'stale_timeout:=60.0',
           '-r', f'joint_states:={ns}/joint_states']
    proc = subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    lines = []
    readers = [threading.Thread(target=lambda f=f: lines.extend((time.monotonic(), ln) for ln in f), daemon=True)
               for f in (proc.stdout, proc.stderr)]
    for t in readers:
        t.start()
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    node = rclpy.create_node('cdr_flood_tester', context=ctx)
    ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(node)
    cmds = []
    try:
        node.create_subscription(Float64MultiArray, f'{ns}/commands', lambda m: cmds.append(np.array(m.data)),
                                 QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE))
        js = node.create_publisher(JointState, f'{ns}/joint_states', 10)
        desired = node.create_publisher(JointTrajectory, f'{ns}/desired', 10)
        end = time.monotonic() + 60
        while time.monotonic() < end and not (js.get_subscription_count() and desired.get_subscription_count()
                                              and node.count_publishers(f'{ns}/commands')):
            ex.spin_once(timeout_sec=0.05)
        model = load_urdf(ARM_PATH)
        qs = [Q + 0.001 * k for k in range(int(FLOOD_S * 50))]
        valid = [bytes(serialize_message(JointState(name=JOINTS, position=q.tolist()))) for q in qs]
        warm = bytes(serialize_message(JointState(name=JOINTS, position=(Q - 0.01).tolist())))
        while not cmds and time.monotonic() < end:   # the model is up and answering
            js.publish(warm)
            ex.spin_once(timeout_sec=0.05)
        assert cmds, 'the node never answered'
        quiet = time.monotonic() + 2.5   # the start-up lines and late answers are out of the way
        while time.monotonic() < quiet:
            ex.spin_once(timeout_sec=0.05)
        cmds.clear()
        rng = random.Random(5)
        t0 = time.monotonic()
        k = 0
        while k < FLOOD_S * FLOOD_HZ:
            if k % 20 == 10:   # a valid state every 20 ms, between garbage
                js.publish(valid[k // 20])
            else:
                (js if k % 2 else desired).publish(_garbage(rng, desired=not k % 2))
            k += 1
            ex.spin_once(timeout_sec=0)
            pause = t0 + k / FLOOD_HZ - time.monotonic()
            if pause > 0:
                time.sleep(pause)
        t1 = time.monotonic()
        deadline = t1 + 2.0
        while time.monotonic() < deadline:
            ex.spin_once(timeout_sec=0.05)
    finally:
        proc.terminate()
        proc.wait(timeout=30)
        for t in readers:
            t.join(timeout=5)
        node.destroy_node()
        ctx.try_shutdown()
    during = [ln for t, ln in lines if t0 <= t <= t1 + 0.5]
    assert len(during) <= 5 * (t1 + 0.5 - t0), during
    assert any('malformed' in ln for ln in during), during   # it was seen, and said (throttled)
    expected = {model.gravity(q).tobytes(): i for i, q in enumerate(qs)}
    order = [expected.get(c.tobytes()) for c in cmds]
    assert None not in order and order == sorted(order), str(order)   # each a valid state's gravity, in order
    assert len(cmds) >= 0.5 * len(qs), (len(cmds), len(qs))   # best effort, depth 1: garbage may displace a few
    assert proc.returncode == 0


@pytest.mark.parametrize('names', [['joint1', 'j2é', 'a_longer_joint_name_3'], ['x'], []])
def test_writer_messages_equal_the_template_and_read_back(names):
    """cdr.Writer (the ~/external_torques path: a JointState with effort only) gives the bytes of
    Template.fill, message after message with new stamps and values, that rclpy reads back; an
    array of another length is refused rather than making a malformed message."""
    from lie_dynamics.ros.core.cdr import joint_state_template
    n = len(names)
    rng = np.random.default_rng(3)
    for sizes in ((0, 0, n), None):
        t, stamp_at, slots = joint_state_template(names, sizes)
        message = t.writer(slots[2:] if sizes else slots, stamp_at).message
        for k in range(3):
            arrays = tuple(rng.normal(size=(1 if sizes else 3, n)))
            ns = 1_700_000_000 * 10 ** 9 + 123_456_789 + k * 1_000_000_007
            data = message(arrays, ns)
            assert data == t.fill(slots[2:] if sizes else slots, arrays, stamp_at, ns)
            msg = deserialize_message(data, JointState)
            assert (msg.header.stamp.sec, msg.header.stamp.nanosec) == divmod(ns, 10 ** 9)
            assert list(msg.name) == names and np.array_equal(msg.effort, arrays[-1])
            assert len(msg.position) == (0 if sizes else n)
    if n:
        with pytest.raises(ValueError, match='values, its slot'):
            message((np.zeros(n + 1),) * 3, 0)
