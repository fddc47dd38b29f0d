"""Reading the node's input messages, in plain Python (no rclpy import): joint names mapped to
the command layout, and every check a joint_states or desired-state message must pass.

A message that fails raises `Rejected(kind, text)`: kind is a short key (length, duplicate,
missing, nonfinite, implausible, points) the node throttles its log line by, text says what is
wrong (name lists quoted from the message are bounded, diagnostics.names_text). Nothing here
counts or logs; the compensator does.
"""
import numpy as np

from ...model.joint_names import in_joint_order, joint_columns
from .diagnostics import names_text


class Rejected(ValueError):
    """An input message that is not used; `kind` names the problem class, str() the details."""

    def __init__(self, kind, text):
        super().__init__(text)
        self.kind = kind
        self.text = text


def columns_refusal(mapped, names, controlled):
    """Why a name list does not map to the controlled joints (model.joint_names.joint_columns'
    JointColumns `mapped` of `names`), as a Rejected, or None when it maps: the one wording of
    the refusal for joint_states, the desired state and trajectories (names quoted bounded)."""
    if mapped.duplicates:
        return Rejected('duplicate', f'duplicate joint names {names_text(mapped.duplicates)}')
    if mapped.missing:
        known = set(controlled)
        other = [j for j in names if j not in known]
        hint = f' (it names {names_text(other)}, which are not controlled joints)' if other else ''
        return Rejected('missing', f'missing controlled joints {names_text(mapped.missing)}{hint}')
    return None


class NameMap:
    """Column indices of the controlled joints in a message's name list (cached per list), by
    the one mapping rule (model.joint_names.joint_columns)."""

    def __init__(self):
        self.names = None
        self.error = None   # Rejected, or None when the list maps
        self.idx = None

    def build(self, names, controlled):
        # kept as given (a decoded sample's tuple, a message's list): the next message's list
        # compares equal to it only in the same type
        self.names = names if isinstance(names, tuple) else list(names)
        mapped = joint_columns(names, controlled)
        self.error = columns_refusal(mapped, names, controlled)
        if self.error is None:
            self.idx = mapped.columns
        return mapped.index


