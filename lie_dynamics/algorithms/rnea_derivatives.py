"""Analytic derivatives of inverse dynamics, dtau/dq and dtau/dqd, in O(n^2).

The recursion of rnea.py (paper eqs 16-21) written in the root frame is

    V_i = sum_{j <= i} A_j xd_j,             a_i = a_0 + sum_{j <= i} (A_j xdd_j + [V_j, A_j xd_j]),
    F_i = Js_i a_i - ad_{V_i}^T Js_i V_i,     tau_k = A_k^T sum_{k <= i} F_i,

with A_j = Ad_{T_j} S_j, Js_i = Ad_{T_i}^-T J_i Ad_{T_i}^-1 and a_0 = (0, -g). It is
differentiated with Proposition 1 (eq 41): for m <= i, d/dx_m moves everything beyond
joint m by the screw A_m, so dA_i = ad_{A_m} A_i and dJs_i = -(ad_{A_m}^T Js_i +
Js_i ad_{A_m}), while the motion of the parent of m is unchanged. The Jacobi identity
[A, [V, W]] = [[A, V], W] + [V, [A, W]] collapses the sums over the path, and with
the subtree sums (composite quantities)

    Jc_k = sum Js_i,   Bc_k = sum (Js_i ad_{V_i} + ad_{V_i}^T Js_i) = -d/dt Jc_k,
    Hc_k = sum Js_i V_i (momentum),   Fc_k = sum F_i        (sums over i with k <= i)

and per-joint twists Z_m = [A_m, V_m], Y_m = [A_m, a_m] + [V_m, Z_m]:

    dtau_k/dx_m  = A_k^T (-Jc_m Y_m + Bc_m Z_m + ad_{Z_m}^T Hc_m - ad_{A_m}^T Fc_m)     k <= m
                 = -Y_m^T Jc_k A_k + Z_m^T (Bc_k^T A_k - ad_{A_k}^T Hc_k)               m < k
    dtau_k/dxd_m = -A_k^T (Bc_m A_m + 2 Jc_m Z_m + ad_{A_m}^T Hc_m)                      k <= m
                 = A_m^T (ad_{A_k}^T Hc_k - Bc_k^T A_k) - 2 Z_m^T Jc_k A_k               m < k

and 0 between bodies on different branches. External wrenches are fixed in their
link frames, so they move with the body and only enter through Fc. A consequence used
in the tests: dtau/dqd = 2 C(q, qd) with C the Christoffel Coriolis matrix (eq 40).
Joint coordinates: dtau_q/dq = E^T (dtau/dx) E (the mimic map x = E q + e0 is affine).

Two evaluations of the same formulas: vectorised numpy over bodies and states, and generated
straight-line code (codegen/traced/derivatives.py), used where codegen.runtime.route says it
is faster (one state, small batches state by state, large batches on numpy rows).
"""
import numpy as np

from ..codegen import runtime
from ..codegen.traced import derivatives as traced
from ..spatial import ad, transpose
from .common import body_constants, chunks, kinematic_state, subtree_sum, to_joints_mat, world_inertias
from .rnea import external_body_wrenches


def _mv(M, v):
    return (M @ v[..., None])[..., 0]


def _derivatives(model, x, xd, xdd, a0, fext):
    _, AdinvT, A = kinematic_state(model, x)
    anc = model.ancestors
    Js = world_inertias(model, AdinvT)
    Axd = A * xd[..., None]
    V = anc @ Axd
    adV = ad(V)
    a = anc @ (A * xdd[..., None] + _mv(adV, Axd)) + a0
    H = _mv(Js, V)
    F = _mv(Js, a) - _mv(transpose(adV), H)
    if fext is not None:
        F = F - _mv(AdinvT, fext)
    X = Js @ adV
    pack = subtree_sum(model, np.concatenate([Js, X + transpose(X), H[..., None], F[..., None]], axis=-1))
    Jc, Bc, Hc, Fc = pack[..., :6], pack[..., 6:12], pack[..., 12], pack[..., 13]
    adA = ad(A)
    Z = _mv(adA, V)
    Y = _mv(adA, a) + _mv(adV, Z)
    adAT = transpose(adA)
    JcAZY = Jc @ np.stack([A, Z, Y], axis=-1)              # Jc A, Jc Z, Jc Y
    JcA, JcZ, JcY = JcAZY[..., 0], JcAZY[..., 1], JcAZY[..., 2]
    BcAZ = Bc @ np.stack([A, Z], axis=-1)
    BcTA = _mv(transpose(Bc), A)
    adATH = _mv(adAT, Hc)
    le = anc.T
    lt = anc - np.eye(model.nb)
    # dtau/dx
    P = -JcY + BcAZ[..., 1] + _mv(transpose(ad(Z)), Hc) - _mv(adAT, Fc)
    R = np.concatenate([-JcA, BcTA - adATH], axis=-1)
    Q = np.concatenate([Y, Z], axis=-1)
    dq = (A @ transpose(P)) * le + (R @ transpose(Q)) * lt
    # dtau/dxd
    Pv = -(BcAZ[..., 0] + 2.0 * JcZ + adATH)
    Rv = np.concatenate([adATH - BcTA, -2.0 * JcA], axis=-1)
    Qv = np.concatenate([A, Z], axis=-1)
    dv = (A @ transpose(Pv)) * le + (Rv @ transpose(Qv)) * lt
    return dq, dv


