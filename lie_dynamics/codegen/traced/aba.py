"""The articulated body algorithm, traced (algorithms/aba.py gives the recursion).

The recursion as straight-line code, in the primed body frames of codegen/frames.py
(S_i = e_z) turned about and shifted along their joint axes into modified
Denavit-Hartenberg frames (x along the common normal to one child's axis), where a joint
transform is Rx(alpha) T(a, 0, d) Rz(x + theta): four constants instead of a rotation and
an offset, which on random chains takes a third of the operations away (_Geometry).
Articulated inertias are general symmetric 6x6 matrices [[A, B], [B^T, C]] (angular rows
first, like twists (w, v) and wrenches (n, f)), traced as nested lists. The source is O(n)
(unlike the O(n^2) CRBA and Cholesky kernels), hence the higher size cap in THRESHOLDS.
"""
import math

import numpy as np

from .. import algebra as la
from .. import looped, runtime
from ..kernel import Trace
from ..runtime import Spec
from ..thresholds import PD_RTOL
from ..tracer import SNAP, Graph, Sym, snap
from ...spatial import hat3

_PLANE = {'z': (0, 1, 2), 'x': (1, 2, 0)}   # a rotation about the third index turns the first two


def _rot_np(axis, c, s):
    i0, i1, i2 = _PLANE[axis]
    R = np.zeros((3, 3))
    R[i0, i0] = R[i1, i1] = c
    R[i1, i0], R[i0, i1] = s, -s
    R[i2, i2] = 1.0
    return R


def _trivial(c, s):
    """A quarter turn (or none): its products fold away when traced."""
    return c in (0.0, 1.0, -1.0) and s in (0.0, 1.0, -1.0)


def _decompose(R, t):
    """(R, t) = Rz(psi) Rx(alpha) T(s) Rz(theta), s = (s_x, s_y, s_z), up to rounding.

    Returns dict psi, alpha, theta (each (cos, sin)) and s, or None if the factors do not
    reproduce (R, t) to 1e-12.
    """
    u = R[:, 2]
    sa = math.hypot(u[0], u[1])
    if sa < SNAP:
        cp, sp, sa, ca = 1.0, 0.0, 0.0, math.copysign(1.0, u[2])
    else:
        cp, sp, ca = -u[1] / sa, u[0] / sa, u[2]
    cp, sp, ca, sa = snap([cp, sp, ca, sa]).tolist()
    Rpa = _rot_np('z', cp, sp) @ _rot_np('x', ca, sa)
    W = Rpa.T @ R
    r = math.hypot(W[0, 0], W[1, 0])
    ct, st = snap([W[0, 0] / r, W[1, 0] / r]).tolist()
    s = snap(Rpa.T @ t)
    if (np.max(np.abs(Rpa @ _rot_np('z', ct, st) - R)) > 1e-12
            or np.max(np.abs(Rpa @ s - t)) > 1e-12 * max(1.0, float(np.max(np.abs(t))))):
        return None
    return dict(psi=(cp, sp), alpha=(ca, sa), theta=(ct, st), s=tuple(float(v) for v in s))


def _cost(dec):
    """Rough traced cost of a decomposed joint transform (for choosing frames)."""
    if dec is None:
        return 1e9
    return (20 * (not _trivial(*dec['psi'])) + 20 * (not _trivial(*dec['alpha']))
            + 10 * sum(v != 0.0 for v in dec['s']) + (not _trivial(*dec['theta'])))


def _dh_candidates(R, t):
    """Poses (Rz(phi), (0, 0, d)) of a frame turned about and shifted along z so that its x axis
    is the common normal from the z axis to the axis of a child joint at (R, t)."""
    u = R[:, 2]
    nxy = math.hypot(u[0], u[1])
    if nxy > 1e-6:
        cp, sp = -u[1] / nxy, u[0] / nxy
        d = (t[2] - u[2] * float(u @ t)) / (nxy * nxy)   # foot of the common normal on z
        # a foot far away (nearly parallel axes) would put the inertias about a far point
        ds = [d, 0.0] if abs(d) <= 2.0 * float(np.linalg.norm(t)) else [0.0]
    else:   # parallel axes: x towards the other axis, any foot
        r = math.hypot(t[0], t[1])
        if r < 1e-12:
            return []
        cp, sp, ds = t[0] / r, t[1] / r, [0.0]
    cp, sp = snap([cp, sp]).tolist()
    return [(_rot_np('z', cp, sp), np.array([0.0, 0.0, float(d)])) for d in ds]


