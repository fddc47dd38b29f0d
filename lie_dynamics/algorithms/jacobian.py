"""Frame Jacobians of links (paper eqs 13-15) and their drift J̇q̇.

Eq 13 writes the body velocity f^-1 ḟ of f = M e^{[B_1] x_1} ... e^{[B_n] x_n} as a sum of
Ad-transformed screws (the paper summary's eq 13 has one sign wrong: the term of x_{n-1} is
e^{-[B_n] x_n} [B_{n-1}] e^{+[B_n] x_n}; docs/architecture.md). Column j of the body
Jacobian of body i is Ad_{f_{j,i}^-1} S_j = Ad_{T_i^-1} A_j for every ancestor-or-self j of i,
with A_j = Ad_{T_j} S_j the joint's screw in the root frame at the current configuration
(eqs 14-15 with the current screws; kinematics.spatial_screws); other columns are zero.
The root-frame (spatial) Jacobian has the columns A_j themselves.

Frames (Pinocchio's getFrameJacobian with the reference frame of the same name):
  * 'local' (LOCAL): the twist of the target frame in its own axes, (R^T ṗ, R^T w).
  * 'world_aligned' (LOCAL_WORLD_ALIGNED): the velocity ṗ of the target frame's origin and
    the angular velocity w, both in root-frame axes.
  * 'world' (WORLD): the spatial twist in the root frame: w and the velocity of the
    body-fixed point at the root origin, ṗ + p x w (the same for every frame fixed to the body).
The target frame is the link frame, or the frame at `point` (given in the link frame) with
the link's orientation. Rows are LINEAR THEN ANGULAR, (vx vy vz wx wy wz), as Pinocchio and
geometry_msgs/Twist order them; the paper's twists (and the rest of this library) are (w, v).

Drift, jacobian_dot_times_qd: Pinocchio's getFrameClassicalAcceleration at q̈ = 0 in the same
frame, so that J q̈ + jacobian_dot_times_qd = that classical acceleration for any q̈:
  * 'world_aligned': (p̈, ẇ) in root-frame axes, exactly J̇ q̇ of this frame's J;
  * 'local': (R^T p̈, R^T ẇ), which is J̇ q̇ of the local J plus (w_b x v_b, 0);
  * 'world': the classical acceleration of the body-fixed point at the root origin, (V̇_v +
    w x V_v, ẇ) for the spatial twist V = (w, V_v): J̇ q̇ of the world J plus (w x V_v, 0).
It comes from eq 19 with q̈ = 0 summed over ancestors (kinematics.spatial_motion):
V̇ = sum_j [V_j, A_j ẋ_j], then p̈ = V̇_v + ẇ x p + w x ṗ.

Mimic joints add multiplier x their column to their master's; locked joints (at their
locked values) and joints that do not move the link add nothing. A link that no controlled
joint moves (fixed to the root, or on a part of the tree the model dropped) has an all-zero
Jacobian and drift.

`jacobian` and `jacobian_dot_times_qd` validate once (state, link, frame, point), then run the
generated kernel (codegen/traced/jacobian.py, one per body and frame): its C form where the
native backend has it (runtime.native; one state or a batch, X given once per state), else
the Python kernel or the vectorised reference below, as codegen.runtime.route says
(THRESHOLDS['jacobian']). Model.jacobian and Model.jacobian_dot_times_qd call the native
kernel of a link frame straight from C (`kernel_of`, dispatch.native_keyed) and this module's
functions when it declines.
"""
import difflib

import numpy as np

from ..codegen import runtime
from ..validation import float_list, vector
from ..codegen.traced import jacobian as traced
from ..model.link_frames import WORLD
from ..spatial import cross
from .common import chunks
from .kinematics import adjoints, spatial_motion, spatial_screws, world_poses

FRAMES = traced.FRAMES
MODES = (None, 'loop', 'rows', 'vectorized')


