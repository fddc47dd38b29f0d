"""Recursive Newton-Euler inverse dynamics on SE(3) (paper section 3.2, eqs 16-21).

The paper's recursion runs link by link in body frames, with f_{i-1,i} = M_i e^{[S_i] x_i}
(eqs 16-17):
    V_i  = Ad_{f_{i-1,i}^-1} V_{i-1} + S_i xd_i                                   (18)
    Vd_i = S_i xdd_i + Ad_{f_{i-1,i}^-1} Vd_{i-1} + ad_{V_i}(S_i xd_i)            (19)
    F_i  = Ad*_{f_{i,i+1}^-1} F_{i+1} + J_i Vd_i - ad*_{V_i}(J_i V_i)             (20)
    tau_i = S_i^T F_i                                                              (21)
with V_0 = 0, Vd_0 = (0, -g) (gravity as a base acceleration).

Two implementations, same results to rounding:
  * kernels.py unrolls this recursion for the model's tree into straight-line arithmetic
    (eq 20's body term regrouped by the Jacobi identity), compiled once per model. One state
    runs it on Python floats; a batch runs it on numpy rows of a chunk of states
    (state-last). This is the normal path.
  * `_reference_*` below is the vectorised root-frame form (ancestor sums, see below). It
    handles models whose screws are not plain URDF joints, models too large to unroll, and
    single states of models with many bodies (where it is faster than the float kernel).
In the root frame the two recursions become sums over ancestors and over subtrees, i.e.
products with the constant ancestor matrix (the block form G of eq 37):
    V^s_i = sum_{j <= i} A_j xd_j,  Vd^s_i = Vd_0 + sum_{j <= i} (A_j xdd_j + [V^s_j, A_j xd_j]),
    tau_i = A_i^T sum_{k >= i} F^s_k,
with A_j = Ad_{T_j} S_j; the per-body term of (20) is evaluated in each body frame.
"""
import numpy as np

from ..codegen import kernels
from .kinematics import ad_matrices, adjoints, spatial_screws, world_poses
from ..spatial import Ad_inv

_CHUNK = 512  # reference path: states per pass, keeps the (chunk, nb, 6, 6) arrays in cache
# Kernel path: below this many states a Python loop of the float kernel beats the numpy-rows
# kernel (each row operation costs ~0.5 us whatever its length; measured crossover ~30 on
# the 7-DoF arm). Above ~48 bodies the float kernel of inverse dynamics (~15 ns per flop) is
# slower than the vectorised reference for one state, so small batches go there.
_SMALL_BATCH = 32
_FLOAT_MAX_BODIES = 48


def _chunks(N, size=_CHUNK):
    return [slice(i, min(N, i + size)) for i in range(0, N, size)] if N > size else [slice(None)]


_F64 = np.dtype(float)
_ND = np.ndarray
_NO_GRAVITY = (0.0, 0.0, 0.0)
_NO_GRAVITY_ROWS = tuple(np.array(0.0) for _ in range(3))


def _fast_single(n, args):
    """Float lists for a single state given as finite float64 arrays of shape (n,), else None.

    The common call from a control loop: skips the generic conversion; finiteness comes from
    Python sums (a non-finite or overflowing sum sends the input to the exact checks).
    """
    lists = []
    s = 0.0
    for x in args:
        if type(x) is not _ND or x.shape != (n,) or x.dtype != _F64:
            return None
        x = x.tolist()
        s += sum(x)
        lists.append(x)
    return lists if s - s == 0.0 else None


def _states(model, args, names):
    """Validated float arrays, all (n,) (one state) or all (N, n); raises ValueError naming the
    argument. Float64 inputs are not copied."""
    n = model.n
    try:
        arrs = [np.asarray(x, dtype=float) for x in args]
    except (ValueError, TypeError):
        arrs = None
    if arrs is not None:
        shape = arrs[0].shape
        if len(shape) in (1, 2) and shape[-1] == n and all(x.shape == shape for x in arrs):
            with np.errstate(over='ignore', invalid='ignore'):  # overflow only means: check exactly
                s = sum(float(x.sum()) for x in arrs)
            if s - s == 0.0:
                return arrs
    # exact checks (also accepts a (n,) state mixed with (1, n) ones, as a single state)
    first = model.check_batch(names[0], args[0])
    arrs = [first] + [model.check_batch(nm, x, first.shape[0]) for nm, x in zip(names[1:], args[1:])]
    return [x[0] for x in arrs] if np.ndim(args[0]) == 1 else arrs


