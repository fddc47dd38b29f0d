"""Derivatives of inverse and forward dynamics, traced (formulas in algorithms/rnea_derivatives.py
and algorithms/aba_derivatives.py)."""
from .. import algebra as la
from .. import looped
from ..frames import joint_transform
from ..kernel import Trace
from ..runtime import Spec
from ..thresholds import PD_RTOL
from ..tracer import Graph
from .cholesky import trace_cho_solve, trace_forward_dynamics, trace_inputs
from .crba import looped_mass_pass


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
    The passes are loops of the per-body steps below (`forward`; `body_terms`, `add_composite`,
    `products`; `pair` per (body, ancestor)), which the looped form (`looped_derivatives`) renders.
    """
    nb = fr.nb
    Rw, pw, Rb = _poses(fr, g, x, center)
    ga = la.mat_vec(Rb, a0)
    A, V, a, Z, Y = ([None] * nb for _ in range(5))
    for b in range(nb):   # forward: screws and twists
        p = fr.parent[b]
        if p >= 0:
            Vp, ap = V[p], a[p]
        else:
            Vp, ap = (ZERO3, ZERO3), (ZERO3, tuple(ga))
        A[b], V[b], Z[b], Y[b], a[b] = forward(fr.revolute[b], (Rw[b], pw[b]), Vp, ap, xd[b], xdd[b])
    # backward: body terms, subtree sums (composites), then joint b's products with its
    # ancestors at once, so that few values are live at a time (the first 256 locals are cheaper, see render.py)
    comp = [None] * nb
    dq = [[0.0] * nb for _ in range(nb)]
    dv = [[0.0] * nb for _ in range(nb)]
    for m in reversed(range(nb)):
        comp[m] = add_composite(comp[m], body_terms(params[m], (Rw[m], pw[m]), V[m], a[m],
                                                    None if fext is None else fext[m]))
        P, Pv, R, Rv = products(g, comp[m], A[m], Z[m], Y[m])
        dq[m][m], dv[m][m] = la.dot6(A[m], P), la.dot6(A[m], Pv)
        k = fr.parent[m]
        while k >= 0:          # k < m
            dq[k][m], dv[k][m], dq[m][k], dv[m][k] = pair(A[k], Z[k], Y[k], P, Pv, R, Rv)
            k = fr.parent[k]
        p = fr.parent[m]
        if p >= 0:
            comp[p] = add_composite(comp[p], comp[m])
    return fr.project(dq), fr.project(dv)


# The steps of the derivative recursion, per body (trace_derivatives and the looped form,
# looped_derivatives, both call them).
ZERO3 = (0.0, 0.0, 0.0)


def pose_down(pose_p, X):
    """A body's pose (R, p) in the fixed frame from its parent's and its joint transform X = (R, t)."""
    (Rp, pp), (R, t) = pose_p, X
    return la.mat_mat(Rp, R), la.vadd(pp, la.mat_vec(Rp, t))


def forward(revolute, pose, Vp, ap, xd, xdd):
    """The forward step of one body at pose (R, p): its screw A (the primed z axis through p), twist
    V, acceleration a, and Z = [A, V], Y = [A, a] + [V, Z], from the parent's twist Vp and
    acceleration ap (the base's at a root). Returns (A, V, Z, Y, a)."""
    Rw, pw = pose
    axis = (Rw[0][2], Rw[1][2], Rw[2][2])
    A = (axis, la.cross(pw, axis)) if revolute else (ZERO3, axis)
    V = la.twist_add(Vp, la.twist_scale(xd, A))
    Z = la.bracket(A, Vp)                                      # [A_b, V_b] = [A_b, V_p]
    Y = la.twist_add(la.bracket(A, ap), la.bracket(Vp, Z))     # [A, a] + [V, Z] (xd_b terms cancel)
    a = la.twist_add(la.twist_add(ap, la.twist_scale(xdd, A)),
                     la.twist_scale(-1.0, la.twist_scale(xd, Z)))   # [V_b, A_b xd_b]
    return A, V, Z, Y, a


def body_terms(params, pose, V, a, fext):
    """One body's terms of the composites, in the fixed frame: (Js, D = d/dt Js, H = Js V, F the net
    wrench Js a - ad_V^T H, less the external wrench fext (n, f) of its primed frame, None: none)."""
    Rw, pw = pose
    Js = _inertia_to_root(params, Rw, pw)   # f_{0,m'} = (Rw, pw)
    H = la.inertia_times(Js, V)
    F = la.twist_add(la.inertia_times(Js, a), la.twist_scale(-1.0, la.ad_t(V, H)))
    if fext is not None:   # body-frame wrench (in frame m') to the root frame
        F = la.twist_add(F, la.twist_scale(-1.0, la.wrench_to_parent(fext, Rw, pw)))
    D = la.inertia_rate(Js, V)
    return Js, D, H, F


def add_composite(c, d):
    """The composites (Jc, Dc, Hc, Fc) c plus d (c None: d)."""
    if c is None:
        return d
    return la.inertia_add(c[0], d[0]), la.inertia_add(c[1], d[1]), la.twist_add(c[2], d[2]), la.twist_add(c[3], d[3])


def products(g, comp, Am, Zm, Ym):
    """Body m's factors of its rows and columns (module docstring of algorithms/rnea_derivatives.py)
    from its composites: (P, Pv, R, Rv) with dtau_k/dx_m = A_k^T P, dtau_k/dxd_m = A_k^T Pv (k <= m)
    and dtau_m/dx_k = R . (Y_k, Z_k), dtau_m/dxd_k = Rv . (A_k, Z_k) (k < m)."""
    J, Dc, Hc, Fc = comp

    def Bc(y):  # Bc_m y = -(d/dt Jc_m) y
        return la.twist_scale(-1.0, la.inertia_times(Dc, y))
    JcA = la.inertia_times(J, Am)
    BcA = Bc(Am)
    adAH = la.ad_t(Am, Hc)
    P = la.twist_add(la.twist_add(la.twist_scale(-1.0, la.inertia_times(J, Ym)), Bc(Zm)),
                     la.twist_add(la.ad_t(Zm, Hc), la.twist_scale(-1.0, la.ad_t(Am, Fc))))
    Pv = la.twist_scale(-1.0, la.twist_add(la.twist_add(BcA, la.twist_scale(2.0, la.inertia_times(J, Zm))), adAH))
    R = (la.twist_scale(-1.0, JcA), la.twist_add(BcA, la.twist_scale(-1.0, adAH)))
    Rv = (la.twist_add(adAH, la.twist_scale(-1.0, BcA)),
          tuple(tuple(g.bake(-2.0 * c) for c in v) for v in JcA))   # used in O(n) products
    return P, Pv, R, Rv


def pair(Ak, Zk, Yk, P, Pv, R, Rv):
    """The four entries of a body m and its ancestor k: (dtau_k/dx_m, dtau_k/dxd_m, dtau_m/dx_k,
    dtau_m/dxd_k)."""
    return (la.dot6(Ak, P), la.dot6(Ak, Pv), la.dot6(R[0], Yk) + la.dot6(R[1], Zk),
            la.dot6(Rv[0], Ak) + la.dot6(Rv[1], Zk))


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
            Rw[b], pw[b] = pose_down((Rw[p], pw[p]) if p >= 0 else (Rb, pb), X[b])
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
    and the solves with the same Cholesky factor: (Q, QD, TAU, P, A0, E0, AR) -> dqdd/dq,
    dqdd/dqd, M^-1 (row-major), then the pivots and diag(M) for the positive-definiteness
    check (as the Cholesky kernel's)."""
    g = Graph()
    co, args, params, ga, taus, arm = trace_inputs(fr, g)
    qdd, M, L, inv_d, pivots = trace_forward_dynamics(fr, g, co['x'], co['xd'], params, ga, taus, arm)
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


# ---------------------------------------------------------------------------- looped form
def _twist(v):
    return tuple(v[:3]), tuple(v[3:6])


def _flat(*twists):
    return [e for t in twists for part in t for e in part]


def _comp_in(v):
    """Composites (Jc, Dc, Hc, Fc) from a register of 31: Jc (10), Dc without its mass (always 0:
    9), Hc, Fc (6 each)."""
    return ((v[0], tuple(v[1:4]), tuple(v[4:10])), (0.0, tuple(v[10:13]), tuple(v[13:19])),
            _twist(v[19:25]), _twist(v[25:31]))


def _comp_flat(c):
    Jc, Dc, Hc, Fc = c
    return [Jc[0], *Jc[1], *Jc[2], *Dc[1], *Dc[2]] + _flat(Hc, Fc)


def looped_derivatives(fr, wrench=False, coriolis=False):
    """The looped native form of the derivative kernels (codegen/looped.py; same arguments and
    outputs as build_inverse_dynamics_derivatives(fr, wrench, coriolis=coriolis)), or None
    (mimic joints): the driver of `looped_passes`."""
    if looped.joints_of(fr) is None or (wrench and coriolis):
        return None
    nb, n = fr.nb, fr.n
    n_out = n * n if coriolis else 2 * n * n
    decl, free = looped.work(_registers(nb, wrench), n_out)
    if coriolis:
        head = 'const double *q = in[0], *qd = in[1], *qdd = 0, *P = par[0], *A0 = 0, *E0 = par[1], *FX = 0;'
    else:
        head = ('const double *q = in[0], *qd = in[1], *qdd = in[2], ' + ('*FX = in[3], ' if wrench else '*FX = 0, ')
                + '*P = par[0], *A0 = par[1], *E0 = par[2];')
    src = [looped.structure(fr), looped_passes(fr, wrench, coriolis), f'''
void lie_kernel(const double *const *in, const double *const *par, double *out)
{{
  {head}
{decl}  der_forward(q, qd, qdd, E0, A0, FX, POSE, V, ACC, AZY, FXW);
  der_backward(P, FXW, POSE, V, ACC, AZY, CMP, out);   /* after every read of the inputs: out may alias them */
{free}}}
''']
    if coriolis:
        states, par_lengths = (n, n), (10 * nb, sum(fr.offset))
    else:
        states, par_lengths = (n, n, n) + ((6 * nb,) if wrench else ()), (10 * nb, 3, sum(fr.offset))
    return looped.rendered(''.join(src), states, par_lengths, n_out)


def _registers(nb, wrench):
    """The register blocks of the derivative passes (looped_passes)."""
    return [('POSE', 12 * nb), ('V', 6 * nb), ('ACC', 6 * nb), ('AZY', 18 * nb), ('CMP', 31 * nb),
            ('FXW', 6 * nb if wrench else 6)]


def looped_passes(fr, wrench=False, coriolis=False, bias=False):
    """C text of the derivative recursion's looped passes (after looped.structure's arrays), the
    fixed frame the base frame (the formulas are covariant; the straight-line trace's moving
    `center` frame would need a pass up the tree first):

      der_forward(q, qd, qdd, E0, A0, FX, POSE, V, ACC, AZY, FXW): per body the joint transform
        (frames.joint_transform), `pose_down` and `forward` (a step per joint kind, free or
        welded), from the base at rest with acceleration -g (A0, None: 0); FX (wrench) copied to
        FXW, so that every input is read in this pass;
      der_backward(P, FXW, POSE, V, ACC, AZY, CMP, out): per body, leaves first, `body_terms`,
        `add_composite`, `products` and the diagonal, the composites added to the parent's (a
        step per free or welded, root or not), then `pair` for every (body, ancestor) with joints:
        out = dtau/dq then dtau/dqd (coriolis: 1/2 dtau/dqd only; Y and Fc, which only dtau/dq
        needs, are pruned from the steps);
      der_bias(P, POSE, V, ACC, AZY, CMP, h) (bias): the same backward steps' `body_terms` and
        `add_composite` for Fc alone, h_j = A^T Fc (the inverse dynamics of the forward pass: with
        qdd = 0, the bias of the forward-dynamics derivatives).
    """
    J = looped.joints_of(fr)
    nb = fr.nb
    zt = (ZERO3, ZERO3)
    fkeys, fsig = looped.classify([(fr.revolute[b], J[b] >= 0) for b in range(nb)])
    bkeys, bsig = looped.classify([(J[b] >= 0, fr.parent[b] < 0) for b in range(nb)])
    src = [looped.table('int', 'DER_FSIG', fsig), looped.table('int', 'DER_BSIG', bsig),
           looped.table('double', 'DER_K0', [e for b in range(nb) for e in looped.pose_out((fr.R[b], fr.t[b]))])]
    for i, (rev, free) in enumerate(fkeys):
        def fwd(g, x, xd, xdd, K, pp, Vp, ap, rev=rev, free=free):
            pose = pose_down(looped.pose_in(pp), joint_transform(g, *looped.pose_in(K), rev, x[0]))
            A, V, Z, Y, a = forward(rev, pose, _twist(Vp), zt if coriolis else _twist(ap), xd[0] if free else 0.0,
                                    xdd[0] if free and not coriolis else 0.0)
            return [looped.pose_out(pose), _flat(V), [] if coriolis else _flat(a),
                    _flat(A, Z) if coriolis else _flat(A, Z, Y)]
        src.append(looped.step(f'der_fwd{i}', fwd, (1, 1, 1, 12, 12, 6, 6)))
    for i, (free, root) in enumerate(bkeys):
        def back(g, P, pose, V, a, fx, Cm, AZY, Cp, free=free, root=root):
            own = body_terms((P[0], tuple(P[1:4]), tuple(P[4:10])), looped.pose_in(pose), _twist(V),
                             zt if coriolis else _twist(a), _twist(fx) if wrench else None)
            comp = add_composite(_comp_in(Cm), own)
            out = [[], [], []]
            if free:
                A, Z, Y = _twist(AZY[:6]), _twist(AZY[6:12]), _twist(AZY[12:18])
                Pq, Pv, R, Rv = products(g, comp, A, Z, Y)
                if coriolis:
                    out[0], out[1] = _flat(Pv, *Rv), [0.5 * la.dot6(A, Pv)]
                else:
                    out[0], out[1] = _flat(Pq, Pv, *R, *Rv), [la.dot6(A, Pq), la.dot6(A, Pv)]
            if not root:
                up = _comp_flat(add_composite(_comp_in(Cp), comp))
                out[2] = up[:25] if coriolis else up    # Coriolis: no Fc
            return out
        src.append(looped.step(f'der_back{i}', back, (10, 12, 6, 6, 6, 31, 18, 31)))
        if bias:
            def bias_step(g, P, pose, V, a, Cm, AZY, Cp, free=free, root=root):
                own = body_terms((P[0], tuple(P[1:4]), tuple(P[4:10])), looped.pose_in(pose), _twist(V),
                                 _twist(a), None)
                comp = add_composite(_comp_in(Cm), own)
                return [[la.dot6(_twist(AZY[:6]), comp[3])] if free else [],
                        [] if root else _flat(add_composite(_comp_in(Cp), comp)[3])]
            src.append(looped.step(f'der_bias{i}', bias_step, (10, 12, 6, 6, 31, 18, 31)))

    def pair_step(g, AZY, PR):
        A, Z, Y = _twist(AZY[:6]), _twist(AZY[6:12]), _twist(AZY[12:18])
        if coriolis:
            Pv, Rv = _twist(PR[:6]), (_twist(PR[6:12]), _twist(PR[12:18]))
            r = pair(A, Z, Y, zt, Pv, (zt, zt), Rv)
            return [[0.5 * r[1], 0.5 * r[3]]]
        Pq, Pv = _twist(PR[:6]), _twist(PR[6:12])
        R, Rv = (_twist(PR[12:18]), _twist(PR[18:24])), (_twist(PR[24:30]), _twist(PR[30:36]))
        return [list(pair(A, Z, Y, Pq, Pv, R, Rv))]
    src.append(looped.step('der_pair', pair_step, (18, 36)))

    def sw(sig, name, keys, call):
        return looped.switch(sig, [f'{name}{i}' for i in range(len(keys))], call)
    fwd_call = sw('DER_FSIG[b]', 'der_fwd', fkeys, '&x, &xd, &xdd, DER_K0 + 12 * b, pp, vp, ap, POSE + 12 * b, '
                                                   'V + 6 * b, ACC + 6 * b, AZY + 18 * b')
    back_call = sw('DER_BSIG[m]', 'der_back', bkeys, 'P + 10 * m, POSE + 12 * m, V + 6 * m, ACC + 6 * m, '
                                                     'FXW + 6 * m, CMP + 31 * m, AZY + 18 * m, CMP + 31 * up, PR, d, '
                                                     'CMP + 31 * up')
    if coriolis:
        write = ('out[jm * NJ + jm] = d[0];', 'out[jk * NJ + jm] = r[0]; out[jm * NJ + jk] = r[1];')
    else:
        write = ('out[jm * NJ + jm] = d[0]; out[NJ * NJ + jm * NJ + jm] = d[1];',
                 'out[jk * NJ + jm] = r[0]; out[NJ * NJ + jk * NJ + jm] = r[1]; '
                 'out[jm * NJ + jk] = r[2]; out[NJ * NJ + jm * NJ + jk] = r[3];')
    src.append(f'''
static void der_forward(const double *q, const double *qd, const double *qdd, const double *E0, const double *A0,
                        const double *FX, double *POSE, double *V, double *ACC, double *AZY, double *FXW)
{{
  /* the base: identity pose, at rest, acceleration -g (its linear part) */
  const double BASE[24] = {{1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0,
                            0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0,
                            A0 ? A0[0] : 0.0, A0 ? A0[1] : 0.0, A0 ? A0[2] : 0.0}};
  (void)E0; (void)ACC; (void)FXW; (void)FX;
  for (int b = 0; b < NB; b++) {{
    const int up = PAR[b];
    const double *pp = up >= 0 ? POSE + 12 * up : BASE, *vp = up >= 0 ? V + 6 * up : BASE + 12,
                 *ap = up >= 0 ? ACC + 6 * up : BASE + 18;
    const double x = X_OF(q, E0, b), xd = JNT[b] >= 0 ? qd[JNT[b]] : 0.0,
                 xdd = JNT[b] >= 0 && qdd ? qdd[JNT[b]] : 0.0;
    (void)xdd;
    {fwd_call}
    if (FX) memcpy(FXW + 6 * b, FX + 6 * b, 6 * sizeof(double));
  }}
}}

static void der_backward(const double *P, const double *FXW, const double *POSE, const double *V,
                         const double *ACC, const double *AZY, double *CMP, double *out)
{{
  (void)ACC; (void)FXW;
  memset(CMP, 0, 31 * NB * sizeof(double));
  memset(out, 0, {1 if coriolis else 2} * NJ * NJ * sizeof(double));
  for (int m = NB - 1; m >= 0; m--) {{
    const int up = PAR[m] >= 0 ? PAR[m] : 0, jm = JNT[m];
    double PR[36], d[2];
    {back_call}
    if (jm < 0) continue;
    {write[0]}
    for (int k = PAR[m]; k >= 0; k = PAR[k]) {{
      const int jk = JNT[k];
      double r[4];
      if (jk < 0) continue;
      der_pair(AZY + 18 * k, PR, r);
      {write[1]}
    }}
  }}
}}
''')
    if bias:
        bias_call = sw('DER_BSIG[m]', 'der_bias', bkeys, 'P + 10 * m, POSE + 12 * m, V + 6 * m, ACC + 6 * m, '
                                                         'CMP + 31 * m, AZY + 18 * m, CMP + 31 * up, &t, '
                                                         'CMP + 31 * up + 25')
        src.append(f'''
static void der_bias(const double *P, const double *POSE, const double *V, const double *ACC, const double *AZY,
                     double *CMP, double *h)
{{
  memset(CMP, 0, 31 * NB * sizeof(double));
  for (int m = NB - 1; m >= 0; m--) {{
    const int up = PAR[m] >= 0 ? PAR[m] : 0;
    double t = 0.0;
    {bias_call}
    if (JNT[m] >= 0) h[JNT[m]] = t;
  }}
}}
''')
    return ''.join(src)


# The tree-sparse factorisation M = L^T D L (Featherstone, Rigid Body Dynamics Algorithms, sec. 6.5,
# "LTDL") and its solves, as C loops over the structure arrays: the factorisation and solves
# of a number matrix, which the straight-line kernel traces densely (traced/cholesky.py, its
# zeros folded at trace time). Looped, the tree's zero pattern is PAR and JNT: eliminating the
# leaves first, L has the zeros of M (no fill-in), and each update is one multiply-subtract, a
# step too small to trace. A pivot D_j is S_j^T I^A_j S_j, the ABA's, positive exactly where the
# dense Cholesky pivots are (both are the Schur complements of M after eliminating other joints).
_LTDL = '''
/* H <- L and D of H = L^T D L: L_ki (i an ancestor of k) in H's row k, D on the diagonal. JORD: the
   joints in tree order; ANC + AOFF[j] .. AOFF[j + 1]: joint j's ancestor joints, nearest first. */
static void ltdl(double *H)
{
  for (int t = NJ - 1; t >= 0; t--) {
    const int jk = JORD[t], *anc = ANC + AOFF[jk], na = AOFF[jk + 1] - AOFF[jk];
    for (int u = 0; u < na; u++) {
      const int ji = anc[u];
      const double a = H[jk * NJ + ji] / H[jk * NJ + jk];
      for (int v = u; v < na; v++) H[ji * NJ + anc[v]] -= a * H[jk * NJ + anc[v]];
      H[jk * NJ + ji] = a;
    }
  }
}

/* The solves in column blocks of LTDL_CB (in cache at every size) and, on x86-64 with gcc and
   glibc (which resolves the clone at load: an ifunc), a vectorised clone for AVX2 where the CPU
   has it: the same operations per element in the same order (-ffp-contract=off: no fused
   multiply-add), so the same bits. */
#define LTDL_CB 32
#if defined(__x86_64__) && defined(__GNUC__) && !defined(__clang__) && defined(__GLIBC__)
#define LTDL_VECTOR __attribute__((target_clones("avx2", "default"), optimize("O3")))
#else
#define LTDL_VECTOR
#endif

static inline void row_sub(double *restrict d, const double *restrict s, double a, int w)
{
  for (int c = 0; c < w; c++) d[c] -= a * s[c];
}

/* B <- sign[g] (L^T D L)^-1 B in each of `regions` blocks g of NJ rows of `width` (ltdl's factors in H). */
LTDL_VECTOR
static void ltdl_solve(const double *H, double *B, int width, int regions, const double *sign)
{
  for (int g = 0; g < regions; g++)
    for (int c0 = 0; c0 < width; c0 += LTDL_CB) {
      const int w = width - c0 < LTDL_CB ? width - c0 : LTDL_CB;
      double *Bg = B + g * NJ * width + c0;
      for (int t = NJ - 1; t >= 0; t--) {            /* L^T w = b: descendants first */
        const int jk = JORD[t], *anc = ANC + AOFF[jk], na = AOFF[jk + 1] - AOFF[jk];
        for (int u = 0; u < na; u++) row_sub(Bg + anc[u] * width, Bg + jk * width, H[jk * NJ + anc[u]], w);
      }
      for (int j = 0; j < NJ; j++) {                 /* z = D^-1 w */
        const double s = sign[g] / H[j * NJ + j];
        for (int c = 0; c < w; c++) Bg[j * width + c] *= s;
      }
      for (int t = 0; t < NJ; t++) {                 /* L x = z: ancestors first */
        const int jk = JORD[t], *anc = ANC + AOFF[jk], na = AOFF[jk + 1] - AOFF[jk];
        for (int u = 0; u < na; u++) row_sub(Bg + jk * width, Bg + anc[u] * width, H[jk * NJ + anc[u]], w);
      }
    }
}
'''


def looped_forward_dynamics_derivatives(fr):
    """The looped native form of FORWARD_DYNAMICS_DERIVATIVES (same arguments and outputs as
    build_forward_dynamics_derivatives, the pivots those of M = L^T D L), or None (mimic joints).
    The driver composes the looped passes: the derivative recursion's forward pass at qdd = 0 and
    its bias (looped_passes: h = C qd + g), M (crba.looped_mass_pass, with the armature), its
    factorisation (_LTDL), qdd = M^-1 (tau - h), the forward pass again at qdd, the derivative
    pass (dtau/dq, dtau/dqd) and one solve of [dtau/dq, dtau/dqd, 1] with the factors, negated
    for the first two."""
    if looped.joints_of(fr) is None:
        return None
    nb, n = fr.nb, fr.n
    nn = n * n
    n_out = 3 * nn + 2 * n
    regs = _registers(nb, False) + [('X', 12 * nb), ('IC', 10 * nb), ('H', nn), ('HB', n), ('QDD', n), ('PV', n),
                                    ('DG', n)]
    decl, free = looped.work(regs, n_out)
    src = [looped.structure(fr), _joint_tree(fr), looped_mass_pass(fr), looped_passes(fr, bias=True), _LTDL, f'''
void lie_kernel(const double *const *in, const double *const *par, double *out)
{{
  const double *q = in[0], *qd = in[1], *tau = in[2], *P = par[0], *A0 = par[1], *E0 = par[2], *AR = par[3];
  const double one[1] = {{1.0}}, signs[3] = {{-1.0, -1.0, 1.0}};
{decl}  der_forward(q, qd, 0, E0, A0, 0, POSE, V, ACC, AZY, FXW);   /* qdd = 0: the bias h */
  der_bias(P, POSE, V, ACC, AZY, CMP, HB);
  crba_pass(q, P, E0, AR, X, IC, H);
  for (int j = 0; j < NJ; j++) DG[j] = H[j * NJ + j];
  ltdl(H);
  for (int j = 0; j < NJ; j++) {{ PV[j] = H[j * NJ + j]; QDD[j] = tau[j] - HB[j]; }}
  ltdl_solve(H, QDD, 1, 1, one);
  der_forward(q, qd, QDD, E0, A0, 0, POSE, V, ACC, AZY, FXW);
  der_backward(P, FXW, POSE, V, ACC, AZY, CMP, out);   /* after every read of the inputs: out may alias them */
  memset(out + 2 * NJ * NJ, 0, NJ * NJ * sizeof(double));
  for (int j = 0; j < NJ; j++) out[2 * NJ * NJ + j * NJ + j] = 1.0;
  ltdl_solve(H, out, NJ, 3, signs);
  memcpy(out + 3 * NJ * NJ, PV, NJ * sizeof(double));
  memcpy(out + 3 * NJ * NJ + NJ, DG, NJ * sizeof(double));
{free}}}
''']
    return looped.rendered(''.join(src), (n, n, n), (10 * nb, 3, sum(fr.offset), n), n_out)


def _joint_tree(fr):
    """The joints' tree for _LTDL: JORD (the joints in tree order), ANC and AOFF (each joint's
    ancestor joints, nearest first: arrays, where walking PAR is a chain of dependent loads)."""
    J = looped.joints_of(fr)
    order, anc, off = [], [], [0] * (fr.n + 1)
    lists = [None] * fr.n
    for b in range(fr.nb):
        if J[b] >= 0:
            order.append(J[b])
            up, k = [], fr.parent[b]
            while k >= 0:
                if J[k] >= 0:
                    up.append(J[k])
                k = fr.parent[k]
            lists[J[b]] = up
    for j in range(fr.n):
        anc += lists[j]
        off[j + 1] = len(anc)
    return looped.table('int', 'JORD', order) + looped.table('int', 'ANC', anc) + looped.table('int', 'AOFF', off)


INVERSE_DYNAMICS_DERIVATIVES = Spec(
    'inverse_dynamics_derivatives', build_inverse_dynamics_derivatives, ('inertia', 'gravity', 'offsets'),
    'inverse_dynamics_derivatives', looped=looped_derivatives)
INVERSE_DYNAMICS_DERIVATIVES_WRENCH = Spec(
    'inverse_dynamics_derivatives_wrench', lambda fr: build_inverse_dynamics_derivatives(fr, wrench=True),
    ('inertia', 'gravity', 'offsets'), 'inverse_dynamics_derivatives',
    looped=lambda fr: looped_derivatives(fr, wrench=True))
CORIOLIS = Spec('coriolis', lambda fr: build_inverse_dynamics_derivatives(fr, coriolis=True),
                ('inertia', 'offsets'), 'inverse_dynamics_derivatives', result=lambda model: ((model.n, model.n), None),
                looped=lambda fr: looped_derivatives(fr, coriolis=True))
FORWARD_DYNAMICS_DERIVATIVES = Spec(
    'forward_dynamics_derivatives', build_forward_dynamics_derivatives, ('inertia', 'gravity', 'offsets', 'armature'),
    'forward_dynamics_derivatives', checked=True, result=lambda model: ((3 * model.n * model.n,), PD_RTOL),
    looped=looped_forward_dynamics_derivatives)
