"""Extended-precision references for the benchmarks and the stability tests.

Errors are measured against the same algorithms evaluated in numpy.longdouble (x86-64: 80-bit
extended, eps = 1.1e-19, ~1000x finer than float64). The model's float64 constants (M_i, S_i,
J_i, gravity) and the float64 inputs are taken as exact, so the reference answers "what would
exact arithmetic give on these numbers". `Generic` is the RNEA of paper eqs 16-21 (and an
articulated-body forward dynamics) written once for any numpy dtype: longdouble for references,
clongdouble for complex-step reference derivatives, float32 / complex128 as benchmarked methods
of their own.
"""
import numpy as np

from lie_dynamics.spatial import cross, hat3

LD = np.longdouble


def _mv(R, v):
    return np.einsum('...ij,...j->...i', R, v)


def _mtv(R, v):
    return np.einsum('...ji,...j->...i', R, v)


class Generic:
    """Paper eqs 16-21 (body frames, one body at a time, vectorised over states) in any dtype.

    Complex dtypes are supported (nothing is conjugated), which gives complex-step derivatives.
    The constants are the model's float64 arrays converted exactly to the working precision.
    """

    def __init__(self, model, dtype=LD):
        self.dtype = np.dtype(dtype)
        real = np.zeros(0, self.dtype).real.dtype
        self.n, self.nb = model.n, model.nb
        self.parent = model.parent.copy()
        self.E, self.e0 = model.E.astype(real), model.e0.astype(real)
        self.MR, self.Mp = model.M[:, :3, :3].astype(real), model.M[:, :3, 3].astype(real)
        self.S, self.J = model.S.astype(real), model.J.astype(real)
        self.g = model.gravity_vector.astype(real)
        w = self.S[:, :3]
        self.theta = np.sqrt(np.sum(w * w, axis=1))           # |w| in working precision (1 for URDF joints)
        self.K = hat3(w)
        self.K2 = self.K @ self.K
        self.Kv = _mv(self.K, self.S[:, 3:])
        self.K2v = _mv(self.K2, self.S[:, 3:])
        self.children = [np.flatnonzero(self.parent == i) for i in range(self.nb)]
        self.chain_like = bool(np.array_equal(model.E, np.eye(model.n)) and not np.any(model.e0))

    def _cast(self, a):
        return np.asarray(a).astype(self.dtype) if np.asarray(a).dtype != self.dtype else np.asarray(a)

    def joint_transforms(self, x):
        """(R, p) of f_{parent,i} = M_i exp([S_i] x_i), (N, nb, 3, 3) and (N, nb, 3), exact exp of the screw."""
        N = x.shape[0]
        R = np.empty((N, self.nb, 3, 3), self.dtype)
        p = np.empty((N, self.nb, 3), self.dtype)
        eye = np.eye(3, dtype=self.dtype)
        for i in range(self.nb):
            xi, th = x[:, i], self.theta[i]
            v = self.S[i, 3:]
            if th > 0:
                t = th * xi
                a = np.sin(t) / th
                b = 2 * np.sin(0.5 * t) ** 2 / (th * th)
                d = (t - np.sin(t)) / (th * th * th)
                Re = eye + a[:, None, None] * self.K[i] + b[:, None, None] * self.K2[i]
                pe = xi[:, None] * v + b[:, None] * self.Kv[i] + d[:, None] * self.K2v[i]
            else:
                Re = np.broadcast_to(eye, (N, 3, 3))
                pe = xi[:, None] * v
            R[:, i] = self.MR[i] @ Re
            p[:, i] = _mv(self.MR[i], pe) + self.Mp[i]
        return R, p

    def inverse_dynamics(self, q, qd, qdd, gravity=True):
        """tau for (N, n) inputs (cast to the working dtype)."""
        q, qd, qdd = (self._cast(np.atleast_2d(a)) for a in (q, qd, qdd))
        N = q.shape[0]
        x, xd, xdd = q @ self.E.T + self.e0, qd @ self.E.T, qdd @ self.E.T
        R, p = self.joint_transforms(x)
        zero = np.zeros((N, 3), self.dtype)
        g = -self.g.astype(self.dtype) if gravity else np.zeros(3, self.dtype)
        W = np.empty((N, self.nb, 3), self.dtype)
        Vv, Aw, Av = (np.empty_like(W) for _ in range(3))
        for i in range(self.nb):
            par = self.parent[i]
            if par < 0:
                wp, vp, awp, avp = zero, zero, zero, zero + g
            else:
                wp, vp, awp, avp = W[:, par], Vv[:, par], Aw[:, par], Av[:, par]
            Ri, pi = R[:, i], p[:, i]
            sw, sv = self.S[i, :3] * xd[:, i, None], self.S[i, 3:] * xd[:, i, None]      # S_i xd_i
            w = _mtv(Ri, wp) + sw                                                       # eq 18
            v = _mtv(Ri, vp - cross(pi, wp)) + sv
            aw = _mtv(Ri, awp) + self.S[i, :3] * xdd[:, i, None] + cross(w, sw)         # eq 19
            av = _mtv(Ri, avp - cross(pi, awp)) + self.S[i, 3:] * xdd[:, i, None] \
                + cross(w, sv) + cross(v, sw)
            W[:, i], Vv[:, i], Aw[:, i], Av[:, i] = w, v, aw, av
        Fm = np.zeros((N, self.nb, 3), self.dtype)
        Ff = np.zeros_like(Fm)
        tau = np.empty((N, self.nb), self.dtype)
        for i in range(self.nb - 1, -1, -1):
            J = self.J[i]
            w, v = W[:, i], Vv[:, i]
            hm, hf = _mv(J[:3, :3], w) + _mv(J[:3, 3:], v), _mv(J[3:, :3], w) + _mv(J[3:, 3:], v)
            m = Fm[:, i] + _mv(J[:3, :3], Aw[:, i]) + _mv(J[:3, 3:], Av[:, i]) + cross(w, hm) + cross(v, hf)
            f = Ff[:, i] + _mv(J[3:, :3], Aw[:, i]) + _mv(J[3:, 3:], Av[:, i]) + cross(w, hf)   # body wrench
            tau[:, i] = m @ self.S[i, :3] + f @ self.S[i, 3:]                                       # eq 21
            par = self.parent[i]
            if par >= 0:   # Ad*_{f^-1} F: the wrench in the parent frame
                Rf = _mv(R[:, i], f)
                Fm[:, par] += _mv(R[:, i], m) + cross(p[:, i], Rf)
                Ff[:, par] += Rf
        return tau @ self.E

    def gravity(self, q):
        z = np.zeros(np.shape(np.atleast_2d(q)))
        return self.inverse_dynamics(q, z, z)

    def mass_matrix(self, q):
        """(N, n, n): column j is the RNEA without gravity and velocity for qdd = e_j."""
        q = np.atleast_2d(q)
        N, n = q.shape
        Q = np.repeat(q, n, axis=0)
        A = np.tile(np.eye(n), (N, 1))
        cols = self.inverse_dynamics(Q, np.zeros_like(Q), A, gravity=False)
        return np.swapaxes(cols.reshape(N, n, n), -1, -2)

    def coriolis_term(self, q, qd):
        return self.inverse_dynamics(q, qd, np.zeros(np.shape(np.atleast_2d(q))), gravity=False)

    def forward_dynamics(self, q, qd, tau):
        """qdd by the articulated body algorithm in the working dtype (see aba.py for the equations)."""
        if not self.chain_like:
            raise ValueError('Generic.forward_dynamics handles models without mimic or locked joints')
        q, qd, tau = (self._cast(np.atleast_2d(a)) for a in (q, qd, tau))
        N, nb = q.shape[0], self.nb
        R, p = self.joint_transforms(q)
        dt = self.dtype
        X = np.zeros((N, nb, 6, 6), dt)     # Ad_{f^-1} = [[R^T, 0], [-R^T [p], R^T]]
        Rt = np.swapaxes(R, -1, -2)
        X[..., :3, :3] = Rt
        X[..., 3:, 3:] = Rt
        X[..., 3:, :3] = -Rt @ hat3(p)
        S = self.S.astype(dt)
        V = np.zeros((N, nb, 6), dt)
        c = np.zeros_like(V)
        IA = np.broadcast_to(self.J.astype(dt), (N, nb, 6, 6)).copy()
        pA = np.zeros_like(V)
        for i in range(nb):
            par = self.parent[i]
            Vp = V[:, par] if par >= 0 else np.zeros((N, 6), dt)
            Sx = S[i] * qd[:, i, None]
            Vi = _mv(X[:, i], Vp) + Sx
            V[:, i] = Vi
            c[:, i] = np.concatenate([cross(Vi[:, :3], Sx[:, :3]),
                                      cross(Vi[:, :3], Sx[:, 3:]) + cross(Vi[:, 3:], Sx[:, :3])], -1)
            h = _mv(self.J[i].astype(dt), Vi)
            pA[:, i] = -np.concatenate([-cross(Vi[:, :3], h[:, :3]) - cross(Vi[:, 3:], h[:, 3:]),
                                        -cross(Vi[:, :3], h[:, 3:])], -1)          # -ad_V^T (J V)
        U = np.zeros((N, nb, 6), dt)
        D = np.zeros((N, nb), dt)
        u = np.zeros((N, nb), dt)
        for i in range(nb - 1, -1, -1):
            Ui = _mv(IA[:, i], S[i])
            Di = Ui @ S[i]
            ui = tau[:, i] - pA[:, i] @ S[i]
            U[:, i], D[:, i], u[:, i] = Ui, Di, ui
            par = self.parent[i]
            if par >= 0:
                Ia = IA[:, i] - Ui[:, :, None] * Ui[:, None, :] / Di[:, None, None]
                pa = pA[:, i] + _mv(Ia, c[:, i]) + Ui * (ui / Di)[:, None]
                Xi = X[:, i]
                IA[:, par] += np.swapaxes(Xi, -1, -2) @ Ia @ Xi
                pA[:, par] += _mtv(Xi, pa)
        acc = np.zeros((N, nb, 6), dt)
        qdd = np.zeros((N, nb), dt)
        a0 = np.concatenate([np.zeros(3), -self.g]).astype(dt)
        for i in range(nb):
            par = self.parent[i]
            ap = _mv(X[:, i], acc[:, par] if par >= 0 else np.broadcast_to(a0, (N, 6))) + c[:, i]
            qdd[:, i] = (u[:, i] - np.einsum('nj,nj->n', U[:, i], ap)) / D[:, i]
            acc[:, i] = ap + S[i] * qdd[:, i, None]
        return qdd

    def derivatives(self, q, qd, qdd, h=None):
        """(dtau/dq, dtau/dqd), (N, n, n), by the complex step Im(tau(x + i h e_j)) / h (complex dtype only)."""
        if self.dtype.kind != 'c':
            raise ValueError('complex-step derivatives need a complex dtype')
        q, qd, qdd = (np.atleast_2d(np.asarray(a, dtype=float)) for a in (q, qd, qdd))
        N, n = q.shape
        h = h if h is not None else (1e-40 if self.dtype.itemsize > 16 else 1e-20)
        eye = np.eye(n) * 1j * h
        Q = (np.repeat(q, 2 * n, axis=0)).astype(self.dtype)
        Qd = (np.repeat(qd, 2 * n, axis=0)).astype(self.dtype)
        Qdd = np.repeat(qdd, 2 * n, axis=0).astype(self.dtype)
        steps = np.tile(eye, (N, 1)).reshape(N, n, n)
        Q.reshape(N, 2 * n, n)[:, :n] += steps
        Qd.reshape(N, 2 * n, n)[:, n:] += steps
        d = (self.inverse_dynamics(Q, Qd, Qdd).imag / h).reshape(N, 2 * n, n)
        return np.swapaxes(d[:, :n], -1, -2), np.swapaxes(d[:, n:], -1, -2)


