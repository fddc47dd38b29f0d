"""Physical consistency of rigid-body inertias: the one check and the one repair rule.

A rigid body of mass m with rotational inertia I_c about its centre of mass is physically
realisable when m >= 0 and the principal moments l1 <= l2 <= l3 of I_c satisfy

    l1 >= 0                  (no negative principal moment)
    l1 + l2 >= l3            (triangle inequality: every moment is a sum of two m r^2 terms)

and a massless body carries no inertia. Real URDFs break these (CAD exports, placeholder
tensors, round-off), so every check compares a violation with a tolerance `RTOL * scale`,
where `scale` is the inertia scale of the whole model (`inertia_scale`): round-off of 1e-20
on a zero tensor, or a 1e-6 placeholder on a 30 kg robot, is not a violation; a tensor that is
wrong by a part in 10^5 of the robot's own inertia is.

The same function (`violations`) serves URDF links (urdf.py), payloads (model.py) and
identified parameters (regressor.py); `repair` is the documented nearest-consistent rule.
"""
import numpy as np

from ..spatial import hat3, spatial_inertia

POLICIES = ('warn', 'strict', 'repair')
# A violation below this fraction of the model's inertia scale is round-off, not an error.
RTOL = 1e-5


class InertiaWarning(UserWarning):
    """A link's inertia is physically inconsistent (computed as written, or repaired)."""


def inertia_scale(J):
    """Inertia scale (kg m^2) of spatial inertias (..., 6, 6): the sum over bodies of half the
    trace of each rotational inertia about the frame it is expressed in (for a point mass
    m at distance r, m r^2). Never zero, so a tolerance relative to it is defined."""
    J = np.asarray(J, dtype=float)
    s = 0.5 * float(np.abs(np.trace(J[..., :3, :3], axis1=-2, axis2=-1)).sum()) if J.size else 0.0
    return s if s > 0 else 1.0


def link_inertia(T, mic):
    """Spatial inertia, about a body frame, of a link (mass, CoM, inertia about the CoM, in the
    link frame) whose frame is at pose T in the body frame."""
    m, com, Ic = mic
    R, p = T[:3, :3], T[:3, 3]
    return spatial_inertia(m, R @ com + p, R @ Ic @ R.T)


def principal_moments(I):
    """Ascending principal moments and axes (columns) of a symmetric 3x3 tensor."""
    I = np.asarray(I, dtype=float)
    return np.linalg.eigh(0.5 * (I + I.T))


def _fmt(x):
    return '[' + ', '.join(f'{v:.6g}' for v in np.ravel(x)) + ']'


def violations(mass, inertia_com, tol, first_moment=None):
    """Rules a body (mass, 3x3 inertia about its CoM) breaks beyond `tol` (kg m^2):
    a list of (rule, detail) pairs, empty when consistent. `first_moment` (m c) is only
    checked for massless bodies given as inertial parameters."""
    m = float(mass)
    I = np.asarray(inertia_com, dtype=float)
    if not (np.isfinite(m) and np.all(np.isfinite(I))):
        return [('non-finite', f'mass {m:.6g}, inertia {_fmt(I)}')]
    if m < 0:
        return [('negative mass', f'mass {m:.6g} kg')]
    ev = principal_moments(I)[0]
    if m == 0:
        h = 0.0 if first_moment is None else float(np.max(np.abs(first_moment)))
        if np.max(np.abs(ev)) > tol or h > 0:
            what = 'first moment or inertia' if first_moment is not None else 'inertia'
            return [('massless with inertia', f'mass 0 with non-zero {what} (principal moments {_fmt(ev)} kg m^2)')]
        return []
    out = []
    if ev[0] < -tol:
        out.append(('negative principal moment', f'principal moments {_fmt(ev)} kg m^2 '
                                                 f'(smallest < 0 beyond the tolerance {tol:.3g})'))
    if ev[0] + ev[1] < ev[2] - tol:
        out.append(('triangle inequality', f'principal moments {_fmt(ev)} kg m^2 '
                                           f'({ev[0]:.6g} + {ev[1]:.6g} < {ev[2]:.6g}, tolerance {tol:.3g})'))
    return out


def repair(mass, inertia_com):
    """Nearest physically consistent (mass, inertia about the CoM), keeping the principal axes:
    a negative mass becomes a massless, inertia-free body; negative principal moments are clipped
    to zero; then the smallest moment is raised until l1 + l2 = l3 holds (a flat body).
    A massless body's inertia is dropped."""
    m = float(mass)
    if m <= 0:
        return 0.0, np.zeros((3, 3))
    ev, R = principal_moments(inertia_com)
    ev = np.maximum(ev, 0.0)
    ev[0] = max(ev[0], ev[2] - ev[1])
    return m, (R * ev) @ R.T


def parameter_consistency(pi, tol=None):
    """Per body (ok, reason) for inertial parameters (nb, 10) (m, m c, I about the body frame,
    regressor.py's order): `violations` of the inertia about the CoM. tol: absolute (kg m^2);
    default RTOL times the bodies' own inertia scale."""
    pi = np.atleast_2d(np.asarray(pi, dtype=float))
    J = parameters_to_inertia(pi)
    if tol is None:
        tol = RTOL * inertia_scale(np.where(np.isfinite(J), J, 0.0))
    out = []
    for i, (p, Ji) in enumerate(zip(pi, J)):
        m = p[0]
        if np.all(np.isfinite(p)) and m > 0:
            c = p[1:4] / m
            Ic = Ji[:3, :3] + m * hat3(c) @ hat3(c)
        else:
            Ic = Ji[:3, :3]
        bad = violations(m, Ic, tol, first_moment=p[1:4])
        out.append((not bad, '; '.join(f'body {i}: {rule}: {detail}' for rule, detail in bad)))
    return out


PARAMETER_NAMES = ('m', 'mcx', 'mcy', 'mcz', 'Ixx', 'Ixy', 'Iyy', 'Ixz', 'Iyz', 'Izz')


def inertia_to_parameters(J):
    """Spatial inertias (..., 6, 6) about the body frames -> parameters (..., 10)
    (m, m c, I_xx, I_xy, I_yy, I_xz, I_yz, I_zz about the frame: Pinocchio's order)."""
    J = np.asarray(J, dtype=float)
    I = J[..., :3, :3]
    return np.stack([J[..., 3, 3], J[..., 2, 4], J[..., 0, 5], J[..., 1, 3],
                     I[..., 0, 0], I[..., 0, 1], I[..., 1, 1], I[..., 0, 2], I[..., 1, 2], I[..., 2, 2]],
                    axis=-1)


def parameters_to_inertia(pi):
    """Parameters (..., 10) -> spatial inertias (..., 6, 6) = [[I, [h]], [-[h], m 1]], h = m c."""
    pi = np.asarray(pi, dtype=float)
    m, hx, hy, hz, xx, xy, yy, xz, yz, zz = np.moveaxis(pi, -1, 0)
    J = np.zeros(pi.shape[:-1] + (6, 6))
    J[..., :3, :3] = np.stack([np.stack([xx, xy, xz], -1), np.stack([xy, yy, yz], -1),
                               np.stack([xz, yz, zz], -1)], -2)
    H = hat3(np.stack([hx, hy, hz], -1))
    J[..., :3, 3:] = H
    J[..., 3:, :3] = -H
    J[..., 3, 3] = J[..., 4, 4] = J[..., 5, 5] = m
    return J


def check_policy(policy):
    if policy not in POLICIES:
        raise ValueError(f"inertia policy must be one of {', '.join(POLICIES)}, got {policy!r}")
    return policy
