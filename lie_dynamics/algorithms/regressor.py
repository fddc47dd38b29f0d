"""Inertial-parameter regressor: tau = Y(q, qd, qdd) pi, linear in the inertial parameters.

The paper notes (after eq 32) that each link's inertia has exactly 10 independent
parameters. Per body, about its own frame and in Pinocchio's order (CONVENTIONS.md),

    pi_i = (m, m c_x, m c_y, m c_z, I_xx, I_xy, I_yy, I_xz, I_yz, I_zz),
    J_i  = [[I, [h]], [-[h], m 1]],  h = m c,  I = I_c - m [c]^2 (inertia about the frame origin).

The body-frame Newton-Euler wrench of eq 20, F = J Vdot - ad_V^T J V, is linear in pi_i:
with V = (w, v) and Vdot = (alpha, a) in body frame (gravity included as Vdot_0 = (0, -g)),

    F = K(V, Vdot) pi_i,   K = [[0,         -[a + w x v],    L(alpha) + [w] L(w)],
                                [a + w x v,  [alpha] + [w]^2, 0                 ]],

where L(u) is the 3x6 matrix with I u = L(u) (I_xx, I_xy, I_yy, I_xz, I_yz, I_zz). The
joint torques are tau_k = sum_{k <= i} (Ad_{T_i^-1} A_k)^T F_i, and Ad_{T_i^-1} A_k is
block (i, k) of G S in the factorisation M = S^T G^T J G S (eq 39): the regressor is

    Y[k, block i] = (G S)_{ik}^T K_i          (k <= i; zero otherwise),

so tau = Y pi with the body-coordinate torques projected by E^T as everywhere else.

Two evaluations: vectorised numpy over bodies and states (`regressor_vectorized`), and
generated straight-line code (codegen.py, `regressor_kernel`) for models of up to
KERNEL_MAX_PAIRS (body, ancestor) pairs, used for one state, small batches (state by state)
and large batches (numpy rows) where the measured crossovers say it is faster.
"""
import math
import struct

import numpy as np

from ..codegen import algebra as la
from ..codegen import runtime
from ..codegen.render import kernel
from ..codegen.tracer import Graph, Sym, snap
from .kinematics import ad_matrices
from ..spatial import hat3
from ..model.inertia import PARAMETER_NAMES, inertia_to_parameters, parameter_consistency, parameters_to_inertia  # noqa: F401
from ..spatial import cross, transpose
from .lagrangian import body_constants, chunks, kinematic_state

# L(u): I u = L(u) iota, iota = (xx, xy, yy, xz, yz, zz); entry (row, col) <- u[idx]
_L_ROW = np.array([0, 0, 0, 1, 1, 1, 2, 2, 2])
_L_COL = np.array([0, 1, 3, 1, 2, 4, 3, 4, 5])
_L_IDX = np.array([0, 1, 2, 0, 1, 2, 0, 1, 2])


def physical_consistency(pi):
    """Per body: (ok, reason) for parameters (nb, 10): the one consistency check
    (inertia.violations) applied to the inertia about each body's CoM."""
    return parameter_consistency(pi)


def inertial_parameters(model):
    """Current parameters (nb * 10,) of the model (payloads included), body order of model.body_joint_names."""
    return inertia_to_parameters(model.J).reshape(-1)


def with_inertial_parameters(model, pi, check=True):
    """A copy of `model` whose bodies have the inertial parameters `pi` ((nb*10,) or (nb, 10)).

    `pi` is the total per body (payloads included): the copy carries it as its link
    inertias and has no separate payloads. check: raise ValueError for physically
    inconsistent parameters (negative mass, invalid inertia about the CoM); identified
    parameters often are, and check=False accepts them (the dynamics stay defined,
    though the mass matrix may then not be positive definite).
    """
    p = np.asarray(pi, dtype=float)
    if p.size != 10 * model.nb or p.ndim not in (1, 2):
        raise ValueError(f'inertial parameters must have shape ({10 * model.nb},) or ({model.nb}, 10) '
                         f'for the {model.nb} bodies, got {p.shape}')
    p = p.reshape(model.nb, 10)
    if not np.all(np.isfinite(p)):
        raise ValueError('inertial parameters contain non-finite values')
    if check:
        bad = [reason for ok, reason in physical_consistency(p) if not ok]
        if bad:
            raise ValueError('inertial parameters are not physically consistent: ' + '; '.join(bad)
                             + ' (pass check=False to accept them)')
    return model.with_body_inertias(parameters_to_inertia(p))


def _K(Vb, Ab):
    """Per-body 6x10 maps K(V, Vdot) with J Vdot - ad_V^T J V = K pi, for (N, nb, 6) inputs."""
    w, v = Vb[..., :3], Vb[..., 3:]
    al, a = Ab[..., :3], Ab[..., 3:]
    shape = Vb.shape[:-1]
    W = hat3(w)
    Alpha = hat3(al)
    acc = a + cross(w, v)
    Acc = hat3(acc)
    Lw = np.zeros(shape + (3, 6))
    La = np.zeros(shape + (3, 6))
    Lw[..., _L_ROW, _L_COL] = w[..., _L_IDX]
    La[..., _L_ROW, _L_COL] = al[..., _L_IDX]
    K = np.zeros(shape + (6, 10))
    K[..., 3:, 0] = acc
    K[..., :3, 1:4] = -Acc
    K[..., 3:, 1:4] = Alpha + W @ W
    K[..., :3, 4:] = La + W @ Lw
    return K


