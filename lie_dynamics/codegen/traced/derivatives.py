"""Derivatives of inverse and forward dynamics, traced (formulas in algorithms/rnea_derivatives.py
and algorithms/aba_derivatives.py)."""
from .. import algebra as la
from ..kernel import Trace
from ..runtime import Spec
from ..thresholds import PD_RTOL
from ..tracer import Graph
from .cholesky import trace_cho_solve, trace_forward_dynamics, trace_inputs


def trace_derivatives(fr, g, x, xd, xdd, params, a0, fext=None, center=0):
    """The O(n^2) derivative formulas of algorithms/rnea_derivatives.py, traced.

    "Root frame" here is any fixed frame: the formulas are covariant, and the outputs are
    scalars. The kernel uses the frame that coincides with body `center`'s primed frame at
    the current configuration, about its origin (on that joint's axis): that body's pose
    is the identity and its screw is e_z, so whole products fold away. Only gravity and the
    poses change. The first body gave the fewest operations on the arm and random chains.
    The 6x6 composite Bc_k = -d/dt Jc_k is carried as the rate of the 10 inertia
    parameters (algebra.inertia_rate), which is all Bc is applied through.

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
    # ancestors at once, so that few values are live at a time (the first 256 locals are cheaper, see render.py)
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


def build_inverse_dynamics_derivatives(fr, wrench=False, center=0, coriolis=False):
    """The generated derivative kernel (trace_derivatives) of this tree: (Q, QD, QDD[, FX], P,
    A0, E0) -> dtau/dq then dtau/dqd, row-major.

    coriolis: only C = 1/2 dtau/dqd, which depends on neither qdd nor gravity; the kernel then
    takes (Q, QD, P, E0) and everything only dtau/dq needs is pruned.
    """
    g = Graph()
    co = fr.trace_coordinates(g, rates=1 if coriolis else 2)
    parg, params = fr.trace_params(g)
    args = list(co['args'])
    fext = None
    if wrench:   # per-state arguments first, then the parameters
        names = [f'f{b}_{k}' for b in range(fr.nb) for k in range(6)]
        args.append(('FX', names))
        fs = [g.input(nm) for nm in names]
        fext = [(tuple(fs[6 * b:6 * b + 3]), tuple(fs[6 * b + 3:6 * b + 6])) for b in range(fr.nb)]
    if coriolis:
        ga = [0.0, 0.0, 0.0]
        co['xdd'] = [0.0] * fr.nb
        args += [parg, co['offset_args']]
    else:
        a0arg, ga = fr.trace_gravity(g)
        args += [parg, a0arg, co['offset_args']]
    dq, dv = trace_derivatives(fr, g, co['x'], co['xd'], co['xdd'], params, ga, fext, center)
    n = fr.n
    if coriolis:
        outputs = [0.5 * dv[r][c] for r in range(n) for c in range(n)]
    else:
        outputs = [dq[r][c] for r in range(n) for c in range(n)] + [dv[r][c] for r in range(n) for c in range(n)]
    return Trace(g, 'rnea_derivatives_kernel', args, outputs)


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
    """algebra.inertia_to_parent with fewer traced products.

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


def build_forward_dynamics_derivatives(fr):
    """Trace qdd (traced/cholesky.py), dtau/dq and dtau/dqd at that qdd (trace_derivatives)
    and the solves with the same Cholesky factor: (Q, QD, TAU, P, A0, E0) -> dqdd/dq,
    dqdd/dqd, M^-1 (row-major), then the pivots and diag(M) for the positive-definiteness
    check (as the Cholesky kernel's)."""
    g = Graph()
    co, args, params, ga, taus = trace_inputs(fr, g)
    qdd, M, L, inv_d, pivots = trace_forward_dynamics(fr, g, co['x'], co['xd'], params, ga, taus)
    n, nb = fr.n, fr.nb
    xdd = [sum((float(fr.E[b, j]) * qdd[j] for j in range(n) if fr.E[b, j] != 0), 0.0) for b in range(nb)]
    dq, dv = trace_derivatives(fr, g, co['x'], co['xd'], xdd, params, ga)
    cols = []
    for D, sign in ((dq, -1.0), (dv, -1.0)):
        cols += [[sign * v for v in trace_cho_solve(L, inv_d, [D[r][c] for r in range(n)])] for c in range(n)]
    cols += [trace_cho_solve(L, inv_d, [1.0 if r == c else 0.0 for r in range(n)]) for c in range(n)]
    outputs = []
    for k in range(3):
        outputs += [cols[k * n + c][r] for r in range(n) for c in range(n)]
    outputs += pivots + [M[j][j] for j in range(n)]
    return Trace(g, 'forward_dynamics_derivatives_kernel', args, outputs)


INVERSE_DYNAMICS_DERIVATIVES = Spec(
    'inverse_dynamics_derivatives', build_inverse_dynamics_derivatives, ('inertia', 'gravity', 'offsets'),
    'inverse_dynamics_derivatives')
INVERSE_DYNAMICS_DERIVATIVES_WRENCH = Spec(
    'inverse_dynamics_derivatives_wrench', lambda fr: build_inverse_dynamics_derivatives(fr, wrench=True),
    ('inertia', 'gravity', 'offsets'), 'inverse_dynamics_derivatives')
CORIOLIS = Spec('coriolis', lambda fr: build_inverse_dynamics_derivatives(fr, coriolis=True),
                ('inertia', 'offsets'), 'inverse_dynamics_derivatives', result=lambda model: ((model.n, model.n), None))
FORWARD_DYNAMICS_DERIVATIVES = Spec(
    'forward_dynamics_derivatives', build_forward_dynamics_derivatives, ('inertia', 'gravity', 'offsets'),
    'forward_dynamics_derivatives', checked=True, result=lambda model: ((3 * model.n * model.n,), PD_RTOL))
