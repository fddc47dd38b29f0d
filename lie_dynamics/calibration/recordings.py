"""Recordings of a robot for calibration: rosbag2 folders and trajectory CSVs, read to arrays, and
the rosbag2 folder the dynamics node writes.

`read_recording(path, topic='/joint_states', joints=None)` returns a `Recording` (stamps,
positions, velocities if every sample has them, measured efforts) from

  * a rosbag2 folder (the one `ros2 bag record` writes: metadata.yaml and its files) in either
    storage format, mcap (Jazzy's default) or sqlite3, with sensor_msgs/msg/JointState on `topic`.
    The container is read by the `rosbags` package (no ROS installation needed), the messages by
    the JointState reader the node uses too (lie_dynamics/cdr.py). A sample's time is its header stamp, or
    the time the bag took it when the stamp is zero (a driver that does not stamp);
  * a trajectory CSV (lie_dynamics.trajectory's format: time, pos.<joint>, vel.<joint>,
    acc.<joint>) with eff.<joint> columns, the measured efforts.

Samples with a non-finite position or effort, or without a value for a joint, are dropped and
counted (`Recording.dropped`); efforts are required (a recording without any is refused with the
reason), velocities are not (`qd` is None unless every kept sample has them). Joints: `joints`,
or every joint the messages name, in the order they first appear.

`write_joint_states(folder, ...)` writes arrays as one JointState topic into a new mcap rosbag2
folder (the node's `~/record`, ros/features/recording.py). No rclpy import.
"""
import os
from typing import NamedTuple, Optional

import numpy as np

from ..cdr import JointStateDecoder, joint_state_template
from ..trajectory import read_csv

__all__ = ['JOINT_STATE_TYPE', 'Recording', 'read_bag', 'read_csv_recording', 'read_recording',
           'write_joint_states']

JOINT_STATE_TYPE = 'sensor_msgs/msg/JointState'


class Recording(NamedTuple):
    """t (N,) s from the first kept sample (t0_ns: its absolute time, ns); joint_names (n);
    q, effort (N, n); qd (N, n) or None; dropped: samples left out (non-finite, or a joint or
    effort missing); messages: samples read; source: what was read (a label for messages)."""
    t: np.ndarray
    joint_names: list
    q: np.ndarray
    qd: Optional[np.ndarray]
    effort: np.ndarray
    dropped: int
    messages: int
    t0_ns: int
    source: str


def _typestore():
    from rosbags.typesys import Stores, get_typestore
    return get_typestore(Stores.ROS2_JAZZY)


def _assemble(stamps_ns, names_of, rows, joints, source):
    """A Recording from per-message (stamp ns, names tuple index, position, velocity, effort)."""
    if joints is None:
        joints = list(dict.fromkeys(n for names in names_of for n in names))
    joints = list(joints)
    N, n = len(stamps_ns), len(joints)
    q, qd, effort = (np.full((N, n), np.nan) for _ in range(3))
    which = np.array([r[0] for r in rows], dtype=int)
    for w, names in enumerate(names_of):
        index = {name: i for i, name in enumerate(names)}
        src = np.array([index.get(j, -1) for j in joints], dtype=int)
        have, src = src >= 0, src[src >= 0]
        ks = np.flatnonzero(which == w)
        for out, col in ((q, 1), (qd, 2), (effort, 3)):
            # the messages with this name list and a full array (empty or short: absent), stacked
            full = [k for k in ks if len(rows[k][col]) == len(names)]
            if full:
                block = np.array([rows[k][col] for k in full], dtype=float).reshape(len(full), len(names))
                out[np.ix_(full, np.flatnonzero(have))] = block[:, src]
    if N and not np.isfinite(effort).any():
        raise ValueError(f'{source}: efforts are required, and no sample has an effort for {joints}: record a '
                         'joint_states stream whose effort field carries the measured joint torques')
    stamps = np.asarray(stamps_ns, dtype=np.int64)
    keep = np.isfinite(q).all(axis=1) & np.isfinite(effort).all(axis=1)
    kept = int(np.count_nonzero(keep))
    if kept < 2:
        raise ValueError(f'{source}: {kept} of {N} samples have finite positions and efforts for {joints}')
    stamps, q, qd, effort = stamps[keep], q[keep], qd[keep], effort[keep]
    t0 = int(stamps[0])
    return Recording((stamps - t0) * 1e-9, joints, q, qd if np.isfinite(qd).all() else None, effort,
                     N - kept, N, t0, source)


