"""Frame Jacobians and their drift J̇q̇, traced (paper eqs 13-15; algorithms/jacobian.py).

Eq 13 writes the body velocity of f = M e^{[B_1] x_1} ... e^{[B_n] x_n} as a sum of
Ad-transformed screws: column j of the body Jacobian of body i is Ad_{f_{j,i}^-1} S_j, i.e.
joint j's screw expressed in frame i. It is computed here from one pose per ancestor
(O(depth)) rather than by carrying every S_j down the chain (O(depth^2)):
  * 'world' and 'world_aligned': T_j from the root down; with the joint axis z_j the third
    column of R_j (codegen.frames turns every axis to z), A_j = Ad_{T_j} S_j = (z_j, t_j x z_j)
    (revolute) or (0, z_j) (prismatic), the current screws of eq 15;
  * 'local': the poses T_{P,j} of the joint frames in the target frame P, from P up to the
    root; the same formula then gives Ad_{T_{P,j}} S_j = Ad_{f_{j,P}^-1} S_j directly.
The drift is eq 19 with q̈ = 0 summed over ancestors (the vectorised RNEA's form,
kinematics.spatial_motion): V̇ = sum_j [V_parent(j), A_j ẋ_j].

Rows are linear then angular (vx vy vz wx wy wz), as Pinocchio and geometry_msgs/Twist order
them; the paper's twists are (w, v). One kernel per (kind, frame, body): the link's pose in
the body frame and the point enter per state as 12 numbers X (rotation row-major, then the
translation, in the body's primed frame; Frames.point_params), so one kernel serves every
link fixed to the body and every point.
"""
from .. import algebra as la
from ..kernel import Trace
from ..runtime import Spec
from ..tracer import Graph

FRAMES = ('world_aligned', 'local', 'world')
_I3 = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))
_ZERO = (0.0, 0.0, 0.0)


def _path(fr, body):
    """Bodies from the root to `body`, parents first."""
    out = []
    while body >= 0:
        out.append(body)
        body = fr.parent[body]
    return out[::-1]


def _screw(fr, j, R, t):
    """(w, v, t): A_j = (z, t x z) (revolute) or (0, z) (prismatic) from the pose (R, t) of
    primed frame j, and the joint's origin t."""
    z = (R[0][2], R[1][2], R[2][2])
    return ((z, la.cross(t, z)) if fr.revolute[j] else (_ZERO, z)) + (t,)


def _columns(fr, g, x, X, path, frame):
    """({j: (w, v, t)}, p): the screws A_j = (w, v) of the path's joints and their origins t in
    the root frame, or in the target frame for 'local'; p the target's origin in the root frame
    ('world_aligned' only, else None).

    Root frame: T_j = T_parent f_j(x_j), from the root down. Target frame: from the target
    T_{P,b} = X^-1 up to the root, T_{P,parent} = T_{P,j} f_j^-1 (f^-1 = (R^T, -R^T t)), so the
    local columns need no rotation at the end."""
    out, p = {}, None
    if frame == 'local':
        RX = (tuple(X[0:3]), tuple(X[3:6]), tuple(X[6:9]))
        R = tuple(zip(*RX))
        t = la.vscale(-1.0, la.mat_vec(R, tuple(X[9:12])))
        for j in reversed(path):
            out[j] = _screw(fr, j, R, t)
            Rf, tf = fr.joint_transform(g, j, x[j])
            R = la.mat_mat(R, tuple(zip(*Rf)))
            t = la.vsub(t, la.mat_vec(R, tf))
        return out, p
    R, t = _I3, _ZERO
    for j in path:
        Rf, tf = fr.joint_transform(g, j, x[j])
        R, t = la.mat_mat(R, Rf), la.vadd(t, la.mat_vec(R, tf))
        out[j] = _screw(fr, j, R, t)
    if frame == 'world_aligned':
        p = la.vadd(t, la.mat_vec(R, tuple(X[9:12])))
    return out, p


