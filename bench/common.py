"""Shared benchmark helpers: interleaved timing, benchmark robots, extended-precision references.

Timing. The machine is shared and noisy, so every benchmark times its candidates in
interleaved rounds (each round runs each candidate once) and reports medians over rounds;
ratios are medians of per-round ratios, so both sides of a ratio saw the same load.

References. Errors are measured against the same algorithms evaluated in numpy.longdouble
(x86-64: 80-bit extended, eps = 1.1e-19, ~1000x finer than float64). The model's float64
constants (M_i, S_i, J_i, gravity) and the float64 inputs are taken as exact, so the
reference answers "what would exact arithmetic give on these numbers". `Generic` below is
the RNEA of paper eqs 16-21 (and an articulated-body forward dynamics) written once for
any numpy dtype: longdouble for references, clongdouble for complex-step reference
derivatives, float32 / complex128 as benchmarked methods of their own.
"""
import argparse
import csv
import json
import os
import time
import xml.etree.ElementTree as ET

import numpy as np

from lie_dynamics.spatial import cross, hat3

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
LD = np.longdouble
EPS64 = float(np.finfo(np.float64).eps)
EPS32 = float(np.finfo(np.float32).eps)


# ------------------------------------------------------------------ timing
def calibrate(fn, target):
    """Calls per measurement so that one measurement takes about `target` seconds."""
    t0 = time.perf_counter()
    fn()
    dt = time.perf_counter() - t0
    number = 1
    while dt * number < target and number < 1_000_000:
        number *= 2
    return number


def time_interleaved(fns, rounds, target):
    """{key: callable} -> {key: array of seconds per call, one entry per round}.

    Every round times every callable once (interleaved), so slow phases of a shared machine
    hit all candidates alike; report medians and medians of per-round ratios.
    """
    numbers = {k: calibrate(f, target) for k, f in fns.items()}
    out = {k: [] for k in fns}
    for _ in range(rounds):
        for k, f in fns.items():
            n = numbers[k]
            t0 = time.perf_counter()
            for _ in range(n):
                f()
            out[k].append((time.perf_counter() - t0) / n)
    return {k: np.array(v) for k, v in out.items()}


def slope(ns, ts, fit_from=16):
    """Log-log slope of ts against ns over ns >= fit_from (fixed per-call costs dominate below)."""
    ns, ts = np.asarray(ns, float), np.asarray(ts, float)
    sel = (ns >= fit_from) & np.isfinite(ts) & (ts > 0)
    if sel.sum() < 2:
        return float('nan')
    return float(np.polyfit(np.log(ns[sel]), np.log(ts[sel]), 1)[0])


# ------------------------------------------------------------------ robots
def default_urdf():
    """The bundled arm (config/arm7.urdf), else the package's embedded copy."""
    path = os.path.join(ROOT, 'config', 'arm7.urdf')
    if os.path.isfile(path):
        return path
    from lie_dynamics import default_urdf_path
    return default_urdf_path()


def arm_xml():
    with open(default_urdf(), encoding='utf-8') as fh:
        return fh.read()


def robot_urdf(n, tree=False, seed=0, mass_ratio=1.0):
    """A random revolute robot with n joints (random axes, offsets, CoMs, inertias).

    tree=False: a serial chain. tree=True: a binary tree (body i hangs off body (i-1)//2, depth
    log2 n), the opposite extreme of branching. Masses and inertias fall geometrically along the
    chain so that the last body is `mass_ratio` times the first (ill-conditioned M when small).
    Joint names are zero-padded so that Pinocchio's alphabetical child order is file order.
    """
    rng = np.random.default_rng(seed)

    def f(v):
        return ' '.join(repr(float(x)) for x in np.atleast_1d(v))
    parts = [f'<robot name="{"tree" if tree else "chain"}{n}">', '<link name="l0"/>']
    for i in range(1, n + 1):
        parent = (i - 1) // 2 if tree and i > 1 else i - 1
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        xyz, rpy = rng.uniform(-0.2, 0.2, 3), rng.uniform(-1, 1, 3)
        s = mass_ratio ** ((i - 1) / max(1, n - 1))
        m = rng.uniform(0.5, 3.0)
        d = rng.uniform(0.05, 0.2, 3)
        I = m / 12 * np.array([d[1] ** 2 + d[2] ** 2, d[0] ** 2 + d[2] ** 2, d[0] ** 2 + d[1] ** 2]) * s
        c = rng.uniform(-0.1, 0.1, 3)
        parts.append(f'<joint name="j{i:03d}" type="revolute"><parent link="l{parent}"/><child link="l{i}"/>'
                     f'<origin xyz="{f(xyz)}" rpy="{f(rpy)}"/><axis xyz="{f(axis)}"/>'
                     '<limit effort="50" velocity="2" lower="-3" upper="3"/></joint>')
        parts.append(f'<link name="l{i}"><inertial><origin xyz="{f(c)}"/><mass value="{f(m * s)}"/>'
                     f'<inertia ixx="{f(I[0])}" ixy="0" ixz="0" iyy="{f(I[1])}" iyz="0" izz="{f(I[2])}"/>'
                     '</inertial></link>')
    parts.append('</robot>')
    return '\n'.join(parts)


