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
straight-line code (codegen.py) for models of up to KERNEL_MAX_BODIES bodies, used for one
state, small batches (state by state) and large batches (numpy rows) where it is faster.
"""
import math

import numpy as np

from ..codegen import algebra as la
from ..codegen import runtime
from ..codegen.render import kernel
from ..codegen.tracer import Graph
from .kinematics import ad_matrices
from ..spatial import transpose
from .rnea import external_body_wrenches
from .lagrangian import body_constants, chunks, kinematic_state, subtree_sum, to_joints_mat, world_inertias


def _mv(M, v):
    return (M @ v[..., None])[..., 0]


def _derivatives(model, x, xd, xdd, a0, fext):
    _, AdinvT, A = kinematic_state(model, x)
    anc = model.ancestors
    Js = world_inertias(model, AdinvT)
    Axd = A * xd[..., None]
    V = anc @ Axd
    adV = ad_matrices(V)
    a = anc @ (A * xdd[..., None] + _mv(adV, Axd)) + a0
    H = _mv(Js, V)
    F = _mv(Js, a) - _mv(transpose(adV), H)
    if fext is not None:
        F = F - _mv(AdinvT, fext)
    X = Js @ adV
    pack = subtree_sum(model, np.concatenate([Js, X + transpose(X), H[..., None], F[..., None]], axis=-1))
    Jc, Bc, Hc, Fc = pack[..., :6], pack[..., 6:12], pack[..., 12], pack[..., 13]
    adA = ad_matrices(A)
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
    P = -JcY + BcAZ[..., 1] + _mv(transpose(ad_matrices(Z)), Hc) - _mv(adAT, Fc)
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
    Runs the generated kernel (below) for models of up to KERNEL_MAX_BODIES bodies, else
    the vectorised form.
    """
    n = model.n
    if not wrenches:
        a, b, c = runtime.is_fast_single(q, n), runtime.is_fast_single(qd, n), runtime.is_fast_single(qdd, n)
        if a is not None and b is not None and c is not None:
            k = _kernel(model, False)
            if k:
                fr, fn, _ = k
                P, E0, A0 = runtime.model_params(model, fr, gravity=True)
                out = np.fromiter(fn(a, b, c, P, A0, E0, sin=math.sin, cos=math.cos), float,
                                  2 * n * n).reshape(2, n, n)
                return out[0], out[1]
    single = np.ndim(q) == 1
    q, qd, qdd = model.check_states(q=q, qd=qd, qdd=qdd)
    N = q.shape[0]
    fext = external_body_wrenches(model, wrenches, N)
    res = _kernel_derivatives(model, q, qd, qdd, fext)
    if res is None:
        return inverse_dynamics_derivatives_vectorized(model, q[0] if single else q, qd[0] if single else qd,
                                                       qdd[0] if single else qdd, wrenches)
    dq, dv = res
    return (dq[0], dv[0]) if single else (dq, dv)


def inverse_dynamics_derivatives_vectorized(model, q, qd, qdd, wrenches=None):
    """inverse_dynamics_derivatives by the vectorised form (numpy over bodies and states)."""
    single = np.ndim(q) == 1
    q, qd, qdd = model.check_states(q=q, qd=qd, qdd=qdd)
    N = q.shape[0]
    c = body_constants(model)
    fext = external_body_wrenches(model, wrenches, N)
    x = model.body_coordinates(q)
    E = model.E
    xd, xdd = qd @ E.T, qdd @ E.T
    nb = model.nb
    dq = np.empty((N, nb, nb))
    dv = np.empty((N, nb, nb))
    for sl in chunks(N, 400 * nb + 8 * nb * nb):
        dq[sl], dv[sl] = _derivatives(model, x[sl], xd[sl], xdd[sl], model.base_acceleration,
                                      None if fext is None else fext[sl])
    dq, dv = to_joints_mat(model, c, dq), to_joints_mat(model, c, dv)
    return (dq[0], dv[0]) if single else (dq, dv)


# ---------------------------------------------------------------------------- generated kernel
# Above this many bodies one state is faster through the vectorised form (measured).
KERNEL_MAX_BODIES = 16
# Batches: the float kernel state by state below _LOOP_BELOW states, the kernel on numpy rows
# from _ROWS_FROM states, the vectorised form in between (measured crossovers, 7-20 bodies).
_LOOP_BELOW = 4
_ROWS_FROM = 128