class _Geometry:
    """Build-time constants of the ABA kernel: the frame b'' of each body and its joint steps.

    Frame b'' = b' Rz(phi_b) Tz(d_b) (pose T_b in b'); both factors commute with the motion of
    joint b, so f_{p'',b''}(x) = T_p^-1 M'_b T_b Z(x), and the inertias and wrenches are moved
    to b'' at run time (params, wrenches). T_b is chosen among the identity and the modified
    Denavit-Hartenberg frames towards each child, for the cheapest transforms of the children
    (ties keep the identity: quarter-turn frames such as the arm's are already cheap).
    steps[b]: f_{p'',b''}(0) decomposed by _decompose.
    """

    def __init__(self, fr):
        nb = fr.nb
        M = [(np.array(fr.R[b]), np.array(fr.t[b])) for b in range(nb)]
        eye = (np.eye(3), np.zeros(3))

        def rel(Tp, b):   # T_p^-1 M'_b (T_b is absorbed in theta and s_z)
            (Rp, pp), (R, t) = Tp, M[b]
            return Rp.T @ R, Rp.T @ (t - pp)
        self.T = []
        for b in range(nb):
            kids = fr.children[b]
            cands = [eye] + [c for k in kids for c in _dh_candidates(*M[k])]
            self.T.append(min(cands, key=lambda T: sum(_cost(_decompose(*rel(T, k))) for k in kids)))
        self.steps = []
        self.ok = True
        for b in range(nb):
            p = fr.parent[b]
            R, t = rel(self.T[p] if p >= 0 else eye, b)
            Rb, pb = self.T[b]
            R, t = R @ Rb, R @ pb + t          # ... T_b
            dec = _decompose(R, t)
            if dec is None:
                self.ok = False
                return
            self.steps.append(dec)
        self.Tinv = [(Rb.T, -(Rb.T @ pb)) for Rb, pb in self.T]
        self.Rinv = np.array([R for R, _ in self.Tinv]).reshape(nb, 3, 3)
        self.tinv = np.array([t for _, t in self.Tinv]).reshape(nb, 3)
        # wrenches (n, f) of body frame b to b'': (G n + t x G f, G f) with G = R Q_b^T, (R, t) = T_b^-1
        self.W = np.zeros((nb, 6, 6))
        for b, (R, t) in enumerate(self.Tinv):
            G = R @ fr.Q[b].T
            self.W[b, :3, :3] = self.W[b, 3:, 3:] = G
            self.W[b, :3, 3:] = hat3(t) @ G

    def params(self, P):
        """Inertia parameters of the primed frames (Frames.inertia_params) in the b''
        frames: algebra.inertia_to_parent with f_{b'',b'} = T_b^-1, for all bodies at once."""
        A = np.asarray(P, dtype=float).reshape(-1, 10)
        m, h = A[:, 0], A[:, 1:4]
        Io = A[:, [4, 5, 6, 5, 7, 8, 6, 8, 9]].reshape(-1, 3, 3)
        R, t = self.Rinv, self.tinv
        Rh = np.einsum('bij,bj->bi', R, h)
        tRh = t[:, :, None] * Rh[:, None, :]
        Ip = (R @ Io @ np.swapaxes(R, 1, 2) - m[:, None, None] * (t[:, :, None] * t[:, None, :])
              - tRh - np.swapaxes(tRh, 1, 2)
              + (m * np.sum(t * t, axis=1) + 2.0 * np.sum(t * Rh, axis=1))[:, None, None] * np.eye(3))
        out = np.column_stack([m, Rh + m[:, None] * t, Ip[:, 0, 0], Ip[:, 0, 1], Ip[:, 0, 2], Ip[:, 1, 1],
                               Ip[:, 1, 2], Ip[:, 2, 2]])
        return out.reshape(-1).tolist()

    def wrenches(self, fext):
        """(N, nb, 6) body-frame wrenches -> (N, 6 nb) in the b'' frames."""
        return np.einsum('bij,nbj->nbi', self.W, fext).reshape(len(fext), -1)


