"""The serialized-trajectory reader and writer (lie_dynamics.ros.trajectories.trajectory_cdr) against rclpy's
own serialization: same arrays, same refusals, a written message that deserializes to the input
with the efforts set."""
import itertools

import numpy as np
import pytest

pytest.importorskip('rclpy')

from builtin_interfaces.msg import Duration  # noqa: E402
from rclpy.serialization import deserialize_message, serialize_message  # noqa: E402
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint  # noqa: E402

from lie_dynamics.ros.trajectories import trajectory_cdr as cdr  # noqa: E402
from lie_dynamics.ros.trajectories.trajectory_msgs import trajectory_arrays  # noqa: E402


def message(rng, k, n, vel, acc, effort=None, frame='map'):
    m = JointTrajectory()
    m.header.frame_id = frame
    m.header.stamp.sec, m.header.stamp.nanosec = 5, 7
    m.joint_names = [f'j{i}é' * (i % 3 + 1) for i in range(k)]   # names of every length, not only ASCII
    for i in range(n):
        p = JointTrajectoryPoint(positions=rng.standard_normal(k).tolist(),
                                 time_from_start=Duration(sec=i, nanosec=i * 1000))
        if vel:
            p.velocities = rng.standard_normal(k).tolist()
        if acc:
            p.accelerations = rng.standard_normal(k).tolist()
        if effort is not None:
            p.effort = rng.standard_normal(effort(i)).tolist()
        m.points.append(p)
    return m


def test_read_and_write_match_rclpy():
    """Every padding pattern: 0..7 joints (a point's size modulo 8 alternates or not), odd and
    even point counts, optional fields, input efforts of any length (ignored, then replaced)."""
    rng = np.random.default_rng(0)
    for k, n, vel, acc, eff, frame in itertools.product(
            (0, 1, 2, 3, 7), (1, 2, 3, 5), (0, 1), (0, 1), (None, lambda i: 2, lambda i: i % 3), ('', 'ab', 'abc')):
        m = message(rng, k, n, vel, acc, eff, frame)
        traj = cdr.read(bytes(serialize_message(m)))
        ref, got = trajectory_arrays(m.joint_names, m.points), cdr.arrays(traj)
        assert got['joint_names'] == list(m.joint_names)
        for key in ('positions', 'velocities', 'accelerations', 'time_from_start'):
            assert (ref[key] is None) == (got[key] is None), key
            if ref[key] is not None:
                np.testing.assert_array_equal(ref[key].reshape(got[key].shape), got[key])
        efforts = rng.standard_normal((n, k))
        out = deserialize_message(cdr.write(traj, efforts), JointTrajectory)
        assert out.header == m.header and list(out.joint_names) == list(m.joint_names)
        for p, q, e in zip(out.points, m.points, efforts, strict=True):
            assert (list(p.positions), list(p.velocities), list(p.accelerations), p.time_from_start) == \
                (list(q.positions), list(q.velocities), list(q.accelerations), q.time_from_start)
            assert list(p.effort) == e.tolist()


def test_refusals_match_trajectory_arrays_and_truncation_is_refused():
    rng = np.random.default_rng(1)

    def ragged(m):
        m.points[1].positions = m.points[1].positions[:-1]

    def some_velocities(m):
        m.points[1].velocities = []
    for change in (ragged, some_velocities):
        m = message(rng, 3, 4, 1, 0)
        change(m)
        with pytest.raises(ValueError) as ref:
            trajectory_arrays(m.joint_names, m.points)
        with pytest.raises(ValueError) as got:
            cdr.read(bytes(serialize_message(m)))
        assert str(got.value) == str(ref.value)
    buf = bytes(serialize_message(message(rng, 3, 4, 1, 1)))
    for cut in range(len(buf) - 1):
        try:
            cdr.read(buf[:cut])
        except ValueError:
            pass
    with pytest.raises(cdr.Unsupported):
        cdr.read(b'\x00\x07\x00\x00' + buf[4:])   # another encoding: the caller deserializes instead
    assert cdr.head(buf) == (list(message(np.random.default_rng(1), 3, 4, 1, 1).joint_names), 4)


def test_large_trajectory_reads_fast():
    """100,000 points: a few strided views (rclpy's deserialization takes seconds)."""
    import time
    n, k = 100_000, 7
    rng = np.random.default_rng(2)
    m = JointTrajectory(joint_names=[f'joint{i}' for i in range(k)])
    p = JointTrajectoryPoint(positions=[0.0] * k, velocities=[0.0] * k)
    m.points = [p] * n
    buf = bytes(serialize_message(m))
    t0 = time.perf_counter()
    traj = cdr.read(buf)
    out = cdr.write(traj, rng.standard_normal((n, k)))
    assert time.perf_counter() - t0 < 5.0   # ~60 ms here; generous for a loaded machine
    assert traj['positions'].shape == (n, k) and len(out) > len(buf)