def inverse_dynamics(model, q, qd, qdd, wrenches=None, with_gravity=True):
    """tau for a state (n,) or a batch (N, n): paper eqs 16-21 (see module docstring).

    wrenches: optional {link: (m, f)} external wrench acting on the link, in the link frame,
    (6,) or (N, 6). with_gravity=False gives M(q) qdd + C(q, qd) qd.
    """
    K = model.__dict__.get('_kernels') or kernels.for_model(model)
    if K is not None and not wrenches and K.structure.nb <= _FLOAT_MAX_BODIES:
        lists = _fast_single(model.n, (q, qd, qdd))
        if lists is not None:
            P, _, A0, E0 = K.params(model)
            return np.array(K.function('id')(*lists, P, A0 if with_gravity else _NO_GRAVITY, E0))
    arrs = _states(model, (q, qd, qdd), ('q', 'qd', 'qdd'))
    single = arrs[0].ndim == 1
    N = 1 if single else len(arrs[0])
    if K is None or (N < _SMALL_BATCH and model.nb > _FLOAT_MAX_BODIES):
        return _reference_inverse_dynamics(model, np.array(arrs), wrenches, with_gravity)
    fext = external_body_wrenches(model, wrenches, N)
    if fext is not None:
        fext = K.structure.wrench_params(fext).reshape(N, 6 * model.nb)
    kind = 'id' if fext is None else 'id_wrench'
    if single or N < _SMALL_BATCH:  # the float kernel, state by state
        P, _, A0, E0 = K.params(model)
        A0 = A0 if with_gravity else _NO_GRAVITY
        f_float = K.function(kind)
        lists = [x.reshape(N, model.n).tolist() for x in arrs] + ([] if fext is None else [fext.tolist()])
        tau = np.array([f_float(x, y, z, P, A0, E0, *w) for x, y, z, *w in zip(*lists)]).reshape(N, model.n)
        return tau[0] if single else tau
    P, _, A0, E0 = K.row_params(model)
    A0 = A0 if with_gravity else _NO_GRAVITY_ROWS
    out = np.empty((N, model.n))
    for sl, f_rows, args, B in K.rows(kind, arrs + ([] if fext is None else [fext])):
        tau = f_rows(*args[:3], P, A0, E0, *args[3:], B)
        for j in range(model.n):
            out[sl, j] = tau[j]
    return out


def gravity(model, q):
    """g(q): eqs 16-21 with V = 0 and Vd_0 = (0, -g); (n,) or (N, n)."""
    K = model.__dict__.get('_kernels') or kernels.for_model(model)
    if K is not None:
        lists = _fast_single(model.n, (q,))
        if lists is not None:
            _, P, A0, E0 = K.params(model)
            return np.array(K.function('gravity')(lists[0], P, A0, E0))
    a = _states(model, (q,), ('q',))[0]
    if K is None:
        return _reference_gravity(model, a)
    if a.ndim == 1 or len(a) < _SMALL_BATCH:  # the float kernel, state by state
        _, P, A0, E0 = K.params(model)
        f_float = K.function('gravity')
        if a.ndim == 1:
            return np.array(f_float(a.tolist(), P, A0, E0))
        return np.array([f_float(x, P, A0, E0) for x in a.tolist()]).reshape(a.shape)
    _, P, A0, E0 = K.row_params(model)
    out = np.empty(a.shape)
    for sl, f_rows, args, B in K.rows('gravity', [a]):
        tau = f_rows(*args, P, A0, E0, B)
        for j in range(model.n):
            out[sl, j] = tau[j]
    return out


