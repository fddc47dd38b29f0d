"""The inertial-parameter regressor, traced (the body columns K_i of algorithms/regressor.py).

Works in the URDF body frames, not codegen's primed frames, so the columns are already
those of the parameters about the body frame. In primed frames the constant 10x10 map of
the parameters (m, Q^T h, Q^T I Q) would be folded into every (body, ancestor) block: the
same operation count for coordinate-axis joints (the arm), 7-50% more for general axes
(counted on the test robots), while here only a few products per body are added (the axis
is not e_z).
"""
from .. import algebra as la
from .. import looped
from ..kernel import Trace
from ..runtime import Spec
from ..tracer import Graph, Sym, snap
from ...spatial import hat3


def _tuple3(a):
    return tuple(float(v) for v in a)


# The steps of the regressor, per body (the straight-line trace below and the looped kernel,
# `looped_regressor`, both call them): the joint transform from its constants, the forward
# twist and acceleration (`motion`), the body's 6x10 block K_i (`body_columns`), the joint screw
# carried to the child frame (`screw_to_child`) and its projection on the block (`project`).
def transform_constants(M, S, revolute):
    """The constants of `joint_transform` for home pose M (4x4) and screw S, snapped: revolute
    (C0, K1, K2, p) with K1 = M_R [u], K2 = K1 [u], C0 = M_R + K2, p = M_p; prismatic
    (M_R, M_p, d = M_R u)."""
    MR, Mp = M[:3, :3], M[:3, 3]
    if revolute:
        u = S[:3]
        K1 = snap(MR @ hat3(u))
        K2 = snap(K1 @ hat3(u))
        C0 = snap(MR + K2)
        return (tuple(_tuple3(row) for row in C0), tuple(_tuple3(row) for row in K1),
                tuple(_tuple3(row) for row in K2), _tuple3(snap(Mp)))
    return tuple(_tuple3(row) for row in snap(MR)), _tuple3(snap(Mp)), _tuple3(snap(MR @ S[3:]))


def joint_transform(g, consts, revolute, x):
    """(R, t) of f_{p,b}(x) = M exp([S] x) in the URDF body frames, traced, from
    transform_constants (floats, or symbols of a looped step).

    Revolute (axis u through the frame origin): R = M_R (1 + sin x [u] + (1 - cos x) [u]^2),
    t = M_p (eqs 10-12); prismatic (direction u): R = M_R, t = M_p + x M_R u. The constant
    matrices are folded into each entry, a form a + b sin x + c cos x.
    """
    if revolute:
        C0, K1, K2, p = consts
        c, s = g.cos(x), g.sin(x)
        return tuple(tuple(C0[r][k] + K1[r][k] * s - K2[r][k] * c for k in range(3)) for r in range(3)), p
    R, p, d = consts
    return R, tuple(o + dk * x for o, dk in zip(p, d, strict=True))


def motion(X, Sb, Vp, Ap, xd, xdd):
    """Eqs 18-19 for one body: (V_b, Vdot_b) from the parent's (Vp, Ap), X = f_{p,b}(x) = (R, t)."""
    R, t = X
    Sxd = la.twist_scale(xd, Sb)
    V = la.twist_add(la.twist_to_child(Vp, R, t), Sxd)                                      # eq 18
    A = la.twist_add(la.twist_add(la.twist_to_child(Ap, R, t), la.twist_scale(xdd, Sb)), la.bracket(V, Sxd))
    return V, A                                                                             # eq 19


def screw_to_child(Z, X):
    """Z_{k,b} = Ad_{f_{p,b}^-1} Z_{k,p}: a joint screw in the parent's frame moved to the body's."""
    return la.twist_to_child(Z, *X)


def project(Z, cols):
    """Z^T K: one block of 10 of the regressor row of the joint whose screw is Z (in the body frame)."""
    return [la.dot6(Z, col) for col in cols]


