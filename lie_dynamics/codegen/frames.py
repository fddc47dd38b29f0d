"""Per-structure constants of the generated kernels: body frames turned so that every joint axis is z."""
import numpy as np

from .algebra import mat_mat, vadd, vscale
from .render import Params
from .tracer import snap


def axis_frame(a):
    """Proper rotation Q with Q e_z = a (a signed permutation when a is a coordinate axis)."""
    a = np.asarray(a, dtype=float)
    nz = np.flatnonzero(np.abs(a) > 0)
    if len(nz) == 1:
        u = np.zeros(3)
        u[(int(nz[0]) + 1) % 3] = 1.0
    else:
        e = np.zeros(3)
        e[int(np.argmin(np.abs(a)))] = 1.0
        u = np.cross(e, a)
        u /= np.linalg.norm(u)
    return np.column_stack([u, np.cross(a, u), a])


def joint_transform(g, R0, t0, revolute, x):
    """(R, t) of M' Rz(x) (revolute) or M' Trans(x e_z) (prismatic), M' = (R0, t0): constants of
    one body (Frames.joint_transform) or symbols of a looped step (looped.py)."""
    if revolute:
        c, s = g.cos(x), g.sin(x)
        Rz = ((c, -s, 0.0), (s, c, 0.0), (0.0, 0.0, 1.0))
        return mat_mat(R0, Rz), t0
    return R0, vadd(t0, vscale(x, (R0[0][2], R0[1][2], R0[2][2])))


