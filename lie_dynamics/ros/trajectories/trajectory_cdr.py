"""trajectory_msgs/JointTrajectory in its serialized form (CDR: what a raw subscription
delivers and a publisher accepts), read and written with numpy; plain Python, no rclpy import.

rclpy converts a message to Python objects point by point while holding the interpreter lock
(~10-20 us a point): a 100,000-point trajectory stalls every other thread, the control path
included, for seconds. Read here, a trajectory whose points all have the same array lengths
(every valid one) is a few strided array views; other ones are walked point by point and
refused with the same reasons as trajectory_msgs.trajectory_arrays. Plain CDR (XCDR1, little
or big endian: what rmw_fastrtps and rmw_cyclonedds send) is read with the primitives of
cdr.py; any other encoding raises Unsupported and the caller deserializes the message instead.

Layout, aligned relative to the payload (after the 4-byte encapsulation header):
header {int32 sec, uint32 nanosec, string frame_id}, string[] joint_names, uint32 point
count, then per point float64[] positions, velocities, accelerations, effort (uint32 count,
then the doubles, aligned to 8 when there are any) and time_from_start {int32, uint32}.
"""
import numpy as np

from ..core.cdr import Buffer, Unsupported, align as _align, truncated
from .trajectory_msgs import block

__all__ = ['FIELDS', 'Unsupported', 'head', 'read', 'arrays', 'write']
FIELDS = ('positions', 'velocities', 'accelerations', 'effort')


def head(buf):
    """(joint_names, number of points) of a serialized JointTrajectory, without reading the points."""
    b, names, n, _ = _head(buf)
    return names, n


def _head(buf):
    b = Buffer(buf, 'trajectory')
    pos = 8                              # header.stamp
    pos += 4 + b.u32(pos)                # header.frame_id
    names, pos = b.strings(pos)
    pos = _align(pos, 4)
    return b, names, b.u32(pos), pos + 4


def _layout(start, counts):
    """([(count offset, data offset)] per field, time offset, size) of a point at payload offset
    `start` whose arrays have `counts` entries (offsets relative to start)."""
    pos, fields = start, []
    for c in counts:
        pos = _align(pos, 4)
        at = pos
        pos += 4
        if c:
            pos = _align(pos, 8)
        fields.append((at - start, pos - start))
        pos += 8 * c
    pos = _align(pos, 4)
    return fields, pos - start, pos + 8 - start


