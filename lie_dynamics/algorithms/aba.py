"""Forward dynamics qdd = M(q)^-1 (tau - h(q, qd)): a Cholesky solve and the O(n) articulated body algorithm.

method='cholesky' (any model): M from the composite rigid body algorithm (crba.py), the
bias h = inverse_dynamics(q, qd, 0, wrenches) from the RNEA, then M = L L^T and two
triangular solves (M is never inverted). A mass matrix that is not numerically positive
definite (a massless body with nothing beyond it, a massless chain) raises ValueError.
Without wrenches, models of up to KERNEL_MAX_BODIES bodies run all of it (CRBA, RNEA bias,
Cholesky, solves) as one generated straight-line kernel (codegen.py).

method='aba': the articulated body algorithm in the Lie-group form of Ploen & Park, in
body frames with X_i = Ad_{f_{i-1,i}^-1} (f_{i-1,i} = M_i e^{[S_i] x_i}, eq 17):

  forward   V_i = X_i V_parent + S_i xd_i,   c_i = ad_{V_i} S_i xd_i                  (eq 18)
            Ia_i = J_i,  pa_i = -ad_{V_i}^T J_i V_i - F_ext,i                          (eq 20)
  backward  U_i = Ia_i S_i,  D_i = S_i^T U_i,  u_i = tau_i - S_i^T pa_i,
            Ia_parent += X_i^T (Ia_i - U_i U_i^T / D_i) X_i,
            pa_parent += X_i^T (pa_i + (Ia_i - U_i U_i^T / D_i) c_i + U_i u_i / D_i)
  forward   a'_i = X_i a_parent + c_i,  xdd_i = (u_i - U_i^T a'_i) / D_i,  a_i = a'_i + S_i xdd_i
            with a_0 = (0, -g)                                                        (eq 19)

Locked joints are welded (no projection, xdd = 0). Mimic joints couple bodies, which this
recursion cannot express: use method='cholesky' for them. Two evaluations: a generated
straight-line kernel (codegen.py; models of up to ABA_KERNEL_MAX_BODIES bodies, with or
without wrenches) on Python floats for one state and small batches and on numpy rows for
large ones, and a vectorised form (bodies at one depth of the tree together, every step
vectorised over states) for the rest. A D_i that is not numerically positive (a joint that
moves no mass) raises ValueError.
"""
import math

import numpy as np

from . import crba, rnea
from ..codegen import algebra as la
from ..codegen import runtime
from ..codegen.render import kernel
from ..codegen.tracer import Graph, SNAP, Sym, snap
from ..codegen.traced.rnea import trace_rnea
from .kinematics import ad_matrices
from ..spatial import transpose
from .rnea import external_body_wrenches
from .lagrangian import kinematic_state

METHODS = ('cholesky', 'aba')
_PD_RTOL = 1e-12


# ---------------------------------------------------------------------------- Cholesky
def cholesky(M):
    """Lower factor L of M = L L^T for (N, n, n); ValueError if some M is not positive definite."""
    try:
        L = np.linalg.cholesky(M)
    except np.linalg.LinAlgError:
        L = None
    else:
        # LAPACK factors some singular matrices (a zero pivot rounded positive): test each pivot
        # against its own diagonal entry, so the test is blind to scale (graded masses are fine)
        # and sees only near-dependence (a joint that moves no mass of its own)
        d = np.diagonal(L, axis1=-2, axis2=-1)
        if (d * d > _PD_RTOL * np.diagonal(M, axis1=-2, axis2=-1)).all():
            return L
    bad = [k for k in range(M.shape[0]) if not _is_pd(M[k])]
    k = int(bad[0])
    ev = np.linalg.eigvalsh(M[k])
    where = f'at state {k} ' if M.shape[0] > 1 else ''
    raise ValueError(f'mass matrix is not positive definite {where}(smallest eigenvalue {ev[0]:.3g}, '
                     f'largest {ev[-1]:.3g}): some joint moves no mass (massless body or chain), '
                     'so forward dynamics is undefined')


def _is_pd(M):
    try:
        L = np.linalg.cholesky(M)
    except np.linalg.LinAlgError:
        return False
    return bool(np.all(np.diagonal(L) ** 2 > _PD_RTOL * np.diagonal(M)))