def scale_chain_masses(xml, ratio):
    """The URDF with the mass and inertia of the k-th movable body of a serial chain scaled by
    ratio^(k/(n-1)), links welded to a body by fixed joints included (CoMs unchanged)."""
    root = ET.fromstring(xml)
    children = {}
    for j in root.findall('joint'):
        children.setdefault(j.find('parent').get('link'), []).append(j)
    links = {lk.get('name'): lk for lk in root.findall('link')}
    child_names = {j.find('child').get('link') for j in root.findall('joint')}
    base = next(name for name in links if name not in child_names)
    factor = {}

    def walk(link, k):
        for j in children.get(link, []):
            kk = k + (j.get('type') != 'fixed')
            factor[j.find('child').get('link')] = kk
            walk(j.find('child').get('link'), kk)
    walk(base, 0)
    ratio = float(ratio)
    n = max(factor.values())
    for name, k in factor.items():
        if k == 0:
            continue
        s = ratio ** ((k - 1) / max(1, n - 1))
        inertial = links[name].find('inertial')
        if inertial is None:
            continue
        mass = inertial.find('mass')
        mass.set('value', repr(float(mass.get('value')) * s))
        inertia = inertial.find('inertia')
        for key in ('ixx', 'ixy', 'ixz', 'iyy', 'iyz', 'izz'):
            if inertia.get(key) is not None:
                inertia.set(key, repr(float(inertia.get(key)) * s))
    return ET.tostring(root, encoding='unicode')


def near_coaxial_urdf(tilt):
    """A 3-joint arm whose last two joints are coaxial up to `tilt` (rad), with a massless link
    between them: both joints turn the last link about (almost) the same line, so M is
    ill-conditioned by geometry (cond ~ 1/tilt^2), not by scale; tilt = 0 makes it singular."""
    def link(name, mass):
        if mass is None:
            return f'<link name="{name}"/>'
        return (f'<link name="{name}"><inertial><origin xyz="0.1 0.02 0.05"/><mass value="{mass}"/>'
                '<inertia ixx="0.01" ixy="0" ixz="0" iyy="0.02" iyz="0" izz="0.015"/></inertial></link>')

    def joint(name, parent, child, xyz, axis):
        return (f'<joint name="{name}" type="revolute"><parent link="{parent}"/><child link="{child}"/>'
                f'<origin xyz="{xyz}"/><axis xyz="{axis}"/>'
                '<limit effort="10" velocity="1" lower="-3" upper="3"/></joint>')
    return ''.join(['<robot name="near_coaxial">', link('l0', None), joint('j1', 'l0', 'l1', '0 0 0.1', '0 1 0'),
                    link('l1', 1.0), joint('j2', 'l1', 'l2', '0 0 0.3', '0 0 1'), link('l2', None),
                    joint('j3', 'l2', 'l3', '0 0 0.2', f'{float(np.sin(tilt))!r} 0 {float(np.cos(tilt))!r}'),
                    link('l3', 1.0),
                    '</robot>'])


def random_states(model, N, seed=0):
    """(q, qd, qdd) of N states, positions inside the joint limits."""
    rng = np.random.default_rng(seed)
    lo = np.where(np.isfinite(model.position_lower), model.position_lower, -np.pi)
    hi = np.where(np.isfinite(model.position_upper), model.position_upper, np.pi)
    return rng.uniform(lo, hi, (N, model.n)), rng.uniform(-1.5, 1.5, (N, model.n)), rng.uniform(-3, 3, (N, model.n))


# ------------------------------------------------------------------ Pinocchio and Modern Robotics
def pinocchio_model(xml, model):
    """(pin, model, data) from the same URDF text, with our gravity."""
    import pinocchio as pin
    pm = pin.buildModelFromXML(xml)
    pm.gravity.linear = model.gravity_vector
    if pm.nq != model.n or pm.nv != model.n:
        raise ValueError('benchmark robots need one revolute/prismatic Pinocchio joint per joint')
    return pin, pm, pm.createData()