def _regressor(model, x, xd, xdd, a0):
    Adinv, AdinvT, A = kinematic_state(model, x)
    anc = model.ancestors
    N, nb = x.shape
    Axd = A * xd[..., None]
    V = anc @ Axd
    acc = anc @ (A * xdd[..., None] + (ad_matrices(V) @ Axd[..., None])[..., 0]) + a0
    VV = Adinv @ np.stack([V, acc], axis=-1)                 # to body frames
    K = _K(VV[..., 0], VV[..., 1])                           # (N, nb, 6, 10)
    GS = (Adinv @ transpose(A)[:, None]) * anc[None, :, None, :]  # (N, i, 6, k)
    Y = transpose(GS) @ K                                        # (N, i, k, 10)
    return np.swapaxes(Y, 1, 2).reshape(N, nb, nb * 10)      # (N, k, 10 i)


def regressor(model, q, qd, qdd):
    """Y(q, qd, qdd) with inverse_dynamics(q, qd, qdd) = Y @ inertial_parameters().

    Shape (n, 10 nb) or (N, n, 10 nb); columns are 10 per body in model.body_joint_names
    order, parameters as PARAMETER_NAMES (Pinocchio's computeJointTorqueRegressor layout).
    Gravity (as set on the model) is included. Runs the generated kernel (below) where the
    measured crossovers say it is faster, else the vectorised form.
    """
    n = model.n
    a, b, c = runtime.is_fast_single(q, n), runtime.is_fast_single(qd, n), runtime.is_fast_single(qdd, n)
    if a is not None and b is not None and c is not None and _pairs(model) <= FLOAT_MAX_PAIRS:
        k = _kernel(model)
        if k:
            return _single(model, k, a, b, c)
    single = np.ndim(q) == 1
    q, qd, qdd = model.check_states(q=q, qd=qd, qdd=qdd)
    Y = _kernel_regressor(model, q, qd, qdd)
    if Y is None:
        Y = _vectorized(model, q, qd, qdd)
    return Y[0] if single else Y


def regressor_vectorized(model, q, qd, qdd):
    """regressor() by the vectorised form (numpy over bodies and states), any model."""
    single = np.ndim(q) == 1
    Y = _vectorized(model, *model.check_states(q=q, qd=qd, qdd=qdd))
    return Y[0] if single else Y


def _vectorized(model, q, qd, qdd):
    """Vectorised path on validated (N, n) arrays -> (N, n, 10 nb)."""
    c = body_constants(model)
    x = model.body_coordinates(q)
    E = model.E
    xd, xdd = qd @ E.T, qdd @ E.T
    N, nb = x.shape
    out = np.empty((N, nb, 10 * nb))
    for sl in chunks(N, 100 * nb + 30 * nb * nb):
        out[sl] = _regressor(model, x[sl], xd[sl], xdd[sl], model.base_acceleration)
    if not c['identity']:
        out = E.T @ out    # a batched matmul: several times faster than the equivalent einsum
    return out


# ---------------------------------------------------------------------------- generated kernel
# Sizes are counted in (body, ancestor-or-self) pairs, the sum of the body depths: the source
# has one block per pair. Compile cap: 300 pairs (a 24-body chain, crba's cap) compile in
# ~0.5-0.8 s (measured); larger models use the vectorised form.
KERNEL_MAX_PAIRS = 300
# The float kernel (~22 ns per traced operation, 60-95 operations per pair) beats the
# vectorised form for one state up to ~130-160 pairs (measured on random chains and trees);
# above FLOAT_MAX_PAIRS only large batches use the kernel, on numpy rows.
FLOAT_MAX_PAIRS = 128
# Batches: the float kernel state by state below _LOOP_BELOW states, the kernel on numpy rows
# from _ROWS_FROM states (_ROWS_FROM_LARGE above _LARGE_PAIRS pairs), the vectorised form in
# between. Measured crossovers: loop ~7 states on the arm, 3-5 on 10-12-body robots with
# general axes; rows ~80 states on the arm and 20-100 up to 64 pairs, 40-280 for 100-300
# pairs (later for chains, earlier for branched trees, whose vectorised form is slower).
_LOOP_BELOW = 6
_ROWS_FROM = 80
_ROWS_FROM_LARGE = 192
_LARGE_PAIRS = 64
_ROWS_CHUNK = 8192


