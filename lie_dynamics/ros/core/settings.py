"""The node's settings, in plain Python (no rclpy import): `Settings`, the typed object of the
parameter values generated from the one table (params.PARAMS), and what the torque laws make of
them: per-joint friction and gains, effort limits, the plausible position ranges, the payload,
and `Plan`, a validated change that Compensator.apply makes current.
"""
from collections.abc import Mapping
from typing import NamedTuple, Optional

import numpy as np

from ...laws import effort_limits, make_friction
from .params import PARAMS, PAYLOAD_KEYS, check_value, defaults, per_joint_values


class Group:
    """The parameters of one dotted prefix: `settings.collision` holds `threshold` and
    `hold_time` (collision.threshold, collision.hold_time). Read-only."""

    def __init__(self, prefix, values):
        object.__setattr__(self, '_prefix', prefix)
        for name, value in values.items():
            object.__setattr__(self, name, value)

    def __setattr__(self, name, value):
        raise AttributeError(f'settings are read-only: {self._prefix}.{name} changes through Settings.replace')

    def __repr__(self):
        items = ', '.join(f'{k}={v!r}' for k, v in vars(self).items() if k != '_prefix')
        return f'{self._prefix}({items})'


def _layout(names):
    """{attribute: [(member or None, full name)]} of dotted parameter names: a name without a dot
    is an attribute, `a.b` is member b of group a. Raises ValueError for a name that cannot be
    one (a group named like a parameter or a method, two dots, not an identifier)."""
    reserved = set(dir(Settings))   # its methods (and the mapping's)
    out = {}
    for name in names:
        parts = name.split('.')
        if len(parts) > 2 or not all(part.isidentifier() for part in parts) or parts[0] in reserved:
            raise ValueError(f'parameter {name!r} has no attribute form')
        out.setdefault(parts[0], []).append((parts[1] if len(parts) == 2 else None, name))
    for head, members in out.items():
        if len(members) > 1 and any(m is None for m, _ in members):
            raise ValueError(f'parameter {head!r} is also a group of parameters')
    return out


class Values(Mapping):
    """Parameter values {dotted name: value} as read-only attributes: a dotted name is a group
    (`payload.link` reads `values.payload.link`). Also a read-only mapping by full name
    (`value(name)` for a name held in a variable, iteration, `dict(values)`), for code that
    handles parameters by name (declaring them, checking or comparing sets of them)."""

    def __init__(self, values):
        values = dict(values)
        self._fill(values, _layout(values))

    def _fill(self, values, layout):
        set_ = object.__setattr__
        set_(self, '_values', values)
        for head, members in layout.items():
            if members[0][0] is None:
                set_(self, head, values[head])
            else:
                set_(self, head, Group(head, {m: values[name] for m, name in members}))

    def value(self, name):
        """The value of parameter `name` (full dotted name)."""
        return self._values[name]

    def differs(self, other, names):
        """Does any of parameters `names` differ between these values and `other`?"""
        mine, theirs = self._values, other._values
        return any(mine[n] != theirs[n] for n in names)

    def __getitem__(self, name):
        return self._values[name]

    def __iter__(self):
        return iter(self._values)

    def __len__(self):
        return len(self._values)

    def __setattr__(self, name, value):
        raise AttributeError(f'settings are read-only: {name} changes through Settings.replace')

    def __repr__(self):
        return f'{type(self).__name__}({self._values!r})'


class Settings(Values):
    """The dynamics node's parameter values, each checked (params.check_value): one read-only
    attribute per entry of params.PARAMS, its default written once, in the table
    (`settings.measured_effort`, `settings.collision.threshold`,
    `settings.friction.coulomb_velocity_epsilon`); see Values.

    Settings(values): the defaults with {name: value} over them (ValueError on an unknown name or
    a bad value); `replace(changes)` makes the settings after a change."""

    def __init__(self, values=None):
        self._checked(defaults(), values)

    def _checked(self, base, changes):
        values = dict(base)
        for name, value in (changes or {}).items():
            values[name] = check_value(name, value)
        self._fill(values, _LAYOUT)

    def replace(self, changes):
        """The settings after `changes` {name: value} (each checked; ValueError)."""
        new = object.__new__(Settings)
        new._checked(self._values, changes)
        return new