def _groups(p0, n, counts):
    """Points sharing one layout, as (first start, stride, how many, layout, their rows), and the
    payload end. A point's padding depends on its start modulo 8 (0 or 4): either every point
    has the first one's layout, or all after the first have the second layout, or the two
    alternate."""
    lay0 = _layout(p0, counts)
    p1 = p0 + lay0[2]
    if p1 % 8 == p0 % 8:
        return [(p0, lay0[2], n, lay0, slice(None))], p0 + n * lay0[2]
    lay1 = _layout(p1, counts)
    if n == 1 or (p1 + lay1[2]) % 8 == p1 % 8:
        return ([(p0, lay0[2], 1, lay0, slice(0, 1)), (p1, lay1[2], n - 1, lay1, slice(1, None))],
                p1 + (n - 1) * lay1[2])
    stride = lay0[2] + lay1[2]
    return ([(p0, stride, (n + 1) // 2, lay0, slice(0, None, 2)), (p1, stride, n // 2, lay1, slice(1, None, 2))],
            p0 + (n // 2) * stride + (n % 2) * lay0[2])


def _regular(b, p0, n):
    """The points as arrays when all have the array lengths of the first one, else None."""
    pos, counts = p0, []
    for _ in FIELDS:   # the first point's counts
        pos = _align(pos, 4)
        c = b.u32(pos)
        if c > b.end // 8:
            return None
        counts.append(c)
        pos += 4
        if c:
            pos = _align(pos, 8)
        pos += 8 * c
    groups, end = _groups(p0, n, counts)
    if end > b.end:
        return None
    out = {f: np.empty((n, c)) for f, c in zip(FIELDS, counts)}
    sec, nsec = np.empty(n, dtype=np.int64), np.empty(n, dtype=np.int64)
    for start, stride, m, (fields, t, _), rows in groups:
        if not m:
            continue
        for f, c, (at, data) in zip(FIELDS, counts, fields):
            if np.any(b.view('u4', start + at, (m,), (stride,)) != c):
                return None
            if c and f != 'effort':
                out[f][rows] = b.view('f8', start + data, (m, c), (stride, 8))
        sec[rows] = b.view('i4', start + t, (m,), (stride,))
        nsec[rows] = b.view('u4', start + t + 4, (m,), (stride,))
    return out, sec, nsec


def _walk(b, p0, n):
    """The points one by one (any array lengths): ({field: rows}, sec, nsec)."""
    rows = {f: [] for f in FIELDS[:3]}
    sec, nsec = np.empty(n, dtype=np.int64), np.empty(n, dtype=np.int64)
    pos = p0
    for i in range(n):
        for f in FIELDS:
            values, pos = b.doubles(pos)
            if f != 'effort':
                rows[f].append(values)
        pos = _align(pos, 4)
        if pos + 8 > b.end:
            raise truncated('trajectory')
        sec[i] = b.view('i4', pos, (1,), (4,))[0]
        nsec[i] = b.view('u4', pos + 4, (1,), (4,))[0]
        pos += 8
    return rows, sec, nsec


def read(buf):
    """A serialized JointTrajectory as arrays: dict with 'prefix' (the bytes before the points),
    'order', 'joint_names', 'sec' and 'nanosec' (N,) of time_from_start, and 'positions',
    'velocities', 'accelerations' ((N, k); velocities / accelerations None when every point
    leaves them empty). Point efforts are not read. Raises ValueError for a malformed or
    truncated message or invalid array lengths (Unsupported: another encoding)."""
    b, names, n, p0 = _head(buf)
    k = len(names)
    if n == 0:
        raise ValueError('trajectory has no points')
    if n > (b.end - p0) // 24:   # a point takes at least 4 counts and the time
        raise truncated('trajectory')
    fast = _regular(b, p0, n)
    if fast is not None and fast[0]['positions'].shape[1] == k and \
            all(fast[0][f].shape[1] in (0, k) for f in ('velocities', 'accelerations')):
        arrays, sec, nsec = fast
        blocks = {f: (arrays[f] if arrays[f].shape[1] or f == 'positions' else None)
                  for f in ('positions', 'velocities', 'accelerations')}
    else:
        rows, sec, nsec = _walk(b, p0, n)
        blocks = {f: block(rows[f], f, k, f == 'positions') for f in rows}
    return dict(prefix=bytes(buf[:4 + p0]), order=b.order, joint_names=names, sec=sec, nanosec=nsec, **blocks)


def arrays(traj):
    """The arrays of `read` as trajectory_msgs.trajectory_arrays returns them."""
    return {'joint_names': list(traj['joint_names']), 'time_from_start': traj['sec'] + traj['nanosec'] * 1e-9,
            'positions': traj['positions'], 'velocities': traj['velocities'],
            'accelerations': traj['accelerations']}


def write(traj, efforts):
    """The serialized message of `read`'s trajectory with every point's effort set to the row of
    `efforts` (N, joints in message order); everything else as read (bytes)."""
    n, k = len(traj['sec']), len(traj['joint_names'])
    efforts = np.asarray(efforts, dtype=float).reshape(n, k)
    fields = [traj['positions'], traj['velocities'], traj['accelerations'], efforts]
    counts = [0 if a is None else a.shape[1] for a in fields]
    prefix = traj['prefix']
    p0 = len(prefix) - 4
    groups, end = _groups(p0, n, counts)
    out = np.zeros(4 + end, dtype=np.uint8)
    out[:len(prefix)] = np.frombuffer(prefix, dtype=np.uint8)
    b = Buffer(out, 'trajectory')
    for start, stride, m, (offsets, t, _), rows in groups:
        if not m:
            continue
        for a, c, (at, data) in zip(fields, counts, offsets):
            b.view('u4', start + at, (m,), (stride,))[:] = c
            if c:
                b.view('f8', start + data, (m, c), (stride, 8))[:] = a[rows]
        b.view('i4', start + t, (m,), (stride,))[:] = traj['sec'][rows]
        b.view('u4', start + t + 4, (m,), (stride,))[:] = traj['nanosec'][rows]
    return out.tobytes()