def body_columns(V, A):
    """The 10 columns of K(V, Vdot) (module docstring) as wrenches (n, f), traced.

    [alpha] + [w]^2 = [alpha] + w w^T - |w|^2 1 is formed once per body (its diagonal as
    -(w_j^2 + w_k^2), which shares the squares), as is L(alpha) + [w] L(w).
    """
    (w, v), (al, a) = V, A
    zero3 = (0.0, 0.0, 0.0)
    acc = la.vadd(a, la.cross(w, v))
    sq = [wk * wk for wk in w]
    B = [[None] * 3 for _ in range(3)]
    for r in range(3):
        B[r][r] = -(sq[(r + 1) % 3] + sq[(r + 2) % 3])
    for r, k in ((0, 1), (0, 2), (1, 2)):
        wrk = w[r] * w[k]
        sgn = 1.0 if (k - r) % 3 == 1 else -1.0      # [alpha]_{rk} = -sgn alpha_j, j the third index
        j = 3 - r - k
        B[r][k] = wrk - sgn * al[j]
        B[k][r] = wrk + sgn * al[j]
    cols = [(zero3, acc)]
    for j in range(3):
        e = [0.0, 0.0, 0.0]
        e[j] = 1.0
        cols.append((la.cross(e, acc), (B[0][j], B[1][j], B[2][j])))

    def L(u):   # columns of L(u), I u = L(u) (xx, xy, yy, xz, yz, zz)
        return ((u[0], 0.0, 0.0), (u[1], u[0], 0.0), (0.0, u[1], 0.0), (u[2], 0.0, u[0]),
                (0.0, u[2], u[1]), (0.0, 0.0, u[2]))
    for lal, lw in zip(L(al), L(w), strict=True):
        cols.append((la.vadd(lal, la.cross(w, lw)), zero3))
    return cols


def trace_regressor(fr, g, M, S, x, xd, xdd, a0):
    """Traced body-coordinate regressor rows Y[k] (nb lists of 10 nb values, zeros as 0.0).

    Forward pass: V, Vdot (eqs 18-19). Per body i: the 10 columns of K_i (the body wrench of
    the RNEA, F = K_i pi_i); for k = i and each ancestor k, the screw of joint k in frame i,
    Z_ki = Ad_{f_{k,i}^-1} S_k (block (i, k) of G S in eq 39), carried down one joint at a
    time, and Y[k, block i] = Z_ki^T K_i. Carrying the one twist down (6 numbers per step)
    costs less than carrying the ten wrench columns of K_i up (60).
    """
    nb = fr.nb
    zero3 = (0.0, 0.0, 0.0)
    V, A, Z = [None] * nb, [None] * nb, [None] * nb
    Y = [[[0.0] * 10 for _ in range(nb)] for _ in range(nb)]
    for b in range(nb):
        p = fr.parent[b]
        X = joint_transform(g, transform_constants(M[b], S[b], fr.revolute[b]), fr.revolute[b], x[b])
        Sb = (_tuple3(S[b, :3]), _tuple3(S[b, 3:]))
        Vp, Ap = (V[p], A[p]) if p >= 0 else ((zero3, zero3), (zero3, tuple(a0)))
        V[b], A[b] = motion(X, Sb, Vp, Ap, xd[b], xdd[b])
        cols = body_columns(V[b], A[b])
        Z[b] = {b: Sb}
        k = b
        while k >= 0:
            if k != b:
                Z[b][k] = screw_to_child(Z[p][k], X)
            Y[k][b] = project(Z[b][k], cols)
            k = fr.parent[k]
    return [[v for blk in row for v in blk] for row in Y]


def build_regressor(fr):
    """k(Q, QD, QDD, A0, E0) -> the non-zero entries of E^T Y, scattered into the (n, 10 nb)
    result (Trace.scatter: the Kernel's packer writes them, zeros as pad bytes)."""
    M, S = fr.M, fr.S
    g = Graph()
    co = fr.trace_coordinates(g, rates=2)
    a0arg, a0 = fr.trace_gravity(g)
    rows = trace_regressor(fr, g, M, S, co['x'], co['xd'], co['xdd'], a0)
    E, n, nb = fr.E, fr.n, fr.nb
    flat = []
    for a in range(n):          # E^T Y: a mimic joint's row goes to its master
        for col in range(10 * nb):
            s = 0.0
            for b in range(nb):
                if E[b, a] != 0:
                    s = s + float(E[b, a]) * rows[b][col]
            flat.append(s)
    # Only the non-zero outputs are returned: zeros (bodies off a joint's subtree, folded
    # terms) are written by the scatter, not computed.
    idx = [i for i, o in enumerate(flat) if isinstance(o, Sym) or o != 0.0]
    args = co['args'] + [a0arg, co['offset_args']]
    return Trace(g, 'regressor_kernel', args, [flat[i] for i in idx], scatter=(idx, len(flat)))


