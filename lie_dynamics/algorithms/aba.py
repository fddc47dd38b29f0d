"""Forward dynamics qdd = M(q)^-1 (tau - h(q, qd)): a Cholesky solve and the O(n) articulated body algorithm.

method='cholesky' (any model): M from the composite rigid body algorithm (crba.py), the
bias h = inverse_dynamics(q, qd, 0, wrenches) from the RNEA, then M = L L^T and two
triangular solves (cholesky.py; M is never inverted). A mass matrix that is not
numerically positive definite (a massless body with nothing beyond it, a massless chain)
raises ValueError. Without wrenches, a generated kernel runs all of it (CRBA, RNEA bias,
Cholesky, solves) as straight-line code (codegen/traced/cholesky.py); from
THRESHOLDS['aba'].looped_from bodies, where the native backend runs the ABA's looped kernel
(codegen/looped.py; not with mimic joints), that kernel answers instead (`_spec`): the same qdd to
rounding in O(n), where the Cholesky kernel's source is O(n^3). The Cholesky reference still
reports a mass matrix that is not positive definite.

method='aba': the articulated body algorithm in the Lie-group form of Ploen & Park, in
body frames with X_i = Ad_{f_{i-1,i}^-1} (f_{i-1,i} = M_i e^{[S_i] x_i}, eq 17):

  forward   V_i = X_i V_parent + S_i xd_i,   c_i = ad_{V_i} S_i xd_i                  (eq 18)
            Ia_i = J_i,  pa_i = -ad_{V_i}^T J_i V_i - F_ext,i   (the RNEA's body wrench at Vd = 0)
  backward  U_i = Ia_i S_i,  D_i = S_i^T U_i + armature_i,  u_i = tau_i - S_i^T pa_i,
            Ia_parent += X_i^T (Ia_i - U_i U_i^T / D_i) X_i,
            pa_parent += X_i^T (pa_i + (Ia_i - U_i U_i^T / D_i) c_i + U_i u_i / D_i)
  forward   a'_i = X_i a_parent + c_i,  xdd_i = (u_i - U_i^T a'_i) / D_i,  a_i = a'_i + S_i xdd_i
            with a_0 = (0, -g)                                                        (eq 19)

Locked joints are welded (no projection, xdd = 0). Mimic joints couple bodies, which this
recursion cannot express: use method='cholesky' for them. Two evaluations: the generated
kernel (codegen/traced/aba.py, with or without wrenches) and `aba_vectorized` (bodies at one
depth of the tree together, every step vectorised over states). A D_i that is not
numerically positive (a joint that moves no mass) raises ValueError.

Each method: validate, then the generated kernel where codegen.runtime.route says so (and
its outputs pass the positive-definiteness test), else the vectorised reference.
"""
import numpy as np

from . import crba, rnea
from .cholesky import PD_RTOL, cho_solve, cholesky
from ..codegen import runtime
from ..codegen.traced import aba as traced_aba
from ..codegen.traced import cholesky as traced_cholesky
from .common import chunks, kinematic_state
from .rnea import external_body_wrenches
from ..spatial import ad, transpose

METHODS = ('cholesky', 'aba')
_MIMIC = "method='aba' does not support mimic joints (they couple bodies); use method='cholesky'"


def forward_dynamics(model, q, qd, tau, wrenches=None, method='cholesky', out=None):
    """Joint accelerations qdd with inverse_dynamics(q, qd, qdd, wrenches) = tau.

    q, qd, tau: (n,) or (N, n). method: 'cholesky' (any model) or 'aba' (O(n); not for
    models with mimic joints). Raises ValueError when the mass matrix is not positive
    definite (massless chains). out: optional float64 array of the result's shape, written
    and returned.
    """
    if method not in METHODS:
        raise ValueError(f"unknown forward dynamics method {method!r}: use one of {METHODS}")
    if not wrenches:   # the fast path (its kernels take no wrenches): the result, or None
        qdd = runtime.fast(model, _spec(model, method))(q, qd, tau, out)
        if qdd is not None:
            return qdd
    return runtime.call(model, _FORWARD_DYNAMICS, (q, qd, tau), out, (wrenches, method))


