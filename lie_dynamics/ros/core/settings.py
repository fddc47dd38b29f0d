"""The node's settings turned into what the torque laws use, in plain Python (no rclpy import):
per-joint friction and gains, effort limits, the plausible position ranges, the payload, and
`Plan`, a validated change that Compensator.apply makes current.
"""
from typing import NamedTuple, Optional

import numpy as np

from ...laws import effort_limits, make_friction
from .params import PAYLOAD_KEYS, per_joint_values

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
    bound, margin = s['continuous_position_bound'], s['position_margin']
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
    viscous = per_joint(s['friction.viscous'], model.damping, n, 'friction.viscous')
    coulomb = per_joint(s['friction.coulomb'], model.friction, n, 'friction.coulomb')
    friction = make_friction(viscous, coulomb, s['friction.coulomb_velocity_epsilon'])
    return Derived(effort_limits(model.effort_limits, s['effort_limit_scale']), friction,
                   gains(s['kp'], n, 'kp'), gains(s['kd'], n, 'kd'), position_bounds(model, s))


def check_payload_pair(s):
    if s['payload.mass'] > 0 and not s['payload.link']:
        raise ValueError('payload.mass > 0 needs payload.link')


def payload_link(s):
    """The link that carries the payload of settings s ('' for none)."""
    return s['payload.link'] if s['payload.mass'] > 0 else ''


def place_payload(model, s, prev_link):
    """Payload and gravity of settings s on `model` (whose payload, if any, is on prev_link).
    Raises ValueError, leaving the model's payload and gravity unchanged."""
    link, mass = s['payload.link'], s['payload.mass']
    if link and mass > 0:
        # the one payload rule (Model.check_payload), checked before anything changes
        model.set_payload(link, mass, s['payload.com'], s['payload.inertia'] or None)
        if prev_link and prev_link != link:
            model.clear_payload(prev_link)
    elif prev_link:
        model.clear_payload(prev_link)
    model.gravity_vector = np.asarray(s['gravity'], dtype=float) * s['gravity_scale']


class Plan(NamedTuple):
    """A validated change (Compensator.plan), made current by Compensator.apply."""
    settings: dict             # all settings after the change
    changes: dict              # the requested changes (to check again if the state moved meanwhile)
    model: Optional[object]    # a new model, already configured with `settings`; None: keep the current one
    info: str                  # where the new model comes from
    derived: Optional[Derived]  # for the model after the change
    base: tuple                # (model, settings) the plan was made against
    # for a new model: (what changed against the running one, its inertia report), computed
    # with the plan (off the control path) for the log lines of the swap
    report: Optional[tuple] = None