def cho_solve(L, B):
    """Solve L L^T X = B for batches: L (N, n, n), B (N, n) or (N, n, k)."""
    vec = B.ndim == 2
    B = B[..., None] if vec else B
    N, n = L.shape[:2]
    if N > 2 * n:
        # many small systems: substitution, one row for all states at a time
        Y = np.empty(B.shape)
        for j in range(n):
            Y[:, j] = (B[:, j] - np.einsum('ni,nik->nk', L[:, j, :j], Y[:, :j])) / L[:, j, j, None]
        X = np.empty(B.shape)
        for j in range(n - 1, -1, -1):
            X[:, j] = (Y[:, j] - np.einsum('ni,nik->nk', L[:, j + 1:, j], X[:, j + 1:])) / L[:, j, j, None]
    else:
        X = np.linalg.solve(transpose(L), np.linalg.solve(L, B))
    return X[..., 0] if vec else X


# ---------------------------------------------------------------------------- ABA
def _structure(model):
    """Depth levels and the joint each body follows; cached per model."""
    return runtime.structural(model, 'aba_structure', lambda: _levels(model))


def _levels(model):
    E = model.E
    nz = E != 0
    rows_ok = np.all(nz.sum(axis=1) <= 1) and np.all(E[nz] == 1.0)
    cols_ok = np.all(nz.sum(axis=0) == 1)
    supported = bool(rows_ok and cols_ok)
    free = nz.any(axis=1)
    joint_of = np.where(free, np.argmax(nz, axis=1), -1)
    levels = []
    for d in range(1, int(model.depth.max()) + 1 if model.nb else 1):
        idx = np.flatnonzero(model.depth == d)
        par = model.parent[idx]
        has_par = par >= 0
        levels.append(dict(idx=idx, par=par[has_par], child=idx[has_par], root=idx[~has_par],
                           unique=len(set(par[has_par].tolist())) == int(has_par.sum())))
    return dict(E=E, supported=supported, free=free, joint_of=joint_of, levels=levels)


def _aba(model, st, x, xd, tau, fext):
    Adinv, _, A, Ad = kinematic_state(model, x, with_ad=True)
    N, nb = x.shape
    anc = model.ancestors
    S, J = model.S, model.J
    # body-frame velocities and the velocity-product accelerations c_i
    Axd = A * xd[..., None]
    Vs = anc @ Axd
    Vb = (Adinv @ Vs[..., None])[..., 0]
    Sxd = S * xd[..., None]
    c = (ad_matrices(Vb) @ Sxd[..., None])[..., 0]
    # X_i = Ad_{T_i^-1} Ad_{T_parent}
    X = Adinv.copy()
    has_par = model.parent >= 0
    X[:, has_par] = Adinv[:, has_par] @ Ad[:, model.parent[has_par]]
    XT = transpose(X)
    IA = np.broadcast_to(J, (N, nb, 6, 6)).copy()
    JV = (J @ Vb[..., None])[..., 0]
    pA = -(transpose(ad_matrices(Vb)) @ JV[..., None])[..., 0]
    if fext is not None:
        pA -= fext
    free = st['free']
    taub = np.zeros((N, nb))
    taub[:, free] = tau[:, st['joint_of'][free]]
    U = np.zeros((N, nb, 6))
    D = np.ones((N, nb))
    u = np.zeros((N, nb))
    for lv in reversed(st['levels']):
        idx = lv['idx']
        Ia, pa = IA[:, idx], pA[:, idx]
        f = free[idx]
        Ui = (Ia @ S[idx][..., None])[..., 0]
        Di = np.einsum('lj,nlj->nl', S[idx], Ui)
        ui = taub[:, idx] - np.einsum('lj,nlj->nl', S[idx], pa)
        scale = np.max(np.abs(Ia), axis=(-1, -2))
        if np.any(f & np.any(~(Di > _PD_RTOL * scale), axis=0)):
            k = int(np.flatnonzero(f & np.any(~(Di > _PD_RTOL * scale), axis=0))[0])
            raise ValueError(f"articulated inertia about joint '{model.body_joint_names[idx[k]]}' is zero: "
                             'the joint moves no mass (massless body or chain), so forward dynamics is undefined')
        Ui = Ui * f[:, None]
        Di = np.where(f, Di, 1.0)
        ui = ui * f
        U[:, idx], D[:, idx], u[:, idx] = Ui, Di, ui
        if not len(lv['child']):
            continue
        Ia = Ia - Ui[..., :, None] * Ui[..., None, :] / Di[..., None, None]
        pa = pa + (Ia @ c[:, idx][..., None])[..., 0] + Ui * (ui / Di)[..., None]
        sel = has_par[idx]
        Xc, XcT = X[:, lv['child']], XT[:, lv['child']]
        dI = XcT @ Ia[:, sel] @ Xc
        dp = (XcT @ pa[:, sel][..., None])[..., 0]
        if lv['unique']:
            IA[:, lv['par']] += dI
            pA[:, lv['par']] += dp
        else:
            np.add.at(IA, (slice(None), lv['par']), dI)
            np.add.at(pA, (slice(None), lv['par']), dp)
    acc = np.zeros((N, nb, 6))
    xdd = np.zeros((N, nb))
    for lv in st['levels']:
        idx = lv['idx']
        ap = np.empty((N, len(idx), 6))
        sel = has_par[idx]
        if len(lv['child']):
            ap[:, sel] = (X[:, lv['child']] @ acc[:, lv['par']][..., None])[..., 0]
        if len(lv['root']):
            ap[:, ~sel] = X[:, lv['root']] @ model.base_acceleration
        ap += c[:, idx]
        xi = (u[:, idx] - np.einsum('nlj,nlj->nl', U[:, idx], ap)) / D[:, idx]
        xi = xi * free[idx]
        xdd[:, idx] = xi
        acc[:, idx] = ap + S[idx] * xi[..., None]
    out = np.empty((N, model.n))
    out[:, st['joint_of'][free]] = xdd[:, free]
    return out