def forward_dynamics_validated(model, arrays, wrenches=None, method='cholesky'):
    """forward_dynamics on validated (N, n) arrays [q, qd, tau] (Model.validate), by the
    kernels or the references. For callers that validated their arguments already."""
    q, qd, tau = arrays
    if method == 'aba':
        if not traced_aba.supports(model):
            raise ValueError(_MIMIC)
        fext = external_body_wrenches(model, wrenches, len(q))
        out = _aba_kernel(model, q, qd, tau, fext)
        if out is None:   # no kernel, a batch size where the vectorised form is faster, or a failed check
            out = _aba_vectorized(model, q, qd, tau, fext)
    else:
        out = None if wrenches else runtime.run(model, _spec(model, method), [q, qd, tau])
        if out is None:
            out = _cholesky_vectorized(model, q, qd, tau, wrenches)
    return out


def forward_dynamics_spec(model):
    """The kernel of forward_dynamics(q, qd, tau) with its defaults (Model.forward_dynamics's C
    method, dispatch.native_first): method='cholesky', as `_spec` chooses it."""
    return _spec(model, 'cholesky')


def _spec(model, method):
    """The kernel of a forward-dynamics call without wrenches. method='cholesky' takes the ABA's
    where that one is looped (runtime.looped: the native backend, from THRESHOLDS['aba'].looped_from
    bodies, no mimic joints): the same qdd to rounding in O(n), where the Cholesky kernel's source
    is O(n^3) and above its native cap the vectorised reference ran (20-120x Pinocchio on chains
    of 100-200 bodies). A declined result (the pivot test) still ends in the Cholesky reference,
    which names the problem."""
    if method == 'aba':
        return traced_aba.spec(model)
    return runtime.derived(model, 'cholesky_spec', lambda: _looped_aba(model))   # runtime.looped's rule, cached


def _looped_aba(model):
    if traced_aba.supports(model):
        s = traced_aba.spec(model)
        if runtime.looped(model, s):
            return s
    return traced_cholesky.FORWARD_DYNAMICS


_FORWARD_DYNAMICS = runtime.Entry(('q', 'qd', 'tau'), rnea.joint_vector, forward_dynamics_validated)


# ---------------------------------------------------------------------------- Cholesky
def forward_dynamics_vectorized(model, q, qd, tau, wrenches=None):
    """forward_dynamics(..., method='cholesky') without its generated kernel: M and h by their
    own dispatch (crba.mass_matrix, rnea.inverse_dynamics), then a batched factorisation."""
    (q, qd, tau), single = model.validate(('q', 'qd', 'tau'), (q, qd, tau))
    out = _cholesky_vectorized(model, q, qd, tau, wrenches)
    return out[0] if single else out


def _cholesky_vectorized(model, q, qd, tau, wrenches):
    """On validated (N, n) arrays: M and the bias h by their validated paths, then the solves."""
    M = crba.mass_matrix_validated(model, q)
    h = rnea.inverse_dynamics_validated(model, [q, qd, np.zeros_like(qd)], wrenches)
    return cho_solve(cholesky(M), tau - h)


def forward_dynamics_kernel(model, q, qd, tau, mode=None):
    """forward_dynamics(..., method='cholesky') from the generated Python kernel: mode 'loop'
    (Python floats, state by state), 'rows' (numpy rows) or None (as route decides). None
    when there is no kernel or a mass matrix fails the positive-definiteness test."""
    (q, qd, tau), single = model.validate(('q', 'qd', 'tau'), (q, qd, tau))
    out = runtime.run(model, traced_cholesky.FORWARD_DYNAMICS, [q, qd, tau], mode, native_first=False)
    return out if out is None or not single else out[0]


# ---------------------------------------------------------------------------- ABA
def aba_kernel(model, q, qd, tau, wrenches=None, mode=None):
    """forward_dynamics(..., method='aba') from the generated kernel: mode 'loop', 'rows' or
    None (the native kernel, else as route decides). None when there is no kernel (too many
    bodies, mimic joints, screws other than unit revolute / prismatic axes) or an
    articulated inertia fails the check (the vectorised form then raises)."""
    (q, qd, tau), single = model.validate(('q', 'qd', 'tau'), (q, qd, tau))
    out = _aba_kernel(model, q, qd, tau, external_body_wrenches(model, wrenches, len(q)), mode)
    return out if out is None or not single else out[0]


