"""Closed-form Lagrangian dynamics (Park, Bobrow & Ploen 1995, section 3.3).

    tau_k = sum_j m_kj(x) xdd_j + sum_ij Gamma_ijk xd_i xd_j + phi_k(x)           (eq 22)

Notation. Bodies are numbered parents first; j <= i means "body j is body i or one of
its ancestors" (for a serial chain: j <= i as integers). T_i is the pose of body i in
the root frame, f_{j,i} = T_j^-1 T_i, and

    A_i = Ad_{T_i} S_i                                                     (eqs 8, 27)

is joint i's screw in the root frame at the current configuration (the paper's
Ad^1_{i-1}(A_i) in the notation of eq 26). The quantities below depend on x only
through these screws, because of the one identity the whole section rests on
(Proposition 1, eq 41): moving joint k turns every body beyond it about A_k, so

    dT_i/dx_k = [A_k] T_i,   dA_i/dx_k = [A_k, A_i] = ad_{A_k} A_i     for k <= i,

and both are 0 otherwise. Proposition 2 (eq 42) is this rule applied twice.

Inertia matrix (eqs 34-39). With the block matrices of eqs 35-37 (written here for
trees: block (i, j) of G is Ad_{f_{j,i}^-1} when j <= i, else 0)

    S = diag(S_1 .. S_n),  J = diag(J_1 .. J_n),  G_ij = Ad_{f_{j,i}^-1},
    M = S^T G^T J G S                                                           (eq 39)

where J_i = [[I_c - m[r]^2, m[r]], [-m[r], m 1]] is the spatial inertia of body i about
its own frame (the notes garble this block; docs/architecture.md has the right one). Column
j of the i-th block row of G S is the body Jacobian of body i, Ad_{T_i^-1} A_j, so
M = sum_i (G S)_i^T J_i (G S)_i. Equation 34, M = A^T L^T D L A, is the same product
written with the home-pose adjoints Q of eq 38 (A = Q S, L = Q G Q^-1, D = Q^-T J Q^-1).
It costs O(n^3); crba.py has the O(n^2) composite-rigid-body evaluation.

Christoffel symbols of the first kind (eq 40)

    Gamma_ijk = 1/2 (dm_kj/dx_i + dm_ki/dx_j - dm_ij/dx_k),   Gamma_ijk = Gamma_jik,

with dM/dx_i from eq 39 and Proposition 1. Write Js_l = Ad_{T_l}^-T J_l Ad_{T_l}^-1 for
the inertia of body l in the root frame and Jc_l = sum_{l <= p} Js_p for its subtree
(composite) inertia; dJs_l/dx_i = -(ad_{A_i}^T Js_l + Js_l ad_{A_i}) for i <= l. For
k <= j the derivative is (zero unless i, j, k lie on one path from the root)

    dm_kj/dx_i = -[A_i, A_k]^T Jc_j A_j                           k < i <= j
               = -[A_i, A_k]^T Jc_i A_j - A_k^T Jc_i [A_i, A_j]    j < i
               = 0                                               i <= k.

The Coriolis matrix C_kj = sum_i Gamma_ijk xd_i satisfies C xd = RNEA(x, xd, 0) - g(x)
and Mdot - 2C skew-symmetric; it is unique with those properties and Gamma_ijk =
Gamma_jik. Contracting eq 40 with xd first gives C without forming Gamma:

    C = 1/2 (Mdot + W^T - W),   Mdot = sum_i xd_i dM/dx_i,   W_jk = sum_i (dM/dx_j)_ki xd_i.

Potential term (eqs 43-45). With the gravity vector g (pointing down) and the CoM c_i of
body i in the root frame, U = -sum_i m_i g^T c_i (eq 43: the notes' sign convention
takes g pointing up). Since dc_i/dx_k = [A_k] c_i = w_k x c_i + v_k for k <= i (the
homogeneous point f_i r of eq 45, differentiated with Proposition 1),

    phi_k = dU/dx_k = -(w_k . (H_k x g) + m_k^sub v_k . g),   A_k = (w_k, v_k),   (eqs 44-45)

with H_k = sum_{k <= i} m_i c_i and m_k^sub = sum_{k <= i} m_i (subtree first moment and
mass). The notes' eq 45 mixes Ad_i^{k+1}(A_k) and M_i: in root-frame terms the
derivative of f_i r is simply [A_k] f_i r with A_k the current screw.

Joint coordinates. Bodies carry coordinates x = E q + e0 (mimic and locked joints, see
model.py). The map is affine, so M_q = E^T M E, C_q = E^T C(E qd) E, g_q = E^T g and
Gamma_q = Gamma contracted with E on each index.

Every function takes a single state (n,) or a batch (N, n) and returns matching shapes.
"""
import numpy as np

from ..codegen.runtime import structural
from ..spatial import ad, cross, transpose
from .common import (body_constants, body_matrices, chunks, kinematic_state, subtree_sum, to_joints_mat,
                     to_joints_vec, world_inertias)
from .kinematics import world_poses


