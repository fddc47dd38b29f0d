"""The inertial-parameter regressor, traced (the body columns K_i of algorithms/regressor.py).

Works in the URDF body frames, not codegen's primed frames, so the columns are already
those of the parameters about the body frame. In primed frames the constant 10x10 map of
the parameters (m, Q^T h, Q^T I Q) would be folded into every (body, ancestor) block: the
same operation count for coordinate-axis joints (the arm), 7-50% more for general axes
(counted on the test robots), while here only a few products per body are added (the axis
is not e_z).
"""
from .. import algebra as la
from ..kernel import Trace
from ..runtime import Spec
from ..tracer import Graph, Sym, snap
from ...spatial import hat3


def _tuple3(a):
    return tuple(float(v) for v in a)


def _joint_transform(g, M, S, revolute, x):
    """(R, t) of f_{p,b}(x) = M exp([S] x) in the URDF body frames, traced.

    Revolute (axis u through the frame origin): R = M_R (1 + sin x [u] + (1 - cos x) [u]^2),
    t = M_p (eqs 10-12); prismatic (direction u): R = M_R, t = M_p + x M_R u. The constant
    matrices are folded into each entry, a form a + b sin x + c cos x.
    """
    MR, Mp = M[:3, :3], M[:3, 3]
    if revolute:
        u = S[:3]
        K1 = snap(MR @ hat3(u))
        K2 = snap(K1 @ hat3(u))
        C0 = snap(MR + K2)
        c, s = g.cos(x), g.sin(x)
        R = tuple(tuple(float(C0[r, k]) + float(K1[r, k]) * s - float(K2[r, k]) * c for k in range(3))
                  for r in range(3))
        return R, _tuple3(snap(Mp))
    d = snap(MR @ S[3:])
    return tuple(_tuple3(row) for row in snap(MR)), tuple(float(o) + float(dk) * x for o, dk in
                                                             zip(snap(Mp), d, strict=True))


def _body_columns(V, A):
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
        R, t = _joint_transform(g, M[b], S[b], fr.revolute[b], x[b])
        Sb = (_tuple3(S[b, :3]), _tuple3(S[b, 3:]))
        Vp, Ap = (V[p], A[p]) if p >= 0 else ((zero3, zero3), (zero3, tuple(a0)))
        Sxd = la.twist_scale(xd[b], Sb)
        V[b] = la.twist_add(la.twist_to_child(Vp, R, t), Sxd)                                 # eq 18
        A[b] = la.twist_add(la.twist_add(la.twist_to_child(Ap, R, t), la.twist_scale(xdd[b], Sb)),
                            la.bracket(V[b], Sxd))                                              # eq 19
        cols = _body_columns(V[b], A[b])
        Z[b] = {b: Sb}
        k = b
        while k >= 0:
            if k != b:
                Z[b][k] = la.twist_to_child(Z[p][k], R, t)
            Y[k][b] = [la.dot6(Z[b][k], col) for col in cols]
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


REGRESSOR = Spec('regressor', build_regressor, ('gravity', 'offsets'), 'regressor',
                 result=lambda model: ((model.n, 10 * model.nb), None), rows_chunk='regressor_rows_chunk')