def trace_derivatives(fr, g, x, xd, xdd, params, a0, fext=None, center=0):
    """The O(n^2) derivative formulas of the module docstring, traced.

    "Root frame" here is any fixed frame: the formulas are covariant, and the outputs are
    scalars. The kernel uses the frame that coincides with body `center`'s primed frame at
    the current configuration, about its origin (on that joint's axis): that body's pose
    is the identity and its screw is e_z, so whole products fold away. Only gravity and the
    poses change. The first body gave the fewest operations on the arm and random chains.
    The 6x6 composite Bc_k = -d/dt Jc_k is carried as the rate of the 10 inertia
    parameters (codegen.inertia_rate), which is all Bc is applied through.

    x, xd, xdd: traced body coordinates and rates; params: per body (m, h, I) in the primed
    frames; a0: base linear acceleration -g (3 values); fext: optional per-body wrenches (n, f)
    in the primed frames. Returns (dtau/dq, dtau/dqd) as nested n x n lists, joint coordinates.
    """
    nb = fr.nb
    zero3 = (0.0, 0.0, 0.0)
    Rw, pw, Rb = _poses(fr, g, x, center)
    ga = la.mat_vec(Rb, a0)
    A, V, a, Z, Y = ([None] * nb for _ in range(5))
    for b in range(nb):   # forward: screws and twists
        p = fr.parent[b]
        if p >= 0:
            Vp, ap = V[p], a[p]
        else:
            Vp, ap = (zero3, zero3), (zero3, tuple(ga))
        axis = (Rw[b][0][2], Rw[b][1][2], Rw[b][2][2])
        A[b] = (axis, la.cross(pw[b], axis)) if fr.revolute[b] else (zero3, axis)
        V[b] = la.twist_add(Vp, la.twist_scale(xd[b], A[b]))
        Z[b] = la.bracket(A[b], Vp)                                      # [A_b, V_b] = [A_b, V_p]
        Y[b] = la.twist_add(la.bracket(A[b], ap), la.bracket(Vp, Z[b]))  # [A, a] + [V, Z] (xd_b terms cancel)
        a[b] = la.twist_add(la.twist_add(ap, la.twist_scale(xdd[b], A[b])),
                            la.twist_scale(-1.0, la.twist_scale(xd[b], Z[b])))   # [V_b, A_b xd_b]
    # backward: body terms, subtree sums (composites), then joint b's products with its
    # ancestors at once, so that few values are live at a time (see codegen._MAX_FAST)
    Jc, Dc, Hc, Fc = ([None] * nb for _ in range(4))
    dq = [[0.0] * nb for _ in range(nb)]
    dv = [[0.0] * nb for _ in range(nb)]
    for m in reversed(range(nb)):
        Js = _inertia_to_root(params[m], Rw[m], pw[m])   # f_{0,m'} = (Rw, pw)
        H = la.inertia_times(Js, V[m])
        F = la.twist_add(la.inertia_times(Js, a[m]), la.twist_scale(-1.0, la.ad_t(V[m], H)))
        if fext is not None:   # body-frame wrench (in frame m') to the root frame
            F = la.twist_add(F, la.twist_scale(-1.0, la.wrench_to_parent(fext[m], Rw[m], pw[m])))
        D = la.inertia_rate(Js, V[m])
        if Jc[m] is None:
            Jc[m], Dc[m], Hc[m], Fc[m] = Js, D, H, F
        else:
            Jc[m], Dc[m] = la.inertia_add(Jc[m], Js), la.inertia_add(Dc[m], D)
            Hc[m], Fc[m] = la.twist_add(Hc[m], H), la.twist_add(Fc[m], F)
        J, Am, Zm = Jc[m], A[m], Z[m]

        def Bc(y, D=Dc[m]):  # Bc_m y = -(d/dt Jc_m) y
            return la.twist_scale(-1.0, la.inertia_times(D, y))
        JcA = la.inertia_times(J, Am)
        BcA = Bc(Am)
        adAH = la.ad_t(Am, Hc[m])
        P = la.twist_add(la.twist_add(la.twist_scale(-1.0, la.inertia_times(J, Y[m])), Bc(Zm)),
                         la.twist_add(la.ad_t(Zm, Hc[m]), la.twist_scale(-1.0, la.ad_t(Am, Fc[m]))))
        Pv = la.twist_scale(-1.0, la.twist_add(la.twist_add(BcA, la.twist_scale(2.0, la.inertia_times(J, Zm))),
                                               adAH))
        R = (la.twist_scale(-1.0, JcA), la.twist_add(BcA, la.twist_scale(-1.0, adAH)))
        Rv = (la.twist_add(adAH, la.twist_scale(-1.0, BcA)),
              tuple(tuple(g.bake(-2.0 * c) for c in v) for v in JcA))   # used in O(n) products
        dq[m][m], dv[m][m] = la.dot6(Am, P), la.dot6(Am, Pv)
        k = fr.parent[m]
        while k >= 0:          # k < m
            dq[k][m], dv[k][m] = la.dot6(A[k], P), la.dot6(A[k], Pv)
            dq[m][k] = la.dot6(R[0], Y[k]) + la.dot6(R[1], Z[k])
            dv[m][k] = la.dot6(Rv[0], A[k]) + la.dot6(Rv[1], Z[k])
            k = fr.parent[k]
        p = fr.parent[m]
        if p >= 0:
            if Jc[p] is None:
                Jc[p], Dc[p], Hc[p], Fc[p] = Jc[m], Dc[m], Hc[m], Fc[m]
            else:
                Jc[p], Dc[p] = la.inertia_add(Jc[p], Jc[m]), la.inertia_add(Dc[p], Dc[m])
                Hc[p], Fc[p] = la.twist_add(Hc[p], Hc[m]), la.twist_add(Fc[p], Fc[m])
    return fr.project(dq), fr.project(dv)