def _sym6_rigid(ic):
    """A rigid inertia (m, h, I) as the 6x6 [[I, [h]], [-[h], m 1]]."""
    m, h, Io = ic
    A = ((Io[0], Io[1], Io[2]), (Io[1], Io[3], Io[4]), (Io[2], Io[4], Io[5]))
    B = ((0.0, -h[2], h[1]), (h[2], 0.0, -h[0]), (-h[1], h[0], 0.0))
    C = ((m, 0.0, 0.0), (0.0, m, 0.0), (0.0, 0.0, m))
    return _sym6_blocks(A, B, C)


def _sym6_blocks(A, B, C):
    K = [[None] * 6 for _ in range(6)]
    for i in range(3):
        for j in range(3):
            K[i][j] = A[i][j]
            K[i][j + 3] = K[j + 3][i] = B[i][j]
            K[i + 3][j + 3] = C[i][j]
    return K


def _split(K):
    return ([K[i][:3] for i in range(3)], [K[i][3:] for i in range(3)], [K[i][3:] for i in range(3, 6)])


def _sym6_add(K, L):
    out = [[None] * 6 for _ in range(6)]
    for i in range(6):
        for j in range(i, 6):
            out[i][j] = out[j][i] = K[i][j] + L[i][j]
    return out


class _Rot:
    """A rotation about a coordinate axis by (c, s) (traced or constant), and the products its
    congruences share: s^2, cs, 2cs, 2s^2."""

    def __init__(self, g, axis, c, s):
        self.i = _PLANE[axis]
        self.c, self.s = c, s
        self.ss, self.cs = s * s, c * s
        self.s2, self.ss2 = g.bake(2.0 * self.cs), g.bake(2.0 * self.ss)
        const = not isinstance(c, Sym) and not isinstance(s, Sym)
        self.perm = tuple(map(tuple, _rot_np(axis, c, s).tolist())) if const and _trivial(c, s) else None

    def vec(self, v, sign=1.0):
        """R v (sign -1: R^T v) for a 3-vector."""
        i0, i1, _ = self.i
        s = sign * self.s
        out = list(v)
        out[i0] = self.c * v[i0] - s * v[i1]
        out[i1] = s * v[i0] + self.c * v[i1]
        return out

    def block(self, M, sym):
        """R M R^T of a 3x3 block. The corner in the turning plane takes 4 products: its
        symmetric part turns at twice the angle, b01 - b10 is invariant."""
        i0, i1, i2 = self.i
        if self.perm is not None:   # a quarter turn: a signed relabelling
            R = self.perm
            return [[la.dot(la.mat_vec(M, R[c]), R[r]) for c in range(3)] for r in range(3)]
        b00, b01 = M[i0][i0], M[i0][i1]
        b10, b11 = M[i1][i0], M[i1][i1]
        dd = b00 - b11
        if sym:
            e1 = dd * self.ss + b01 * self.s2
            e2 = dd * self.cs - b01 * self.ss2
        else:
            sb = b01 + b10
            e1 = dd * self.ss + sb * self.cs
            e2 = dd * self.cs - sb * self.ss
        out = [list(r) for r in M]
        out[i0][i0], out[i1][i1] = b00 - e1, b11 + e1
        out[i0][i1], out[i1][i0] = b01 + e2, b10 + e2
        col = self.vec([M[k][i2] for k in range(3)])
        out[i0][i2], out[i1][i2] = col[i0], col[i1]
        row = self.vec([M[i2][k] for k in range(3)]) if not sym else col
        out[i2][i0], out[i2][i1] = row[i0], row[i1]
        return out

    def sym6(self, K):
        A, B, C = _split(K)
        return _sym6_blocks(self.block(A, True), self.block(B, False), self.block(C, True))


def _sym6_translate(K, t):
    """T K T^T, T = [[1, [t]], [0, 1]]: an inertia about frame b moved to frame a, with b at
    a-position t and the same orientation (X^T K X for f_ab = (1, t)).

    B' = B + [t] C,  A' = A + B [t]^T + [t] B'^T  (row i of B [t]^T is t x (row i of B)).
    """
    A, B, C = _split(K)
    tC = [la.cross(t, C[j]) for j in range(3)]                 # column j of [t] C
    Bp = [[B[i][j] + tC[j][i] for j in range(3)] for i in range(3)]
    P = [la.cross(t, B[i]) for i in range(3)]
    Q = [la.cross(t, Bp[i]) for i in range(3)]
    Ap = [[None] * 3 for _ in range(3)]
    for i in range(3):
        for j in range(i, 3):
            Ap[i][j] = Ap[j][i] = A[i][j] + P[i][j] + Q[j][i]
    return _sym6_blocks(Ap, Bp, C)


