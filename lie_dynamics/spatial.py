"""SO(3)/SE(3) toolkit of Park, Bobrow & Ploen (1995), section 3.1.

Conventions (docs/architecture.md): twists V = (w, v) and wrenches F = (m, f) are
6-vectors ordered angular first. Every function broadcasts over leading axes, so a
batch of N rotations is an array of shape (N, 3, 3).

Exp and log use series expansions near theta = 0 and a dedicated branch near
theta = pi, so they keep full precision where the textbook closed forms lose it
(the stability benchmark shows where the naive forms fail).
"""
import numpy as np

# Below these angles the closed-form coefficients lose digits to cancellation;
# the series used instead are truncated far below machine precision there.
_SERIES_EXP = 1e-2
_SERIES_LOG = 1e-2
# Above pi - _NEAR_PI the axis is read from the symmetric part of R (the skew part
# loses digits as theta / sin(theta) grows).
_NEAR_PI = 0.5


def hat3(w):
    """[w]: the so(3) matrix of a 3-vector (cross-product matrix), in w's float type (so the
    extended-precision references use it too)."""
    w = np.asarray(w)
    w = w if w.dtype.kind == 'f' else w.astype(float)
    out = np.zeros(w.shape[:-1] + (3, 3), dtype=w.dtype)
    out[..., 0, 1] = -w[..., 2]
    out[..., 0, 2] = w[..., 1]
    out[..., 1, 0] = w[..., 2]
    out[..., 1, 2] = -w[..., 0]
    out[..., 2, 0] = -w[..., 1]
    out[..., 2, 1] = w[..., 0]
    return out


def vee3(W):
    """Inverse of hat3 (reads the skew part of W)."""
    W = np.asarray(W)
    return np.stack([W[..., 2, 1], W[..., 0, 2], W[..., 1, 0]], axis=-1)


def hat6(V):
    """[V] = [[[w], v], [0, 0]]: the se(3) matrix of a twist V = (w, v)."""
    V = np.asarray(V, dtype=float)
    out = np.zeros(V.shape[:-1] + (4, 4), dtype=V.dtype)
    out[..., :3, :3] = hat3(V[..., :3])
    out[..., :3, 3] = V[..., 3:]
    return out


def vee6(X):
    """Inverse of hat6."""
    X = np.asarray(X)
    return np.concatenate([vee3(X[..., :3, :3]), X[..., :3, 3]], axis=-1)


def _norm3(w):
    return np.sqrt(np.sum(w * w, axis=-1))


def _exp_coefficients(theta):
    """sin(t)/t, (1 - cos t)/t^2, (t - sin t)/t^3 with series below _SERIES_EXP."""
    t2 = theta * theta
    small = theta < _SERIES_EXP
    ts = np.where(small, 1.0, theta)  # safe divisor
    s = np.sin(ts)
    half = np.sin(0.5 * ts)
    a = np.where(small, 1 - t2 / 6 * (1 - t2 / 20 * (1 - t2 / 42)), s / ts)
    b = np.where(small, 0.5 - t2 / 24 * (1 - t2 / 30 * (1 - t2 / 56)), 2 * half * half / (ts * ts))
    d = np.where(small, 1 / 6 - t2 / 120 * (1 - t2 / 42 * (1 - t2 / 72)), (ts - s) / (ts * ts * ts))
    return a, b, d


def exp3(w):
    """exp([w]) in SO(3), Rodrigues' formula (paper eq 11) for a rotation vector w."""
    w = np.asarray(w, dtype=float)
    theta = _norm3(w)
    a, b, _ = _exp_coefficients(theta)
    K = hat3(w)
    eye = np.broadcast_to(np.eye(3), K.shape)
    return eye + a[..., None, None] * K + b[..., None, None] * (K @ K)


def exp6(V):
    """exp([V]) in SE(3) for a twist V = (w, v) (paper eqs 10-12, without unit axis)."""
    V = np.asarray(V, dtype=float)
    w, v = V[..., :3], V[..., 3:]
    theta = _norm3(w)
    a, b, d = _exp_coefficients(theta)
    K = hat3(w)
    K2 = K @ K
    eye = np.broadcast_to(np.eye(3), K.shape)
    R = eye + a[..., None, None] * K + b[..., None, None] * K2
    Gm = eye + b[..., None, None] * K + d[..., None, None] * K2
    T = np.zeros(V.shape[:-1] + (4, 4))
    T[..., :3, :3] = R
    T[..., :3, 3] = np.einsum('...ij,...j->...i', Gm, v)
    T[..., 3, 3] = 1.0
    return T