_LAYOUT = _layout(p.name for p in PARAMS)

# Settings whose change steps the command: with ramp_time > 0 the node blends across them.
BLEND_KEYS = ('mode', 'gravity', 'gravity_scale', 'robot_compensates_gravity') + PAYLOAD_KEYS


def per_joint(values, urdf_values, n, name):
    """Friction coefficients: [] -> URDF, [c] -> every joint, n values -> per joint. None when all 0."""
    out = per_joint_values(name, values, n, urdf_values)
    return out if np.any(out != 0) else None


def gains(values, n, name):
    """PD gains: [] -> 0, [k] -> every joint, n values -> per joint. None when all 0."""
    out = per_joint_values(name, values, n)
    return out if np.any(out != 0) else None


class PositionBounds(NamedTuple):
    """Plausible positions: controlled joints within [lower, upper] (URDF limits widened by
    position_margin; +-continuous_position_bound without limits), locked joints within +-locked."""
    lower: np.ndarray
    upper: np.ndarray
    locked: float


def position_bounds(model, s):
    """PositionBounds of settings s for `model`. NaN fails every comparison with them, so one
    range check also catches non-finite positions."""
    bound, margin = s.continuous_position_bound, s.position_margin
    lo = np.asarray(model.position_lower, dtype=float) - margin
    hi = np.asarray(model.position_upper, dtype=float) + margin
    return PositionBounds(np.where(np.isfinite(lo), lo, -bound), np.where(np.isfinite(hi), hi, bound), bound)


class Derived(NamedTuple):
    """What the laws and checks use for one (model, settings) pair."""
    limits: object                 # laws.EffortLimits
    friction: Optional[object]     # laws.Friction or None (off)
    kp: Optional[np.ndarray]       # per-joint gains or None (0)
    kd: Optional[np.ndarray]
    bounds: PositionBounds


def derive(model, s):
    """Derived of settings s for `model`. Raises ValueError."""
    n = model.n
    viscous = per_joint(s.friction.viscous, model.damping, n, 'friction.viscous')
    coulomb = per_joint(s.friction.coulomb, model.friction, n, 'friction.coulomb')
    friction = make_friction(viscous, coulomb, s.friction.coulomb_velocity_epsilon)
    return Derived(effort_limits(model.effort_limits, s.effort_limit_scale), friction,
                   gains(s.kp, n, 'kp'), gains(s.kd, n, 'kd'), position_bounds(model, s))


def check_payload_pair(s):
    if s.payload.mass > 0 and not s.payload.link:
        raise ValueError('payload.mass > 0 needs payload.link')


def payload_link(s):
    """The link that carries the payload of settings s ('' for none)."""
    return s.payload.link if s.payload.mass > 0 else ''


def place_payload(model, s, prev_link):
    """Payload and gravity of settings s on `model` (whose payload, if any, is on prev_link).
    Raises ValueError, leaving the model's payload and gravity unchanged."""
    link, mass = s.payload.link, s.payload.mass
    if link and mass > 0:
        # the one payload rule (Model.check_payload), checked before anything changes
        model.set_payload(link, mass, s.payload.com, s.payload.inertia or None)
        if prev_link and prev_link != link:
            model.clear_payload(prev_link)
    elif prev_link:
        model.clear_payload(prev_link)
    model.gravity_vector = np.asarray(s.gravity, dtype=float) * s.gravity_scale


class Plan(NamedTuple):
    """A validated change (Compensator.plan), made current by Compensator.apply."""
    settings: 'Settings'       # all settings after the change
    changes: dict              # the requested changes (to check again if the state moved meanwhile)
    model: Optional[object]    # a new model, already configured with `settings`; None: keep the current one
    info: str                  # where the new model comes from
    derived: Optional[Derived]  # for the model after the change
    base: tuple                # (model, settings) the plan was made against
    # for a new model: (what changed against the running one, its inertia report), computed
    # with the plan (off the control path) for the log lines of the swap
    report: Optional[tuple] = None
    # when calibration_file is involved (Configuration._calibrate): (the model without calibration
    # or payload, its CalibrationResult or None, the description model the plan was given or None)
    calibration: Optional[tuple] = None