def _build_kernel(fr, wrench, center=0, coriolis=False):
    """The generated derivative kernel (trace_derivatives) of this tree: (Q, QD, QDD, P, A0,
    E0[, FX]) -> dtau/dq then dtau/dqd, row-major.

    coriolis: only C = 1/2 dtau/dqd, which depends on neither qdd nor gravity; the kernel then
    takes (Q, QD, P, E0) and everything only dtau/dq needs is pruned.
    """
    g = Graph()
    co = fr.trace_coordinates(g, rates=1 if coriolis else 2)
    parg, params = fr.trace_params(g)
    if coriolis:
        ga = [0.0, 0.0, 0.0]
        co['xdd'] = [0.0] * fr.nb
        args = co['args'] + [parg, co['offset_args']]
    else:
        ga = [g.input(f'g{k}') for k in range(3)]
        args = co['args'] + [parg, ('A0', [f'g{k}' for k in range(3)]), co['offset_args']]
    fext = None
    if wrench:
        names = [f'f{b}_{k}' for b in range(fr.nb) for k in range(6)]
        args.append(('FX', names))
        fs = [g.input(nm) for nm in names]
        fext = [(tuple(fs[6 * b:6 * b + 3]), tuple(fs[6 * b + 3:6 * b + 6])) for b in range(fr.nb)]
    dq, dv = trace_derivatives(fr, g, co['x'], co['xd'], co['xdd'], params, ga, fext, center)
    n = fr.n
    if coriolis:
        outputs = [0.5 * dv[r][c] for r in range(n) for c in range(n)]
    else:
        outputs = [dq[r][c] for r in range(n) for c in range(n)] + [dv[r][c] for r in range(n) for c in range(n)]
    return kernel(g, 'rnea_derivatives_kernel', args, outputs)


def _poses(fr, g, x, r):
    """Poses (R, p) of every body frame b' in frame r' at this configuration, and the base's R.

    Up the path from r: pose(parent) = pose(c) X_c^-1; then down: pose(b) = pose(parent) X_b.
    """
    nb = fr.nb
    X = [fr.joint_transform(g, b, x[b]) for b in range(nb)]
    eye = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))
    Rw, pw = [None] * nb, [None] * nb
    Rw[r], pw[r] = eye, (0.0, 0.0, 0.0)
    c = r
    while True:
        R, t = X[c]
        Rp = tuple(tuple(la.dot(Rw[c][i], R[j]) for j in range(3)) for i in range(3))   # R_c R^T
        pp = la.vsub(pw[c], la.mat_vec(Rp, t))
        p = fr.parent[c]
        if p < 0:
            Rb, pb = Rp, pp
            break
        Rw[p], pw[p] = Rp, pp
        c = p
    for b in range(nb):
        if Rw[b] is None:
            p = fr.parent[b]
            R, t = X[b]
            Rp, pp = (Rw[p], pw[p]) if p >= 0 else (Rb, pb)
            Rw[b] = la.mat_mat(Rp, R)
            pw[b] = la.vadd(pp, la.mat_vec(Rp, t))
    return Rw, pw, Rb


