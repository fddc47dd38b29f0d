"""CDR, the serialized form of ROS messages (what a raw subscription delivers and what a rosbag2
file holds), read and written with the standard library and numpy; no ROS import. The one
implementation of the primitives (encapsulation, alignment, counts, strings, array views), of
the stamp conversion, of the sensor_msgs/JointState reader (`JointStateDecoder`) and of
`Template`/`Writer`, the writer of fixed-shape messages. The node's readers build on it
(ros/core/cdr.py: joint_states and the desired state; ros/trajectories/trajectory_cdr.py: whole
trajectories), and so do the rosbag2 recordings (calibration/recordings.py).

Plain CDR (XCDR1, little or big endian: what rmw_fastrtps and rmw_cyclonedds send) is read;
any other encapsulation raises Unsupported. Offsets are relative to the payload (after the
4-byte encapsulation header); a value of n bytes is aligned to min(n, 8). Strings are a uint32
length (the terminating NUL included) and the bytes; they decode as rclpy decodes them:
UTF-8 with replacement characters, cut at the first NUL.
"""
import struct
from typing import NamedTuple

import numpy as np

_ORDER = {b'\x00\x01': '<', b'\x00\x00': '>'}
_U32 = {'<': struct.Struct('<I'), '>': struct.Struct('>I')}
_STAMP = {'<': struct.Struct('<iII'), '>': struct.Struct('>iII')}   # sec, nanosec, frame_id length
_F8 = {'<': np.dtype('<f8'), '>': np.dtype('>f8')}
_STAMP_LE = struct.Struct('<iI')   # builtin_interfaces/Time, as Template writes it
_F8_LE = _F8['<']
_new = tuple.__new__   # a NamedTuple's generated __new__ costs a Python call per message


class Unsupported(ValueError):
    """A serialized message in an encoding this module does not read."""


def align(pos, n):
    return (pos + n - 1) & ~(n - 1)


def truncated(what='message'):
    return ValueError(f'serialized {what} is truncated')


def stamp_ns(sec, nanosec):
    """A builtin_interfaces Time (sec, nanosec) as integer nanoseconds: the one conversion."""
    return sec * 1_000_000_000 + nanosec


def stamp_parts(ns):
    """(sec, nanosec) of integer nanoseconds (the inverse of stamp_ns)."""
    return divmod(ns, 1_000_000_000)


def _text(raw):
    """A CDR string's bytes as rclpy decodes them (C string: up to the first NUL)."""
    end = raw.find(b'\0')
    return (raw if end < 0 else raw[:end]).decode('utf-8', 'replace')


class Buffer:
    """A serialized message: its byte order and payload length; reads at payload offsets."""

    def __init__(self, buf, what='message'):
        if len(buf) < 4:
            raise truncated(what)
        self.order = _ORDER.get(bytes(buf[:2]))
        if self.order is None:
            raise Unsupported(f'CDR encapsulation {bytes(buf[:2]).hex()} is not read here')
        self.buf = buf
        self.end = len(buf) - 4   # payload length
        self.what = what

    def u32(self, pos):
        """The uint32 at payload offset pos."""
        if pos + 4 > self.end:
            raise truncated(self.what)
        return _U32[self.order].unpack_from(self.buf, 4 + pos)[0]

    def view(self, dtype, start, shape, strides):
        """Array view of the payload from offset `start` (read-only on bytes, writable on arrays)."""
        return np.ndarray(shape, dtype=self.order + dtype, buffer=self.buf, offset=4 + start, strides=strides)

    def string(self, pos):
        """(text, offset after it) of the string at payload offset pos (aligned here)."""
        pos = align(pos, 4)
        size = self.u32(pos)
        pos += 4
        if size > self.end - pos:
            raise truncated(self.what)
        return _text(bytes(self.buf[4 + pos:4 + pos + size])), pos + size

    def strings(self, pos):
        """(list of texts, offset after them) of the string sequence at payload offset pos."""
        pos = align(pos, 4)
        count = self.u32(pos)
        pos += 4
        if count > (self.end - pos) // 4:   # each string takes at least its length
            raise truncated(self.what)
        out = []
        for _ in range(count):
            text, pos = self.string(pos)
            out.append(text)
        return out, pos

    def doubles(self, pos):
        """(float64 array view, offset after it) of the float64 sequence at payload offset pos."""
        pos = align(pos, 4)
        count = self.u32(pos)
        pos += 4
        if count:
            pos = align(pos, 8)
        if count > (self.end - pos) // 8:
            raise truncated(self.what)
        return np.frombuffer(self.buf, _F8[self.order], count, 4 + pos), pos + 8 * count