def modern_robotics_lists(model):
    """(Mlist, Glist, Slist) of Modern Robotics for a serial chain model.

    MR puts link frame {i} at the centre of mass with G_i = diag(I_c, m 1) there, Mlist the
    home poses of {i} in {i-1} (plus an end frame), Slist the space-frame screws (w, v).
    """
    from lie_dynamics import spatial as se3
    if np.any(model.parent != np.arange(-1, model.nb - 1)) or not np.array_equal(model.E, np.eye(model.n)) \
            or np.any(model.e0 != 0):
        raise ValueError('Modern Robotics needs a serial chain without mimic or locked joints')
    T = np.eye(4)
    frames, G, S = [], [], []
    for b in range(model.nb):
        T = T @ model.M[b]                      # body frame at q = 0
        J = model.J[b]
        m = J[3, 3]
        c = np.array([J[2, 4], J[0, 5], J[1, 3]]) / m if m > 0 else np.zeros(3)  # J[:3, 3:] = m[c]
        C = T @ se3.transform(p=c)              # CoM frame, body orientation
        Ic = J[:3, :3] + m * se3.hat3(c) @ se3.hat3(c)
        G.append(np.block([[Ic, np.zeros((3, 3))], [np.zeros((3, 3)), m * np.eye(3)]]))
        S.append(se3.Ad(T) @ model.S[b])
        frames.append(C)
    Mlist = [frames[0]] + [se3.inv(frames[i - 1]) @ frames[i] for i in range(1, model.nb)] + [np.eye(4)]
    return np.array(Mlist), np.array(G), np.array(S).T


# ------------------------------------------------------------------ dtype-generic dynamics
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


def rel_err(x, ref, axis=None):
    """max |x - ref| / max |ref| (max norm), in float; inf when x is not finite."""
    x = np.asarray(x)
    ref = np.asarray(ref)
    if axis is None:
        if not np.all(np.isfinite(x)):
            return float('inf')
        return float(np.max(np.abs(x.astype(ref.dtype) - ref)) / max(np.max(np.abs(ref)), np.finfo(float).tiny))
    num = np.max(np.abs(x.astype(ref.dtype) - ref), axis=axis)
    den = np.maximum(np.max(np.abs(ref), axis=axis), np.finfo(float).tiny)
    out = (num / den).astype(float)
    bad = ~np.all(np.isfinite(x), axis=axis)
    out[bad] = np.inf
    return out


def boundary(xs, errs, tol):
    """Failure region on a grid: (smallest, largest) x where err > tol (or not finite), else None."""
    xs, errs = np.asarray(xs, float), np.asarray(errs, float)
    bad = ~(errs <= tol)
    if not bad.any():
        return None
    return float(xs[bad].min()), float(xs[bad].max())


def write_tables(out, name, md, data, rows=None, fields=None):
    """A section's files in `out`: name.md (md), name.json (data) and, given rows (dicts),
    name.csv with columns `fields` (default: the first row's keys; other keys are left out)."""
    os.makedirs(out, exist_ok=True)
    with open(os.path.join(out, f'{name}.md'), 'w', encoding='utf-8') as fh:
        fh.write(md)
    if rows is not None:
        rows = list(rows)
        with open(os.path.join(out, f'{name}.csv'), 'w', newline='', encoding='utf-8') as fh:
            w = csv.DictWriter(fh, fieldnames=fields or list(rows[0]), extrasaction='ignore')
            w.writeheader()
            w.writerows(rows)
    with open(os.path.join(out, f'{name}.json'), 'w', encoding='utf-8') as fh:
        json.dump(data, fh, indent=1)


def savefig(fig, path):
    """PNG at ~100 dpi (small enough to commit copies)."""
    fig.savefig(path, dpi=100)
    import matplotlib.pyplot as plt
    plt.close(fig)


def setup_matplotlib():
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    return plt


def section_main(argv, doc, run, markdown):
    """The command line of a benchmark section: --quick, --out DIR; runs it and prints its tables."""
    ap = argparse.ArgumentParser(description=doc.split('\n')[0])
    ap.add_argument('--quick', action='store_true')
    ap.add_argument('--out', default=os.path.join(HERE, 'out'))
    args = ap.parse_args(argv)
    print(markdown(run(args.quick, args.out)))
    return 0