def ld_cholesky_solve(M, b):
    """Solve M x = b for SPD (N, n, n) M in the arrays' dtype (numpy.linalg has no longdouble)."""
    M = np.array(M, copy=True)
    N, n, _ = M.shape
    L = np.zeros_like(M)
    for j in range(n):
        d = M[:, j, j] - np.einsum('nk,nk->n', L[:, j, :j], L[:, j, :j])
        L[:, j, j] = np.sqrt(d)
        L[:, j + 1:, j] = (M[:, j + 1:, j] - np.einsum('nik,nk->ni', L[:, j + 1:, :j], L[:, j, :j])) / L[:, j, j, None]
    y = np.zeros_like(b)
    for j in range(n):
        y[:, j] = (b[:, j] - np.einsum('nk,nk->n', L[:, j, :j], y[:, :j])) / L[:, j, j]
    x = np.zeros_like(b)
    for j in range(n - 1, -1, -1):
        x[:, j] = (y[:, j] - np.einsum('nk,nk->n', L[:, j + 1:, j], x[:, j + 1:])) / L[:, j, j]
    return x


# ------------------------------------------------------------------ exp / log references
def _exp_coeffs_ld(t):
    """sin t / t, (1 - cos t)/t^2, (t - sin t)/t^3 in longdouble, series below 1e-3."""
    t = np.asarray(t, LD)
    t2 = t * t
    small = t < LD('1e-3')
    ts = np.where(small, LD(1), t)
    a = np.where(small, 1 - t2 / 6 + t2 * t2 / 120 - t2 ** 3 / 5040, np.sin(ts) / ts)
    b = np.where(small, LD(1) / 2 - t2 / 24 + t2 * t2 / 720 - t2 ** 3 / 40320, 2 * np.sin(ts / 2) ** 2 / (ts * ts))
    d = np.where(small, LD(1) / 6 - t2 / 120 + t2 * t2 / 5040 - t2 ** 3 / 362880, (ts - np.sin(ts)) / ts ** 3)
    return a, b, d


def exp6_ld(w, v=None):
    """exp([w, v]) in longdouble, (..., 4, 4); w, v longdouble (..., 3)."""
    w = np.asarray(w, LD)
    v = np.zeros_like(w) if v is None else np.asarray(v, LD)
    a, b, d = _exp_coeffs_ld(np.sqrt(np.sum(w * w, axis=-1)))
    K = hat3(w)
    K2 = K @ K
    eye = np.eye(3, dtype=LD)
    T = np.zeros(w.shape[:-1] + (4, 4), LD)
    T[..., :3, :3] = eye + a[..., None, None] * K + b[..., None, None] * K2
    T[..., :3, 3] = _mv(eye + b[..., None, None] * K + d[..., None, None] * K2, v)
    T[..., 3, 3] = 1
    return T
