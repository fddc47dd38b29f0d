"""Inertial-parameter regressor: tau = Y(q, qd, qdd) pi, linear in the inertial parameters.

The paper notes (after eq 32) that each link's inertia has exactly 10 independent
parameters. Per body, about its own frame and in Pinocchio's order (CONVENTIONS.md),

    pi_i = (m, m c_x, m c_y, m c_z, I_xx, I_xy, I_yy, I_xz, I_yz, I_zz),
    J_i  = [[I, [h]], [-[h], m 1]],  h = m c,  I = I_c - m [c]^2 (inertia about the frame origin).

The body-frame Newton-Euler wrench of eq 20, F = J Vdot - ad_V^T J V, is linear in pi_i:
with V = (w, v) and Vdot = (alpha, a) in body frame (gravity included as Vdot_0 = (0, -g)),

    F = K(V, Vdot) pi_i,   K = [[0,         -[a + w x v],    L(alpha) + [w] L(w)],
                                [a + w x v,  [alpha] + [w]^2, 0                 ]],

where L(u) is the 3x6 matrix with I u = L(u) (I_xx, I_xy, I_yy, I_xz, I_yz, I_zz). The
joint torques are tau_k = sum_{k <= i} (Ad_{T_i^-1} A_k)^T F_i, and Ad_{T_i^-1} A_k is
block (i, k) of G S in the factorisation M = S^T G^T J G S (eq 39): the regressor is

    Y[k, block i] = (G S)_{ik}^T K_i          (k <= i; zero otherwise),

so tau = Y pi with the body-coordinate torques projected by E^T as everywhere else.
"""
import copy

import numpy as np

from .kinematics import ad_matrices
from .se3 import hat3
from .lagrangian import _chunks, _constants, _cross, _swap, kinematic_state

PARAMETER_NAMES = ('m', 'mcx', 'mcy', 'mcz', 'Ixx', 'Ixy', 'Iyy', 'Ixz', 'Iyz', 'Izz')

# L(u): I u = L(u) iota, iota = (xx, xy, yy, xz, yz, zz); entry (row, col) <- u[idx]
_L_ROW = np.array([0, 0, 0, 1, 1, 1, 2, 2, 2])
_L_COL = np.array([0, 1, 3, 1, 2, 4, 3, 4, 5])
_L_IDX = np.array([0, 1, 2, 0, 1, 2, 0, 1, 2])


def inertia_to_parameters(J):
    """Spatial inertias (..., 6, 6) about the body frames -> parameters (..., 10)."""
    J = np.asarray(J, dtype=float)
    I = J[..., :3, :3]
    return np.stack([J[..., 3, 3], J[..., 2, 4], J[..., 0, 5], J[..., 1, 3],
                     I[..., 0, 0], I[..., 0, 1], I[..., 1, 1], I[..., 0, 2], I[..., 1, 2], I[..., 2, 2]],
                    axis=-1)


def parameters_to_inertia(pi):
    """Parameters (..., 10) -> spatial inertias (..., 6, 6) = [[I, [h]], [-[h], m 1]]."""
    pi = np.asarray(pi, dtype=float)
    m, hx, hy, hz, xx, xy, yy, xz, yz, zz = np.moveaxis(pi, -1, 0)
    J = np.zeros(pi.shape[:-1] + (6, 6))
    J[..., 0, 0], J[..., 0, 1], J[..., 0, 2] = xx, xy, xz
    J[..., 1, 0], J[..., 1, 1], J[..., 1, 2] = xy, yy, yz
    J[..., 2, 0], J[..., 2, 1], J[..., 2, 2] = xz, yz, zz
    H = np.zeros(pi.shape[:-1] + (3, 3))
    H[..., 0, 1], H[..., 0, 2], H[..., 1, 2] = -hz, hy, -hx
    H = H - _swap(H)
    J[..., :3, 3:] = H
    J[..., 3:, :3] = -H
    J[..., 3, 3] = J[..., 4, 4] = J[..., 5, 5] = m
    return J


def physical_consistency(pi):
    """Per body: (ok, reason) for parameters (nb, 10): m >= 0 and, for m > 0, an inertia about
    the CoM that is positive semidefinite and obeys the triangle inequality."""
    pi = np.atleast_2d(np.asarray(pi, dtype=float))
    out = []
    for i, p in enumerate(pi):
        m = p[0]
        if not np.isfinite(p).all():
            out.append((False, f'body {i}: non-finite parameters'))
            continue
        if m < 0:
            out.append((False, f'body {i}: negative mass {m:g}'))
            continue
        J = parameters_to_inertia(p)
        if m == 0:
            ok = np.allclose(J, 0.0)
            out.append((ok, '' if ok else f'body {i}: zero mass with non-zero first moment or inertia'))
            continue
        c = p[1:4] / m
        C = np.array([[0, -c[2], c[1]], [c[2], 0, -c[0]], [-c[1], c[0], 0]])
        Ic = J[:3, :3] + m * C @ C
        ev = np.linalg.eigvalsh(0.5 * (Ic + Ic.T))
        tol = 1e-9 * max(1.0, abs(ev[-1]))
        if ev[0] < -tol:
            out.append((False, f'body {i}: inertia about the CoM is not positive semidefinite '
                               f'(principal moments {ev.tolist()})'))
        elif ev[0] + ev[1] < ev[2] - tol:
            out.append((False, f'body {i}: principal moments {ev.tolist()} violate the triangle inequality'))
        else:
            out.append((True, ''))
    return out


