"""Reading the node's input messages, in plain Python (no rclpy import): joint names mapped to
the command layout, and every check a joint_states or desired-state message must pass.

A message that fails raises `Rejected(kind, text)`: kind is a short key (length, duplicate,
missing, nonfinite, points) the node throttles its log line by, text says what is wrong.
Nothing here counts or logs; the compensator does.
"""
import numpy as np


class Rejected(ValueError):
    """An input message that is not used; `kind` names the problem class, str() the details."""

    def __init__(self, kind, text):
        super().__init__(text)
        self.kind = kind
        self.text = text


class NameMap:
    """Column indices of the controlled joints in a message's name list (cached per list)."""

    def __init__(self):
        self.names = None
        self.error = None   # Rejected, or None when the list maps
        self.idx = None

    def build(self, names, controlled):
        self.names = list(names)
        self.error = None
        index = {}
        dup = []
        for i, name in enumerate(names):
            if name in index:
                dup.append(name)
            index[name] = i
        if dup:
            self.error = Rejected('duplicate', f'duplicate joint names {sorted(set(dup))}')
            return index
        missing = [j for j in controlled if j not in index]
        if missing:
            other = [j for j in names if j not in set(controlled)]
            hint = f' (it names {other}, which are not controlled joints)' if other else ''
            self.error = Rejected('missing', f'missing controlled joints {missing}{hint}')
            return index
        self.idx = np.array([index[j] for j in controlled], dtype=int)
        return index


class JointStateReader:
    """Positions and velocities of one model's joints from sensor_msgs/JointState fields.

    Controlled joints come out in model order; locked joints present in the message are fed to
    the model (model.set_locked, only when their values change) and remembered in `known`, a
    dict the owner keeps across models (the next model starts from the last measured values).
    """

    def __init__(self, model, known):
        self.model = model
        self.known = known
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
        that differ, duplicate names, a missing controlled joint, a non-finite used position."""
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
        q = pos[m.idx]
        if np.count_nonzero(np.isfinite(q)) != q.size:  # (hot path: count_nonzero is cheaper than .all())
            bad = [self.model.joint_names[k] for k in np.flatnonzero(~np.isfinite(q))]
            raise Rejected('nonfinite', f'non-finite positions for {bad}')
        if len(self.lock_idx):
            lv = pos[self.lock_idx]
            if np.count_nonzero(np.isfinite(lv)) != lv.size:
                bad = [self.lock_names[k] for k in np.flatnonzero(~np.isfinite(lv))]
                raise Rejected('nonfinite', f'non-finite positions for {bad}')
            if self.last_locked is None or not np.array_equal(lv, self.last_locked):
                vals = dict(zip(self.lock_names, lv.tolist(), strict=True))
                self.model.set_locked(vals)
                self.known.update(vals)
                self.last_locked = lv
        return q

    def velocity(self, velocity):
        """(qd, complete): controlled joint velocities of the message last read by `positions`;
        an absent array or a NaN/inf entry is unavailable and used as 0 (complete = False)."""
        if not len(velocity):
            return np.zeros(self.model.n), False
        qd = np.asarray(velocity, dtype=float)[self.map.idx]
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
        a = np.asarray(values, dtype=float)[name_map.idx]
        if not np.isfinite(a).all():
            bad = [layout[k] for k in np.flatnonzero(~np.isfinite(a))]
            raise Rejected('nonfinite', f'non-finite {field} for {bad}')
        out.append(a)
    return tuple(out)
