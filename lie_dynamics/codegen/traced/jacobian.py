"""Frame Jacobians and their drift J̇q̇, traced (paper eqs 13-15; algorithms/jacobian.py).

Eq 13 writes the body velocity of f = M e^{[B_1] x_1} ... e^{[B_n] x_n} as a sum of
Ad-transformed screws: column j of the body Jacobian of body i is Ad_{f_{j,i}^-1} S_j. With
A_j = Ad_{T_j} S_j the joint's screw in the root frame at the current configuration (eq 15
with the current screws), that column is Ad_{T_i^-1} A_j: one world pose per ancestor
(O(depth)) instead of carrying every S_j down the chain (O(depth^2)). In the primed frames of
codegen.frames the joint axis of body j is the third column z_j of its world rotation R_j, so
    A_j = (z_j, t_j x z_j) (revolute),  (0, z_j) (prismatic).
The drift is eq 19 with q̈ = 0 summed over ancestors in the root frame (the vectorised
RNEA's form, kinematics.spatial_motion): V̇ = sum_j [V_j, A_j ẋ_j].

Rows are linear then angular (vx vy vz wx wy wz), as Pinocchio and geometry_msgs/Twist order
them; the paper's twists are (w, v). One kernel per (kind, frame, body): the link's pose in
the body frame and the point enter per state as 12 numbers X (rotation row-major, then the
translation, in the body's primed frame; Frames.point_params), so one kernel serves every
link fixed to the body and every point.
"""
from .. import algebra as la
from ..render import kernel
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


def _screws(fr, g, x, path):
    """{j: (R_j, t_j, w_j, v_j)}: world pose of primed frame j and its spatial screw A_j."""
    out = {}
    for j in path:
        Rf, tf = fr.joint_transform(g, j, x[j])
        p = fr.parent[j]
        Rp, tp = (out[p][0], out[p][1]) if p >= 0 else (_I3, _ZERO)
        R, t = la.mat_mat(Rp, Rf), la.vadd(tp, la.mat_vec(Rp, tf))
        z = (R[0][2], R[1][2], R[2][2])
        out[j] = (R, t) + ((z, la.cross(t, z)) if fr.revolute[j] else (_ZERO, z))
    return out


def _frame(g, X, R, t):
    """(R_P, p_P): world pose of the target frame, X = (R_X row-major, t_X) in body frame (R, t)."""
    RX = (tuple(X[0:3]), tuple(X[3:6]), tuple(X[6:9]))
    return la.mat_mat(R, RX), la.vadd(t, la.mat_vec(R, tuple(X[9:12])))


def trace_jacobian(fr, g, x, X, body, frame):
    """The 6 x n Jacobian (row-major, rows v then w) of the target frame on `body`."""
    path = _path(fr, body)
    A = _screws(fr, g, x, path)
    Rb, tb = A[body][0], A[body][1]
    RP, pP = _frame(g, X, Rb, tb) if frame != 'world' else (None, None)
    cols = {}
    for j in path:
        _, t, w, v = A[j]
        if frame == 'world':
            lin = v
        elif fr.revolute[j]:    # v + w x p = w x (p - t): the point's velocity about the axis
            lin = la.cross(w, la.vsub(pP, t))
        else:
            lin = v
        if frame == 'local':
            lin, w = la.mat_t_vec(RP, lin), la.mat_t_vec(RP, w)
        cols[j] = tuple(lin) + tuple(w)
    out = [[0.0] * fr.n for _ in range(6)]
    for k in range(fr.n):
        for j in path:
            e = float(fr.E[j, k])
            if e != 0.0:
                for r in range(6):
                    out[r][k] = out[r][k] + e * cols[j][r]
    return [v for row in out for v in row]


def trace_drift(fr, g, x, xd, X, body, frame):
    """J̇q̇ of the target frame on `body` as Pinocchio's classical acceleration at q̈ = 0 in that
    frame (algorithms/jacobian.py): 6 values, linear then angular."""
    path = _path(fr, body)
    A = _screws(fr, g, x, path)
    V = {}
    wd, vd = _ZERO, _ZERO
    for j in path:
        _, _, w, v = A[j]
        a = (la.vscale(xd[j], w), la.vscale(xd[j], v))
        p = fr.parent[j]
        if p >= 0:    # [V_j, A_j xd_j] = [V_parent, A_j xd_j] (eq 19, q̈ = 0)
            bw, bv = la.bracket(V[p], a)
            wd, vd = la.vadd(wd, bw), la.vadd(vd, bv)
            V[j] = la.twist_add(V[p], a)
        else:
            V[j] = a
    w, vs = V[body]
    if frame == 'world':   # the body-fixed point at the world origin
        return list(la.vadd(vd, la.cross(w, vs))) + list(wd)
    RP, pP = _frame(g, X, A[body][0], A[body][1])
    pd = la.vadd(vs, la.cross(w, pP))                                   # ṗ = v + w x p
    lin = la.vadd(la.vadd(vd, la.cross(wd, pP)), la.cross(w, pd))      # p̈ at q̈ = 0
    if frame == 'local':
        return list(la.mat_t_vec(RP, lin)) + list(la.mat_t_vec(RP, wd))
    return list(lin) + list(wd)


def build(fr, kind, frame, body):
    """k(Q[, QD], X, E0) -> the Jacobian (6 n, row-major) or J̇q̇ (6), as render.kernel."""
    g = Graph()
    co = fr.trace_coordinates(g, rates=1 if kind == 'jacobian_dot' else 0)
    names = [f'lk{k}' for k in range(12)]
    X = [g.input(nm) for nm in names]
    args = co['args'] + [('X', names), co['offset_args']]
    if kind == 'jacobian':
        outputs = trace_jacobian(fr, g, co['x'], X, body, frame)
    else:
        outputs = trace_drift(fr, g, co['x'], co['xd'], X, body, frame)
    return kernel(g, f'{kind}_kernel', args, outputs)


_SPECS = {}


def spec(kind, frame, body):
    """The Spec of one kernel: kind 'jacobian' or 'jacobian_dot', a frame of FRAMES, a body index.
    Its name carries all three (the compiled code is shared per structure under that name)."""
    key = (kind, frame, body)
    s = _SPECS.get(key)
    if s is None:
        s = _SPECS.setdefault(key, Spec(f'{kind}_{frame}_b{body}', lambda fr: build(fr, kind, frame, body),
                                        ('offsets',), 'jacobian'))
    return s