def _skew(u):
    return np.array([[0.0, -u[2], u[1]], [u[2], 0.0, -u[0]], [-u[1], u[0], 0.0]])


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
        K1 = snap(MR @ _skew(u))
        K2 = snap(K1 @ _skew(u))
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

    Forward pass: V, Vdot (eqs 18-19). Per body i: the 10 columns of K_i (F = K_i pi_i,
    eq 20); for k = i and each ancestor k, the screw of joint k in frame i,
    Z_ki = Ad_{f_{k,i}^-1} S_k (block (i, k) of G S in eq 39), carried down one joint at a
    time, and Y[k, block i] = Z_ki^T K_i. Carrying the one twist down (6 numbers per step)
    costs less than carrying the ten wrench columns of K_i up (60).

    Works in the URDF body frames, not codegen's primed frames, so the columns are already
    those of the parameters about the body frame. In primed frames the constant 10x10 map
    of the parameters (m, Q^T h, Q^T I Q) would be folded into every (body, ancestor) block:
    the same operation count for coordinate-axis joints (the arm), 7-50% more for general
    axes (counted on the test robots), while here only a few products per body are added
    (the axis is not e_z).
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


def _build_kernel(fr):
    M, S = fr.M, fr.S
    g = Graph()
    co = fr.trace_coordinates(g, rates=2)
    a0 = [g.input(f'g{k}') for k in range(3)]
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
    # terms) are pad bytes ('x', packed as NUL bytes, i.e. 0.0) of the struct that writes the
    # float path's result: ~3x faster than np.array/np.fromiter of the returned tuple.
    idx = [i for i, o in enumerate(flat) if isinstance(o, Sym) or o != 0.0]
    fmt, i = [], 0
    keep = np.zeros(len(flat), bool)
    keep[idx] = True
    while i < len(flat):
        j = i
        while j < len(flat) and keep[j] == keep[i]:
            j += 1
        fmt.append(f'{j - i}d' if keep[i] else f'{8 * (j - i)}x')
        i = j
    packer = struct.Struct('=' + ''.join(fmt))   # native byte order, no alignment
    args = co['args'] + [('A0', [f'g{k}' for k in range(3)]), co['offset_args']]
    return kernel(g, 'regressor_kernel', args, [flat[i] for i in idx]) + (np.array(idx, dtype=np.intp), packer)


def _pairs(model):
    """Number of (body, ancestor-or-self) pairs."""
    return runtime.pairs(model)


def _kernel(model):
    """The model's kernel tuple, or False (built on first use)."""
    return _pairs(model) <= KERNEL_MAX_PAIRS and runtime.compiled(model, 'regressor', _build_kernel)


def _single(model, k, q, qd, qdd):
    """One state (float lists) on the float kernel -> (n, 10 nb)."""
    fr, fn, _, _, packer = k
    _, E0, A0 = runtime.model_params(model, fr, gravity=True)
    out = np.empty((model.n, 10 * model.nb))
    packer.pack_into(out, 0, *fn(q, qd, qdd, A0, E0, sin=math.sin, cos=math.cos))
    return out


def regressor_kernel(model, q, qd, qdd, mode=None):
    """regressor() from the generated kernel, or None when the model has none (screws that
    are not plain URDF joints, or more than KERNEL_MAX_PAIRS (body, ancestor) pairs).

    mode: 'loop' (Python floats, state by state), 'rows' (numpy rows over the states) or None
    (by batch size; then also None where the vectorised form is faster).
    """
    single = np.ndim(q) == 1
    q, qd, qdd = model.check_states(q=q, qd=qd, qdd=qdd)
    Y = _kernel_regressor(model, q, qd, qdd, mode)
    return Y if Y is None or not single else Y[0]


def _kernel_regressor(model, q, qd, qdd, mode=None):
    """Kernel path on validated (N, n) arrays -> (N, n, 10 nb), or None (see regressor_kernel)."""
    N, n = q.shape
    if mode is None:
        pairs = _pairs(model)
        if N < _LOOP_BELOW and pairs <= FLOAT_MAX_PAIRS:
            mode = 'loop'
        elif N >= (_ROWS_FROM if pairs <= _LARGE_PAIRS else _ROWS_FROM_LARGE):
            mode = 'rows'
    elif mode not in ('loop', 'rows'):
        raise ValueError(f"mode must be 'loop', 'rows' or None, got {mode!r}")
    k = _kernel(model) if mode else False
    if not k:
        return None
    fr, fn, _, idx, packer = k
    _, E0, A0 = runtime.model_params(model, fr, gravity=True)
    m = 10 * model.nb * n
    if mode == 'loop':
        out = np.empty((N, n, 10 * model.nb))
        for s, (a, b, c) in enumerate(zip(q.tolist(), qd.tolist(), qdd.tolist(), strict=True)):
            packer.pack_into(out, 8 * m * s, *fn(a, b, c, A0, E0, sin=math.sin, cos=math.cos))
        return out
    out = np.zeros((N, m))
    for s in range(0, N, _ROWS_CHUNK):   # bounds the (outputs, states) work array of run_rows
        sl = slice(s, s + _ROWS_CHUNK)
        out[sl, idx] = runtime.run_rows(fn, [q[sl], qd[sl], qdd[sl], A0, E0], len(idx))
    return out.reshape(N, n, 10 * model.nb)