# ---------------------------------------------------------------------------- looped form
def _consts_flat(consts, revolute):
    """transform_constants as 30 values (a prismatic joint's padded with zeros)."""
    mats, vecs = (consts[:3], consts[3:]) if revolute else (consts[:1], consts[1:])
    out = [e for Mx in mats for row in Mx for e in row] + [e for v in vecs for e in v]
    return out + [0.0] * (30 - len(out))


def _consts_in(K, revolute):
    """transform_constants from 30 values (_consts_flat)."""
    mat = [tuple(tuple(K[9 * m + 3 * r:9 * m + 3 * r + 3]) for r in range(3)) for m in range(3)]
    if revolute:
        return mat[0], mat[1], mat[2], tuple(K[27:30])
    return mat[0], tuple(K[9:12]), tuple(K[12:15])


def _columns_pattern():
    """Positions of the entries of body_columns (10 wrenches, flattened) that are not structurally
    zero: a looped body step stores only those, the pair step reads them back."""
    g = Graph()
    V, A = [[tuple(g.input(f'{nm}{k}') for k in range(i, i + 3)) for i in (0, 3)] for nm in 'va']
    flat = [e for col in body_columns(V, A) for part in col for e in part]
    return [i for i, e in enumerate(flat) if isinstance(e, Sym) or e != 0.0]


def _columns_in(C, nz):
    """body_columns' 10 wrenches from its stored entries C at positions nz, zeros elsewhere."""
    flat = [0.0] * 60
    for i, c in zip(nz, C, strict=True):
        flat[i] = c
    return [(tuple(flat[6 * k:6 * k + 3]), tuple(flat[6 * k + 3:6 * k + 6])) for k in range(10)]


_PAIR_ARGS = 'Z + ZL[p] + 6 * i, X + 12 * b, COLS, zb + 6 * i, out + (size_t)PJ[i] * 10 * NB + 10 * b'


def _pose_pattern(revolute, pat):
    """The entries of a body's pose (looped.pose_out) that its body step stores as constants (folded
    in its pair step), None for the others, for step signature pattern `pat` (looped.exact)."""
    g = Graph()
    K = [c if c is not None else g.input(f'k{k}') for k, c in enumerate(pat)]
    X = joint_transform(g, _consts_in(K[:30], revolute), revolute, g.input('x'))
    return tuple(None if isinstance(e, Sym) else e for e in looped.pose_out(X))