def read_bag(path, topic='/joint_states', joints=None):
    """A Recording of the sensor_msgs/JointState messages on `topic` in the rosbag2 folder `path`
    (mcap or sqlite3). The container is read by rosbags, the messages by the JointState reader the node
    uses too (lie_dynamics/cdr.py: rclpy's serializer leaves trailing alignment bytes, which rosbags'
    deserializer refuses). Raises ValueError: not a rosbag2 folder, no such topic (naming the
    topics it has), another message type, no efforts."""
    from rosbags.rosbag2 import Reader
    from rosbags.rosbag2.errors import ReaderError

    path = os.fspath(path)
    if not os.path.isfile(os.path.join(path, 'metadata.yaml')):
        raise ValueError(f'{path}: no metadata.yaml, not a rosbag2 folder (a recording that was killed has '
                         'none: `ros2 bag reindex` writes it)')
    try:
        reader = Reader(path)
        reader.open()
    except (ReaderError, OSError, KeyError) as exc:
        raise ValueError(f'{path}: not a readable rosbag2 folder ({exc})') from None
    try:
        conns = [c for c in reader.connections if c.topic == topic]
        if not conns:
            have = sorted({f'{c.topic} ({c.msgtype})' for c in reader.connections})
            raise ValueError(f"{path}: no topic '{topic}'; the bag has {', '.join(have) or 'no topics'}")
        wrong = [c.msgtype for c in conns if c.msgtype != JOINT_STATE_TYPE]
        if wrong:
            raise ValueError(f"{path}: topic '{topic}' holds {wrong[0]}, not {JOINT_STATE_TYPE}")
        decoder = JointStateDecoder()
        stamps, rows, names_of, which = [], [], [], {}
        for k_msg, (_, log_ns, raw) in enumerate(reader.messages(connections=conns)):
            try:
                msg = decoder.read(raw)
            except ValueError as exc:
                raise ValueError(f"{path}: message {k_msg} on '{topic}': {exc}") from None
            k = which.get(msg.names)
            if k is None:
                k = which[msg.names] = len(names_of)
                names_of.append(msg.names)
            stamps.append(msg.stamp if msg.stamp else log_ns)
            rows.append((k, msg.position, msg.velocity, msg.effort))
    finally:
        reader.close()
    if not rows:
        raise ValueError(f"{path}: topic '{topic}' has no messages")
    return _assemble(stamps, names_of, rows, joints, f"{path} ({topic})")


def read_csv_recording(path, joints=None):
    """A Recording of a trajectory CSV with eff.<joint> columns (lie_dynamics.trajectory.read_csv).
    Raises ValueError naming the file and the problem."""
    traj = read_csv(path)
    if 'efforts' not in traj:
        raise ValueError(f'{path}: efforts are required: the CSV needs an eff.<joint> column (the measured '
                         f'effort) for every pos.<joint> column {traj["joint_names"]}')
    names = tuple(traj['joint_names'])
    t = traj['time_from_start']
    if not np.isfinite(t).all():
        bad = int(np.argmax(~np.isfinite(t)))
        raise ValueError(f'{path}: non-finite time on data row {bad + 1}')
    vel = traj.get('velocities')
    vel = [()] * len(t) if vel is None else vel
    rows = [(0, p, v, e) for p, v, e in zip(traj['positions'], vel, traj['efforts'])]
    stamps = np.round(t * 1e9).astype(np.int64)
    return _assemble(stamps, [names], rows, joints, os.fspath(path))


def read_recording(path, topic='/joint_states', joints=None):
    """A Recording from a rosbag2 folder (mcap or sqlite3) or a trajectory CSV with efforts."""
    if os.path.isdir(path):
        return read_bag(path, topic, joints)
    if not os.path.exists(path):
        raise ValueError(f'{path}: no such file or folder')
    if os.fspath(path).lower().endswith(('.mcap', '.db3')):
        raise ValueError(f'{path}: give the rosbag2 folder that holds this file (with its metadata.yaml)')
    return read_csv_recording(path, joints)


def write_joint_states(folder, names, stamps_ns, q, qd, effort, topic='/joint_states', log_ns=None):
    """Write samples as sensor_msgs/JointState messages into a new mcap rosbag2 folder `folder` (it
    must not exist). stamps_ns (N,) header stamps, ns (0: none); q, qd, effort (N, n), a row of
    qd with a NaN is written without velocities; log_ns (N,) the bag's times (default: the
    stamps). Returns the number of messages written."""
    from rosbags.rosbag2 import StoragePlugin, Writer

    if os.path.lexists(folder):
        raise ValueError(f'{folder} exists already: a recording is written into a new folder')
    stamps = np.asarray(stamps_ns, dtype=np.int64)
    log = stamps if log_ns is None else np.asarray(log_ns, dtype=np.int64)
    names = [str(n) for n in names]
    n = len(names)
    # serialized by the node's fixed-layout writer (16x faster than rosbags' serializer here)
    writers = {}
    for with_velocity in (True, False):
        t, stamp_at, slots = joint_state_template(names, (n, n if with_velocity else 0, n))
        writers[with_velocity] = t.writer(slots if with_velocity else [slots[0], slots[2]], stamp_at)
    has_velocity = np.isfinite(qd).all(axis=1)
    with Writer(folder, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        conn = writer.add_connection(topic, JOINT_STATE_TYPE, typestore=_typestore())
        for k in range(len(stamps)):
            if has_velocity[k]:
                data = writers[True].message((q[k], qd[k], effort[k]), int(stamps[k]))
            else:
                data = writers[False].message((q[k], effort[k]), int(stamps[k]))
            writer.write(conn, int(log[k]), data)
    return len(stamps)