def aba_vectorized(model, q, qd, tau, wrenches=None):
    """forward_dynamics(..., method='aba') by the vectorised form only (numpy over the bodies
    of one depth and over states), whatever the model and batch size."""
    single = np.ndim(q) == 1
    q = model.check_batch('q', q)
    N = q.shape[0]
    qd, tau = model.check_batch('qd', qd, N), model.check_batch('tau', tau, N)
    out = _aba_vectorized(model, q, qd, tau, external_body_wrenches(model, wrenches, N))
    return out[0] if single else out


def _aba_vectorized(model, q, qd, tau, fext):
    """The vectorised ABA on validated (N, n) arrays; fext: (N, nb, 6) body wrenches or None.
    Raises ValueError for mimic joints and for a zero articulated inertia."""
    st = _structure(model)
    if not st['supported']:
        raise ValueError("method='aba' does not support mimic joints (they couple bodies); "
                         "use method='cholesky'")
    N = q.shape[0]
    x = model.body_coordinates(q)
    xd = qd @ model.E.T
    out = np.empty((N, model.n))
    step = max(1, (1 << 20) // (60 * max(1, model.nb)))
    for i in range(0, N, step):
        sl = slice(i, min(N, i + step))
        out[sl] = _aba(model, st, x[sl], xd[sl], tau[sl], None if fext is None else fext[sl])
    return out


def forward_dynamics(model, q, qd, tau, wrenches=None, method='cholesky'):
    """Joint accelerations qdd with inverse_dynamics(q, qd, qdd, wrenches) = tau.

    q, qd, tau: (n,) or (N, n). method: 'cholesky' (any model) or 'aba' (O(n); not for
    models with mimic joints). Raises ValueError when the mass matrix is not positive
    definite (massless chains).
    """
    if method not in METHODS:
        raise ValueError(f"unknown forward dynamics method {method!r}: use one of {METHODS}")
    if method == 'cholesky' and not wrenches:
        n = model.n
        a, b, c = runtime.is_fast_single(q, n), runtime.is_fast_single(qd, n), runtime.is_fast_single(tau, n)
        if a is not None and b is not None and c is not None:
            k = _kernel(model)
            if k:   # one state through the generated kernel, on Python floats
                fr, fn, _ = k
                P, E0, A0 = runtime.model_params(model, fr, gravity=True)
                out = single_checked(fn, (P, A0, E0), a, b, c, n)
                if out is not None:
                    return np.array(out)
            # not positive definite, or no kernel: plain 2-D calls (checked, with the message)
            M = crba.mass_matrix(model, q)
            h = rnea.inverse_dynamics(model, q, qd, np.zeros(n))
            return cho_solve(cholesky(M[None]), (np.asarray(tau, dtype=float) - h)[None])[0]
    if method == 'aba' and not wrenches:
        n = model.n
        a, b, c = runtime.is_fast_single(q, n), runtime.is_fast_single(qd, n), runtime.is_fast_single(tau, n)
        if a is not None and b is not None and c is not None:
            out = _aba_single(model, a, b, c)
            if out is not None:
                return out
    single = np.ndim(q) == 1
    q = model.check_batch('q', q)
    N = q.shape[0]
    qd = model.check_batch('qd', qd, N)
    tau = model.check_batch('tau', tau, N)
    if method == 'aba':
        st = _structure(model)
        if not st['supported']:
            raise ValueError("method='aba' does not support mimic joints (they couple bodies); "
                             "use method='cholesky'")
        fext = external_body_wrenches(model, wrenches, N)
        out = _aba_kernel_forward_dynamics(model, q, qd, tau, fext)
        if out is None:   # no kernel, a batch size where the vectorised form is faster, or a failed check
            out = _aba_vectorized(model, q, qd, tau, fext)
    else:
        out = None if wrenches else _kernel_forward_dynamics(model, q, qd, tau)
        if out is None:
            M = crba.mass_matrix(model, q)
            h = rnea.inverse_dynamics(model, q, qd, np.zeros_like(qd), wrenches)
            out = cho_solve(cholesky(M), tau - h)
    return out[0] if single else out


# ---------------------------------------------------------------------------- generated kernel
KERNEL_MAX_BODIES = 24
_KERNEL_ROWS_FROM = 48


def _build_kernel(fr):
    """Trace qdd = M^-1 (tau - h): the CRBA of crba.py, the RNEA bias (eqs 16-21) and a
    Cholesky factorisation with two triangular solves, all straight-line for this tree.

    Outputs qdd, then the Cholesky pivots d_j^2 and the diagonal of M (the caller checks
    positive definiteness with them; a negative pivot makes sqrt fail on floats).
    """
    g = Graph()
    co, args, params, ga, taus = trace_inputs(fr, g)
    z, M, L, inv_d, pivots = trace_forward_dynamics(fr, g, co['x'], co['xd'], params, ga, taus)
    n = fr.n
    outputs = z + pivots + [M[j][j] for j in range(n)]
    return kernel(g, 'forward_dynamics_kernel', args, outputs)


def trace_inputs(fr, g):
    """Symbols of a forward-dynamics kernel: (coordinates, argument lists (Q, QD, TAU, P, A0,
    E0), inertia parameters, -g, joint torques)."""
    co = fr.trace_coordinates(g, rates=1)
    parg, params = fr.trace_params(g)
    ga = [g.input(f'g{k}') for k in range(3)]
    n = fr.n
    taus = [g.input(f'u{j}') for j in range(n)]
    args = co['args'] + [('TAU', [f'u{j}' for j in range(n)]), parg, ('A0', [f'g{k}' for k in range(3)]),
                         co['offset_args']]
    return co, args, params, ga, taus


def trace_forward_dynamics(fr, g, x, xd, params, a0, taus):
    """qdd = M^-1 (tau - h) traced: CRBA, the RNEA bias (eqs 16-21) with qdd = 0, Cholesky and
    two triangular solves. Returns (qdd, M, L, 1 / diag(L), pivots)."""
    from . import crba as crba_mod
    n = fr.n
    X = [fr.joint_transform(g, b, x[b]) for b in range(fr.nb)]
    M = crba_mod.trace_mass_matrix(fr, g, params, X)
    tau_b = trace_rnea(fr, g, x, xd, [0.0] * fr.nb, params, a0, X)
    h = [sum((float(fr.E[b, j]) * tau_b[b] for b in range(fr.nb) if fr.E[b, j] != 0), 0.0) for j in range(n)]
    L, inv_d, pivots = trace_cholesky(g, M)
    return trace_cho_solve(L, inv_d, [taus[j] - h[j] for j in range(n)]), M, L, inv_d, pivots


def trace_cholesky(g, M):
    """M = L L^T traced (M: nested n x n list). Returns (L, 1 / diag(L), pivots d_j^2); a
    negative pivot makes sqrt fail on floats, and the caller tests the pivots (PD check)."""
    n = len(M)
    L = [[0.0] * n for _ in range(n)]
    inv_d, pivots = [0.0] * n, [0.0] * n
    for j in range(n):
        s = M[j][j]
        for k in range(j):
            s = s - L[j][k] * L[j][k]
        pivots[j] = s
        d = g.sqrt(s)
        inv_d[j] = g.inv(d)
        L[j][j] = d
        for i in range(j + 1, n):
            s = M[i][j]
            for k in range(j):
                s = s - L[i][k] * L[j][k]
            L[i][j] = s * inv_d[j]
    return L, inv_d, pivots


def trace_cho_solve(L, inv_d, b):
    """x with L L^T x = b, traced: forward then backward substitution."""
    n = len(b)
    y = [0.0] * n
    for i in range(n):
        s = b[i]
        for k in range(i):
            s = s - L[i][k] * y[k]
        y[i] = s * inv_d[i]
    z = [0.0] * n
    for i in reversed(range(n)):
        s = y[i]
        for k in range(i + 1, n):
            s = s - L[k][i] * z[k]
        z[i] = s * inv_d[i]
    return z


def _kernel(model):
    if model.nb > KERNEL_MAX_BODIES:
        return False
    return runtime.compiled(model, 'forward_dynamics', _build_kernel)


def _kernel_forward_dynamics(model, q, qd, tau):
    """Kernel path for validated (N, n) arrays without wrenches; None when not applicable or
    when the mass matrix fails the positive-definiteness test (the caller reports it)."""
    k = _kernel(model)
    if not k:
        return None
    fr, fn, _ = k
    P, E0, A0 = runtime.model_params(model, fr, gravity=True)
    return run_checked(fn, (P, A0, E0), q, qd, tau, model.n, q.shape[0] >= _KERNEL_ROWS_FROM)


def single_checked(fn, params, q, qd, tau, n_out):
    """One state (lists of floats) through a Cholesky kernel (see run_checked): its first n_out
    outputs, or None when the mass matrix fails the positive-definiteness test."""
    P, A0, E0 = params
    try:
        vals = fn(q, qd, tau, P, A0, E0, sin=math.sin, cos=math.cos, sqrt=math.sqrt)
    except (ValueError, ZeroDivisionError):   # sqrt of a negative pivot, or a zero pivot
        return None
    n = len(q)
    s = sum(vals[:n_out])
    if s - s == 0.0 and all(p > _PD_RTOL * d for p, d in zip(vals[n_out:n_out + n], vals[n_out + n:], strict=True)):
        return vals[:n_out]
    return None


def run_checked(fn, params, q, qd, tau, n_out, rows):
    """Run a Cholesky kernel (its outputs end with the pivots and diag(M), n each) on validated
    (N, n) arrays: state by state on floats, or on numpy rows. Returns its first n_out outputs
    (N, n_out), or None when some mass matrix fails the positive-definiteness test."""
    n = q.shape[1]
    P, A0, E0 = params
    if not rows:
        try:
            vals = np.array([fn(a, b, c, P, A0, E0, sin=math.sin, cos=math.cos, sqrt=math.sqrt)
                             for a, b, c in zip(q.tolist(), qd.tolist(), tau.tolist(), strict=True)])
        except (ValueError, ZeroDivisionError):   # sqrt of a negative pivot, or a zero pivot
            return None
    else:
        vals = runtime.run_rows(fn, [q, qd, tau, P, A0, E0], n_out + 2 * n)
    piv, diag = vals[:, n_out:n_out + n], vals[:, n_out + n:]
    if not (np.all(np.isfinite(vals[:, :n_out])) and np.all(piv > _PD_RTOL * diag)):
        return None
    return vals[:, :n_out]


# ---------------------------------------------------------------------------- generated ABA kernel
# The recursion of the module docstring as straight-line code, in the primed body frames of
# codegen.Frames (S_i = e_z) turned about and shifted along their joint axes into modified
# Denavit-Hartenberg frames (x along the common normal to one child's axis), where a joint
# transform is Rx(alpha) T(a, 0, d) Rz(x + theta): four constants instead of a rotation and
# an offset, which on random chains takes a third of the operations away (_Geometry).
# Articulated inertias are general symmetric 6x6 matrices [[A, B], [B^T, C]] (angular rows
# first, like twists (w, v) and wrenches (n, f)), traced as nested lists.
#
# The source is O(n) (unlike the O(n^2) kernels capped at 24 bodies): build time grows by
# ~12 ms per body (0.3 s at 24, 0.7 s at 60, 1.2 s at 120, measured) while the kernel stays
# ~10x faster than the vectorised form, which on a chain goes level by level (8 ms at 64
# joints against 0.6 ms); above this many bodies the vectorised form is used.
ABA_KERNEL_MAX_BODIES = 128
# Batches: the float kernel state by state below _ABA_LOOP_BELOW states, the kernel on numpy
# rows from _ABA_ROWS_FROM states (measured crossovers 28-48 states for 2-24 bodies; the
# vectorised form was never clearly faster in between).
_ABA_LOOP_BELOW = 32
_ABA_ROWS_FROM = 32

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
            self.W[b, :3, 3:] = _hat(t) @ G

    def params(self, P):
        """Inertia parameters of the primed frames (codegen.Frames.inertia_params) in the b''
        frames: codegen.inertia_to_parent with f_{b'',b'} = T_b^-1, for all bodies at once."""
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


def _hat(v):
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


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

    def __init__(self, g, dec, revolute, x):
        ct, st = dec['theta']
        sx, sy, sz = dec['s']
        steps = []
        if revolute:   # Rz(theta) Rz(x): a quarter turn folds into cos x, sin x; else cos(x + theta)
            if _trivial(ct, st) or not isinstance(x, Sym):
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


def trace_aba(fr, geom, g, x, xd, taus, params, a0, fext=None):
    """The articulated body algorithm of the module docstring (eqs 17-20), traced in the b''
    frames of `geom`, where S_i = e_z: U_i = Ia_i S_i is column k of Ia_i (k = 2 for a revolute
    joint, 5 for a prismatic one), D_i its entry k and u_i = tau_i - (pa_i)_k. The update
    Ia - U U^T / D has row and column k exactly zero.

    x, xd: body coordinates and rates; taus: per body the torque of its joint (0.0 for welded
    bodies); params: per body (m, h, I) in b''; a0: base linear acceleration -g; fext: optional
    per-body wrenches (n, f) in b''. Returns per body (xdd_i, D_i, scale_i), None for welded
    bodies; scale_i is the trace of the 3x3 block of Ia_i that D_i lies in (same units as D_i,
    and >= D_i for a positive semi-definite Ia_i).
    """
    nb = fr.nb
    free = [bool(np.any(fr.E[b] != 0)) for b in range(nb)]
    X = [_Joint(g, geom.steps[b], fr.revolute[b], x[b]) for b in range(nb)]
    kk = [2 if fr.revolute[b] else 5 for b in range(nb)]
    V, c = [None] * nb, [None] * nb
    for b in range(nb):                                          # eq 18
        p, k = fr.parent[b], kk[b]
        Vp = X[b].twist_to_child(V[p]) if p >= 0 else [0.0] * 6
        V[b] = list(Vp)
        V[b][k] = Vp[k] + xd[b]
        # c = [V, S xd]: xd (w x e_z, v x e_z) (revolute) or xd (0, w x e_z) (prismatic)
        if k == 2:
            c[b] = [Vp[1] * xd[b], -(Vp[0] * xd[b]), 0.0, Vp[4] * xd[b], -(Vp[3] * xd[b]), 0.0]
        else:
            c[b] = [0.0, 0.0, 0.0, Vp[1] * xd[b], -(Vp[0] * xd[b]), 0.0]
    Ia, pa = [None] * nb, [None] * nb
    U, Dinv, u, out = [None] * nb, [None] * nb, [None] * nb, [None] * nb
    for b in reversed(range(nb)):
        p, k = fr.parent[b], kk[b]
        w, v = tuple(V[b][:3]), tuple(V[b][3:])
        n_, f_ = la.ad_t((w, v), la.inertia_times(params[b], (w, v)))
        own = [-e for e in n_ + f_]                              # eq 20: -ad_V^T J V
        if fext is not None:
            own = [a - e for a, e in zip(own, fext[b][0] + fext[b][1], strict=True)]
        P = own if pa[b] is None else [a + e for a, e in zip(pa[b], own, strict=True)]
        K = _sym6_rigid(params[b])
        if Ia[b] is not None:
            K = _sym6_add(Ia[b], K)
        if free[b]:
            col = [K[i][k] for i in range(6)]
            D = col[k]
            Dinv[b] = g.inv(D)
            u[b] = taus[b] - P[k]
            U[b] = [1.0 if i == k else g.bake(col[i] * Dinv[b]) for i in range(6)]    # U / D
            out[b] = (D, K[k - 2][k - 2] + K[k - 1][k - 1] + D)
            if p < 0:
                continue
            Ka = [[0.0] * 6 for _ in range(6)]
            for i in range(6):
                for j in range(i, 6):
                    if i != k and j != k:
                        Ka[i][j] = Ka[j][i] = K[i][j] - col[i] * U[b][j]
            # pa + Ia^A c + U u / D; its entry k is tau exactly
            P = [taus[b] if i == k else P[i] + la.dot(Ka[i], c[b]) + U[b][i] * u[b] for i in range(6)]
            K = Ka
        else:
            if p < 0:
                continue
            P = [P[i] + la.dot(K[i], c[b]) for i in range(6)]
        Kp = X[b].inertia_to_parent(K)
        Ia[p] = Kp if Ia[p] is None else _sym6_add(Ia[p], Kp)
        Pp = X[b].wrench_to_parent(P)
        pa[p] = Pp if pa[p] is None else [a + e for a, e in zip(pa[p], Pp, strict=True)]
    acc = [None] * nb
    base = [0.0, 0.0, 0.0] + list(a0)
    res = [None] * nb
    for b in range(nb):                                          # eq 19
        p, k = fr.parent[b], kk[b]
        ap = X[b].twist_to_child(acc[p] if p >= 0 else base)
        ap = [a + e for a, e in zip(ap, c[b], strict=True)]
        if free[b]:
            s = u[b] * Dinv[b]
            for i in range(6):
                if i != k:
                    s = s - U[b][i] * ap[i]
            res[b] = (s - ap[k],) + out[b]                       # xdd = (u - U^T a') / D
            ap[k] = s                                            # a = a' + S xdd
        acc[b] = ap
    return res


def _build_aba_kernel(fr, wrench=False):
    """Trace qdd by the articulated body algorithm (trace_aba) for this tree.

    Arguments (Q, QD, TAU, P, A0, E0[, FX]) as the Cholesky kernel's, but P and FX in the
    frames of _Geometry (its params and wrenches). Outputs qdd, then per joint D_i and its
    scale (trace_aba); the caller checks D_i > _PD_RTOL * scale, blind to the scale of the
    masses as the Cholesky kernel's pivot test. None when the frames cannot be built.
    """
    geom = _Geometry(fr)
    if not geom.ok:
        return None
    g = Graph()
    co = fr.trace_coordinates(g, rates=1)
    parg, params = fr.trace_params(g)
    ga = [g.input(f'g{k}') for k in range(3)]
    n, nb = fr.n, fr.nb
    taus = [g.input(f'u{j}') for j in range(n)]
    joint_of = [None] * nb
    for b in range(nb):
        for j in range(n):
            if fr.E[b, j] != 0:
                joint_of[b] = j
    args = co['args'] + [('TAU', [f'u{j}' for j in range(n)]), parg, ('A0', [f'g{k}' for k in range(3)]),
                         co['offset_args']]
    fext = None
    if wrench:
        names = [f'f{b}_{k}' for b in range(nb) for k in range(6)]
        args.append(('FX', names))
        fs = [g.input(nm) for nm in names]
        fext = [(tuple(fs[6 * b:6 * b + 3]), tuple(fs[6 * b + 3:6 * b + 6])) for b in range(nb)]
    res = trace_aba(fr, geom, g, co['x'], co['xd'], [0.0 if j is None else taus[j] for j in joint_of],
                    params, ga, fext)
    per_joint = [None] * n
    for b in range(nb):
        if joint_of[b] is not None:
            per_joint[joint_of[b]] = res[b]
    outputs = [r[i] for i in range(3) for r in per_joint]
    return kernel(g, 'aba_kernel', args, outputs) + (geom,)


def _aba_kernel(model, wrench=False):
    """(frames, function, source, geometry) of the model's ABA kernel, or False (too many bodies,
    mimic joints, or screws other than unit revolute / prismatic axes)."""
    if model.nb > ABA_KERNEL_MAX_BODIES or not _structure(model)['supported']:
        return False
    return runtime.compiled(model, 'aba_wrench' if wrench else 'aba', lambda fr: _build_aba_kernel(fr, wrench))


def _aba_params(model, k):
    """(P, A0, E0) for an ABA kernel: the inertias in its frames, cached until the model changes."""
    fr, _, _, geom = k
    P, E0, A0 = runtime.model_params(model, fr, gravity=True)
    return runtime.derived(model, 'aba_params', lambda: geom.params(P)), A0, E0


def _aba_accept(out, n):
    """Every D_i above _PD_RTOL times its scale (trace_aba), and a finite result."""
    s = sum(out[:n])
    return s - s == 0.0 and all(d > _PD_RTOL * m for d, m in zip(out[n:2 * n], out[2 * n:], strict=True))


def _aba_single(model, q, qd, tau):
    """One state (lists of floats) through the ABA kernel on Python floats; None when there is
    no kernel or the articulated inertias fail the check (the caller then reports it)."""
    def bind():
        k = _aba_kernel(model)
        return (k and k[1],) + (_aba_params(model, k) if k else ())
    c = runtime.derived(model, 'aba_single', bind)   # one look-up for the kernel and its parameters
    fn = c[0]
    if not fn:
        return None
    try:
        out = fn(q, qd, tau, *c[1:], sin=math.sin, cos=math.cos)
    except (ValueError, ZeroDivisionError, OverflowError):
        return None
    n = model.n
    return np.array(out[:n]) if _aba_accept(out, n) else None


def _aba_kernel_forward_dynamics(model, q, qd, tau, fext=None, mode=None):
    """ABA kernel on validated (N, n) arrays; fext: (N, nb, 6) body-frame wrenches or None.

    mode: 'loop' (Python floats, state by state), 'rows' (numpy rows) or None (by batch size).
    None when the vectorised form is to be used: no kernel, a batch size where it is faster,
    or some articulated inertia failing the check (the vectorised form then raises).
    """
    N, n = q.shape
    if mode is None:
        mode = 'loop' if N < _ABA_LOOP_BELOW else 'rows' if N >= _ABA_ROWS_FROM else None
    k = _aba_kernel(model, fext is not None) if mode else False
    if not k:
        return None
    fr, fn, _, geom = k
    P, A0, E0 = _aba_params(model, k)
    extra = [] if fext is None else [geom.wrenches(fext)]
    if mode == 'loop':
        vals = []
        for r in zip(q.tolist(), qd.tolist(), tau.tolist(), *[e.tolist() for e in extra], strict=True):
            try:
                out = fn(*r[:3], P, A0, E0, *r[3:], sin=math.sin, cos=math.cos)
            except (ValueError, ZeroDivisionError, OverflowError):
                return None
            if not _aba_accept(out, n):
                return None
            vals.append(out[:n])
        return np.array(vals).reshape(N, n)

    try:
        vals = runtime.run_rows(fn, [q, qd, tau, P, A0, E0] + extra, 3 * n)
    except (ZeroDivisionError, OverflowError):   # D from parameters alone (Python floats) is 0
        return None
    D, scale = vals[:, n:2 * n], vals[:, 2 * n:]
    if not (np.all(np.isfinite(vals[:, :n])) and np.all(D > _PD_RTOL * scale)):
        return None
    return vals[:, :n]