def inertial_parameters(model):
    """Current parameters (nb * 10,) of the model (payloads included), body order of model.body_joint_names."""
    return inertia_to_parameters(model.J).reshape(-1)


def with_inertial_parameters(model, pi, check=True):
    """A copy of `model` whose bodies have the inertial parameters `pi` ((nb*10,) or (nb, 10)).

    `pi` is the total per body (payloads included): the copy carries it as its link
    inertias and has no separate payloads. check: raise ValueError for physically
    inconsistent parameters (negative mass, invalid inertia about the CoM); identified
    parameters often are, and check=False accepts them (the dynamics stay defined,
    though the mass matrix may then not be positive definite).
    """
    p = np.asarray(pi, dtype=float)
    if p.size != 10 * model.nb or p.ndim not in (1, 2):
        raise ValueError(f'inertial parameters must have shape ({10 * model.nb},) or ({model.nb}, 10) '
                         f'for the {model.nb} bodies, got {p.shape}')
    p = p.reshape(model.nb, 10)
    if not np.all(np.isfinite(p)):
        raise ValueError('inertial parameters contain non-finite values')
    if check:
        bad = [reason for ok, reason in physical_consistency(p) if not ok]
        if bad:
            raise ValueError('inertial parameters are not physically consistent: ' + '; '.join(bad)
                             + ' (pass check=False to accept them)')
    new = copy.deepcopy(model)
    new._payloads = {}
    new.J_links = parameters_to_inertia(p)
    new._update_inertia()
    return new


def _K(Vb, Ab):
    """Per-body 6x10 maps K(V, Vdot) with J Vdot - ad_V^T J V = K pi, for (N, nb, 6) inputs."""
    w, v = Vb[..., :3], Vb[..., 3:]
    al, a = Ab[..., :3], Ab[..., 3:]
    shape = Vb.shape[:-1]
    W = hat3(w)
    Alpha = hat3(al)
    acc = a + _cross(w, v)
    Acc = hat3(acc)
    Lw = np.zeros(shape + (3, 6))
    La = np.zeros(shape + (3, 6))
    Lw[..., _L_ROW, _L_COL] = w[..., _L_IDX]
    La[..., _L_ROW, _L_COL] = al[..., _L_IDX]
    K = np.zeros(shape + (6, 10))
    K[..., 3:, 0] = acc
    K[..., :3, 1:4] = -Acc
    K[..., 3:, 1:4] = Alpha + W @ W
    K[..., :3, 4:] = La + W @ Lw
    return K


def _regressor(model, x, xd, xdd, a0):
    Adinv, AdinvT, A = kinematic_state(model, x)
    anc = model.ancestors
    N, nb = x.shape
    Axd = A * xd[..., None]
    V = anc @ Axd
    acc = anc @ (A * xdd[..., None] + (ad_matrices(V) @ Axd[..., None])[..., 0]) + a0
    VV = Adinv @ np.stack([V, acc], axis=-1)                 # to body frames
    K = _K(VV[..., 0], VV[..., 1])                           # (N, nb, 6, 10)
    GS = (Adinv @ _swap(A)[:, None]) * anc[None, :, None, :]  # (N, i, 6, k)
    Y = _swap(GS) @ K                                        # (N, i, k, 10)
    return np.swapaxes(Y, 1, 2).reshape(N, nb, nb * 10)      # (N, k, 10 i)


def regressor(model, q, qd, qdd):
    """Y(q, qd, qdd) with inverse_dynamics(q, qd, qdd) = Y @ inertial_parameters().

    Shape (n, 10 nb) or (N, n, 10 nb); columns are 10 per body in model.body_joint_names
    order, parameters as PARAMETER_NAMES (Pinocchio's computeJointTorqueRegressor layout).
    Gravity (as set on the model) is included.
    """
    single = np.ndim(q) == 1
    q = model._batch('q', q)
    N = q.shape[0]
    qd = model._batch('qd', qd, N)
    qdd = model._batch('qdd', qdd, N)
    c = _constants(model)
    x = model.body_coordinates(q)
    E = model.E
    xd, xdd = qd @ E.T, qdd @ E.T
    nb = model.nb
    out = np.empty((N, nb, 10 * nb))
    for sl in _chunks(N, 100 * nb + 30 * nb * nb):
        out[sl] = _regressor(model, x[sl], xd[sl], xdd[sl], model._a0)
    if not c['identity']:
        out = np.einsum('ka,nkp->nap', E, out)
    return out[0] if single else out