# ---------------------------------------------------------------------------- eq 39
def _mass_closed_form(model, x):
    Adinv, _, A = kinematic_state(model, x)
    N, nb = x.shape
    # G S: block (i, j) = Ad_{f_{j,i}^-1} S_j = Ad_{T_i^-1} A_j for j <= i, else 0
    GS = (Adinv @ transpose(A)[:, None]) * model.ancestors[None, :, None, :]   # (N, nb, 6, nb)
    JGS = model.J @ GS                                                      # J G S
    return transpose(GS.reshape(N, nb * 6, nb)) @ JGS.reshape(N, nb * 6, nb)   # S^T G^T J G S


def mass_matrix(model, q):
    """M(q) = S^T G^T J G S (paper eq 39, equivalently A^T L^T D L A, eq 34); O(n^3).

    q: (n,) or (N, n). Returns (n, n) or (N, n, n), symmetric positive (semi)definite.
    """
    nb = model.nb
    return body_matrices(model, q, _mass_closed_form, 12 * nb * nb + 72 * nb)


def block_factors(model, q):
    """The block matrices of eqs 35-37 for one state: (S, G, J), so that M = S^T G^T J G S.

    S (6nb, nb) stacks the body-frame screws (the paper's 6n x 6n Diag[S_i] acting on
    scalar joint rates), G (6nb, 6nb) is lower block-triangular with G_ij =
    Ad_{f_{j,i}^-1} for j <= i (zero blocks between branches of a tree), J (6nb, 6nb) is
    block diagonal. Body coordinates: project with model.E for the joint-space M.
    Meant for inspection and teaching; mass_matrix() never forms these dense matrices.
    """
    q = model.check_batch('q', q)
    if q.shape[0] != 1:
        raise ValueError('block_factors takes a single state q of shape (n,)')
    x = model.body_coordinates(q)
    Adinv, _, A = kinematic_state(model, x)
    Ad = np.linalg.inv(Adinv[0])  # small, for exposition only
    nb = model.nb
    G = np.zeros((nb, 6, nb, 6))
    for i in range(nb):
        for j in range(nb):
            if model.ancestors[i, j]:
                G[i, :, j, :] = Adinv[0, i] @ Ad[j]   # Ad_{T_i^-1 T_j} = Ad_{f_{j,i}^-1}
    S = np.zeros((nb, 6, nb))
    S[np.arange(nb), :, np.arange(nb)] = model.S
    Jb = np.zeros((nb, 6, nb, 6))
    Jb[np.arange(nb), :, np.arange(nb), :] = model.J
    return S.reshape(6 * nb, nb), G.reshape(6 * nb, 6 * nb), Jb.reshape(6 * nb, 6 * nb)


# ---------------------------------------------------------------------------- eqs 40-42
def _christoffel_masks(anc):
    """Masks for dm_kj/dx_i (module docstring): mb[i,k,j] = [k<=j][k<i<=j], mc[i,k,j] = [k~j][max(k,j)<i]."""
    nb = anc.shape[0]
    le = anc.T                  # le[a, b] = [a <= b]
    lt = (anc - np.eye(nb)).T   # lt[a, b] = [a < b]
    # [k<=j] [k<i] [i<=j]  -> indices (i, k, j)
    mb = le[None, :, :] * lt.T[:, :, None] * le[:, None, :]
    # deeper of (k, j) is a proper ancestor of i, and k, j comparable
    # for k<=j that is [j<i]; for j<=k it is [k<i]
    kj_le = le[None, :, :]  # [k<=j]
    mc = kj_le * lt.T[:, None, :] + kj_le.transpose(0, 2, 1) * lt.T[:, :, None]
    mc = np.where(np.eye(nb, dtype=bool)[None], mc * 0.5, mc)  # k = j counted twice above
    return mb, mc


def _dM_body(model, c, x):
    """dM/dx_i for body coordinates: (N, nb_i, nb_k, nb_j), from Proposition 1."""
    _, AdinvT, A = kinematic_state(model, x)
    Js = world_inertias(model, AdinvT)
    Jc = subtree_sum(model, Js)
    At = transpose(A)[:, None]                           # (N, 1, 6, nb)
    Br = ad(A) @ At                         # Br[n, i, :, k] = [A_i, A_k]
    F = Jc @ At                                      # F[n, c, :, j] = Jc_c A_j
    Fd = np.einsum('njaj->nja', F)                   # Jc_j A_j, (N, nb, 6)
    BrT = transpose(Br)                                  # (N, i, k, 6)
    X1 = BrT @ transpose(Fd)[:, None]                    # [i,k,j] = [A_i,A_k] . Jc_j A_j
    X2 = BrT @ F                                     # [i,k,j] = [A_i,A_k] . Jc_i A_j
    mb, mc = structural(model, 'christoffel_masks', lambda: _christoffel_masks(model.ancestors))
    Y = mb * X1 + mc * X2
    return -(Y + transpose(Y))


