"""Forward kinematics on the tree: f_{i-1,i} = M_i e^{[S_i] x_i} (paper eq 17) for all bodies at once.

Per-call work is vectorised across bodies as well as states: the joint transforms are
one contraction, the world poses T_i = T_{parent(i)} f_{parent(i),i} come from pointer
jumping (ceil(log2 depth) batched products, not one product per body), and the adjoints
of every body are built in a handful of array operations.
"""
import numpy as np

from ..spatial import Ad, ad

# Permutation swapping the angular and linear halves of a 6-vector.
_SWAP = np.array([3, 4, 5, 0, 1, 2])


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

    Ad_T (spatial.Ad) maps body twists to the root frame; Ad_T^-T maps body wrenches to the
    root frame. Ad_{T^-1} = P Ad_T^T P with P the half swap, so it is a gather of Ad_T.
    """
    A = Ad(T)
    return A, A[..., _SWAP[:, None], _SWAP]  # (Ad_{T^-1})^T


def spatial_screws(model, Ad):
    """A_i = Ad_{T_i} S_i: joint screws in the root frame, (N, nb, 6)."""
    return (Ad @ model.S[:, :, None])[..., 0]


def spatial_motion(model, A, xd, xdd=None, a0=None):
    """Root-frame twists V and accelerations Vd of every body, (N, nb, 6) each: eqs 18-19
    summed over ancestors, V_i = sum_{j <= i} A_j xd_j and
    Vd_i = Vd_0 + sum_{j <= i} (A_j xdd_j + [V_j, A_j xd_j]), with A = spatial_screws(...).
    xdd None: the velocity-product (drift) part only; a0: the base acceleration Vd_0 or None."""
    Axd = A * xd[..., None]
    V = model.ancestors @ Axd
    acc = (ad(V) @ Axd[..., None])[..., 0]
    if xdd is not None:
        acc = A * xdd[..., None] + acc
    Vd = model.ancestors @ acc
    return V, (Vd if a0 is None else Vd + a0)