class JointStateSample(NamedTuple):
    """One sensor_msgs/JointState as the node's decision core takes it: stamp in ns, the names
    (a tuple, shared with the previous sample while the message's name list stays the same),
    and read-only float64 arrays in message order (an absent array is empty)."""
    stamp: int
    names: tuple
    position: np.ndarray
    velocity: np.ndarray
    effort: np.ndarray


class Layout(NamedTuple):
    """The layout of the last joint_states message a JointStateDecoder read (its fast path's
    test, JointStateDecoder.layout): the message's length, its encapsulation (4 bytes), its bytes
    from the frame_id's length to the position count (`key`, bytes 12..key_end), the velocity and
    effort counts (`counts`, read by `count_struct` at the absolute offsets `count_at`), each
    array's (count, absolute offset of its first value), the names."""
    length: int
    head: bytes
    key: bytes
    key_end: int
    count_struct: struct.Struct
    counts: tuple
    arrays: tuple
    names: tuple
    count_at: tuple


class JointStateDecoder:
    """Serialized sensor_msgs/JointState -> JointStateSample. Keeps the last name list (and its
    bytes), so that a stream naming the same joints decodes them once, and the last message's
    layout: a message of the same length whose bytes from the frame_id to the positions and
    whose velocity and effort counts are those of the last one has its arrays where the last
    one had them, read without walking the message again (a stream's every message but the
    first; the stamp and the doubles are what changes).

    Layout: header {int32 sec, uint32 nanosec, string frame_id}, string[] name, float64[]
    position, velocity, effort."""

    def __init__(self):
        self._names_raw = None
        self._names = ()
        # the last message's Layout; None after one that was not read
        self._same = None

    @property
    def layout(self):
        """The Layout the next message is read by without walking it (the last message's), or
        None (none read yet, or the last one was not read or not little-endian)."""
        return self._same

    def read(self, buf):
        """The sample of `buf` (bytes). Raises ValueError for a malformed or truncated message
        (Unsupported: another encoding)."""
        same = self._same
        if (same is not None and len(buf) == same[0] and buf[12:same[3]] == same[2] and buf[:4] == same[1]
                and same[4].unpack_from(buf) == same[5]):
            sec, nanosec = _STAMP_LE.unpack_from(buf, 4)
            (n0, o0), (n1, o1), (n2, o2) = same[6]
            return _new(JointStateSample, (stamp_ns(sec, nanosec), same[7],
                                           np.frombuffer(buf, _F8_LE, n0, o0), np.frombuffer(buf, _F8_LE, n1, o1),
                                           np.frombuffer(buf, _F8_LE, n2, o2)))
        self._same = None
        b = Buffer(buf, 'joint_states')
        if b.end < 16:
            raise truncated('joint_states')
        sec, nanosec, size = _STAMP[b.order].unpack_from(buf, 4)
        pos = 12 + size
        if size > b.end - 12:
            raise truncated('joint_states')
        names, pos = self._read_names(b, buf, align(pos, 4))
        arrays, at = [], []   # at: each array's (payload offset of its count, of its first value)
        for _ in range(3):
            count_at = align(pos, 4)
            a, pos = b.doubles(pos)
            arrays.append(a)
            at.append((count_at, pos - 8 * len(a)))
        if b.order == '<' and len(names):   # the layout the next message of this stream is checked against
            key_end = 4 + at[0][0] + 4   # the bytes from the frame_id's length to the position count
            v, e = 4 + at[1][0], 4 + at[2][0]
            counts = struct.Struct(f'<{v}xI{e - v - 4}xI')   # the velocity and effort counts
            self._same = Layout(len(buf), bytes(buf[:4]), bytes(buf[12:key_end]), key_end, counts,
                                counts.unpack_from(buf),
                                tuple((len(a), 4 + start) for a, (_, start) in zip(arrays, at, strict=True)), names,
                                (v, e))
        return JointStateSample(stamp_ns(sec, nanosec), names, *arrays)

    def _read_names(self, b, buf, pos):
        count = b.u32(pos)
        raw = self._names_raw
        if raw is not None and buf[4 + pos:4 + pos + len(raw)] == raw:   # the same names as last time
            return self._names, pos + len(raw)
        names, end = b.strings(pos)
        self._names_raw = bytes(buf[4 + pos:4 + end]) if count else None
        self._names = tuple(names)
        return self._names, end