def _link(model, link):
    """(body, pose of the link in the body's URDF frame, kernel parameters or None); body WORLD
    when no controlled joint moves the link (a DROPPED link too: its Jacobian is zero as well)."""
    if not isinstance(link, str) or link not in model.link_frames:
        close = difflib.get_close_matches(str(link), list(model.link_frames), n=3)
        hint = f"; did you mean {', '.join(repr(c) for c in close)}?" if close else \
            f' ({len(model.link_frames)} links, e.g. {list(model.link_frames)[-1]!r})' if model.link_frames else ''
        raise ValueError(f'unknown link {link!r}{hint}')
    b, T = model.link_frames[link]
    if b < 0:
        return WORLD, None, None
    fr = runtime.frames(model)
    return b, T, (fr.point_params(b, T) if fr.supported else None)


def target(model, link, frame, point):
    """Validated (body, T, X, p): the link's body (WORLD: no controlled joint moves it), its pose T
    (4x4) in the body's URDF frame, the target frame's 12 kernel parameters X (None without a
    kernel) and the point as 3 floats (None: the link frame's origin)."""
    if frame not in FRAMES:
        raise ValueError(f'unknown frame {frame!r}: use one of {", ".join(repr(f) for f in FRAMES)}')
    b, T, X = runtime.derived(model, ('jacobian_link', link), lambda: _link(model, link)) \
        if isinstance(link, str) else _link(model, link)
    if point is None:
        return b, T, X, None
    p = float_list(point, 3)
    if p is None:
        p = vector('point', point, 3, ' (a point in the link frame, m)').tolist()
    if X is not None:   # the frame at the point: t + R p
        p0, p1, p2 = p
        X = X[:9] + [X[9 + r] + X[3 * r] * p0 + X[3 * r + 1] * p1 + X[3 * r + 2] * p2 for r in range(3)]
    return b, T, X, p


def jacobian(model, q, link, frame='world_aligned', point=None, mode=None):
    """The 6 x n frame Jacobian of `link` (or of `point`, in the link frame): (6, n) for q (n,),
    (N, 6, n) for q (N, n). Rows (vx vy vz wx wy wz); frames and conventions in the module
    docstring. mode: None (the native kernel, else route decides), 'loop' / 'rows' (the Python
    kernel, None when the model has none) or 'vectorized' (the reference)."""
    return _call(model, 'jacobian', (q,), link, frame, point, mode)


def jacobian_dot_times_qd(model, q, qd, link, frame='world_aligned', point=None, mode=None):
    """J̇q̇ as the classical acceleration at q̈ = 0 (module docstring): (6,) or (N, 6), rows
    (ax ay az alpha_x alpha_y alpha_z). mode as in `jacobian`."""
    return _call(model, 'jacobian_dot', (q, qd), link, frame, point, mode)


def _kernel_of(model, kind, link, frame):
    """(spec, X as an array) of a link frame's kernel, or False (a link no controlled joint
    moves, no kernel); cached per version."""
    b, _, X, _ = target(model, link, frame, None)
    return (traced.spec(kind, frame, b), np.array(X)) if b >= 0 and X is not None else False


def kernel_of(kind, model, link, frame='world_aligned', point=None):
    """(spec, (X,)) of the native-first methods' kernel for these arguments (dispatch.native_keyed:
    Model.jacobian and Model.jacobian_dot_times_qd look it up once per link and frame, then call
    it from C with the states and X), or False: a point, a link no controlled joint moves, no
    kernel. An unknown link or frame raises here as in `target`; the method then runs its
    Python form, which raises the same."""
    if point is not None or type(link) is not str or type(frame) is not str:
        return False
    k = runtime.derived(model, (kind, link, frame), lambda: _kernel_of(model, kind, link, frame))
    return (k[0], (k[1],)) if k else False


