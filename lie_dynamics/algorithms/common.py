"""Helpers shared by the vectorised algorithms: batching in chunks, per-model constants, the
root-frame kinematic state, subtree sums and the projection from body to joint coordinates."""
import numpy as np

from ..codegen.runtime import THRESHOLDS, derived
from ..spatial import transpose
from .kinematics import adjoints, spatial_screws, world_poses


def chunks(N, per_state):
    """Slices over N states so that a chunk holds about THRESHOLDS['vectorized_budget'] floats
    of work arrays (per_state: floats of work per state; the O(n^3) ones scale with nb^3).
    Every vectorised algorithm batches this way."""
    size = max(1, min(N, THRESHOLDS['vectorized_budget'] // max(1, per_state)))
    return [slice(i, min(N, i + size)) for i in range(0, N, size)]


def body_constants(model):
    """Per-model constants derived from the (settable) inertias, cached until the model changes."""
    def compute():
        J, E = model.J, model.E
        return dict(mass=J[:, 3, 3].copy(),
                    first=np.stack([J[:, 2, 4], J[:, 0, 5], J[:, 1, 3]], axis=-1),  # m c, body frame
                    identity=E.shape[0] == E.shape[1] and np.array_equal(E, np.eye(E.shape[0])))
    return derived(model, 'body_constants', compute)


def to_joints_vec(model, c, X):
    """(N, nb) body quantity -> (N, n) joint quantity (tau = E^T tau_body)."""
    return X if c['identity'] else X @ model.E


def to_joints_mat(model, c, X):
    """(N, nb, nb) -> E^T X E."""
    if c['identity']:
        return X
    E = model.E
    return E.T @ X @ E


def kinematic_state(model, x, with_ad=False):
    """Root-frame quantities shared by the closed-form algorithms, for body coordinates x (N, nb).

    Returns (Adinv, AdinvT, A): Ad_{T_i^-1} and Ad_{T_i}^-T for every body (N, nb, 6, 6) and
    the root-frame screws A_i = Ad_{T_i} S_i (N, nb, 6); with_ad=True appends Ad_{T_i}.
    """
    Ad, AdinvT = adjoints(world_poses(model, x))
    A = spatial_screws(model, Ad)
    if with_ad:
        return transpose(AdinvT), AdinvT, A, Ad
    return transpose(AdinvT), AdinvT, A


def world_inertias(model, AdinvT):
    """Js_i = Ad_{T_i}^-T J_i Ad_{T_i}^-1: body inertias about the root frame, (N, nb, 6, 6)."""
    return AdinvT @ model.J @ transpose(AdinvT)


def subtree_sum(model, X):
    """sum over the subtree of each body: out_i = sum_{i <= p} X_p along axis 1."""
    N, nb = X.shape[:2]
    flat = X.reshape(N, nb, -1)
    return (model.ancestors.T @ flat).reshape(X.shape)


def body_matrices(model, q, fn, per_state):
    """fn(model, x) -> (N, nb, nb) body-coordinate matrices, evaluated on the states of q in
    chunks (per_state: floats of work arrays per state, see chunks) and projected to joints
    (E^T X E).
    q: (n,) or (N, n) -> (n, n) or (N, n, n)."""
    single = np.ndim(q) == 1
    q = model.check_batch('q', q)
    c = body_constants(model)
    x = model.body_coordinates(q)
    N, nb = x.shape
    out = np.empty((N, nb, nb))
    for sl in chunks(N, per_state):
        out[sl] = fn(model, x[sl])
    out = to_joints_mat(model, c, out)
    return out[0] if single else out