class Frames:
    """Per-model constants for kernels: body frames turned so that every joint axis is z.

    Body frame b' = body frame b rotated by Q_b (Q_b e_z = joint axis). Then
    f_{p',b'}(x) = M'_b Rz(x) (revolute) or M'_b Trans(x e_z) (prismatic), with the
    constant M'_b = (R'_b, t'_b) = (Q_p^T R_b Q_b, Q_p^T p_b). Inertias are runtime
    parameters moved to the primed frames (`inertia_params`), so payload, gravity and
    locked-joint changes never recompile.
    """

    def __init__(self, model):
        self.nb, self.n = model.nb, model.n
        self.parent = [int(p) for p in model.parent]
        w, v = model.S[:, :3], model.S[:, 3:]
        nw, nv = np.linalg.norm(w, axis=1), np.linalg.norm(v, axis=1)
        self.revolute = [bool(abs(a - 1) < 1e-12 and b == 0) for a, b in zip(nw, nv, strict=True)]
        prismatic = [bool(a == 0 and abs(b - 1) < 1e-12) for a, b in zip(nw, nv, strict=True)]
        self.supported = all(r or p for r, p in zip(self.revolute, prismatic, strict=True))
        if not self.supported:
            return
        self.Q = np.array([axis_frame(w[b] if self.revolute[b] else v[b]) for b in range(self.nb)])
        self.R, self.t = [], []
        for b in range(self.nb):
            p = self.parent[b]
            Qp = self.Q[p] if p >= 0 else np.eye(3)
            R = snap(Qp.T @ model.M[b, :3, :3] @ self.Q[b])
            self.R.append(tuple(tuple(float(x) for x in row) for row in R))
            self.t.append(tuple(float(x) for x in snap(Qp.T @ model.M[b, :3, 3])))
        self.M, self.S = model.M.copy(), model.S.copy()   # URDF frames (the regressor's kernel)
        self.E = model.E.copy()
        self.offset = [bool(np.any(model.L[b] != 0) or model.c0[b] != 0) for b in range(self.nb)]
        self.children = [[] for _ in range(self.nb)]
        for b, p in enumerate(self.parent):
            if p >= 0:
                self.children[p].append(b)

    def inertia_table(self, J):
        """(nb, 10) array: per body (m, h, I_xx, I_xy, I_xz, I_yy, I_yz, I_zz) in the primed frame."""
        Qt = np.swapaxes(self.Q, 1, 2)
        Io = Qt @ J[:, :3, :3] @ self.Q
        h = np.einsum('bij,bj->bi', Qt, np.stack([J[:, 2, 4], J[:, 0, 5], J[:, 1, 3]], axis=1))
        return np.column_stack([J[:, 3, 3], h, Io[:, 0, 0], Io[:, 0, 1], Io[:, 0, 2], Io[:, 1, 1],
                                Io[:, 1, 2], Io[:, 2, 2]])

    def subtree_params(self, J):
        """(nb, 4) array: per body the subtree mass and h'_b + sum over children c of m_sub,c t'_c
        (the parameters of the gravity kernel, traced/rnea.py)."""
        m = J[:, 3, 3].copy()
        h = self.inertia_table(J)[:, 1:4].copy()
        for b in range(self.nb - 1, -1, -1):  # children have larger indices
            for c in self.children[b]:
                m[b] += m[c]
                h[b] += m[c] * np.array(self.t[c])
        return np.column_stack([m, h])

    def inertia_params(self, J):
        """inertia_table as one flat list (the P argument of the traced kernels)."""
        return self.inertia_table(J).reshape(-1).tolist()

    def wrench_params(self, fext):
        """(..., nb, 6) body-frame wrenches (n, f) -> the same in the primed frames (Q^T n, Q^T f)."""
        out = np.empty_like(fext)
        out[..., :3] = np.einsum('bji,...bj->...bi', self.Q, fext[..., :3])
        out[..., 3:] = np.einsum('bji,...bj->...bi', self.Q, fext[..., 3:])
        return out

    def point_params(self, b, T):
        """A frame T (4x4) fixed in body b, given in b's URDF frame, as the 12 numbers of the
        Jacobian kernels (traced/jacobian.py): Q_b^T R row-major, then Q_b^T t (frame b')."""
        Qt = self.Q[b].T
        return (Qt @ T[:3, :3]).reshape(-1).tolist() + (Qt @ T[:3, 3]).tolist()

    def offsets(self, e0):
        return [float(e0[b]) for b in range(self.nb) if self.offset[b]]

    # ---- tracing helpers
    def trace_coordinates(self, g, rates=0):
        """Symbols for q (and qd, qdd) and the body coordinates; returns dict of lists."""
        n, nb = self.n, self.nb
        out = {'args': []}
        q = [g.input(f'q{j}') for j in range(n)]
        out['args'].append(('Q', [f'q{j}' for j in range(n)]))
        e = {b: g.input(f'e{b}') for b in range(nb) if self.offset[b]}
        x = []
        for b in range(nb):
            s = e.get(b, 0.0)
            for j in range(n):
                s = s + float(self.E[b, j]) * q[j]
            x.append(s)
        out['x'] = x
        for k, (nm, lst) in enumerate((('QD', 'qv'), ('QDD', 'qa'))[:rates]):
            syms = [g.input(f'{lst}{j}') for j in range(n)]
            out['args'].append((nm, [f'{lst}{j}' for j in range(n)]))
            xs = []
            for b in range(nb):
                s = 0.0
                for j in range(n):
                    s = s + float(self.E[b, j]) * syms[j]
                xs.append(s)
            out['xd' if k == 0 else 'xdd'] = xs
        out['offset_args'] = Params('E0', [f'e{b}' for b in range(nb) if self.offset[b]])
        return out

    def trace_params(self, g):
        names = [f'p{b}_{k}' for b in range(self.nb) for k in range(10)]
        syms = [g.input(nm) for nm in names]
        per = [syms[10 * b:10 * b + 10] for b in range(self.nb)]
        return Params('P', names), [(p[0], tuple(p[1:4]), tuple(p[4:10])) for p in per]

    def trace_gravity(self, g):
        """(the A0 argument list, symbols of -g): the linear base acceleration, a parameter."""
        names = [f'g{k}' for k in range(3)]
        return Params('A0', names), [g.input(nm) for nm in names]

    def trace_armature(self, g):
        """(the AR argument list, its symbols): the armature of each joint (Model.armature), a
        parameter, so that setting it never recompiles."""
        names = [f'ar{j}' for j in range(self.n)]
        return Params('AR', names), [g.input(nm) for nm in names]

    def joint_transform(self, g, b, x):
        """(R, t) of f_{p',b'}(x) as traced 3x3 / 3-vector."""
        return joint_transform(g, self.R[b], self.t[b], self.revolute[b], x)

    def project(self, Mx):
        """E^T Mx E for a traced nb x nb nested list."""
        E, n, nb = self.E, self.n, self.nb
        out = [[0.0] * n for _ in range(n)]
        for a in range(n):
            for c in range(n):
                s = 0.0
                for i in range(nb):
                    if E[i, a] == 0:
                        continue
                    for j in range(nb):
                        if E[j, c] != 0:
                            s = s + float(E[i, a] * E[j, c]) * Mx[i][j]
                out[a][c] = s
        return out