class Template:
    """A serialized message (little-endian plain CDR) whose shape is fixed: written once with
    zeros, then each message is a copy with its stamp and double arrays put in place (the dynamics
    topics publish at up to the joint_states rate: a copy costs less than rclpy's conversion and
    serialization of a message object, measured by bench.node_callback). Built by the `int32`,
    `uint32`, `string`, `strings` and `doubles` calls in the message's field order; `doubles(n)`
    returns its slot for `fill`."""

    def __init__(self):
        self.buf = bytearray(b'\x00\x01\x00\x00')   # CDR_LE encapsulation; offsets count after it

    def _put(self, data, alignment):
        pos = align(len(self.buf) - 4, alignment)
        self.buf += b'\0' * (pos - (len(self.buf) - 4)) + data
        return pos + 4

    def int32(self, v=0):
        return self._put(struct.pack('<i', v), 4)

    def uint32(self, v=0):
        return self._put(struct.pack('<I', v), 4)

    def string(self, text):
        raw = text.encode('utf-8') + b'\0'
        self.uint32(len(raw))
        self._put(raw, 1)

    def strings(self, texts):
        self.uint32(len(texts))
        for t in texts:
            self.string(t)

    def doubles(self, n):
        """A sequence<double> of n zeros; returns its slot (start, end) in the buffer."""
        self.uint32(n)
        start = self._put(b'\0' * (8 * n), 8 if n else 1)
        return start, start + 8 * n

    def fill(self, slots, arrays, stamp_at=None, stamp=0):
        """The message: this template with each array (n float64) in its slot, and a
        builtin_interfaces/Time of `stamp` (ns) at offset `stamp_at`."""
        out = bytearray(self.buf)
        for (a, b), x in zip(slots, arrays, strict=True):
            out[a:b] = np.ascontiguousarray(x, dtype='<f8').tobytes()
        if stamp_at is not None:
            _STAMP_LE.pack_into(out, stamp_at, *stamp_parts(stamp))
        return bytes(out)

    def writer(self, slots, stamp_at=None):
        """fill(slots, ., stamp_at, .) for a message published at every sample: a Writer."""
        return Writer(self.buf, slots, stamp_at)


def joint_state_template(names, sizes=None):
    """(Template, stamp offset, slots of position, velocity, effort) of a sensor_msgs/JointState
    with these names and an empty frame_id; sizes: the three arrays' lengths (default: one
    value per name each). The one writer of a JointState's layout (the dynamics and contact
    topics, the recordings of ~/record)."""
    t = Template()
    stamp_at = t.int32()
    t.uint32()
    t.string('')
    t.strings(names)
    return t, stamp_at, [t.doubles(len(names) if sizes is None else k) for k in (sizes or range(3))]


def multi_array_template(size, dims=()):
    """(Template, [data slot]) of a std_msgs/Float64MultiArray of `size` doubles whose layout
    has the rows `dims`, each (label, size, stride), and data_offset 0. The one writer of its
    layout (the node's effort command: no dims; the dynamics topics' matrices)."""
    t = Template()
    t.uint32(len(dims))
    for label, n, stride in dims:
        t.string(label)
        t.uint32(n)
        t.uint32(stride)
    t.uint32(0)   # data_offset
    return t, [t.doubles(size)]


class Writer:
    """Template.fill with the slots and stamp offset fixed, for a message published at every
    sample: the template cut into its constant pieces once, each message the pieces joined with
    the packed stamp and the arrays' bytes (half the time of filling a copy of the buffer).
    message(arrays, stamp) -> the message's bytes (a method, not __call__: an instance call
    costs more); an array of another length than its slot raises ValueError. One caller at a
    time (the pieces are reused)."""

    def __init__(self, buf, slots, stamp_at=None):
        cuts = sorted([(a, b, k) for k, (a, b) in enumerate(slots)]
                      + ([] if stamp_at is None else [(stamp_at, stamp_at + 8, None)]))
        self.parts, self.where, pos = [], [None] * len(slots), 0   # where: (part, size) per array
        self.stamp_part = None
        for a, b, k in cuts:
            self.parts += [bytes(buf[pos:a]), bytes(buf[a:b])]
            if k is None:
                self.stamp_part = len(self.parts) - 1
            else:
                self.where[k] = (len(self.parts) - 1, b - a)
            pos = b
        self.parts.append(bytes(buf[pos:]))

    def message(self, arrays, stamp=0):
        parts = self.parts
        k = 0
        for i, size in self.where:
            data = np.asarray(arrays[k], dtype=_F8['<']).tobytes()
            if len(data) != size:
                raise ValueError(f'array {k} has {len(data) // 8} values, its slot {size // 8}')
            parts[i] = data
            k += 1
        if self.stamp_part is not None:
            parts[self.stamp_part] = _STAMP_LE.pack(*stamp_parts(stamp))
        return b''.join(parts)