class _Joint:
    """Traced X_i = Ad_{f^-1} for f = f_{p'',b''}(x) (see _Geometry) as a product of steps from
    the child side: rotations about z or x and translations."""

    def __init__(self, g, dec, revolute, x, cs=None):
        """dec: _decompose's factors (constants, or symbols in a looped step); x: the joint
        coordinate; cs: (cos, sin) of x + theta when known (a looped step's registers)."""
        ct, st = dec['theta']
        sx, sy, sz = dec['s']
        steps = []
        if revolute:   # Rz(theta) Rz(x): a quarter turn folds into cos x, sin x; else cos(x + theta)
            if cs is not None:
                c, s = cs
            elif _trivial(ct, st) or not isinstance(x, Sym):
                c, s = g.cos(x), g.sin(x)
                c, s = ct * c - st * s, st * c + ct * s
            else:
                c, s = g.cos(x + math.atan2(st, ct)), g.sin(x + math.atan2(st, ct))
            steps.append(_Rot(g, 'z', c, s))
            steps.append((sx, sy, sz))
        else:
            steps.append((0.0, 0.0, x + sz))
            steps.append(_Rot(g, 'z', ct, st))
            steps.append((sx, sy, 0.0))
        steps.append(_Rot(g, 'x', *dec['alpha']))
        steps.append(_Rot(g, 'z', *dec['psi']))
        # drop identities
        self.steps = [s for s in steps if (isinstance(s, _Rot) and not (s.c == 1.0 and s.s == 0.0))
                      or (isinstance(s, tuple) and any(isinstance(v, Sym) or v != 0.0 for v in s))]

    def inertia_to_parent(self, K):
        """X^T K X."""
        for st in self.steps:
            K = st.sym6(K) if isinstance(st, _Rot) else _sym6_translate(K, st)
        return K

    def wrench_to_parent(self, F):
        """X^T F: (n, f) -> (R n + t x R f, R f), step by step."""
        n_, f_ = list(F[:3]), list(F[3:])
        for st in self.steps:
            if isinstance(st, _Rot):
                n_, f_ = st.vec(n_), st.vec(f_)
            else:
                n_ = la.vadd(n_, la.cross(st, f_))
        return list(n_) + list(f_)

    def twist_to_child(self, V):
        """X V: (w, v) -> (R^T w, R^T (v - t x w)), step by step."""
        w, v = list(V[:3]), list(V[3:])
        for st in reversed(self.steps):
            if isinstance(st, _Rot):
                w, v = st.vec(w, -1.0), st.vec(v, -1.0)
            else:
                v = la.vsub(v, la.cross(st, w))
        return list(w) + list(v)


def trace_aba(fr, geom, g, x, xd, taus, params, a0, armature, fext=None):
    """The articulated body algorithm of algorithms/aba.py (eqs 17-19), traced in the b''
    frames of `geom`, where S_i = e_z: U_i = Ia_i S_i is column k of Ia_i (k = 2 for a revolute
    joint, 5 for a prismatic one), D_i = its entry k + the joint's armature and u_i = tau_i -
    (pa_i)_k, as Pinocchio's aba. The update Ia - U U^T / D has row and column k equal to
    armature_i U_i / D_i, zero where the armature is the constant 0.0: the rigid variant
    (build_aba(armature=False)) folds those terms away, the armature as a parameter costs the
    kernel more operations on the arm whatever its value (`spec` picks the variant).

    x, xd: body coordinates and rates; taus: per body the torque of its joint (0.0 for welded
    bodies); params: per body (m, h, I) in b''; a0: base linear acceleration -g; armature: per
    body the armature of its joint (0.0 for welded bodies); fext: optional per-body wrenches
    (n, f) in b''. Returns per body (xdd_i, D_i, scale_i), None for welded bodies;
    scale_i is the trace of the 3x3 block of Ia_i that D_i lies in plus the armature (same
    units as D_i, and >= D_i for a positive semi-definite Ia_i).

    Three passes over the bodies, each one step per body (`velocity`, `articulate` then
    `to_parent`, `acceleration`): the looped native form (`looped_aba`) renders the same steps.
    """
    nb = fr.nb
    free = [bool(np.any(fr.E[b] != 0)) for b in range(nb)]
    X = [_Joint(g, geom.steps[b], fr.revolute[b], x[b]) for b in range(nb)]
    kk = [2 if fr.revolute[b] else 5 for b in range(nb)]
    V, c = [None] * nb, [None] * nb
    for b in range(nb):                                          # eq 18
        p = fr.parent[b]
        V[b], c[b] = velocity(X[b], V[p] if p >= 0 else None, xd[b], kk[b])
    Ia, pa = [None] * nb, [None] * nb
    piv = [None] * nb
    for b in reversed(range(nb)):
        p = fr.parent[b]
        K, P, piv[b] = articulate(g, free[b], kk[b], params[b], V[b], c[b], Ia[b], pa[b], taus[b], armature[b],
                                  None if fext is None else fext[b], p < 0)
        if p >= 0:
            Ia[p], pa[p] = to_parent(X[b], K, P, Ia[p], pa[p])
    acc = [None] * nb
    base = [0.0, 0.0, 0.0] + list(a0)
    res = [None] * nb
    for b in range(nb):                                          # eq 19
        p = fr.parent[b]
        acc[b], xdd = acceleration(X[b], acc[p] if p >= 0 else base, c[b], kk[b], piv[b])
        if free[b]:
            res[b] = (xdd,) + piv[b][3]
    return res


