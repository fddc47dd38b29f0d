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

Bodies at one depth of the tree are processed together, and every step is vectorised
over states. Locked joints are welded (no projection, xdd = 0). Mimic joints couple
bodies, which this recursion cannot express: use method='cholesky' for them.
"""
import math

import numpy as np

from . import crba, rnea
from . import codegen as cg
from .codegen import model_cache
from .kinematics import ad_matrices
from .lagrangian import _swap, external_body_wrenches, kinematic_state

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
        X = np.linalg.solve(_swap(L), np.linalg.solve(L, B))
    return X[..., 0] if vec else X


# ---------------------------------------------------------------------------- ABA
def _structure(model):
    """Depth levels and the joint each body follows; cached per model."""
    mc = model_cache(model)
    cache = mc.get('aba')
    if cache is not None:
        return cache
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
    cache = dict(E=E, supported=supported, free=free, joint_of=joint_of, levels=levels)
    mc['aba'] = cache
    return cache


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
    XT = _swap(X)
    IA = np.broadcast_to(J, (N, nb, 6, 6)).copy()
    JV = (J @ Vb[..., None])[..., 0]
    pA = -(_swap(ad_matrices(Vb)) @ JV[..., None])[..., 0]
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
            ap[:, ~sel] = X[:, lv['root']] @ model._a0
        ap += c[:, idx]
        xi = (u[:, idx] - np.einsum('nlj,nlj->nl', U[:, idx], ap)) / D[:, idx]
        xi = xi * free[idx]
        xdd[:, idx] = xi
        acc[:, idx] = ap + S[idx] * xi[..., None]
    out = np.empty((N, model.n))
    out[:, st['joint_of'][free]] = xdd[:, free]
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
        a, b, c = cg.is_fast_single(q, n), cg.is_fast_single(qd, n), cg.is_fast_single(tau, n)
        if a is not None and b is not None and c is not None:
            k = _kernel(model)
            if k:   # one state through the generated kernel, on Python floats
                fr, fn, _ = k
                P, E0, A0 = cg.model_params(model, fr, gravity=True)
                try:
                    out = fn(a, b, c, P, A0, E0, sin=math.sin, cos=math.cos, sqrt=math.sqrt)
                except (ValueError, ZeroDivisionError):
                    out = None
                if out is not None and all(d > _PD_RTOL * m for d, m in zip(out[n:2 * n], out[2 * n:])):
                    return np.array(out[:n])
            # not positive definite, or no kernel: plain 2-D calls (checked, with the message)
            M = crba.mass_matrix(model, q)
            h = rnea.inverse_dynamics(model, q, qd, np.zeros(n))
            return cho_solve(cholesky(M[None]), (np.asarray(tau, dtype=float) - h)[None])[0]
    single = np.ndim(q) == 1
    q = model._batch('q', q)
    N = q.shape[0]
    qd = model._batch('qd', qd, N)
    tau = model._batch('tau', tau, N)
    if method == 'aba':
        st = _structure(model)
        if not st['supported']:
            raise ValueError("method='aba' does not support mimic joints (they couple bodies); "
                             "use method='cholesky'")
        fext = external_body_wrenches(model, wrenches, N)
        x = model.body_coordinates(q)
        xd = qd @ model.E.T
        out = np.empty((N, model.n))
        step = max(1, (1 << 20) // (60 * max(1, model.nb)))
        for i in range(0, N, step):
            sl = slice(i, min(N, i + step))
            out[sl] = _aba(model, st, x[sl], xd[sl], tau[sl], None if fext is None else fext[sl])
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
    from . import crba as crba_mod
    g = cg.Graph()
    co = fr.trace_coordinates(g, rates=1)
    parg, params = fr.trace_params(g)
    ga = [g.input(f'g{k}') for k in range(3)]
    n = fr.n
    taus = [g.input(f'u{j}') for j in range(n)]
    X = [fr.joint_transform(g, b, co['x'][b]) for b in range(fr.nb)]
    M = crba_mod.trace_mass_matrix(fr, g, params, X)
    tau_b = cg.trace_rnea(fr, g, co['x'], co['xd'], [0.0] * fr.nb, params, ga, X)
    h = [sum((float(fr.E[b, j]) * tau_b[b] for b in range(fr.nb) if fr.E[b, j] != 0), 0.0) for j in range(n)]
    rhs = [taus[j] - h[j] for j in range(n)]
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
    y = [0.0] * n
    for i in range(n):
        s = rhs[i]
        for k in range(i):
            s = s - L[i][k] * y[k]
        y[i] = s * inv_d[i]
    z = [0.0] * n
    for i in reversed(range(n)):
        s = y[i]
        for k in range(i + 1, n):
            s = s - L[k][i] * z[k]
        z[i] = s * inv_d[i]
    outputs = z + pivots + [M[j][j] for j in range(n)]
    args = co['args'] + [('TAU', [f'u{j}' for j in range(n)]), parg, ('A0', [f'g{k}' for k in range(3)]),
                         co['offset_args']]
    src = cg.emit(g, 'forward_dynamics_kernel', args, outputs)
    return cg.compile_function(src, 'forward_dynamics_kernel'), src


def _kernel(model):
    if model.nb > KERNEL_MAX_BODIES:
        return False
    return cg.compiled(model, 'forward_dynamics', _build_kernel)


def _kernel_forward_dynamics(model, q, qd, tau):
    """Kernel path for validated (N, n) arrays without wrenches; None when not applicable or
    when the mass matrix fails the positive-definiteness test (the caller reports it)."""
    k = _kernel(model)
    if not k:
        return None
    fr, fn, _ = k
    P, E0, A0 = cg.model_params(model, fr, gravity=True)
    N, n = q.shape
    if N < _KERNEL_ROWS_FROM:
        try:
            vals = np.array([fn(a, b, c, P, A0, E0, sin=math.sin, cos=math.cos, sqrt=math.sqrt)
                             for a, b, c in zip(q.tolist(), qd.tolist(), tau.tolist())])
        except (ValueError, ZeroDivisionError):   # sqrt of a negative pivot, or a zero pivot
            return None
    else:
        vals = cg.run_rows(lambda Q, QD, T, sin, cos, sqrt: fn(Q, QD, T, P, A0, E0, sin=sin, cos=cos, sqrt=sqrt),
                           [q, qd, tau], (), 3 * n)
    piv, diag = vals[:, n:2 * n], vals[:, 2 * n:]
    if not (np.all(np.isfinite(vals[:, :n])) and np.all(piv > _PD_RTOL * diag)):
        return None
    return vals[:, :n]