def _aba_kernel(model, q, qd, tau, fext, mode=None):
    if fext is None:
        return runtime.run(model, traced_aba.spec(model), [q, qd, tau], mode)
    return runtime.run(model, traced_aba.spec(model, True), [q, qd, tau, traced_aba.wrenches(model, fext)], mode)


def aba_vectorized(model, q, qd, tau, wrenches=None):
    """forward_dynamics(..., method='aba') by the vectorised form only (numpy over the bodies
    of one depth and over states), whatever the model and batch size."""
    (q, qd, tau), single = model.validate(('q', 'qd', 'tau'), (q, qd, tau))
    out = _aba_vectorized(model, q, qd, tau, external_body_wrenches(model, wrenches, len(q)))
    return out[0] if single else out


def _aba_vectorized(model, q, qd, tau, fext):
    """The vectorised ABA on validated (N, n) arrays; fext: (N, nb, 6) body wrenches or None.
    Raises ValueError for mimic joints and for a zero articulated inertia."""
    if not traced_aba.supports(model):
        raise ValueError(_MIMIC)
    st = runtime.structural(model, 'aba_levels', lambda: _levels(model))
    N = q.shape[0]
    x = model.body_coordinates(q)
    xd = qd @ model.E.T
    out = np.empty((N, model.n))
    for sl in chunks(N, 120 * max(1, model.nb)):
        out[sl] = _aba(model, st, x[sl], xd[sl], tau[sl], None if fext is None else fext[sl])
    return out


def _levels(model):
    """Depth levels and the joint each body follows."""
    nz = model.E != 0
    free = nz.any(axis=1)
    joint_of = np.where(free, np.argmax(nz, axis=1), -1)
    levels = []
    for d in range(1, int(model.depth.max()) + 1 if model.nb else 1):
        idx = np.flatnonzero(model.depth == d)
        par = model.parent[idx]
        has_par = par >= 0
        levels.append(dict(idx=idx, par=par[has_par], child=idx[has_par], root=idx[~has_par],
                           unique=len(set(par[has_par].tolist())) == int(has_par.sum())))
    return dict(free=free, joint_of=joint_of, levels=levels)


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
    c = (ad(Vb) @ Sxd[..., None])[..., 0]
    # X_i = Ad_{T_i^-1} Ad_{T_parent}
    X = Adinv.copy()
    has_par = model.parent >= 0
    X[:, has_par] = Adinv[:, has_par] @ Ad[:, model.parent[has_par]]
    XT = transpose(X)
    IA = np.broadcast_to(J, (N, nb, 6, 6)).copy()
    JV = (J @ Vb[..., None])[..., 0]
    pA = -(transpose(ad(Vb)) @ JV[..., None])[..., 0]
    if fext is not None:
        pA -= fext
    free = st['free']
    taub = np.zeros((N, nb))
    taub[:, free] = tau[:, st['joint_of'][free]]
    arm = np.zeros(nb)   # the armature of each body's joint: D_i = S_i^T Ia_i S_i + armature
    arm[free] = model.armature[st['joint_of'][free]]
    U = np.zeros((N, nb, 6))
    D = np.ones((N, nb))
    u = np.zeros((N, nb))
    for lv in reversed(st['levels']):
        idx = lv['idx']
        Ia, pa = IA[:, idx], pA[:, idx]
        f = free[idx]
        Ui = (Ia @ S[idx][..., None])[..., 0]
        Di = np.einsum('lj,nlj->nl', S[idx], Ui) + arm[idx]
        ui = taub[:, idx] - np.einsum('lj,nlj->nl', S[idx], pa)
        scale = np.max(np.abs(Ia), axis=(-1, -2))
        if np.any(f & np.any(~(Di > PD_RTOL * scale), axis=0)):
            k = int(np.flatnonzero(f & np.any(~(Di > PD_RTOL * scale), axis=0))[0])
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