def _project3(model, c, D):
    if c['identity']:
        return D
    return np.einsum('ia,jb,kc,nijk->nabc', model.E, model.E, model.E, D, optimize=True)


def mass_matrix_derivatives(model, q):
    """dM/dq: array D with D[..., a, :, :] = dM/dq_a, shape (n, n, n) or (N, n, n, n).

    Closed form from eq 39 and Proposition 1 (eq 41); see the module docstring.
    """
    single = np.ndim(q) == 1
    q = model.check_batch('q', q)
    c = body_constants(model)
    x = model.body_coordinates(q)
    N, nb = x.shape
    out = np.empty((N, nb, nb, nb))
    for sl in chunks(N, 6 * nb ** 3 + 40 * nb * nb):
        out[sl] = _dM_body(model, c, x[sl])
    out = _project3(model, c, out)
    return out[0] if single else out


def christoffel(model, q):
    """Christoffel symbols of the first kind Gamma[i, j, k] (paper eq 40), joint coordinates.

    tau_k = sum_j m_kj qdd_j + sum_ij Gamma_ijk qd_i qd_j + g_k (eq 22); Gamma_ijk = Gamma_jik.
    Shape (n, n, n) or (N, n, n, n). O(n^3) memory per state.
    """
    single = np.ndim(q) == 1
    D = mass_matrix_derivatives(model, q)
    D = D[None] if single else D
    G = 0.5 * (D + np.transpose(D, (0, 2, 1, 3)) - np.transpose(D, (0, 2, 3, 1)))
    return G[0] if single else G


def coriolis_matrix(model, q, qd):
    """C(q, qd) with C_kj = sum_i Gamma_ijk qd_i (eqs 40-42).

    C qd = inverse_dynamics(q, qd, 0) - g(q) and Mdot - 2C is skew-symmetric.
    Evaluated as C = 1/2 (Mdot + W^T - W) with W_jk = sum_i (dM/dq_j)_ki qd_i, which is
    eq 40 contracted with qd before Gamma is formed. q, qd: (n,) or (N, n).
    """
    single = np.ndim(q) == 1
    q, qd = model.check_states(q=q, qd=qd)
    c = body_constants(model)
    x = model.body_coordinates(q)
    u = qd @ model.E.T
    N, nb = x.shape
    out = np.empty((N, nb, nb))
    for sl in chunks(N, 6 * nb ** 3 + 40 * nb * nb):
        D = _dM_body(model, c, x[sl])
        us = u[sl]
        Mdot = np.einsum('niab,ni->nab', D, us)
        W = (D @ us[:, None, :, None])[..., 0]            # W[n, j, k] = sum_i D[j, k, i] u_i
        out[sl] = 0.5 * (Mdot + transpose(W) - W)
    out = to_joints_mat(model, c, out)
    return out[0] if single else out


# ---------------------------------------------------------------------------- eqs 43-45
def _com_moments(model, c, x):
    """Root-frame screws A and first moments m_i c_i (root frame), for x (N, nb)."""
    T = world_poses(model, x)
    R, p = T[..., :3, :3], T[..., :3, 3]
    h = (R @ c['first'][..., None])[..., 0] + c['mass'][:, None] * p   # m_i c_i, root frame
    return T, h


def potential_energy(model, q):
    """U(q) = -sum_i m_i g . c_i(q) (paper eq 43, gravity as set on the model). (N,) or scalar."""
    single = np.ndim(q) == 1
    q = model.check_batch('q', q)
    c = body_constants(model)
    _, h = _com_moments(model, c, model.body_coordinates(q))
    U = -np.sum(h, axis=1) @ model.gravity_vector
    return float(U[0]) if single else U


def gravity(model, q):
    """phi(q) = dU/dq from the potential energy (paper eqs 43-45); agrees with rnea.gravity."""
    single = np.ndim(q) == 1
    q = model.check_batch('q', q)
    c = body_constants(model)
    x = model.body_coordinates(q)
    T, h = _com_moments(model, c, x)
    R, p = T[..., :3, :3], T[..., :3, 3]
    w = R @ model.S[:, :3, None]
    w = w[..., 0]                                              # joint axis in the root frame
    v = cross(p, w) + (R @ model.S[:, 3:, None])[..., 0]      # linear part of A = Ad_T S
    H = model.ancestors.T @ h                                  # subtree first moments
    msub = model.ancestors.T @ c['mass']                       # subtree masses
    g = model.gravity_vector
    phi = -(np.einsum('nka,nka->nk', w, cross(H, g)) + msub * (v @ g))
    phi = to_joints_vec(model, c, phi)
    return phi[0] if single else phi


def kinetic_energy(model, q, qd):
    """T = 1/2 qd^T M(q) qd (eq 23 with the 1/2 the notes drop). (N,) or scalar."""
    single = np.ndim(q) == 1
    q, qd = model.check_states(q=q, qd=qd)
    M = mass_matrix(model, q)
    T = 0.5 * np.einsum('ni,nij,nj->n', qd, M, qd)
    return float(T[0]) if single else T