# The steps of the ABA, per body (trace_aba and the looped form, looped_aba, both call them).
def velocity(X, Vp, xd, k):
    """Eq 18 for one body: (V_i, c_i = [V_i, S_i xd_i]) from its parent's twist Vp (None at a root)."""
    Vp = X.twist_to_child(Vp) if Vp is not None else [0.0] * 6
    V = list(Vp)
    V[k] = Vp[k] + xd
    # c = [V, S xd]: xd (w x e_z, v x e_z) (revolute) or xd (0, w x e_z) (prismatic)
    if k == 2:
        return V, [Vp[1] * xd, -(Vp[0] * xd), 0.0, Vp[4] * xd, -(Vp[3] * xd), 0.0]
    return V, [0.0, 0.0, 0.0, Vp[1] * xd, -(Vp[0] * xd), 0.0]


def articulate(g, free, k, params, V, c, Ia, pa, tau, armature, fext, root):
    """The backward step of one body: its articulated inertia and bias (Ia, pa: what its children
    passed, None for none), its pivot, and what it passes to its parent. Returns (K, P, piv): K,
    P the inertia and wrench for the parent (None at a root), piv (U / D, 1 / D, u, (D, scale))
    of a free joint, None for a welded body."""
    w, v = tuple(V[:3]), tuple(V[3:])
    n_, f_ = la.ad_t((w, v), la.inertia_times(params, (w, v)))
    own = [-e for e in n_ + f_]                              # bias wrench -ad_V^T J V
    if fext is not None:
        own = [a - e for a, e in zip(own, fext[0] + fext[1], strict=True)]
    P = own if pa is None else [a + e for a, e in zip(pa, own, strict=True)]
    K = _sym6_rigid(params)
    if Ia is not None:
        K = _sym6_add(Ia, K)
    if not free:
        return (None, None, None) if root else (K, [P[i] + la.dot(K[i], c) for i in range(6)], None)
    col = [K[i][k] for i in range(6)]
    D = col[k] + armature
    Dinv = g.inv(D)
    u = tau - P[k]
    U = [g.bake(col[i] * Dinv) for i in range(6)]                      # U / D
    piv = (U, Dinv, u, (D, K[k - 2][k - 2] + K[k - 1][k - 1] + D))
    if root:
        return None, None, piv
    Ka = [[0.0] * 6 for _ in range(6)]
    for i in range(6):
        for j in range(i, 6):
            if i != k and j != k:
                Ka[i][j] = Ka[j][i] = K[i][j] - col[i] * U[j]
    w = armature * Dinv    # row k of Ia^A: col - col col[k] / D = armature col / D
    for j in range(6):
        Ka[k][j] = Ka[j][k] = col[j] * w
    P = [P[i] + la.dot(Ka[i], c) + U[i] * u for i in range(6)]    # pa + Ia^A c + U u / D
    return Ka, P, piv


def to_parent(X, K, P, Ia, pa):
    """The parent's (Ia, pa) (None: nothing yet) plus a child's K and P moved to the parent frame."""
    Kp = X.inertia_to_parent(K)
    Pp = X.wrench_to_parent(P)
    return (Kp if Ia is None else _sym6_add(Ia, Kp),
            Pp if pa is None else [a + e for a, e in zip(pa, Pp, strict=True)])