def _inertia_to_root(ic, R, t):
    """codegen.inertia_to_parent with fewer traced products.

    With g = R h + m t / 2: I' = R I R^T + 2 (t . g) 1 - t g^T - g t^T, h' = R h + m t.
    """
    m, h, Io = ic
    Rh = la.mat_vec(R, h)
    mt = la.vscale(m, t)
    hp = la.vadd(Rh, mt)
    gv = la.vadd(Rh, la.vscale(0.5, mt))
    Ir = la.sym_rot(R, Io)
    d = 2.0 * la.dot(t, gv)
    Ip = []
    for k, (r, c) in enumerate(((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))):
        v = Ir[k] - (t[r] * gv[c] + gv[r] * t[c])
        if r == c:
            v = v + d
        Ip.append(v)
    return m, hp, tuple(Ip)


def _kernel(model, wrench):
    if model.nb > KERNEL_MAX_BODIES:
        return False
    return runtime.compiled(model, 'rnea_derivatives_wrench' if wrench else 'rnea_derivatives',
                       lambda fr: _build_kernel(fr, wrench))


def _coriolis_kernel(model):
    if model.nb > KERNEL_MAX_BODIES:
        return False
    return runtime.compiled(model, 'coriolis', lambda fr: _build_kernel(fr, False, coriolis=True))


def coriolis_matrix(model, q, qd):
    """C(q, qd) = 1/2 dtau/dqd by the differentiated recursion (the dtau/dqd half of the
    derivative kernel). This is the Christoffel C of eqs 40-42: tau is quadratic in qd with
    symmetric Gamma_ijk = Gamma_jik, so d/dqd_j sum_i,l Gamma_ilk qd_i qd_l = 2 sum_i Gamma_ijk qd_i.
    q, qd: (n,) or (N, n) -> (n, n) or (N, n, n).
    """
    n = model.n
    a, b = runtime.is_fast_single(q, n), runtime.is_fast_single(qd, n)
    if a is not None and b is not None:
        k = _coriolis_kernel(model)
        if k:
            fr, fn, _ = k
            P, E0 = runtime.model_params(model, fr)
            return np.fromiter(fn(a, b, P, E0, sin=math.sin, cos=math.cos), float, n * n).reshape(n, n)
    single = np.ndim(q) == 1
    q, qd = model.check_states(q=q, qd=qd)
    N = q.shape[0]
    k = _coriolis_kernel(model)
    if not k or _LOOP_BELOW <= N < _ROWS_FROM:
        C = 0.5 * inverse_dynamics_derivatives_vectorized(model, q, qd, np.zeros_like(qd))[1]
    else:
        fr, fn, _ = k
        P, E0 = runtime.model_params(model, fr)
        if N < _LOOP_BELOW:
            C = np.array([fn(a, b, P, E0, sin=math.sin, cos=math.cos)
                          for a, b in zip(q.tolist(), qd.tolist(), strict=True)])
        else:
            C = runtime.run_rows(fn, [q, qd, P, E0], n * n)
        C = C.reshape(N, n, n)
    return C[0] if single else C


def _kernel_derivatives(model, q, qd, qdd, fext, mode=None):
    """Kernel path on validated (N, n) arrays; fext: (N, nb, 6) body-frame wrenches or None.

    mode: 'loop' (Python floats, state by state), 'rows' (numpy rows) or None (by batch size;
    returns None where the vectorised form is faster or the model has no kernel).
    """
    N = q.shape[0]
    if mode is None:
        mode = 'loop' if N < _LOOP_BELOW else 'rows' if N >= _ROWS_FROM else None
    k = _kernel(model, fext is not None) if mode else False
    if not k:
        return None
    fr, fn, _ = k
    P, E0, A0 = runtime.model_params(model, fr, gravity=True)
    N, n = q.shape
    extra = ()
    if fext is not None:
        extra = (fr.wrench_params(fext).reshape(N, -1),)
    if mode == 'loop':
        rows = zip(q.tolist(), qd.tolist(), qdd.tolist(), *[e.tolist() for e in extra], strict=True)
        vals = np.array([fn(*r[:3], P, A0, E0, *r[3:], sin=math.sin, cos=math.cos) for r in rows])
    else:
        vals = runtime.run_rows(fn, [q, qd, qdd, P, A0, E0] + list(extra), 2 * n * n)
    vals = vals.reshape(N, 2, n, n)
    return vals[:, 0], vals[:, 1]
