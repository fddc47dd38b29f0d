"""What the decision core made of one joint_states message, in plain Python (no rclpy import).

`SampleResult` is made once per message by the compensator (`Compensator.result`) and handed,
when accepted, to every per-sample feature (features/base.py) after the command went out.
It is a tuple: its fields cannot be rebound, and its arrays are read-only (the core keeps `q`
as the state the stale action holds). The mapped arrays (`velocity`, `qd`, `effort`) are made
on first use and kept in `memo`, so a feature that does not read them costs nothing.
"""
from typing import NamedTuple, Optional

import numpy as np

from ...model.joint_names import in_joint_order

_EMPTY = np.empty(0)
_EMPTY.flags.writeable = False
_new = tuple.__new__   # the generated NamedTuple __new__ costs a Python call per message


def _frozen(a):
    a.setflags(write=False)   # cheaper than a.flags.writeable (no flags object per call)
    return a


class SampleResult(NamedTuple):
    """One joint_states message after the core: `accepted` (a command was computed from it) or
    not, and then `reason` (the rejection class: length, duplicate, missing, nonfinite,
    implausible, old, nonfinite_output, malformed, no_model) and `why` (the text logged).

    stamp: header stamp in ns (0: none). For an accepted state: q (validated positions, model
    order), the `model` that computed the command and its `version` then, `names` (the command
    layout, the same list object while it holds), and the message's own arrays with `columns`
    (the message column of each controlled joint, model order) for readers that map them
    themselves. A rejected one carries q = None, model None, version -1.
    """
    stamp: int
    accepted: bool
    reason: str
    why: str
    q: Optional[np.ndarray]
    model: object
    version: int
    names: object
    columns: Optional[np.ndarray]
    message_velocity: np.ndarray
    message_effort: np.ndarray
    memo: dict

    @classmethod
    def accept(cls, stamp, q, model, names, columns, velocity, effort):
        q.setflags(write=False)
        return _new(cls, (stamp, True, '', '', q, model, model.version, names, columns, velocity, effort, {}))

    @classmethod
    def reject(cls, stamp, reason, why):
        return cls(stamp, False, reason, why, None, None, -1, None, None, _EMPTY, _EMPTY, {})

    def _mapped(self, key, values):
        m = self.memo
        out = m.get(key)
        if out is None:
            out = in_joint_order(values, self.columns) if len(values) else np.full(len(self.q), np.nan)
            m[key] = _frozen(out)
        return out

    @property
    def velocity(self):
        """Velocities as the message gave them, model order (NaN where absent)."""
        return self._mapped('velocity', self.message_velocity)

    @property
    def effort(self):
        """Efforts as the message gave them, model order (NaN where absent)."""
        return self._mapped('effort', self.message_effort)

    @property
    def qd(self):
        """The velocity as the torque laws use it: absent or non-finite entries as 0."""
        m = self.memo
        out = m.get('qd')
        if out is None:
            v = self.velocity
            out = m['qd'] = _frozen(np.where(np.isfinite(v), v, 0.0))
        return out