def acceleration(X, ap, c, k, piv):
    """Eq 19 for one body: (a_i, xdd_i) from the parent's acceleration ap (the base's at a root);
    piv None (welded): xdd None."""
    ap = X.twist_to_child(ap)
    ap = [a + e for a, e in zip(ap, c, strict=True)]
    if piv is None:
        return ap, None
    U, Dinv, u, _ = piv
    xdd = u * Dinv
    for i in range(6):
        xdd = xdd - U[i] * ap[i]                      # xdd = (u - U^T a') / D
    ap[k] = ap[k] + xdd                                  # a = a' + S xdd
    return ap, xdd


def build_aba(fr, wrench=False, armature=True):
    """Trace qdd by the articulated body algorithm (trace_aba) for this tree.

    Arguments (Q, QD, TAU[, FX], P, A0, E0, AR) as the Cholesky kernel's, but P and FX in the
    frames of _Geometry (its params and wrenches). armature=False: the rigid variant, without
    AR, the armature the constant 0.0 (the same trace with its terms folded away). Outputs qdd,
    then per joint D_i and its scale (trace_aba); the caller checks D_i > PD_RTOL * scale, blind to the scale of the
    masses as the Cholesky kernel's pivot test. None when the frames cannot be built.
    """
    geom = _Geometry(fr)
    if not geom.ok:
        return None
    g = Graph()
    co = fr.trace_coordinates(g, rates=1)
    parg, params = fr.trace_params(g)
    a0arg, ga = fr.trace_gravity(g)
    n, nb = fr.n, fr.nb
    taus = [g.input(f'u{j}') for j in range(n)]
    joint_of = [None] * nb
    for b in range(nb):
        for j in range(n):
            if fr.E[b, j] != 0:
                joint_of[b] = j
    args = co['args'] + [('TAU', [f'u{j}' for j in range(n)])]
    fext = None
    if wrench:   # per-state arguments first, then the parameters
        names = [f'f{b}_{k}' for b in range(nb) for k in range(6)]
        args.append(('FX', names))
        fs = [g.input(nm) for nm in names]
        fext = [(tuple(fs[6 * b:6 * b + 3]), tuple(fs[6 * b + 3:6 * b + 6])) for b in range(nb)]
    args += [parg, a0arg, co['offset_args']]
    if armature:
        ararg, arm = fr.trace_armature(g)
        args.append(ararg)
    else:
        arm = [0.0] * n
    res = trace_aba(fr, geom, g, co['x'], co['xd'], [0.0 if j is None else taus[j] for j in joint_of],
                    params, ga, [0.0 if j is None else arm[j] for j in joint_of], fext)
    per_joint = [None] * n
    for b in range(nb):
        if joint_of[b] is not None:
            per_joint[joint_of[b]] = res[b]
    outputs = [r[i] for i in range(3) for r in per_joint]
    return Trace(g, 'aba_kernel', args, outputs)


def _looped_consts(dec):
    """A body's 12 constants in a looped step (the driver's stride): psi, alpha, theta (cos, sin
    each), s, theta's angle, a pad."""
    ct, st = dec['theta']
    out = [*dec['psi'], *dec['alpha'], ct, st, *dec['s'], math.atan2(st, ct), 0.0, 0.0]
    assert len(out) == 12
    return out


def _looped_key(rev, free, root, dec):
    """A body's step signature: joint kind, free or welded, root, and which of its constants are
    exact (a rotation by zero, a zero offset: folded as in the straight-line trace)."""
    return (rev, free, root, dec['psi'] == (1.0, 0.0), dec['alpha'] == (1.0, 0.0),
            dec['theta'] == (1.0, 0.0), *(v == 0.0 for v in dec['s']))


def _looped_dec(key, K):
    """_decompose's factors as a looped step sees them: symbols K, constants where the key says."""
    _, _, _, psi, alpha, theta, s0, s1, s2 = key
    return dict(psi=(1.0, 0.0) if psi else (K[0], K[1]), alpha=(1.0, 0.0) if alpha else (K[2], K[3]),
                theta=(1.0, 0.0) if theta else (K[4], K[5]),
                s=tuple(0.0 if z else K[6 + i] for i, z in enumerate((s0, s1, s2))))


