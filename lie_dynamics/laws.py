"""Torque laws, friction compensation and the effort clamp, in plain numpy (no ROS).

One place for each formula: the dynamics node's decision logic (lie_dynamics.ros.core.compensator:
streaming commands, the stale action, trajectory efforts) and the trajectory fill
(lie_dynamics.trajectory) call these functions; nothing else computes a law, friction or a clamp.

Notation (controlled joints, model order): q, qd measured position and velocity; desired =
(q_d, qd_d, qdd_d); e = q_d - q, de = qd_d - qd; kp, kd per-joint gains (None = all 0);
ID(q, qd, qdd) = M(q) qdd + C(q, qd) qd + g(q), the model's inverse dynamics (one RNEA call,
gravity as the model's gravity_vector, payloads included); f(v) = b v + fc tanh(v / eps) the
friction compensation (None = off).

    gravity          tau = g(q) [+ C(q, qd) qd if velocity_terms] + f(qd)
    feedforward      tau = ID(q_d, qd_d, qdd_d) + f(qd_d) + Kp e + Kd de
    computed_torque  tau = ID(q, qd, qdd_d + Kp e + Kd de) + f(qd)
                         = M(q) (qdd_d + Kp e + Kd de) + C(q, qd) qd + g(q) + f(qd)
    pd               tau = Kp e + Kd de

Every law takes (model, q, qd, desired, kp, kd, friction, velocity_terms) and the keyword
gravity: False leaves every g term out (the law at zero gravity: a robot that adds g(q) itself,
the node's robot_compensates_gravity). A measured velocity of None (unavailable) counts as 0.
`uses_velocity` says whether a law reads qd at all, so a caller can skip reading it. `clamp`
limits a torque (or a batch of torques) to the effort limits and never lets a non-finite value
through.

Any finite gains, coefficients and states are accepted: a product that overflows (kp = 1e308)
is +-inf, inf - inf is NaN, silently (no numpy warning on stderr for every state), and `clamp`
limits or refuses the result. The public functions compute under one np.errstate each.
"""
import functools
from typing import NamedTuple, Optional

import numpy as np

# Velocity scale of the smooth Coulomb term tanh(v / eps), rad/s (m/s): the default of the
# node's friction.coulomb_velocity_epsilon and of fill_trajectory_efforts(eps=...).
COULOMB_VELOCITY_EPSILON = 0.05

MODES = ('gravity', 'feedforward', 'computed_torque', 'pd')



def _quiet(fn):
    """fn with numpy's overflow and invalid-value warnings off (see the module docstring)."""
    @functools.wraps(fn)
    def quiet(*args, **kwargs):
        with np.errstate(over='ignore', invalid='ignore'):
            return fn(*args, **kwargs)
    return quiet


# ---------------------------------------------------------------------------------------------- friction

class Friction(NamedTuple):
    """Friction compensation coefficients per joint (None = that term off) and the Coulomb eps."""
    viscous: Optional[np.ndarray] = None
    coulomb: Optional[np.ndarray] = None
    eps: float = COULOMB_VELOCITY_EPSILON


def _friction_torque(v, viscous=None, coulomb=None, eps=COULOMB_VELOCITY_EPSILON):
    """Friction compensation b v + fc tanh(v / eps) at velocity v, (n,) or a batch (N, n).

    viscous (b) and coulomb (fc): per joint (or scalars), None = that term off. The Coulomb term
    is smooth: it passes through 0 at rest and reaches ~fc (0.96 fc) at |v| = 2 eps.
    """
    f = None
    if viscous is not None:
        f = viscous * v
    if coulomb is not None:
        c = coulomb * np.tanh(v / eps)
        f = c if f is None else f + c
    return np.zeros(np.shape(v)) if f is None else f


def _add_friction(tau, v, friction):
    """tau + friction_torque(v, *friction); tau itself when friction is None (off) or v is None
    (velocity unavailable, counts as 0: no friction torque)."""
    if friction is None or v is None:
        return tau
    return tau + _friction_torque(v, *friction)


friction_torque = _quiet(_friction_torque)
add_friction = _quiet(_add_friction)


def make_friction(viscous=None, coulomb=None, eps=COULOMB_VELOCITY_EPSILON):
    """Friction(...) from per-joint coefficients, or None when every coefficient is 0 / absent."""
    parts = []
    for c in (viscous, coulomb):
        c = None if c is None else np.asarray(c, dtype=float)
        parts.append(c if c is not None and np.any(c != 0) else None)
    if parts[0] is None and parts[1] is None:
        return None
    return Friction(parts[0], parts[1], float(eps))


# ---------------------------------------------------------------------------------------------- torque laws

def _feedback(q, qd, desired, kp=None, kd=None):
    """Kp (q_d - q) + Kd (qd_d - qd), or None when both gains are None (qd None counts as 0)."""
    fb = None
    if kp is not None:
        fb = kp * (desired[0] - q)
    if kd is not None:
        d = kd * (desired[1] if qd is None else desired[1] - qd)
        fb = d if fb is None else fb + d
    return fb


