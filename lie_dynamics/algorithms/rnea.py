"""Recursive Newton-Euler inverse dynamics on SE(3) (paper section 3.2, eqs 16-21).

The recursion, link by link in body frames, is written out once, in
lie_dynamics/codegen/traced/rnea.py, and traced from there into generated kernels.

Two implementations, same results to rounding:
  * the generated kernel (codegen), compiled once per model structure: one state runs it on
    Python floats; a batch on numpy rows of a chunk of states (state-last). This is the
    normal path (codegen.runtime.route decides, by THRESHOLDS).
  * `inverse_dynamics_vectorized` / `gravity_vectorized` below: the vectorised root-frame
    form (ancestor sums). They handle models whose screws are not plain URDF joints, models
    too large to unroll, and single states of models with many bodies.
In the root frame the two recursions become sums over ancestors and over subtrees, i.e.
products with the constant ancestor matrix (the block form G of eq 37):
    V^s_i = sum_{j <= i} A_j xd_j,  Vd^s_i = Vd_0 + sum_{j <= i} (A_j xdd_j + [V^s_j, A_j xd_j]),
    tau_i = A_i^T sum_{k >= i} F^s_k,
with A_j = Ad_{T_j} S_j; the per-body Newton-Euler wrench is evaluated in each body frame.
"""
import numpy as np

from ..codegen import runtime
from ..codegen.traced import rnea as traced
from .common import chunks
from .kinematics import adjoints, spatial_motion, spatial_screws, world_poses
from ..spatial import ad, Ad_inv

# Vectorised path: floats of work per state, so that chunks of 512 states keep the
# (chunk, nb, 6, 6) arrays in cache.
_PER_STATE = 4096

_ID_NO_GRAVITY = traced.INVERSE_DYNAMICS.variant(('inertia', 'no_gravity', 'offsets', 'armature'))
_ID_WRENCH_NO_GRAVITY = traced.INVERSE_DYNAMICS_WRENCH.variant(('inertia', 'no_gravity', 'offsets', 'armature'))


def inverse_dynamics(model, q, qd, qdd, wrenches=None, with_gravity=True, out=None):
    """tau for a state (n,) or a batch (N, n): paper eqs 16-21 (see module docstring).

    wrenches: optional {link: (m, f)} external wrench acting on the link, in the link frame,
    (6,) or (N, 6). with_gravity=False gives M(q) qdd + C(q, qd) qd. out: optional float64
    array of the result's shape to write into (a control loop then allocates nothing).
    """
    if not wrenches:   # the fast path (its kernel takes no wrenches): the result, or None
        tau = runtime.fast(model, traced.INVERSE_DYNAMICS if with_gravity else _ID_NO_GRAVITY)(q, qd, qdd, out)
        if tau is not None:
            return tau
    return runtime.call(model, _INVERSE_DYNAMICS, (q, qd, qdd), out, (wrenches, with_gravity))


def inverse_dynamics_validated(model, arrs, wrenches=None, with_gravity=True):
    """inverse_dynamics on validated (N, n) arrays [q, qd, qdd] (Model.validate) -> (N, n): the
    kernel, else the vectorised form. For callers that validated their arguments already."""
    N = len(arrs[0])
    fext = external_body_wrenches(model, wrenches, N)
    if fext is None:
        spec = traced.INVERSE_DYNAMICS if with_gravity else _ID_NO_GRAVITY
    else:
        spec = traced.INVERSE_DYNAMICS_WRENCH if with_gravity else _ID_WRENCH_NO_GRAVITY
        arrs = arrs + [runtime.frames(model).wrench_params(fext).reshape(N, 6 * model.nb)]
    tau = runtime.run(model, spec, arrs, c_order=True)
    return _vectorized(model, np.array(arrs[:3]), fext, with_gravity) if tau is None else tau


def joint_vector(model):
    """The shape of one state's joint torques or accelerations: (n,)."""
    return (model.n,)


_INVERSE_DYNAMICS = runtime.Entry(('q', 'qd', 'qdd'), joint_vector, inverse_dynamics_validated)


def inverse_dynamics_vectorized(model, q, qd, qdd, wrenches=None, with_gravity=True):
    """inverse_dynamics by the vectorised root-frame form only, whatever the model and batch size."""
    arrs, single = model.validate(('q', 'qd', 'qdd'), (q, qd, qdd))
    tau = _vectorized(model, np.array(arrs), external_body_wrenches(model, wrenches, len(arrs[0])), with_gravity)
    return tau[0] if single else tau


