"""Payload identification: the inertial parameters of an unknown rigid load on one link.

A payload rigidly attached to link L adds its 10 inertial parameters pi_L (mass, first moments
m c and rotational inertia about the link frame, in regressor.py's order) to the body b that
carries L. Torques are linear in them (regressor.py): with Y_b the regressor's 10 columns of
body b and A the constant linear map from parameters about the link frame to parameters about
the body frame (the link sits at a fixed pose T_bL in b),

    Y_b(q, qd, qdd) A pi_L = tau_measured - tau_model(q, qd, qdd),

where tau_model is the model's inverse dynamics without any payload. `identify_payload` stacks
this over the samples and solves it with identification.least_squares. What the data determine
is reported, not invented: from static poses only the mass and the first moments (the CoM) act
(gravity alone), so the inertia stays unknown and the payload is returned as a point mass; a
moving trajectory determines the rest. The result is physically consistent or refused: a
non-positive identified mass raises ValueError (no payload, or data that do not show one); an
identified inertia that breaks the consistency rules (inertia.py) is replaced by the nearest
consistent one (inertia.repair) and says so.
"""
from dataclasses import dataclass, field

import numpy as np

from ..model.inertia import (PARAMETER_NAMES, RTOL, inertia_to_parameters, link_inertia, parameters_to_inertia,
                             repair, violations)
from ..spatial import Ad_inv
from .identification import least_squares
from .regressor import regressor_validated
from .rnea import inverse_dynamics_validated


@dataclass
class PayloadResult:
    """Outcome of `identify_payload`: mass (kg), com (3,) m and inertia (6,) about the CoM in
    link axes (ixx, ixy, ixz, iyy, iyz, izz; None when the data do not determine it: a point
    mass), determined {parameter name: bool}, residual_rms (n,) N m of the fit, rank of the
    payload regressor (of 10), repaired (the identified inertia was made consistent) and a
    one-line summary."""
    link: str
    mass: float
    com: np.ndarray
    inertia: object
    determined: dict = field(default_factory=dict)
    residual_rms: np.ndarray = None
    rank: int = 0
    repaired: bool = False
    summary: str = ''


def link_to_body_map(T):
    """A (10, 10): parameters about the body frame = A @ parameters about a link frame at pose T."""
    Ad = Ad_inv(T)  # a body-frame twist in the link frame: J_body = Ad^T J_link Ad
    J = parameters_to_inertia(np.eye(10))  # linear in the parameters: map each basis vector
    return inertia_to_parameters(Ad.T @ J @ Ad).T


def identify_payload(model, link, q, qd, qdd, tau_measured, rcond=1e-8):
    """Fit a payload on `link` to measured motor torques. q, qd, qdd, tau_measured: (N, n).
    Returns a PayloadResult; raises ValueError naming the problem (unknown link, a link that
    cannot move any controlled joint, data that excite nothing, a non-positive mass)."""
    if link not in model.link_frames:
        raise ValueError(f"unknown link '{link}' for the payload")
    b, T = model.link_frames[link]
    if b < 0:
        raise ValueError(f"link '{link}' does not move with any controlled joint: a payload there changes no torque")
    q, qd, qdd, tau = model.check_states(q=q, qd=qd, qdd=qdd, tau_measured=tau_measured)   # the one validation
    N, n = q.shape
    bare = model.with_body_inertias(model.J_links)  # the model without payloads
    Y = regressor_validated(model, [q, qd, qdd])[:, :, 10 * b:10 * b + 10] @ link_to_body_map(T)
    y = tau - inverse_dynamics_validated(bare, [q, qd, qdd])
    fit = least_squares(Y.reshape(N * n, 10), y.reshape(N * n), np.zeros(10), rcond)
    if fit['rank'] == 0 or not fit['determined'][0]:
        raise ValueError(f"the data do not determine a payload mass on '{link}' (no gravity or motion acts on it)")
    pi = fit['parameters']
    m = float(pi[0])
    if not m > 0:
        raise ValueError(f"identified payload mass {m:.4g} kg on '{link}' is not positive: no payload, or bad data")
    determined = dict(zip(PARAMETER_NAMES, fit['determined'].tolist()))
    com = pi[1:4] / m if all(fit['determined'][1:4]) else np.zeros(3)
    inertia, repaired = None, False
    if all(fit['determined'][4:]):
        # inertia about the link origin -> about the CoM (parallel axes)
        Ic = parameters_to_inertia(pi)[:3, :3] - link_inertia(np.eye(4), (m, com, np.zeros((3, 3))))[:3, :3]
        if violations(m, Ic, RTOL * model.inertia_scale):
            m, Ic = repair(m, Ic)
            repaired = True
        inertia = np.array([Ic[0, 0], Ic[0, 1], Ic[0, 2], Ic[1, 1], Ic[1, 2], Ic[2, 2]])
    rms = np.sqrt(np.mean(fit['residual'].reshape(N, n) ** 2, axis=0))
    unknown = [k for k, v in determined.items() if not v]
    summary = (f"payload on '{link}': mass {m:.4g} kg, CoM {np.round(com, 4).tolist()} m"
               + ('' if inertia is not None else ', inertia not determined (point mass)')
               + (', inertia repaired to be physically consistent' if repaired else '')
               + f'; residual rms {float(np.sqrt(np.mean(rms ** 2))):.3g} N m'
               + (f"; not determined by these data: {', '.join(unknown)}" if unknown else ''))
    return PayloadResult(link=link, mass=m, com=com, inertia=inertia, determined=determined, residual_rms=rms,
                         rank=fit['rank'], repaired=repaired, summary=summary)