class JointStateReader:
    """Positions and velocities of one model's joints from sensor_msgs/JointState fields.

    Controlled joints come out in model order; locked joints present in the message are fed to
    the model (model.set_locked, only when their values change) and remembered in `known`, a
    dict the owner keeps across models (the next model starts from the last measured values).
    bounds: settings.PositionBounds, the plausible positions (None: finite is enough).
    """

    def __init__(self, model, known, bounds=None):
        self.model = model
        self.known = known
        self.bounds = bounds
        self.map = NameMap()
        self.lock_idx = None
        self.lock_names = ()
        self.last_locked = None
        known_here = {k: v for k, v in known.items() if k in set(model.locked_joint_names)}
        if known_here:
            model.set_locked(known_here)

    def _build(self, names):
        index = self.map.build(names, self.model.joint_names)
        if self.map.error is None:
            self.lock_names = [j for j in self.model.locked_joint_names if j in index]
            self.lock_idx = np.array([index[j] for j in self.lock_names], dtype=int)
            self.last_locked = None

    def positions(self, names, position, velocity, effort):
        """Controlled joint positions (model order) of one message. Raises Rejected: array lengths
        that differ, duplicate names, a missing controlled joint, a used position that is
        non-finite or outside `bounds`."""
        n_names = len(names)
        if len(position) != n_names or len(velocity) not in (0, n_names) or len(effort) not in (0, n_names):
            raise Rejected('length', f'array lengths differ: {n_names} names, {len(position)} positions, '
                                     f'{len(velocity)} velocities, {len(effort)} efforts')
        m = self.map
        if names != m.names:
            self._build(names)
        if m.error is not None:
            raise m.error
        pos = np.asarray(position, dtype=float)
        q = in_joint_order(pos, m.idx)
        b = self.bounds
        # one range check also fails NaN (hot path: count_nonzero is cheaper than .all())
        if b is None:
            if np.count_nonzero(np.isfinite(q)) != q.size:
                self._refuse(q, self.model.joint_names, None, None)
        elif np.count_nonzero((q >= b.lower) & (q <= b.upper)) != q.size:
            self._refuse(q, self.model.joint_names, b.lower, b.upper)
        if len(self.lock_idx):
            lv = pos[self.lock_idx]
            if b is None:
                if np.count_nonzero(np.isfinite(lv)) != lv.size:
                    self._refuse(lv, self.lock_names, None, None)
            elif np.count_nonzero(np.abs(lv) <= b.locked) != lv.size:
                self._refuse(lv, self.lock_names, -b.locked, b.locked)
            if self.last_locked is None or not np.array_equal(lv, self.last_locked):
                vals = dict(zip(self.lock_names, lv.tolist(), strict=True))
                self.model.set_locked(vals)
                self.known.update(vals)
                self.last_locked = lv
        return q

    @staticmethod
    def _refuse(values, names, lower, upper):
        """Raise Rejected for the non-finite values (nonfinite), else for those outside [lower, upper]."""
        bad = ~np.isfinite(values)
        if bad.any():
            raise Rejected('nonfinite', f'non-finite positions for {names_text(np.asarray(names)[bad].tolist())}')
        lower, upper = np.broadcast_to(lower, values.shape), np.broadcast_to(upper, values.shape)
        out = [f'{names[k]}={values[k]:.6g} outside [{lower[k]:.6g}, {upper[k]:.6g}]'
               for k in np.flatnonzero((values < lower) | (values > upper))]
        raise Rejected('implausible', 'implausible positions (URDF limits widened by position_margin, '
                                      f'continuous_position_bound): {names_text(out, 4)}')

    def velocity(self, velocity):
        """(qd, complete): controlled joint velocities of the message last read by `positions`;
        an absent array or a NaN/inf entry is unavailable and used as 0 (complete = False)."""
        if not len(velocity):
            return np.zeros(self.model.n), False
        qd = in_joint_order(velocity, self.map.idx)
        ok = np.isfinite(qd)
        if np.count_nonzero(ok) != qd.size:
            return np.where(ok, qd, 0.0), False
        return qd, True


def read_desired(names, points, layout, name_map, topic=''):
    """(q_d, qd_d, qdd_d) in `layout` order from a desired-state message (JointTrajectory
    joint_names and points). Raises Rejected.

    Exactly one point; positions for every name; velocities and accelerations either one per
    name or absent (= 0); the controlled joints present and finite (other names are ignored).
    name_map: a NameMap kept by the caller (rebuilt only when the name list changes).
    """
    if len(points) != 1:
        raise Rejected('points', f'{len(points)} points: {topic} takes exactly one '
                                 '(whole trajectories go to ~/trajectory_in)')
    p = points[0]
    n_names = len(names)
    pos, vel, acc = p.positions, p.velocities, p.accelerations
    if len(pos) != n_names or len(vel) not in (0, n_names) or len(acc) not in (0, n_names):
        raise Rejected('length', f'array lengths differ: {n_names} joint names, {len(pos)} '
                                 f'positions, {len(vel)} velocities, {len(acc)} accelerations')
    if names != name_map.names:
        name_map.build(names, layout)
    if name_map.error is not None:
        raise name_map.error
    n = len(layout)
    out = []
    for field, values in (('positions', pos), ('velocities', vel), ('accelerations', acc)):
        if not len(values):
            out.append(np.zeros(n))
            continue
        a = in_joint_order(values, name_map.idx)
        if not np.isfinite(a).all():
            bad = [layout[k] for k in np.flatnonzero(~np.isfinite(a))]
            raise Rejected('nonfinite', f'non-finite {field} for {names_text(bad)}')
        out.append(a)
    return tuple(out)
