"""Algebra on tuples, for tracing: entries are floats or tracer symbols alike.

3-vectors are tuples, 3x3 matrices tuples of rows. Spatial quantities follow the paper's
conventions (docs/architecture.md): twists V = (w, v) and wrenches F = (n, f) as pairs of
3-vectors, angular first; a rigid-body inertia as (m, h, I) with h = m c the first moment
and I = (xx, xy, xz, yy, yz, zz) about the frame origin, so that
J = [[I, [h]], [-[h], m 1]] (the 6x6 form of lie_dynamics.spatial.spatial_inertia).
These are the traced counterparts of lie_dynamics.spatial's Ad, ad and bracket, written
on pairs so that the tracer never sees the structural zeros of a 6x6 matrix.
"""


def mat_vec(R, v):
    return tuple(R[r][0] * v[0] + R[r][1] * v[1] + R[r][2] * v[2] for r in range(3))


def mat_t_vec(R, v):
    return tuple(R[0][c] * v[0] + R[1][c] * v[1] + R[2][c] * v[2] for c in range(3))


def mat_mat(A, B):
    return tuple(tuple(A[r][0] * B[0][c] + A[r][1] * B[1][c] + A[r][2] * B[2][c] for c in range(3))
                 for r in range(3))


def cross(a, b):
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


def dot(a, b):
    s = 0.0
    for x, y in zip(a, b, strict=True):
        s = s + x * y
    return s


def vadd(a, b):
    return tuple(x + y for x, y in zip(a, b, strict=True))


def vsub(a, b):
    return tuple(x - y for x, y in zip(a, b, strict=True))


def vscale(k, a):
    return tuple(k * x for x in a)


def sym_rot(R, Io):
    """R I R^T for symmetric I given as (xx, xy, xz, yy, yz, zz); same layout out."""
    xx, xy, xz, yy, yz, zz = Io
    Im = ((xx, xy, xz), (xy, yy, yz), (xz, yz, zz))
    RI = mat_mat(R, Im)
    def e(r, c):
        return RI[r][0] * R[c][0] + RI[r][1] * R[c][1] + RI[r][2] * R[c][2]
    return (e(0, 0), e(0, 1), e(0, 2), e(1, 1), e(1, 2), e(2, 2))


def sym_vec(Io, v):
    xx, xy, xz, yy, yz, zz = Io
    return (xx * v[0] + xy * v[1] + xz * v[2], xy * v[0] + yy * v[1] + yz * v[2],
            xz * v[0] + yz * v[1] + zz * v[2])



# ---------------------------------------------------------------------------- spatial algebra
def hat(w):
    """[w]: the cross-product matrix of a 3-vector."""
    return ((0.0, -w[2], w[1]), (w[2], 0.0, -w[0]), (-w[1], w[0], 0.0))


def inertia_to_parent(ic, R, t):
    """Inertia (m, h, I) of a body in frame b' expressed about frame p', with f_{p',b'} = (R, t).

    h' = R h + m t,  I' = R I R^T + m(|t|^2 1 - t t^T) + 2 (t . R h) 1 - t (R h)^T - (R h) t^T.
    """
    m, h, Io = ic
    Rh = mat_vec(R, h)
    hp = vadd(Rh, vscale(m, t))
    Ir = sym_rot(R, Io)
    tt = dot(t, t)
    th = dot(t, Rh)
    d = m * tt + 2.0 * th
    pairs = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))
    Ip = []
    for k, (r, c) in enumerate(pairs):
        v = Ir[k] - m * (t[r] * t[c]) - (t[r] * Rh[c] + Rh[r] * t[c])
        if r == c:
            v = v + d
        Ip.append(v)
    return m, hp, tuple(Ip)


def wrench_to_parent(F, R, t):
    """A wrench (n, f) in frame b' expressed in frame p': (R n + t x R f, R f)."""
    n_, f_ = F
    Rf = mat_vec(R, f_)
    return vadd(mat_vec(R, n_), cross(t, Rf)), Rf


def inertia_times(ic, V):
    """J V for J = [[I, [h]], [-[h], m 1]] and V = (w, v): (I w + h x v, m v - h x w)."""
    m, h, Io = ic
    w, v = V
    return vadd(sym_vec(Io, w), cross(h, v)), vsub(vscale(m, v), cross(h, w))


def bracket(X, Y):
    """[X, Y] = ad_X Y for twists X = (w1, v1), Y = (w2, v2): (w1 x w2, w1 x v2 + v1 x w2)."""
    (w1, v1), (w2, v2) = X, Y
    return cross(w1, w2), vadd(cross(w1, v2), cross(v1, w2))


def ad_t(X, F):
    """ad_X^T F for a twist X = (w, v) and a wrench F = (n, f): (-(w x n) - v x f, -(w x f))."""
    (w, v), (n_, f_) = X, F
    return vscale(-1.0, vadd(cross(w, n_), cross(v, f_))), vscale(-1.0, cross(w, f_))


def inertia_rate(ic, V):
    """d/dt of a root-frame inertia (m, h, I) moving with twist V = (w, v): (0, hdot, Idot).

    hdot = w x h + m v,  Idot = [w] I - I [w] + 2 (h . v) 1 - v h^T - h v^T.
    (Equals -(ad_V^T J + J ad_V) in 6x6 form, with 10 numbers instead of 21.)
    """
    m, h, Io = ic
    w, v = V
    hd = vadd(cross(w, h), vscale(m, v))
    xx, xy, xz, yy, yz, zz = Io
    Im = ((xx, xy, xz), (xy, yy, yz), (xz, yz, zz))
    WI = mat_mat(hat(w), Im)  # [w] I ; I [w] = -( [w] I )^T since I sym, [w] skew
    hv = 2.0 * dot(h, v)
    out = []
    for r, c in ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2)):
        e = WI[r][c] + WI[c][r] - (v[r] * h[c] + h[r] * v[c])
        if r == c:
            e = e + hv
        out.append(e)
    return 0.0, hd, tuple(out)


def inertia_add(a, b):
    return a[0] + b[0], vadd(a[1], b[1]), vadd(a[2], b[2])


def twist_add(a, b):
    return vadd(a[0], b[0]), vadd(a[1], b[1])


def twist_scale(k, a):
    return vscale(k, a[0]), vscale(k, a[1])


def dot6(a, b):
    return dot(a[0], b[0]) + dot(a[1], b[1])


def twist_to_child(V, R, t):
    """Ad_{f^-1} V for f = (R, t) (frame b' in p'): a twist in p' expressed in b'."""
    w, v = V
    return mat_t_vec(R, w), mat_t_vec(R, vsub(v, cross(t, w)))