def _looped_steps(g, key, K, JT):
    """The joint (_Joint) of a looped step from its registers JT: (cos, sin) of x + theta for a
    revolute joint, (x, -) for a prismatic one."""
    rev = key[0]
    return _Joint(g, _looped_dec(key, K), rev, JT[0], (JT[0], JT[1]) if rev else None)


def looped_aba(fr, armature=True):
    """The looped native form of the ABA kernels (codegen/looped.py): trace_aba's three passes, one
    step per body and pass (`velocity`; `articulate` then `to_parent`; `acceleration`), rendered
    once per step signature (_looped_key). Same arguments and outputs as build_aba(fr, False,
    armature). None for mimic joints or frames that cannot be built."""
    J = looped.joints_of(fr)
    geom = _Geometry(fr)
    if J is None or not geom.ok:
        return None
    nb, n = fr.nb, fr.n
    free = [j >= 0 for j in J]
    keys, sig = looped.classify([_looped_key(fr.revolute[b], free[b], fr.parent[b] < 0, geom.steps[b])
                                 for b in range(nb)])
    src = [looped.structure(fr), looped.table('int', 'SIG', sig),
           looped.table('double', 'K0', [v for b in range(nb) for v in _looped_consts(geom.steps[b])])]
    for i, key in enumerate(keys):
        rev, fre, root = key[:3]
        k = 2 if rev else 5

        def vel(g, x, xd, K, Vp, key=key, rev=rev, fre=fre, root=root, k=k):
            JT = [g.cos(x[0] + K[9]), g.sin(x[0] + K[9])] if rev else [x[0], 0.0]
            V, c = velocity(_looped_steps(g, key, K, JT), None if root else Vp, xd[0] if fre else 0.0, k)
            return [JT, V, c]

        def back(g, P, V, c, Ia, pa, tau, ar, K, JT, Iap, pap, fre=fre, root=root, key=key, k=k):
            params = (P[0], tuple(P[1:4]), tuple(P[4:10]))
            Ka, Pa, piv = articulate(g, fre, k, params, V, c, looped.sym6_in(Ia), pa, tau[0] if fre else 0.0,
                                     ar[0] if fre and armature else 0.0, None, root)
            out = [[], [], [], []]
            if piv is not None:
                out[0], out[1] = list(piv[0]) + [piv[1], piv[2]], list(piv[3])
            if not root:
                Iap, pap = to_parent(_looped_steps(g, key, K, JT), Ka, Pa, looped.sym6_in(Iap), pap)
                out[2], out[3] = looped.sym6_out(Iap), list(pap)
            return out

        def acc(g, K, JT, ap, c, piv, key=key, fre=fre, root=root, k=k):
            base = [0.0, 0.0, 0.0] + list(ap[:3]) if root else ap
            a, xdd = acceleration(_looped_steps(g, key, K, JT), base, c, k,
                                  (piv[:6], piv[6], piv[7], None) if fre else None)
            return [a, [xdd] if fre else []]
        src.append(looped.step(f'vel{i}', vel, (1, 1, 12, 6)))
        src.append(looped.step(f'back{i}', back, (10, 6, 6, 21, 6, 1, 1, 12, 2, 21, 6)))
        src.append(looped.step(f'acc{i}', acc, (12, 2, 6, 6, 8)))

    def sw(name, call):
        return looped.switch('SIG[b]', [f'{name}{i}' for i in range(len(keys))], call)
    vel_call = sw('vel', '&x, &xd, K0 + 12 * b, V + 6 * up, JT + 2 * b, V + 6 * b, C + 6 * b')
    back_call = sw('back', 'P + 10 * b, V + 6 * b, C + 6 * b, IA + 21 * b, PA + 6 * b, &t, &ar, K0 + 12 * b, '
                           'JT + 2 * b, IA + 21 * up, PA + 6 * up, UD + 8 * b, ds, IA + 21 * up, PA + 6 * up')
    acc_call = sw('acc', 'K0 + 12 * b, JT + 2 * b, PAR[b] >= 0 ? ACC + 6 * up : A0, C + 6 * b, UD + 8 * b, '
                         'ACC + 6 * b, &xdd')
    ar = 'JNT[b] >= 0 ? AR[JNT[b]] : 0.0' if armature else '0.0'
    decl, free = looped.work([(a, w * nb) for a, w in (('JT', 2), ('V', 6), ('C', 6), ('IA', 21), ('PA', 6), ('UD', 8),
                                                       ('ACC', 6))] + [('OUT', 3 * n)], 3 * n)
    src.append(f'''
void lie_kernel(const double *const *in, const double *const *par, double *out)
{{
  const double *q = in[0], *qd = in[1], *tau = in[2], *P = par[0], *A0 = par[1], *E0 = par[2];
  {'const double *AR = par[3];' if armature else ''}
{decl}  (void)E0;
  memset(IA, 0, 21 * NB * sizeof(double));
  memset(PA, 0, 6 * NB * sizeof(double));
  for (int b = 0; b < NB; b++) {{
    const int up = PAR[b] >= 0 ? PAR[b] : 0;
    const double x = X_OF(q, E0, b), xd = JNT[b] >= 0 ? qd[JNT[b]] : 0.0;
    {vel_call}
  }}
  for (int b = NB - 1; b >= 0; b--) {{
    const int up = PAR[b] >= 0 ? PAR[b] : 0;
    const double t = JNT[b] >= 0 ? tau[JNT[b]] : 0.0, ar = {ar};
    double ds[2] = {{0.0, 0.0}};
    {back_call}
    if (JNT[b] >= 0) {{ OUT[NJ + JNT[b]] = ds[0]; OUT[2 * NJ + JNT[b]] = ds[1]; }}
  }}
  for (int b = 0; b < NB; b++) {{
    const int up = PAR[b] >= 0 ? PAR[b] : 0;
    double xdd = 0.0;
    {acc_call}
    if (JNT[b] >= 0) OUT[JNT[b]] = xdd;
  }}
  memcpy(out, OUT, 3 * NJ * sizeof(double));   /* after every read of the inputs: out may alias them */
{free}}}
''')
    pars = (10 * nb, 3, sum(fr.offset)) + ((n,) if armature else ())
    return looped.rendered(''.join(src), (n, n, n), pars, 3 * n)


