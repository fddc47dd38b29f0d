"""Forward kinematics on the tree: f_{i-1,i} = M_i e^{[S_i] x_i} (paper eq 17) for all bodies at once.

Per-call work is vectorised across bodies as well as states: the joint transforms are
one contraction, the world poses T_i = T_{parent(i)} f_{parent(i),i} come from pointer
jumping (ceil(log2 depth) batched products, not one product per body), and the adjoints
of every body are built in a handful of array operations.
"""
import numpy as np

# Permutation swapping the angular and linear halves of a 6-vector.
_SWAP = np.array([3, 4, 5, 0, 1, 2])
# ad_V as a gather from (w, v, 0): ad_V = [[[w], 0], [[v], [w]]].
_AD_IDX = np.full(36, 6)
_AD_SGN = np.zeros(36)
for _blk_r, _blk_c, _off in ((0, 0, 0), (3, 3, 0), (3, 0, 3)):
    for _r, _c, _k, _s in ((0, 1, 2, -1), (0, 2, 1, 1), (1, 0, 2, 1), (1, 2, 0, -1), (2, 0, 1, -1), (2, 1, 0, 1)):
        _AD_IDX[(_blk_r + _r) * 6 + _blk_c + _c] = _off + _k
        _AD_SGN[(_blk_r + _r) * 6 + _blk_c + _c] = _s


def joint_transforms(model, x):
    """f_{parent,i}(x_i) for x of shape (N, nb) -> (N, nb, 4, 4)."""
    s, c = np.sin(x), np.cos(x)
    coef = np.stack([s, 1.0 - c, x, x - s], axis=-1)  # see Model._precompute
    N, nb = x.shape
    return (coef[:, :, None, :] @ model.transform_coefficients).reshape(N, nb, 4, 4) + model.M


def world_poses(model, x):
    """Poses of all body frames in the root frame, (N, nb, 4, 4)."""
    T = joint_transforms(model, x)
    for idx, src in model.pointer_jumps:
        T[:, idx] = T[:, src] @ T[:, idx]
    return T


def adjoints(T):
    """(Ad_T, Ad_T^-T) for poses T (..., 4, 4).

    Ad_T = [[R, 0], [[p]R, R]] maps body twists to the root frame; Ad_T^-T maps body
    wrenches to the root frame. Ad_{T^-1} = P Ad_T^T P with P the half swap, so one
    product [p]R serves both.
    """
    R = T[..., :3, :3]
    p = T[..., :3, 3]
    shape = T.shape[:-2]
    P = np.zeros(shape + (3, 3))
    P[..., 0, 1], P[..., 0, 2], P[..., 1, 2] = -p[..., 2], p[..., 1], -p[..., 0]
    P -= np.swapaxes(P, -1, -2)
    Ad = np.zeros(shape + (6, 6))
    Ad[..., :3, :3] = R
    Ad[..., 3:, 3:] = R
    Ad[..., 3:, :3] = P @ R
    AdinvT = Ad[..., _SWAP[:, None], _SWAP]  # (Ad_{T^-1})^T
    return Ad, AdinvT


def ad_matrices(V):
    """ad_V for twists V (..., 6) -> (..., 6, 6), by one gather (no per-block assembly)."""
    Vp = np.concatenate([V, np.zeros(V.shape[:-1] + (1,))], axis=-1)
    return (Vp[..., _AD_IDX] * _AD_SGN).reshape(V.shape[:-1] + (6, 6))


def spatial_screws(model, Ad):
    """A_i = Ad_{T_i} S_i: joint screws in the root frame, (N, nb, 6)."""
    return (Ad @ model.S[:, :, None])[..., 0]