def _call(model, kind, states, link, frame, point, mode):
    k = kernel_of(kind, model, link, frame, point) if mode is None else False   # a link frame's kernel
    if k:
        r = runtime.fast(model, k[0])(*states, *k[1])
        if r is not None:
            return r
    if mode not in MODES:
        raise ValueError(f'mode must be one of {MODES}, got {mode!r}')
    b, T, X, p = target(model, link, frame, point)
    if b >= 0 and X is not None and mode is None and point is not None:   # the frame at a point: X given here
        r = runtime.fast(model, traced.spec(kind, frame, b))(*states, np.array(X))
        if r is not None:
            return r
    entry = _JACOBIAN if kind == 'jacobian' else _DRIFT
    return runtime.call(model, entry, states, None, (kind, frame, b, T, X, p, mode))


def _validated(model, arrays, kind, frame, b, T, X, p, mode):
    """runtime.call's full path: (N, 6, n) or (N, 6) on validated (N, n) arrays, or None (a
    forced kernel mode the model has not)."""
    N = len(arrays[0])
    shape = (N, 6, model.n) if kind == 'jacobian' else (N, 6)
    if b < 0:
        return np.zeros(shape)
    out = _evaluate(model, kind, frame, b, T, X, p, arrays, mode)
    return None if out is None else out.reshape(shape)


_JACOBIAN = runtime.Entry(('q',), None, _validated)
_DRIFT = runtime.Entry(('q', 'qd'), None, _validated)


def _evaluate(model, kind, frame, b, T, X, p, arrays, mode):
    """On validated (N, n) arrays: the kernel (its C form first when mode is None), else, for
    mode None or 'vectorized', the reference; X the same for every state."""
    N = len(arrays[0])
    if mode != 'vectorized':
        vals = None
        if X is not None:
            X = np.broadcast_to(np.array(X), (N, 12))
            vals = runtime.run(model, traced.spec(kind, frame, b), arrays + [X], mode)
        if vals is not None or mode is not None:
            return vals
    out = np.empty((N, 6, model.n) if kind == 'jacobian' else (N, 6))
    if p is not None:
        T = T.copy()
        T[:3, 3] += T[:3, :3] @ p
    for sl in chunks(N, 200 * model.nb):
        out[sl] = _reference(model, kind, frame, b, T, *(a[sl] for a in arrays))
    return out


# ---------------------------------------------------------------- vectorised (reference) path
def _reference(model, kind, frame, b, T, q, qd=None):
    """Eqs 13-15 (and the drift of eq 19) in the root frame for validated (N, n) states."""
    x = model.body_coordinates(q)
    Tw = world_poses(model, x)
    A = spatial_screws(model, adjoints(Tw)[0])               # A_j = Ad_{T_j} S_j, (w, v)
    TP = Tw[:, b] @ T                                         # the target frame in the root frame
    R, p = TP[:, :3, :3], TP[:, :3, 3]
    if kind == 'jacobian':
        cols = np.einsum('nbi,bk->nki', A * model.ancestors[b][None, :, None], model.E)   # (N, n, 6)
        w, v = cols[..., :3], cols[..., 3:]
        lin = v if frame == 'world' else v + cross(w, p[:, None, :])    # ṗ = v + w x p
        if frame == 'local':
            lin, w = lin @ R, w @ R                                      # rows times R: R^T per column
        return np.swapaxes(np.concatenate([lin, w], axis=-1), -1, -2)
    V, Vd = spatial_motion(model, A, qd @ model.E.T)
    (w, v), (wd, vd) = (V[:, b, :3], V[:, b, 3:]), (Vd[:, b, :3], Vd[:, b, 3:])
    if frame == 'world':
        lin = vd + cross(w, v)
    else:
        lin = vd + cross(wd, p) + cross(w, v + cross(w, p))                 # p̈ = V̇_v + ẇ x p + w x ṗ
        if frame == 'local':
            lin, wd = (lin[:, None] @ R)[:, 0], (wd[:, None] @ R)[:, 0]
    return np.concatenate([lin, wd], axis=-1)