def trace_jacobian(fr, g, x, X, body, frame):
    """(outputs, index): the entries of the 6 x n Jacobian (row-major, rows v then w) of the target
    frame on `body` in the columns of the joints that move it (the path's, and their mimics'),
    and their flat indices; every other entry is structurally zero."""
    path = _path(fr, body)
    A, p = _columns(fr, g, x, X, path, frame)
    cols = {}
    for j in path:
        w, v, t = A[j]
        if p is not None and fr.revolute[j]:   # v + w x p = w x (p - t): the velocity of the point p
            v = la.cross(w, la.vsub(p, t))
        cols[j] = tuple(v) + tuple(w)
    n, out, moved = fr.n, {}, []
    for k in range(n):
        col = [0.0] * 6
        terms = [(float(fr.E[j, k]), j) for j in path if fr.E[j, k] != 0.0]
        for e, j in terms:
            for r in range(6):
                col[r] = col[r] + e * cols[j][r]
        if terms:
            moved.append(k)
            out[k] = col
    idx = [r * n + k for r in range(6) for k in moved]
    return [out[i % n][i // n] for i in idx], idx


def trace_drift(fr, g, x, xd, X, body, frame):
    """J̇q̇ of the target frame on `body` as Pinocchio's classical acceleration at q̈ = 0 in that
    frame (algorithms/jacobian.py): 6 values, linear then angular.

    V̇ = sum_j [V_parent(j), A_j ẋ_j] (eq 19, q̈ = 0) holds in the root frame and, the bracket
    being Ad-equivariant, with the columns in the target frame too (then V̇ is the body
    acceleration): 'local' and 'world' are both (v̇ + w x v, ẇ), each in its own frame."""
    path = _path(fr, body)
    A, p = _columns(fr, g, x, X, path, frame)
    wd, vd = _ZERO, _ZERO
    V = None
    for j in path:
        w, v, _ = A[j]
        a = (la.vscale(xd[j], w), la.vscale(xd[j], v))
        if V is None:
            V = a
        else:
            bw, bv = la.bracket(V, a)
            wd, vd = la.vadd(wd, bw), la.vadd(vd, bv)
            V = la.twist_add(V, a)
    w, v = V
    if p is None:
        return list(la.vadd(vd, la.cross(w, v))) + list(wd)
    pd = la.vadd(v, la.cross(w, p))                                    # ṗ = v + w x p
    return list(la.vadd(la.vadd(vd, la.cross(wd, p)), la.cross(w, pd))) + list(wd)   # p̈ at q̈ = 0


def build(fr, kind, frame, body):
    """k(Q[, QD], X, E0) -> the Jacobian (6 n, row-major) or J̇q̇ (6): its Trace."""
    g = Graph()
    co = fr.trace_coordinates(g, rates=1 if kind == 'jacobian_dot' else 0)
    names = [f'lk{k}' for k in range(12)]
    X = [g.input(nm) for nm in names]
    args = co['args'] + [('X', names), co['offset_args']]
    if kind == 'jacobian':
        # A link off a long path (a tree's) leaves most columns zero: then only the path's columns
        # are outputs, written over zeros (Trace.scatter): no code for the rest (on a 200-body
        # tree, 1,158 stores of 0.0). A chain's tip moves with every joint: no scatter, no memset.
        outputs, idx = trace_jacobian(fr, g, co['x'], X, body, frame)
        size = 6 * fr.n
        return Trace(g, f'{kind}_kernel', args, outputs, scatter=(idx, size) if len(idx) < size else None)
    return Trace(g, f'{kind}_kernel', args, trace_drift(fr, g, co['x'], co['xd'], X, body, frame))


_SPECS = {}


def spec(kind, frame, body):
    """The Spec of one kernel: kind 'jacobian' or 'jacobian_dot', a frame of FRAMES, a body index.
    Its name carries all three (the compiled code is shared per structure under that name)."""
    key = (kind, frame, body)
    s = _SPECS.get(key)
    if s is None:
        shape = (lambda m: ((6, m.n), None)) if kind == 'jacobian' else (lambda m: ((6,), None))
        s = _SPECS.setdefault(key, Spec(f'{kind}_{frame}_b{body}', lambda fr: build(fr, kind, frame, body),
                                        ('offsets',), 'jacobian', result=shape))
    return s