def log3(R):
    """Rotation vector w with exp3(w) = R, |w| in [0, pi].

    Away from pi the axis comes from the skew part, (R - R^T)/2 = sin(t)[u];
    near pi that part vanishes, so the axis is read from the symmetric part,
    (R + R^T)/2 = cos(t) I + (1 - cos t) u u^T, and its sign from the skew part.
    """
    R = np.asarray(R, dtype=float)
    skew = 0.5 * vee3(R - np.swapaxes(R, -1, -2))
    s = _norm3(skew)
    c = 0.5 * (np.trace(R, axis1=-2, axis2=-1) - 1.0)
    theta = np.arctan2(s, c)
    small = theta < _SERIES_LOG
    # theta / sin(theta), series near zero (to theta^6: the theta^6 term is 2e-15 at 1e-2)
    t2 = theta * theta
    ratio = np.where(small, 1 + t2 / 6 * (1 + 7 * t2 / 60 * (1 + 31 * t2 / 294)),
                     theta / np.where(small, 1.0, np.sin(theta)))
    w = ratio[..., None] * skew
    near_pi = theta > np.pi - _NEAR_PI
    if np.any(near_pi):
        Rp = R[near_pi]
        cp = c[near_pi]
        B = 0.5 * (Rp + np.swapaxes(Rp, -1, -2)) - cp[..., None, None] * np.eye(3)
        B = B / (1.0 - cp)[..., None, None]  # = u u^T
        k = np.argmax(np.diagonal(B, axis1=-2, axis2=-1), axis=-1)
        col = np.take_along_axis(B, k[..., None, None], axis=-1)[..., 0]
        u = col / np.sqrt(np.take_along_axis(np.diagonal(B, axis1=-2, axis2=-1), k[..., None], -1))
        sign = np.where(np.sum(u * skew[near_pi], axis=-1) < 0, -1.0, 1.0)
        w = np.array(w, copy=True)
        w[near_pi] = (sign * theta[near_pi])[..., None] * u
    return w


def log6(T):
    """Twist V = (w, v) with exp6(V) = T; w = log3(R), v = G(w)^-1 p."""
    T = np.asarray(T, dtype=float)
    w = log3(T[..., :3, :3])
    theta = _norm3(w)
    small = theta < _SERIES_LOG
    ts = np.where(small, 1.0, theta)
    # G^-1 = I - [w]/2 + k [w]^2, k = 1/t^2 - cot(t/2)/(2t); cot form stays finite at pi.
    k = np.where(small, 1 / 12 + theta * theta / 720 * (1 + theta * theta / 42),
                 1 / (ts * ts) - 1 / (2 * ts * np.tan(0.5 * ts)))
    K = hat3(w)
    eye = np.broadcast_to(np.eye(3), K.shape)
    Ginv = eye - 0.5 * K + k[..., None, None] * (K @ K)
    v = np.einsum('...ij,...j->...i', Ginv, T[..., :3, 3])
    return np.concatenate([w, v], axis=-1)


def inv(T):
    """T^-1 = (R^T, -R^T p) without a general matrix inverse."""
    T = np.asarray(T, dtype=float)
    Rt = np.swapaxes(T[..., :3, :3], -1, -2)
    out = np.zeros_like(T)
    out[..., :3, :3] = Rt
    out[..., :3, 3] = -np.einsum('...ij,...j->...i', Rt, T[..., :3, 3])
    out[..., 3, 3] = 1.0
    return out


def Ad(T):
    """Ad_T = [[R, 0], [[p] R, R]] (paper eq 1): maps twists from frame {b} to {a}, T = T_ab."""
    T = np.asarray(T, dtype=float)
    R = T[..., :3, :3]
    out = np.zeros(T.shape[:-2] + (6, 6))
    out[..., :3, :3] = R
    out[..., 3:, 3:] = R
    out[..., 3:, :3] = hat3(T[..., :3, 3]) @ R
    return out


