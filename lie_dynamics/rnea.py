"""Recursive Newton-Euler inverse dynamics on SE(3) (paper section 3.2, eqs 16-21).

The paper's recursion runs link by link in body frames:
    V_i  = Ad_{f_{i-1,i}^-1} V_{i-1} + S_i xd_i                                   (18)
    Vd_i = S_i xdd_i + Ad_{f_{i-1,i}^-1} Vd_{i-1} + ad_{V_i}(S_i xd_i)            (19)
    F_i  = Ad*_{f_{i,i+1}^-1} F_{i+1} + J_i Vd_i - ad*_{V_i}(J_i V_i)             (20)
    tau_i = S_i^T F_i                                                              (21)
with V_0 = 0, Vd_0 = (0, -g) (gravity as a base acceleration). Expressed in the root
frame the two recursions become sums over ancestors and over subtrees, i.e. products
with the constant ancestor matrix (the block form G of eq 37):
    V^s_i = sum_{j <= i} A_j xd_j,  Vd^s_i = Vd_0 + sum_{j <= i} (A_j xdd_j + [V^s_j, A_j xd_j]),
    tau_i = A_i^T sum_{k >= i} F^s_k,
with A_j = Ad_{T_j} S_j. The per-body Newton-Euler term (20) is evaluated in each body
frame, where J_i is constant. Only the chain of transforms stays sequential (and is
log-depth, see kinematics.py); everything else is vectorised across bodies and states.
"""
import numpy as np

from .kinematics import ad_matrices, adjoints, spatial_screws, world_poses

_CHUNK = 512  # states per pass: keeps the (chunk, nb, 6, 6) work arrays in cache


def _chunks(N):
    return [slice(i, min(N, i + _CHUNK)) for i in range(0, N, _CHUNK)] if N > _CHUNK else [slice(None)]


def _external(model, wrenches, N):
    """{link: wrench in link frame} -> (N, nb, 6) body-frame wrenches, or None."""
    if not wrenches:
        return None
    out = np.zeros((N, model.nb, 6))
    for link, w in dict(wrenches).items():
        if link not in model.link_frames:
            raise ValueError(f"unknown link '{link}' in wrenches")
        w = np.asarray(w, dtype=float)
        if w.shape not in ((6,), (N, 6)):
            raise ValueError(f"wrench on '{link}' must have shape (6,) or ({N}, 6), got {w.shape}")
        if not np.all(np.isfinite(w)):
            raise ValueError(f"wrench on '{link}' contains non-finite values")
        b, T = model.link_frames[link]
        if b < 0:  # on the world, or on a part that cannot move a controlled joint
            continue
        # a wrench in frame l, expressed in body frame b: F_b = Ad_{T_bl^-1}^T F_l
        Ad_lb_T = adjoints(np.linalg.inv(T))[0].T
        out[:, b] += w @ Ad_lb_T.T
    return out


def inverse_dynamics(model, q, qd, qdd, wrenches=None, with_gravity=True):
    """tau for a state (n,) or a batch (N, n); see module docstring for the equations."""
    single = np.ndim(q) == 1
    q = model._batch('q', q)
    N = q.shape[0]
    qd = model._batch('qd', qd, N)
    qdd = model._batch('qdd', qdd, N)
    fext = _external(model, wrenches, N)
    a0 = model._a0 if with_gravity else np.zeros(6)
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


def gravity(model, q):
    """g(q): RNEA with V = 0 and Vd_0 = (0, -g)."""
    single = np.ndim(q) == 1
    q = model._batch('q', q)
    x = model.body_coordinates(q)
    out = np.empty((q.shape[0], model.n))
    for sl in _chunks(q.shape[0]):
        out[sl] = _gravity(model, x[sl])
    return out[0] if single else out


def _gravity(model, x):
    Ad, AdinvT = adjoints(world_poses(model, x))
    A = spatial_screws(model, Ad)
    # body-frame base acceleration: Ad_{T^-1} (0, -g) = AdinvT^T (0, -g)
    Vdb = np.swapaxes(AdinvT[..., 3:, :], -1, -2) @ model._a0[3:]
    Fb = (model.J @ Vdb[..., None])[..., 0]
    Fs = (AdinvT @ Fb[..., None])[..., 0]
    Fsub = model.ancestors.T @ Fs
    return np.einsum('nbi,nbi->nb', A, Fsub) @ model.E