def looped_regressor(fr):
    """The looped native form of REGRESSOR (codegen/looped.py), or None (mimic joints). Steps:
    per body, by depth-first order (looped.dfs_order), `joint_transform`, `motion`,
    `body_columns` and its own block (`project` of its screw), one step per signature (joint
    kind, welded or root, the exact constants: looped.exact); per (body, moving ancestor) pair
    `screw_to_child` then `project`, one step per pattern of the body's pose (its constant
    entries folded: _pose_pattern), the ancestor's screw carried in a register block per depth
    along the current path (Z)."""
    J = looped.joints_of(fr)
    if J is None:
        return None
    nb, n = fr.nb, fr.n
    nz = _columns_pattern()
    K = [_consts_flat(transform_constants(fr.M[b], fr.S[b], fr.revolute[b]), fr.revolute[b]) + list(_tuple3(fr.S[b]))
         for b in range(nb)]
    keys, sig = looped.classify([(fr.revolute[b], J[b] >= 0, fr.parent[b] < 0, tuple(looped.exact(v) for v in K[b]))
                                 for b in range(nb)])
    order = looped.dfs_order(fr)
    depth, active = [0] * nb, [0] * nb      # the body's depth, its moving bodies from the root (itself included)
    for b in order:
        p = fr.parent[b]
        depth[b] = depth[p] + 1 if p >= 0 else 0
        active[b] = (active[p] if p >= 0 else 0) + (J[b] >= 0)
    levels = max(depth) + 1
    src = [looped.structure(fr), looped.table('int', 'SIG', sig), looped.table('int', 'ORD', order),
           looped.table('int', 'AD', active), looped.table('int', 'ZL', [3 * d * (d + 1) for d in depth]),
           looped.table('double', 'K0', [v for k in K for v in k])]
    for i, (rev, fre, root, pat) in enumerate(keys):
        def body(g, x, xd, xdd, Kb, Vp, Ap, rev=rev, fre=fre, root=root, pat=pat):
            Kc = [Kb[k] if v is None else v for k, v in enumerate(pat)]
            X = joint_transform(g, _consts_in(Kc[:30], rev), rev, x[0])
            Sb = (tuple(Kc[30:33]), tuple(Kc[33:36]))
            zero3 = (0.0, 0.0, 0.0)
            vp, ap = ((zero3, zero3), (zero3, tuple(Ap[3:]))) if root else \
                ((tuple(Vp[:3]), tuple(Vp[3:])), (tuple(Ap[:3]), tuple(Ap[3:])))
            V, A = motion(X, Sb, vp, ap, xd[0] if fre else 0.0, xdd[0] if fre else 0.0)
            cols = body_columns(V, A)
            flat = [e for col in cols for part in col for e in part]
            own = project(Sb, cols) if fre else [0.0] * 10
            return [looped.pose_out(X), [*V[0], *V[1]], [*A[0], *A[1]], [flat[k] for k in nz], own]
        src.append(looped.step(f'body{i}', body, (1, 1, 1, 36, 6, 6)))

    poses, psig = looped.classify([_pose_pattern(keys[sig[b]][0], keys[sig[b]][3]) for b in range(nb)])
    src.append(looped.table('int', 'PSIG', psig))
    for i, pose in enumerate(poses):
        def pair(g, Zp, X, C, pose=pose):
            Xc = looped.pose_in([X[k] if c is None else c for k, c in enumerate(pose)])
            Z = screw_to_child((tuple(Zp[:3]), tuple(Zp[3:])), Xc)
            return [[*Z[0], *Z[1]], project(Z, _columns_in(C, nz))]
        src.append(looped.step(f'pair{i}', pair, (6, 12, len(nz))))
    pair_loop = ' '.join(f'case {i}: for (int i = 0; i < na; i++) pair{i}({_PAIR_ARGS}); break;'
                         for i in range(len(poses)))
    body_call = looped.switch('SIG[b]', [f'body{i}' for i in range(len(keys))],
                              '&x, &xd, &xdd, K0 + 36 * b, p >= 0 ? V + 6 * p : ZERO6, p >= 0 ? A + 6 * p : base, '
                              'X + 12 * b, V + 6 * b, A + 6 * b, COLS, yb')
    decl, free = looped.work([('QS', 3 * n), ('X', 12 * nb), ('V', 6 * nb), ('A', 6 * nb),
                              ('Z', 3 * levels * (levels + 1)), ('COLS', len(nz))], n * 10 * nb)
    src.append(f'''
static const double ZERO6[6] = {{0.0, 0.0, 0.0, 0.0, 0.0, 0.0}};

void lie_kernel(const double *const *in, const double *const *par, double *out)
{{
  const double *A0 = par[0], *E0 = par[1];
{decl}  int PJ[NB];           /* the joints of the moving bodies on the current path, from the root */
  double scratch[10];   /* a welded body's own block: no row */
  (void)E0;
  memcpy(QS, in[0], NJ * sizeof(double));   /* before `out` is written: it may alias the inputs */
  memcpy(QS + NJ, in[1], NJ * sizeof(double));
  memcpy(QS + 2 * NJ, in[2], NJ * sizeof(double));
  const double *q = QS, *qd = QS + NJ, *qdd = QS + 2 * NJ;
  const double base[6] = {{0.0, 0.0, 0.0, A0[0], A0[1], A0[2]}};
  memset(out, 0, (size_t)NJ * 10 * NB * sizeof(double));
  for (int o = 0; o < NB; o++) {{
    const int b = ORD[o], p = PAR[b], j = JNT[b];
    const double x = X_OF(q, E0, b), xd = j >= 0 ? qd[j] : 0.0, xdd = j >= 0 ? qdd[j] : 0.0;
    double *const yb = j >= 0 ? out + (size_t)j * 10 * NB + 10 * b : scratch;
    {body_call}
    double *const zb = Z + ZL[b];
    const int na = p >= 0 ? AD[p] : 0;
    switch (PSIG[b]) {{ {pair_loop} }}
    if (j >= 0) {{ memcpy(zb + 6 * na, K0 + 36 * b + 30, 6 * sizeof(double)); PJ[na] = j; }}
  }}
{free}}}
''')
    return looped.rendered(''.join(src), (n, n, n), (3, sum(fr.offset)), n * 10 * nb)


REGRESSOR = Spec('regressor', build_regressor, ('gravity', 'offsets'), 'regressor',
                 result=lambda model: ((model.n, 10 * model.nb), None), rows_chunk='regressor_rows_chunk',
                 looped=looped_regressor)