def inverse_dynamics_derivatives(model, q, qd, qdd, wrenches=None):
    """(dtau/dq, dtau/dqd) of tau = inverse_dynamics(q, qd, qdd, wrenches), analytic.

    Single state (n,) -> two (n, n) arrays; batch (N, n) -> two (N, n, n) arrays.
    dtau[k, m] = d tau_k / d q_m (Pinocchio's computeRNEADerivatives layout).
    wrenches: {link: (m, f)} in the link frame, as for inverse_dynamics.
    """
    n = model.n
    if not wrenches:   # the common case first: the kernel takes it or declines (None)
        out = runtime.fast(model, traced.INVERSE_DYNAMICS_DERIVATIVES)(q, qd, qdd)
        if out is not None:
            out = out.reshape(out.shape[:-1] + (2, n, n))
            return out[..., 0, :, :], out[..., 1, :, :]
    (q, qd, qdd), single = model.validate(('q', 'qd', 'qdd'), (q, qd, qdd))
    fext = external_body_wrenches(model, wrenches, len(q))
    res = _kernel(model, q, qd, qdd, fext)
    if res is None:
        res = _vectorized(model, q, qd, qdd, fext)
    return (res[0][0], res[1][0]) if single else res


def inverse_dynamics_derivatives_kernel(model, q, qd, qdd, wrenches=None, mode=None):
    """inverse_dynamics_derivatives from the generated Python kernel: mode 'loop' (Python
    floats, state by state), 'rows' (numpy rows) or None (as route decides); None without a
    kernel."""
    (q, qd, qdd), single = model.validate(('q', 'qd', 'qdd'), (q, qd, qdd))
    res = _kernel(model, q, qd, qdd, external_body_wrenches(model, wrenches, len(q)), mode, native_first=False)
    return res if res is None or not single else (res[0][0], res[1][0])


def _kernel(model, q, qd, qdd, fext, mode=None, native_first=True):
    """On validated (N, n) arrays; fext: (N, nb, 6) body-frame wrenches or None."""
    N, n = q.shape
    if fext is None:
        vals = runtime.run(model, traced.INVERSE_DYNAMICS_DERIVATIVES, [q, qd, qdd], mode, native_first)
    else:
        fx = runtime.frames(model).wrench_params(fext).reshape(N, -1)
        vals = runtime.run(model, traced.INVERSE_DYNAMICS_DERIVATIVES_WRENCH, [q, qd, qdd, fx], mode, native_first)
    if vals is None:
        return None
    vals = vals.reshape(N, 2, n, n)
    return vals[:, 0], vals[:, 1]


def inverse_dynamics_derivatives_vectorized(model, q, qd, qdd, wrenches=None):
    """inverse_dynamics_derivatives by the vectorised form (numpy over bodies and states)."""
    (q, qd, qdd), single = model.validate(('q', 'qd', 'qdd'), (q, qd, qdd))
    dq, dv = _vectorized(model, q, qd, qdd, external_body_wrenches(model, wrenches, len(q)))
    return (dq[0], dv[0]) if single else (dq, dv)


def _vectorized(model, q, qd, qdd, fext):
    N = q.shape[0]
    c = body_constants(model)
    x = model.body_coordinates(q)
    E = model.E
    xd, xdd = qd @ E.T, qdd @ E.T
    nb = model.nb
    dq = np.empty((N, nb, nb))
    dv = np.empty((N, nb, nb))
    for sl in chunks(N, 400 * nb + 8 * nb * nb):
        dq[sl], dv[sl] = _derivatives(model, x[sl], xd[sl], xdd[sl], model.base_acceleration,
                                      None if fext is None else fext[sl])
    return to_joints_mat(model, c, dq), to_joints_mat(model, c, dv)


def coriolis_matrix(model, q, qd):
    """C(q, qd) = 1/2 dtau/dqd by the differentiated recursion (the dtau/dqd half of the
    derivative kernel). This is the Christoffel C of eqs 40-42: tau is quadratic in qd with
    symmetric Gamma_ijk = Gamma_jik, so d/dqd_j sum_i,l Gamma_ilk qd_i qd_l = 2 sum_i Gamma_ijk qd_i.
    q, qd: (n,) or (N, n) -> (n, n) or (N, n, n).
    """
    n = model.n
    C = runtime.fast(model, traced.CORIOLIS)(q, qd)
    if C is not None:
        return C
    (q, qd), single = model.validate(('q', 'qd'), (q, qd))
    C = runtime.run(model, traced.CORIOLIS, [q, qd])
    C = 0.5 * _vectorized(model, q, qd, np.zeros_like(qd), None)[1] if C is None else C.reshape(len(q), n, n)
    return C[0] if single else C


def coriolis_matrix_vectorized(model, q, qd):
    """coriolis_matrix by the vectorised form: 1/2 dtau/dqd of inverse_dynamics_derivatives_vectorized."""
    return 0.5 * inverse_dynamics_derivatives_vectorized(model, q, qd, np.zeros_like(np.asarray(qd, dtype=float)))[1]
