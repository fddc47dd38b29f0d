"""The fused command path: a serialized joint_states message to the command's bytes in one native
call, for the common case, in plain Python around it (no rclpy import).

Between two states 1 ms apart the caches are cold, and each of the Python path's small numpy and
Python calls (decode, map, check, law, clamp, encode) costs several times its warm cost
(docs/benchmarks.md, section 5). The fused path is a fast path of that Python path, never a
second set of rules: for a message repeating the last layout the decoder read (cdr.JointStateDecoder's
fast path), whose used positions pass the reader's range check, under the mode's own law
(gravity without velocity terms or friction, feedforward, computed torque without friction; a fresh
desired state) computed by the model's native kernel, with no ramp or silence in force, the
native Command (codegen/native_command.c) computes the same bits, clamped to the effort limits
as laws.clamp clamps them, and the core keeps the same state (Compensator.on_fast_command: a
clamped command counted and logged by laws.clamp itself, as on the Python path). Anything else
declines (None) and the Python path decides, counts, logs and publishes as without it: a layout
change, a check failing, a non-finite torque, a mode or an option it does not cover, no native
kernel, no C compiler.

A Command is made for one key (the law, settings, model and its version, the reader's map and
locked values, the layout, the writers); a change of any makes the next. A new desired state is
handed to the Command made (Command.desired): one may come at every state. A new
layout's first two messages take the Python path (its first is walked by the decoder, the second
read by its fast path shows that the layout repeats).
"""
import sys

import numpy as np

from ...codegen import native
from ...laws import LAWS

_LAW = {'gravity': 0, 'feedforward': 1, 'computed_torque': 2}
_F8_LE = np.dtype('<f8')
_INDEX = np.dtype(np.intp)
_TANH = np.tanh.types.index('d->d')   # numpy's float64 tanh loop: the friction law's tanh, bit for bit


def _same(key, last):
    """Is `key` the last one? Its objects the same ones (a tuple compares each pair by identity
    first: all identical, no comparison runs) or equal; an array in it that is not the same
    object (NumPy's == is elementwise): not the same."""
    try:
        return key == last
    except ValueError:
        return False