def Ad_inv(T):
    """Ad_{T^-1} = [[R^T, 0], [-R^T [p], R^T]], computed without inverting T."""
    T = np.asarray(T, dtype=float)
    Rt = np.swapaxes(T[..., :3, :3], -1, -2)
    out = np.zeros(T.shape[:-2] + (6, 6))
    out[..., :3, :3] = Rt
    out[..., 3:, 3:] = Rt
    out[..., 3:, :3] = -Rt @ hat3(T[..., :3, 3])
    return out


def Ad_star(T):
    """Coadjoint Ad*_T = Ad_T^T (paper eqs 2, 5): pulls wrenches back from {a} to {b}."""
    return np.swapaxes(Ad(T), -1, -2)


# ad_V as a gather from (w, v, 0): entry k of the 6x6 matrix is sign[k] * (w, v, 0)[index[k]].
_AD_INDEX = np.full(36, 6)
_AD_SIGN = np.zeros(36)
for _r0, _c0, _off in ((0, 0, 0), (3, 3, 0), (3, 0, 3)):      # blocks [w], [w] and [v]
    for _r, _c, _k, _s in ((0, 1, 2, -1), (0, 2, 1, 1), (1, 0, 2, 1), (1, 2, 0, -1), (2, 0, 1, -1), (2, 1, 0, 1)):
        _AD_INDEX[(_r0 + _r) * 6 + _c0 + _c] = _off + _k
        _AD_SIGN[(_r0 + _r) * 6 + _c0 + _c] = _s


def ad(V):
    """ad_V = [[[w], 0], [[v], [w]]]: the Lie bracket ad_V W = [V, W] on se(3), for twists
    (..., 6), built by one gather (no per-block assembly: the vectorised algorithms call it
    on every body of every state)."""
    V = np.asarray(V, dtype=float)
    Vp = np.concatenate([V, np.zeros(V.shape[:-1] + (1,))], axis=-1)
    return (Vp[..., _AD_INDEX] * _AD_SIGN).reshape(V.shape[:-1] + (6, 6))


def ad_star(V):
    """Dual ad*_V = ad_V^T (the RNEA's backward pass subtracts ad*_V(J V): codegen/traced/rnea.py)."""
    return np.swapaxes(ad(V), -1, -2)


def bracket(V, W):
    """[V, W] = ad_V W = (w1 x w2, w1 x v2 + v1 x w2), without building 6x6 matrices."""
    V = np.asarray(V, dtype=float)
    W = np.asarray(W, dtype=float)
    w1, v1, w2, v2 = V[..., :3], V[..., 3:], W[..., :3], W[..., 3:]
    return np.concatenate([cross(w1, w2), cross(w1, v2) + cross(v1, w2)], axis=-1)


def transpose(X):
    """Batched matrix transpose: swaps the last two axes (a view)."""
    return np.swapaxes(X, -1, -2)


def cross(a, b):
    """a x b over the last axis. np.cross carries ~30 us of fixed overhead per call; this is a
    handful of ufuncs."""
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    return np.stack([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], axis=-1)


def spatial_inertia(mass, com, inertia_com):
    """J = [[I_c - m[r]^2, m[r]], [-m[r], m 1]] about a frame whose origin is not the CoM.

    (The paper summary garbles this block; docs/architecture.md gives the settled form.)
    """
    r = hat3(np.asarray(com, dtype=float))
    J = np.zeros((6, 6))
    J[:3, :3] = np.asarray(inertia_com, dtype=float) - mass * (r @ r)
    J[:3, 3:] = mass * r
    J[3:, :3] = -mass * r
    J[3:, 3:] = mass * np.eye(3)
    return J


def transform(R=None, p=None):
    """Homogeneous 4x4 transform from a rotation and a translation."""
    T = np.eye(4)
    if R is not None:
        T[:3, :3] = R
    if p is not None:
        T[:3, 3] = p
    return T


def rpy_to_matrix(rpy):
    """URDF roll-pitch-yaw (fixed axes x, y, z): R = Rz(yaw) Ry(pitch) Rx(roll)."""
    r, p, y = rpy
    cr, sr, cp, sp, cy, sy = np.cos(r), np.sin(r), np.cos(p), np.sin(p), np.cos(y), np.sin(y)
    return np.array([
        [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
        [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
        [-sp, cp * sr, cp * cr],
    ])