feedback = _quiet(_feedback)


@_quiet
def gravity_law(model, q, qd=None, desired=None, kp=None, kd=None, friction=None, velocity_terms=False,
                gravity=True):
    """g(q) [+ C(q, qd) qd if velocity_terms and qd is known] + f(qd). desired and gains unused."""
    if qd is not None and velocity_terms:
        tau = model.inverse_dynamics(q, qd, np.zeros(model.n), with_gravity=gravity)
    else:
        tau = model.gravity(q) if gravity else np.zeros(model.n)
    return _add_friction(tau, qd, friction)


@_quiet
def feedforward_law(model, q, qd=None, desired=None, kp=None, kd=None, friction=None, velocity_terms=False,
                    gravity=True):
    """ID(q_d, qd_d, qdd_d) + f(qd_d) + Kp e + Kd de: the model at the desired state, PD on the error."""
    q_d, qd_d, qdd_d = desired
    tau = _add_friction(model.inverse_dynamics(q_d, qd_d, qdd_d, with_gravity=gravity), qd_d, friction)
    fb = _feedback(q, qd, desired, kp, kd)
    return tau if fb is None else tau + fb


@_quiet
def computed_torque_law(model, q, qd=None, desired=None, kp=None, kd=None, friction=None, velocity_terms=False,
                        gravity=True):
    """ID(q, qd, qdd_d + Kp e + Kd de) + f(qd): always with C(q, qd) qd (velocity_terms unused)."""
    if qd is None:
        qd = np.zeros(model.n)
    fb = _feedback(q, qd, desired, kp, kd)
    qdd = desired[2] if fb is None else desired[2] + fb
    try:
        tau = model.inverse_dynamics(q, qd, qdd, with_gravity=gravity)
    except ValueError:
        if fb is None or np.isfinite(qdd).all():
            raise
        tau = np.full(np.shape(qdd), np.nan)   # an overflowing feedback: non-finite, refused by `clamp`
    return _add_friction(tau, qd, friction)


@_quiet
def pd_law(model, q, qd=None, desired=None, kp=None, kd=None, friction=None, velocity_terms=False, gravity=True):
    """Kp e + Kd de only: no model terms, no friction."""
    fb = _feedback(q, qd, desired, kp, kd)
    return np.zeros(model.n) if fb is None else fb


LAWS = {'gravity': gravity_law, 'feedforward': feedforward_law, 'computed_torque': computed_torque_law,
        'pd': pd_law}


def torque(mode, model, q, qd=None, desired=None, kp=None, kd=None, friction=None, velocity_terms=False,
           gravity=True):
    """The torque law `mode` (one of MODES); see the module docstring."""
    return LAWS[mode](model, q, qd, desired, kp, kd, friction, velocity_terms, gravity=gravity)


def uses_velocity(mode, kd=None, friction=None, velocity_terms=False):
    """Does law `mode` read the measured velocity qd with these gains and friction?"""
    if mode == 'gravity':
        return bool(velocity_terms) or friction is not None
    if mode == 'computed_torque':
        return True
    return kd is not None  # feedforward (friction at qd_d), pd


# ---------------------------------------------------------------------------------------------- clamp

class EffortLimits(NamedTuple):
    """Per-joint effort limits for `clamp`: `limit` >= 0 (inf = unlimited), and `bound`, the same
    with inf replaced by the largest float, so that `abs(tau) <= bound` fails for inf and NaN."""
    limit: np.ndarray
    bound: np.ndarray


def effort_limits(limits, scale=1.0):
    """EffortLimits of +-limits * scale (a missing limit, inf, stays unlimited also for scale 0)."""
    limits = np.asarray(limits, dtype=float)
    lim = np.full(limits.shape, np.inf)   # inf (or NaN): unlimited, also for scale 0 (no inf * 0)
    np.multiply(limits, scale, out=lim, where=np.isfinite(limits))
    return EffortLimits(lim, np.minimum(lim, np.finfo(float).max))


def clamp(tau, limits):
    """tau (n,) or a batch (N, n) clipped to +-limits -> (clamped, over).

    limits: EffortLimits (see effort_limits) or per-joint limits. clamped is None when a value is
    non-finite after clipping (NaN, or inf without a finite limit: never publish it); +-inf with a
    finite limit is clipped to it. over: boolean mask shaped like tau of the values that exceeded
    their limit (callers count and name the joints), None when none did.
    """
    if not isinstance(limits, EffortLimits):
        limits = effort_limits(limits)
    # fast path: every value finite and within its limit (count_nonzero: half the cost of .all())
    if np.count_nonzero(np.abs(tau) <= limits.bound) == np.size(tau):
        return tau, None
    lim = limits.limit
    over = np.abs(tau) > lim
    if over.any():
        tau = np.clip(tau, -lim, lim)
    else:
        over = None
    if not np.isfinite(tau).all():
        return None, over
    return tau, over