def supports(model):
    """True when every joint moves exactly one body with multiplier 1 (no mimic joints, which
    couple bodies: the recursion cannot express them)."""
    def compute():
        nz = model.E != 0
        return bool(np.all(nz.sum(axis=1) <= 1) and np.all(model.E[nz] == 1.0) and np.all(nz.sum(axis=0) == 1))
    return runtime.structural(model, 'one_body_per_joint', compute)


def _geometry(model):
    """The kernel's frames (_Geometry) of this model's structure, without tracing."""
    return runtime.structural(model, 'aba_geometry', lambda: _Geometry(runtime.frames(model)))


def _inertias(model):
    """The inertia parameters in the kernel's frames (_Geometry.params)."""
    return tuple(_geometry(model).params(runtime.parameter(model, 'inertia')))


def wrenches(model, fext):
    """(N, nb, 6) body-frame wrenches -> the FX argument of the kernels (their frames)."""
    return _geometry(model).wrenches(fext)


ABA = Spec('aba', lambda fr: build_aba(fr, False), (_inertias, 'gravity', 'offsets', 'armature'), 'aba',
           supports=supports, checked=True, result=lambda model: ((model.n,), PD_RTOL), looped=looped_aba)
ABA_WRENCH = Spec('aba_wrench', lambda fr: build_aba(fr, True), (_inertias, 'gravity', 'offsets', 'armature'),
                  'aba', supports=supports, checked=True, result=lambda model: ((model.n,), PD_RTOL))
# The rigid variants, for a model whose armature is all zero (the default): the same trace with
# the armature the constant 0.0, which folds its terms away (bench/probes/aba_armature.py).
ABA_RIGID = Spec('aba_rigid', lambda fr: build_aba(fr, False, False), (_inertias, 'gravity', 'offsets'), 'aba',
                 supports=supports, checked=True, result=lambda model: ((model.n,), PD_RTOL),
                 looped=lambda fr: looped_aba(fr, False))
ABA_WRENCH_RIGID = Spec('aba_wrench_rigid', lambda fr: build_aba(fr, True, False), (_inertias, 'gravity', 'offsets'),
                        'aba', supports=supports, checked=True, result=lambda model: ((model.n,), PD_RTOL))


def spec(model, wrench=False):
    """The ABA kernel for this model: the rigid variant while its armature is all zero (cached
    until the model's version changes, which set_armature bumps)."""
    rigid = runtime.derived(model, 'armature_zero', lambda: not model.armature.any())
    if wrench:
        return ABA_WRENCH_RIGID if rigid else ABA_WRENCH
    return ABA_RIGID if rigid else ABA