def external_body_wrenches(model, wrenches, N):
    """{link: wrench (m, f) acting on the link, in the link frame} -> (N, nb, 6) body-frame wrenches.

    A wrench (shape (6,) or (N, 6)) on link l, rigidly attached to body b at T_bl, acts on body b
    as Ad_{T_bl^-1}^T w. Links fixed to the world, or to a part of the tree that cannot move a
    controlled joint, take no effect. None when there are no wrenches.
    """
    if not wrenches:
        return None
    if not isinstance(wrenches, dict):
        raise ValueError('wrenches must be a dict {link name: (m, f) wrench in the link frame}')
    out = np.zeros((N, model.nb, 6))
    for link, w in wrenches.items():
        if link not in model.link_frames:
            raise ValueError(f"unknown link '{link}' in wrenches")
        w = np.asarray(w, dtype=float)
        if w.shape not in ((6,), (N, 6)):
            raise ValueError(f"wrench on '{link}' must have shape (6,) or ({N}, 6), got {w.shape}")
        if not np.all(np.isfinite(w)):
            raise ValueError(f"wrench on '{link}' contains non-finite values")
        b, T = model.link_frames[link]
        if b >= 0:
            out[:, b] += w @ Ad_inv(T)  # row form of Ad_{T_bl^-1}^T w
    return out


# ---------------------------------------------------------------- reference (vectorised) path
def _reference_inverse_dynamics(model, a, wrenches, with_gravity):
    """Root-frame form of eqs 16-21 on a validated (3, n) or (3, N, n) array."""
    single = a.ndim == 2
    q, qd, qdd = (a[:, None] if single else a)
    N = q.shape[0]
    fext = external_body_wrenches(model, wrenches, N)
    a0 = model.base_acceleration if with_gravity else np.zeros(6)
    x = model.body_coordinates(q)
    xd = qd @ model.E.T
    xdd = qdd @ model.E.T
    tau = np.empty((N, model.n))
    for sl in _chunks(N):
        tau[sl] = _rnea(model, x[sl], xd[sl], xdd[sl], a0, None if fext is None else fext[sl])
    return tau[0] if single else tau


def _rnea(model, x, xd, xdd, a0, fext):
    Ad, AdinvT = adjoints(world_poses(model, x))
    A = spatial_screws(model, Ad)
    Axd = A * xd[..., None]
    V = model.ancestors @ Axd                                  # eq 18, summed over ancestors
    acc = A * xdd[..., None] + (ad_matrices(V) @ Axd[..., None])[..., 0]
    Vd = model.ancestors @ acc + a0                             # eq 19
    # to body frames (Ad_{T^-1} = AdinvT^T), where J_i is constant
    VV = np.stack([V, Vd], axis=-1)
    VVb = np.swapaxes(AdinvT, -1, -2) @ VV
    JVV = model.J @ VVb
    Vb = VVb[..., 0]
    Fb = JVV[..., 1] - (np.swapaxes(ad_matrices(Vb), -1, -2) @ JVV[..., 0:1])[..., 0]   # eq 20
    if fext is not None:
        Fb = Fb - fext
    Fs = (AdinvT @ Fb[..., None])[..., 0]
    Fsub = model.ancestors.T @ Fs                               # subtree sums (backward pass)
    tau_b = np.einsum('nbi,nbi->nb', A, Fsub)                   # eq 21
    return tau_b @ model.E


def _reference_gravity(model, q):
    """Root-frame gravity on a validated (n,) or (N, n) array."""
    single = q.ndim == 1
    q = q[None] if single else q
    x = model.body_coordinates(q)
    out = np.empty((q.shape[0], model.n))
    for sl in _chunks(q.shape[0]):
        out[sl] = _gravity(model, x[sl])
    return out[0] if single else out


def _gravity(model, x):
    Ad, AdinvT = adjoints(world_poses(model, x))
    A = spatial_screws(model, Ad)
    # body-frame base acceleration: Ad_{T^-1} (0, -g) = AdinvT^T (0, -g)
    Vdb = np.swapaxes(AdinvT[..., 3:, :], -1, -2) @ model.base_acceleration[3:]
    Fb = (model.J @ Vdb[..., None])[..., 0]
    Fs = (AdinvT @ Fb[..., None])[..., 0]
    Fsub = model.ancestors.T @ Fs
    return np.einsum('nbi,nbi->nb', A, Fsub) @ model.E