class FusedCommand:
    """The fused command path of `core` (a Compensator) reading what `decoder` (the node's
    cdr.JointStateDecoder) read last. `taken` and `declined` count its outcomes."""

    def __init__(self, core, decoder):
        self.core, self.decoder = core, decoder
        self._key = None
        self._desired = None  # the core's desired state the Command has
        self._path = None    # the native Command for the key, or None: decline
        self._views = None   # (count, offset) of the velocity and effort arrays
        self._pending = None  # the command made, until `accepted`
        # the decoder's layout at the last call: a Command is made for a layout the decoder read
        # twice in a row (by its fast path the second time), not for one it walks at every
        # message (a publisher whose padding bytes change: rclpy's serialize_message)
        self._layout = None
        self.taken = self.declined = 0

    def command(self, buf, writers):
        """(command bytes, ~/commanded_efforts bytes or None) for the serialized joint_states
        `buf`, or None (declined: nothing changed, the Python path takes it). The caller
        publishes them, then calls `accepted`. writers: Outputs.writers' pair for the core's layout."""
        core = self.core
        now = core.clock()
        law = core.fast_law(now)
        if law is None:
            self.declined += 1
            return None
        model, reader, layout = core.model, core.reader, self.decoder.layout
        if layout is not self._layout or layout is None:   # a layout read once: made when it repeats
            self._layout = layout
            self.declined += 1
            return None
        key = (law, core.settings, model, model.version, reader, reader.map.names, reader.last_locked, layout,
               writers[0], writers[1], core.limits)
        desired = core.desired
        if not _same(key, self._key):
            self._path = self._make(law, model, reader, layout, writers)
            self._key, self._desired = key, desired
        path = self._path
        if desired is not self._desired and path is not None:   # (not a new Command: one may come at every state)
            path.desired(*self._desired_arrays(law, model))
            self._desired = desired
        r = path(buf) if path is not None else None
        if r is None or core.refuses_stamp(r[0]):
            self.declined += 1
            return None
        self._pending = (law, buf, r, now)
        return r[3], r[4]

    def accepted(self):
        """After the command of `command` went out: the core keeps its state as on_sample would
        (Compensator.on_fast_command; nothing in it changes the command)."""
        law, buf, (stamp, q, tau, _, _, clamped), now = self._pending
        self._pending = None
        (n1, o1), (n2, o2) = self._views
        self.core.on_fast_command(law, stamp, q, tau, np.frombuffer(buf, _F8_LE, n1, o1),
                                  np.frombuffer(buf, _F8_LE, n2, o2), now, clamped)
        self.taken += 1

    def _make(self, law, model, reader, layout, writers):
        """The native Command for this key, or None when the fused path does not cover it."""
        core, s = self.core, self.core.settings
        mod = native.module()
        if (mod is None or sys.byteorder != 'little' or layout is None or law not in _LAW
                or s.robot_compensates_gravity or (law == 'gravity' and s.include_velocity_terms)):
            return None
        m = reader.map
        names = layout.names
        if m.names != names or m.error is not None:   # the reader maps this name list first
            return None
        (n0, o0), (n1, o1), (n2, o2) = layout.arrays
        if n0 != len(names) or n1 not in (0, n0) or n2 not in (0, n0):
            return None
        need_v = bool(core.needs_velocity[law])
        lock_idx = np.ascontiguousarray(reader.lock_idx, dtype=_INDEX)
        if need_v and not n1 or (len(lock_idx) and reader.last_locked is None):
            return None
        n = model.n
        cmd_w, js_w = writers
        if cmd_w.where != [(1, 8 * n)] or cmd_w.stamp_part is not None or len(cmd_w.parts) != 3:
            return None
        if js_w is not None and (js_w.where != [(3, 8 * n)] or js_w.stamp_part != 1 or len(js_w.parts) != 5):
            return None
        base, q_d, qd_d, qdd_d = self._desired_arrays(law, model)
        method = None
        if law != 'feedforward':
            method = type(model).gravity if law == 'gravity' else type(model).inverse_dynamics
        b = reader.bounds
        lower = upper = None
        if b is not None:
            lower = np.ascontiguousarray(np.broadcast_to(b.lower, (n,)), dtype=float)
            upper = np.ascontiguousarray(np.broadcast_to(b.upper, (n,)), dtype=float)
        last_locked = (np.ascontiguousarray(reader.last_locked, dtype=float) if len(lock_idx) else None)
        cols = np.ascontiguousarray(m.idx, dtype=_INDEX)
        v_at, e_at = layout.count_at
        gains = [None if g is None else np.ascontiguousarray(np.broadcast_to(g, (n,)), dtype=float)
                 for g in (core.kp, core.kd)]
        bound = np.ascontiguousarray(core.limits.bound, dtype=float)
        limit = np.ascontiguousarray(core.limits.limit, dtype=float)
        friction = core.friction if law != 'feedforward' else None   # (feedforward's is at qd_d: in base)
        viscous = coulomb = None
        if friction is not None:
            viscous, coulomb = [None if f is None else np.ascontiguousarray(np.broadcast_to(f, (n,)), dtype=float)
                                for f in (friction.viscous, friction.coulomb)]
        arrays = (cols, lower, upper, lock_idx, last_locked, base, q_d, qd_d, qdd_d, *gains, bound, limit, viscous,
                  coulomb)
        try:
            path = mod.command_path(
                layout.length, layout.head, layout.key, v_at, layout.counts[0], e_at, layout.counts[1], o0, o1, n0,
                cols, lower, upper, lock_idx, last_locked, float(b.locked) if b is not None else float('nan'),
                _LAW[law], int(need_v), method, model, base, q_d, qd_d, qdd_d, *gains, bound, limit,
                tuple(cmd_w.parts), None if js_w is None else tuple(js_w.parts), arrays, viscous, coulomb,
                float(friction.eps) if friction is not None else 1.0, np.tanh, _TANH)
        except ValueError:   # a form it does not take (an index out of the message): the Python path
            return None
        self._views = ((n1, o1), (n2, o2))
        return path

    def _desired_arrays(self, law, model):
        """(base, q_d, qd_d, qdd_d) of the core's desired state for law `law`: None each for
        gravity; base, feedforward's model term ID(desired) + f(qd_d), by the law itself without
        its gains (None for computed torque)."""
        if law == 'gravity':
            return None, None, None, None
        core = self.core
        desired = tuple(np.ascontiguousarray(a, dtype=float) for a in core.desired)
        base = None
        if law == 'feedforward':
            base = np.ascontiguousarray(LAWS[law](model, None, None, desired, None, None, core.friction,
                                                  core.settings.include_velocity_terms), dtype=float)
        return (base, *desired)
