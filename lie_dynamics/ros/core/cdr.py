"""The node's readers of serialized messages: joint_states (`JointStateDecoder`, a JointStateSample
without a Python message) and the desired state (`read_joint_trajectory`); whole trajectories
are in trajectories/trajectory_cdr.py. Plain Python, no rclpy import. The CDR primitives, the
stamp conversion, the JointState reader and `Template`, the writer of fixed-shape messages (the
dynamics topics), are the math core's (lie_dynamics/cdr.py, which the rosbag2 recordings share);
they stay importable from here.

Reading a JointState serialized instead of letting rclpy build a message object both costs less
(no Python message, no per-element conversion) and keeps a malformed message off rclpy's
deserializer, which logs every failure unthrottled.
"""
from typing import NamedTuple

import numpy as np

from ...cdr import (Buffer, JointStateDecoder, JointStateSample, Template, Unsupported, Writer, align,
                    joint_state_template, multi_array_template, stamp_ns, stamp_parts, truncated)

__all__ = ['Buffer', 'JointStateDecoder', 'JointStateSample', 'Point', 'Template', 'Unsupported', 'Writer',
           'align', 'joint_state_template', 'multi_array_template', 'read_joint_trajectory', 'sample_of', 'stamp_ns',
           'stamp_parts', 'truncated']


def sample_of(msg):
    """The JointStateSample of a sensor_msgs/JointState message object (benchmarks and tools
    that hold one; the node itself reads the serialized form, read_joint_state)."""
    s = msg.header.stamp
    arrays = [np.frombuffer(a, dtype=float) if hasattr(a, 'typecode') else np.array(a, dtype=float)
              for a in (msg.position, msg.velocity, msg.effort)]
    for a in arrays:
        a.flags.writeable = False
    return JointStateSample(stamp_ns(s.sec, s.nanosec), tuple(msg.name), *arrays)


class Point(NamedTuple):
    """One trajectory_msgs/JointTrajectoryPoint's arrays (read-only views; effort not read)."""
    positions: np.ndarray
    velocities: np.ndarray
    accelerations: np.ndarray


def read_joint_trajectory(buf, one=False):
    """(joint_names, points) of a serialized trajectory_msgs/JointTrajectory, every point read.
    one=True (a desired state, which has exactly one; the core checks it: messages.read_desired):
    a message with another number of points is not read beyond its count, and `points` is then
    range(count) (the core refuses it by its length). Raises ValueError for a malformed or
    truncated message (Unsupported: another encoding).

    Layout: header {int32 sec, uint32 nanosec, string frame_id}, string[] joint_names, then the
    points: float64[] positions, velocities, accelerations, effort, time_from_start {int32, uint32}."""
    b = Buffer(buf, 'trajectory')
    if b.end < 12:
        raise truncated('trajectory')
    _, pos = b.string(8)
    names, pos = b.strings(pos)
    pos = align(pos, 4)
    count = b.u32(pos)
    pos += 4
    if count > (b.end - pos) // 24:   # a point takes at least its four counts and the time
        raise truncated('trajectory')
    if one and count != 1:
        return names, range(count)
    points = []
    for _ in range(count):
        arrays = []
        for _ in range(4):
            a, pos = b.doubles(pos)
            arrays.append(a)
        pos = align(pos, 4) + 8
        if pos > b.end:
            raise truncated('trajectory')
        points.append(Point(*arrays[:3]))
    return names, points