def gravity(model, q, out=None):
    """g(q): eqs 16-21 with V = 0 and Vd_0 = (0, -g); (n,) or (N, n). out: as inverse_dynamics."""
    tau = runtime.fast(model, traced.GRAVITY)(q, out)   # the fast path: the result, or None
    return runtime.call(model, _GRAVITY, (q,), out) if tau is None else tau


def gravity_validated(model, arrs):
    """gravity on validated (N, n) arrays [q] (Model.validate) -> (N, n): the kernel, else the
    vectorised form. For callers that validated their arguments already."""
    tau = runtime.run(model, traced.GRAVITY, arrs, c_order=True)
    return _gravity_vectorized(model, arrs[0]) if tau is None else tau


_GRAVITY = runtime.Entry(('q',), joint_vector, gravity_validated)


def coriolis_term(model, q, qd, out=None):
    """C(q, qd) qd: eqs 16-21 at qdd = 0 without gravity; (n,) or (N, n). out: as inverse_dynamics."""
    tau = runtime.fast(model, traced.CORIOLIS_TERM)(q, qd, out)   # the fast path: the result, or None
    return runtime.call(model, _CORIOLIS_TERM, (q, qd), out) if tau is None else tau


def coriolis_term_validated(model, arrs):
    """coriolis_term on validated (N, n) arrays [q, qd] -> (N, n): its kernel, else inverse
    dynamics at qdd = 0 without gravity."""
    tau = runtime.run(model, traced.CORIOLIS_TERM, arrs, c_order=True)
    if tau is None:
        tau = inverse_dynamics_validated(model, [arrs[0], arrs[1], np.zeros_like(arrs[1])], None, False)
    return tau


_CORIOLIS_TERM = runtime.Entry(('q', 'qd'), joint_vector, coriolis_term_validated)


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


# ---------------------------------------------------------------- vectorised (reference) path
def _vectorized(model, a, fext, with_gravity):
    """Root-frame form of eqs 16-21 on a validated (3, N, n) array -> (N, n); fext: (N, nb, 6)
    body wrenches or None."""
    q, qd, qdd = a
    N = q.shape[0]
    a0 = model.base_acceleration if with_gravity else np.zeros(6)
    x = model.body_coordinates(q)
    xd = qd @ model.E.T
    xdd = qdd @ model.E.T
    tau = np.empty((N, model.n))
    for sl in chunks(N, _PER_STATE):
        tau[sl] = _rnea(model, x[sl], xd[sl], xdd[sl], a0, None if fext is None else fext[sl])
    if model.armature.any():   # the rotors: M + diag(armature), as the kernels
        tau += qdd * model.armature
    return tau


def _rnea(model, x, xd, xdd, a0, fext):
    Ad, AdinvT = adjoints(world_poses(model, x))
    A = spatial_screws(model, Ad)
    V, Vd = spatial_motion(model, A, xd, xdd, a0)              # eqs 18-19, summed over ancestors
    # to body frames (Ad_{T^-1} = AdinvT^T), where J_i is constant
    VV = np.stack([V, Vd], axis=-1)
    VVb = np.swapaxes(AdinvT, -1, -2) @ VV
    JVV = model.J @ VVb
    Vb = VVb[..., 0]
    Fb = JVV[..., 1] - (np.swapaxes(ad(Vb), -1, -2) @ JVV[..., 0:1])[..., 0]   # J Vd - ad*_V J V
    if fext is not None:
        Fb = Fb - fext
    Fs = (AdinvT @ Fb[..., None])[..., 0]
    Fsub = model.ancestors.T @ Fs                               # subtree sums (backward pass)
    tau_b = np.einsum('nbi,nbi->nb', A, Fsub)                   # S^T F
    return tau_b @ model.E


def gravity_vectorized(model, q):
    """gravity by the vectorised root-frame form only."""
    (q,), single = model.validate(('q',), (q,))
    out = _gravity_vectorized(model, q)
    return out[0] if single else out


def _gravity_vectorized(model, q):
    x = model.body_coordinates(q)
    out = np.empty((q.shape[0], model.n))
    for sl in chunks(q.shape[0], _PER_STATE):
        out[sl] = _gravity(model, x[sl])
    return out


def _gravity(model, x):
    Ad, AdinvT = adjoints(world_poses(model, x))
    A = spatial_screws(model, Ad)
    # body-frame base acceleration: Ad_{T^-1} (0, -g) = AdinvT^T (0, -g)
    Vdb = np.swapaxes(AdinvT[..., 3:, :], -1, -2) @ model.base_acceleration[3:]
    Fb = (model.J @ Vdb[..., None])[..., 0]
    Fs = (AdinvT @ Fb[..., None])[..., 0]
    Fsub = model.ancestors.T @ Fs
    return np.einsum('nbi,nbi->nb', A, Fsub) @ model.E
