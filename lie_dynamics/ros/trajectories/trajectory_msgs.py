"""trajectory_msgs/JointTrajectory <-> the arrays of `trajectory.fill_trajectory_efforts`.

ROS layer, no rclpy import: `trajectory_arrays` reads any object shaped like the message
(joint_names; points with positions, velocities, accelerations, time_from_start.sec/nanosec),
so the node's decision logic stays testable without ROS. Only `trajectory_message` (arrays
-> a new message) imports trajectory_msgs, when called.
"""
import array

import numpy as np


def _seconds(duration):
    return duration.sec + duration.nanosec * 1e-9


def block(rows, field, k, required):
    """(N, k) array of one per-point field given as its N rows (sequences of floats), or None
    when every row is empty and the field is not required. Raises ValueError naming the point."""
    lengths = {len(r) for r in rows}
    if lengths == {0} and not required:
        return None
    if lengths != {k}:
        ok = (k,) if required else (0, k)
        bad = next((i for i, r in enumerate(rows) if len(r) not in ok), None)
        if bad is not None:
            raise ValueError(f'trajectory point {bad} has {len(rows[bad])} {field} for {k} joints')
        bad = next(i for i, r in enumerate(rows) if len(r) == 0)
        raise ValueError(f'trajectory {field} given for some points only (point {bad} has none)')
    if k and all(isinstance(r, array.array) and r.typecode == 'd' for r in rows):  # message fields
        return np.frombuffer(b''.join([r.tobytes() for r in rows]), dtype=float).reshape(len(rows), k).copy()
    return np.array([list(r) for r in rows], dtype=float).reshape(len(rows), k)


def trajectory_arrays(joint_names, points):
    """Arrays for `fill_trajectory_efforts` from a JointTrajectory's joint_names and points.

    velocities / accelerations: None when every point leaves them empty (they are then
    derived); given for some points only, or any per-point length that differs from the
    number of joint names, raises ValueError naming the point. Point efforts are ignored.
    """
    names = list(joint_names)
    k = len(names)
    if not points:
        raise ValueError('trajectory has no points')
    return {
        'joint_names': names,
        'time_from_start': np.array([_seconds(p.time_from_start) for p in points], dtype=float),
        'positions': block([p.positions for p in points], 'positions', k, True),
        'velocities': block([p.velocities for p in points], 'velocities', k, False),
        'accelerations': block([p.accelerations for p in points], 'accelerations', k, False),
    }


def set_point_efforts(points, efforts):
    """Write row k of `efforts` (N, joints in message order) into points[k].effort, in place."""
    eff = np.ascontiguousarray(efforts, dtype=float)
    for p, row in zip(points, eff, strict=True):
        p.effort = array.array('d', row.tobytes())


def trajectory_message(joint_names, time_from_start, positions, velocities=None, accelerations=None,
                       efforts=None):
    """A trajectory_msgs/JointTrajectory from arrays ((N, k) per field, times in s)."""
    from builtin_interfaces.msg import Duration
    from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

    msg = JointTrajectory()
    msg.joint_names = list(joint_names)
    fields = (('positions', positions), ('velocities', velocities), ('accelerations', accelerations),
              ('effort', efforts))
    for k, t in enumerate(np.asarray(time_from_start, dtype=float)):
        p = JointTrajectoryPoint()
        sec = int(np.floor(t))
        p.time_from_start = Duration(sec=sec, nanosec=min(int(round((t - sec) * 1e9)), 999_999_999))
        for field, a in fields:
            if a is not None:
                setattr(p, field, array.array('d', np.ascontiguousarray(a[k], dtype=float).tobytes()))
        msg.points.append(p)
    return msg
