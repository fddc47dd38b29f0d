"""The recursive Newton-Euler algorithm, traced (paper section 3.2, eqs 16-21).

The paper's recursion runs link by link in body frames, with f_{i-1,i} = M_i e^{[S_i] x_i}
(eqs 16-17):
    V_i  = Ad_{f_{i-1,i}^-1} V_{i-1} + S_i xd_i                                   (18)
    Vd_i = S_i xdd_i + Ad_{f_{i-1,i}^-1} Vd_{i-1} + ad_{V_i}(S_i xd_i)            (19)
    F_i  = Ad*_{f_{i,i+1}^-1} F_{i+1} + J_i Vd_i - ad*_{V_i}(J_i V_i)             (20)
    tau_i = S_i^T F_i                                                              (21)
with V_0 = 0, Vd_0 = (0, -g) (gravity as a base acceleration).

Traced in the primed frames of codegen.frames (body frame b' turned so that the joint axis
is z): f_{p',b'}(x) = M'_b Rz(x) or M'_b Trans(z x), S'_b = (e_z, 0) or (0, e_z), and
tau_b = S'_b^T F_b is one component of the wrench. Inertias are parameters in the primed
frames, so payload, gravity and locked-joint changes never recompile.
"""
import numpy as np

from .. import algebra as la
from ..kernel import Trace
from ..render import Params
from ..runtime import Spec
from ..tracer import Graph
from ...spatial import hat3


def _lin(K, vec, add=None):
    """K @ vec (+ add) for a constant matrix K: zero entries fold away."""
    out = []
    for j in range(K.shape[0]):
        acc = add[j] if add is not None else 0.0
        for k in range(len(vec)):
            c = float(K[j, k])
            if c != 0.0:
                acc = acc + c * vec[k]
        out.append(acc)
    return tuple(out)


def _rz(c, s, u, transpose):
    """Rz(x) u, or Rz(x)^T u, with c = cos x, s = sin x."""
    if transpose:
        return (c * u[0] + s * u[1], c * u[1] - s * u[0], u[2])
    return (c * u[0] - s * u[1], s * u[0] + c * u[1], u[2])


def _home_adjoints(fr):
    """Ad_{M'^-1} = [[R'^T, 0], [-R'^T [t'], R'^T]] per body (constant 6x6 arrays)."""
    out = []
    for R, t in zip(fr.R, fr.t, strict=True):
        R = np.array(R)
        K = np.zeros((6, 6))
        K[:3, :3] = K[3:, 3:] = R.T
        K[3:, :3] = -R.T @ hat3(np.array(t))
        out.append(K)
    return out


def trig(fr, g, x):
    """(cos x_b, sin x_b) of each revolute body coordinate (None for prismatic), traced; the
    graph shares them with any other use of the same angles (e.g. fr.joint_transform)."""
    return [(g.cos(xb), g.sin(xb)) if rev else None for xb, rev in zip(x, fr.revolute, strict=True)]


def _coordinates(fr, g, rates):
    co = fr.trace_coordinates(g, rates=rates)
    return co, trig(fr, g, co['x'])


def joint_torques(fr, tau_b):
    """Joint values from body values (the mimic map E): tau_j = sum_b E_bj tau_b."""
    return [sum((float(fr.E[b, j]) * tau_b[b] for b in range(fr.nb) if fr.E[b, j] != 0), 0.0)
            for j in range(fr.n)]


def _to_child(fr, Ks, cs, x, b, U):
    """Ad_{f^-1} U: a twist U (6 values) of body b's parent, in b' (the first term of eqs 18-19).
    f = M'_b Rz(x) (revolute) or M'_b Trans(z x) (prismatic), so Ad_{f^-1} = Rz^T Ad_{M'^-1}
    or, for the shift, v += x (w_y, -w_x, 0)."""
    U = _lin(Ks[b], U)
    if fr.revolute[b]:
        c, s = cs[b]
        return _rz(c, s, U[:3], True) + _rz(c, s, U[3:], True)
    xb = x[b]
    return U[:3] + (U[3] + xb * U[1], U[4] - xb * U[0], U[5])


def _to_parent(fr, Ks, cs, x, b, F, Fp):
    """Fp + Ad*_{f^-1} F: body b's wrench F added to its parent's Fp (the first term of eq 20)."""
    if fr.revolute[b]:
        c, s = cs[b]
        G = _rz(c, s, F[:3], False) + _rz(c, s, F[3:], False)
    else:  # Ad*_{Trans(z x)}: n += (z x) x f
        xb = x[b]
        G = (F[0] - xb * F[4], F[1] + xb * F[3], F[2]) + tuple(F[3:])
    return list(_lin(Ks[b].T, G, add=Fp))       # Ad*_{M'^-1} = K^T


def trace_inverse_dynamics(fr, cs, x, xd, xdd, params, ga, fx=None):
    """Body torques tau_b of the RNEA, eqs 18-21 in the primed frames, traced: THE traced
    RNEA (the inverse-dynamics kernels, and the bias h = C qd + g of the Cholesky forward
    dynamics with xdd = 0). cs: trig(fr, g, x); params: per body (m, h, I) (fr.trace_params);
    ga: the base acceleration -g (3 values); fx: optional external wrenches (6 per body, in
    the primed body frames), subtracted from the body wrenches."""
    nb = fr.nb
    Ks = _home_adjoints(fr)
    ga = tuple(ga)
    V, Vd, F = [None] * nb, [None] * nb, [None] * nb
    zero = (0.0, 0.0, 0.0)
    for b in range(nb):
        p = fr.parent[b]
        Vp = V[p] if p >= 0 else zero + zero
        Vdp = Vd[p] if p >= 0 else zero + ga
        U, Ud = _to_child(fr, Ks, cs, x, b, Vp), _to_child(fr, Ks, cs, x, b, Vdp)
        w, v, wd, vd = U[:3], U[3:], Ud[:3], Ud[3:]
        if fr.revolute[b]:
            w = (w[0], w[1], w[2] + xd[b])                                     # eq 18: + S xd
            # eq 19: + S xdd + ad_{V_i}(S xd); ad_V(e_z xd, 0) = (w x e_z xd, v x e_z xd)
            wd = (wd[0] + w[1] * xd[b], wd[1] - w[0] * xd[b], wd[2] + xdd[b])
            vd = (vd[0] + v[1] * xd[b], vd[1] - v[0] * xd[b], vd[2])
        else:
            v = (v[0], v[1], v[2] + xd[b])                                     # eq 18: + S xd
            # eq 19: + S xdd + ad_V(0, e_z xd) = (0, w x e_z xd)
            vd = (vd[0] + w[1] * xd[b], vd[1] - w[0] * xd[b], vd[2] + xdd[b])
        V[b], Vd[b] = w + v, wd + vd
        # eq 20, body term J Vd - ad*_V (J V) with J = [[I_o, [h]], [-[h], m]], rewritten with
        # the Jacobi identity (fewer products, same value): with a = vd + w x v,
        #   n = I_o wd + w x (I_o w) + h x a,   f = m a + wd x h + w x (w x h)
        m, h, (ixx, ixy, ixz, iyy, iyz, izz) = params[b]
        Io = ((ixx, ixy, ixz), (ixy, iyy, iyz), (ixz, iyz, izz))
        acc = la.vadd(vd, la.cross(w, v))
        Iw = la.sym_vec((ixx, ixy, ixz, iyy, iyz, izz), w)
        wh = la.cross(w, h)
        Fn = la.vadd(la.vadd(tuple(Io[r][0] * wd[0] + Io[r][1] * wd[1] + Io[r][2] * wd[2] for r in range(3)),
                             la.cross(w, Iw)), la.cross(h, acc))
        Ff = la.vadd(la.vadd(la.vscale(m, acc), la.cross(wd, h)), la.cross(w, wh))
        if fx is not None:
            Fn = la.vsub(Fn, fx[6 * b:6 * b + 3])
            Ff = la.vsub(Ff, fx[6 * b + 3:6 * b + 6])
        F[b] = list(Fn) + list(Ff)
    tau_b = [None] * nb
    for b in range(nb - 1, -1, -1):                        # backward pass, eqs 20-21
        Fb = F[b]
        tau_b[b] = Fb[2] if fr.revolute[b] else Fb[5]
        p = fr.parent[b]
        if p >= 0:
            F[p] = _to_parent(fr, Ks, cs, x, b, Fb, F[p])
    return tau_b


def trace_momentum(fr, cs, x, xd, params):
    """Body components of the generalized momentum p = M qd and of C^T qd, traced.

    The velocities of eq 18, the body momenta J_i V_i, summed over each subtree by the
    transport of eq 20: H_i = J_i V_i + sum_children Ad*_{f^-1} H_child. Then p_i = S_i^T H_i
    and (C^T qd)_i = S_i^T ad*_{V_i} H_i: eq 20 for the subtree reads F_i = dH_i/dt - ad*_{V_i}
    H_i (dH_i/dt taken in frame i, where S_i is constant), so pdot_i = tau_i(+gravity) +
    S_i^T ad*_{V_i} H_i, which is the C^T qd of pdot = tau + C^T qd - g (observer.py). One
    O(n) pass, instead of M and C (O(n^2) each)."""
    nb = fr.nb
    Ks = _home_adjoints(fr)
    V, H = [None] * nb, [None] * nb
    for b in range(nb):
        p = fr.parent[b]
        U = _to_child(fr, Ks, cs, x, b, V[p] if p >= 0 else (0.0,) * 6)
        k = 2 if fr.revolute[b] else 5
        V[b] = U[:k] + (U[k] + xd[b],) + U[k + 1:]                           # eq 18
        n_, f_ = la.inertia_times(params[b], (V[b][:3], V[b][3:]))
        H[b] = list(n_) + list(f_)
    p_b, c_b = [None] * nb, [None] * nb
    for b in range(nb - 1, -1, -1):
        (w0, w1, _), (v0, v1, _) = V[b][:3], V[b][3:]
        n_, f_ = H[b][:3], H[b][3:]
        if fr.revolute[b]:    # S^T ad*_V H = e_z . (-(w x n) - v x f)
            p_b[b] = n_[2]
            c_b[b] = -(w0 * n_[1] - w1 * n_[0]) - (v0 * f_[1] - v1 * f_[0])
        else:                 # e_z . (-(w x f))
            p_b[b] = f_[2]
            c_b[b] = -(w0 * f_[1] - w1 * f_[0])
        p = fr.parent[b]
        if p >= 0:
            H[p] = _to_parent(fr, Ks, cs, x, b, H[b], H[p])
    return p_b, c_b


def with_armature(tau, armature, rates):
    """tau_j + armature_j rate_j per joint: the rotor term of M + diag(armature) times a joint
    rate (qdd in inverse dynamics, qd in the momentum). The rotor spins with its joint
    coordinate, so it adds to no body wrench and nothing else in the recursion."""
    return [t + a * r for t, a, r in zip(tau, armature, rates, strict=True)]


def build_momentum(fr):
    """k(Q, QD, P, E0, AR) -> (p = M qd, then C^T qd) tuple (trace_momentum; the armature
    adds to p only: it is constant, so it adds nothing to Mdot nor to C)."""
    g = Graph()
    co, cs = _coordinates(fr, g, 1)
    parg, params = fr.trace_params(g)
    ararg, arm = fr.trace_armature(g)
    p_b, c_b = trace_momentum(fr, cs, co['x'], co['xd'], params)
    qd = [g.input(nm) for nm in co['args'][1][1]]
    return Trace(g, 'momentum_kernel', co['args'] + [parg, co['offset_args'], ararg],
                  with_armature(joint_torques(fr, p_b), arm, qd) + joint_torques(fr, c_b))


def build_inverse_dynamics(fr, wrench):
    """k(Q, QD, QDD[, FX], P, A0, E0, AR) -> tau tuple: eqs 18-21 in primed frames, plus the
    armature times qdd (its Trace)."""
    g = Graph()
    co, cs = _coordinates(fr, g, 2)
    parg, params = fr.trace_params(g)
    a0arg, ga = fr.trace_gravity(g)
    args, fx = list(co['args']), None
    if wrench:   # per-state arguments first, then the parameters
        names = [f'f{b}_{k}' for b in range(fr.nb) for k in range(6)]
        args.append(('FX', names))
        fx = [g.input(nm) for nm in names]
    ararg, arm = fr.trace_armature(g)
    args += [parg, a0arg, co['offset_args'], ararg]
    tau_b = trace_inverse_dynamics(fr, cs, co['x'], co['xd'], co['xdd'], params, ga, fx)
    qdd = [g.input(nm) for nm in co['args'][2][1]]
    return Trace(g, 'inverse_dynamics_kernel', args, with_armature(joint_torques(fr, tau_b), arm, qdd))


def build_coriolis_term(fr):
    """k(Q, QD, P, E0) -> C(q, qd) qd tuple: the traced RNEA (trace_inverse_dynamics) at qdd = 0
    without gravity, the zeros constants (folded away: no qdd or g argument to pass)."""
    g = Graph()
    co, cs = _coordinates(fr, g, 1)
    parg, params = fr.trace_params(g)
    tau_b = trace_inverse_dynamics(fr, cs, co['x'], co['xd'], [0.0] * fr.nb, params, (0.0, 0.0, 0.0))
    return Trace(g, 'coriolis_term_kernel', co['args'] + [parg, co['offset_args']], joint_torques(fr, tau_b))


def trace_gravity(fr, cs, x, params, ga):
    """Body torques of g(q), traced: params per body (subtree mass, first moment: 4 symbols,
    Frames.subtree_params), ga = -g (3 symbols), cs = trig(fr, g, x).

    With V = 0 and Vdot_0 = (0, -g), eq 19 leaves only the linear acceleration a_i = R^T a_p,
    and the subtree sum of eq 20 is (H_i x a_i, m_i a_i): subtree mass m_i (a parameter)
    and first moment H_i = h'_i + sum_c (R_c H_c + m_c p_c), its constant part folded into
    the parameters. Eq 21 is then one component.
    """
    nb = fr.nb
    ga = tuple(ga)
    R0 = [np.array(R) for R in fr.R]
    acc = [None] * nb
    for b in range(nb):
        p = fr.parent[b]
        u = _lin(R0[b].T, acc[p] if p >= 0 else ga)
        acc[b] = _rz(*cs[b], u, True) if fr.revolute[b] else u
    H = [tuple(ps[1:]) for ps in params]
    tau_b = [None] * nb
    for b in range(nb - 1, -1, -1):
        a = acc[b]
        tau_b[b] = H[b][0] * a[1] - H[b][1] * a[0] if fr.revolute[b] else params[b][0] * a[2]
        p = fr.parent[b]
        if p < 0:
            continue
        if fr.revolute[b]:
            u = _rz(*cs[b], H[b], False)
        else:  # H + m_sub z x
            u = (H[b][0], H[b][1], H[b][2] + params[b][0] * x[b])
        H[p] = _lin(R0[b], u, add=H[p])
    return tau_b


def subtree_inputs(g, nb, name='P', prefix='p'):
    """(argument list, per-body symbols) of the gravity parameters (Frames.subtree_params)."""
    names = [f'{prefix}{b}_{k}' for b in range(nb) for k in range(4)]
    syms = [g.input(nm) for nm in names]
    return Params(name, names), [syms[4 * b:4 * b + 4] for b in range(nb)]


def build_gravity(fr):
    """k(Q, P, A0, E0) -> g(q) tuple (trace_gravity), P = Frames.subtree_params (as
    build_inverse_dynamics)."""
    g = Graph()
    co, cs = _coordinates(fr, g, 0)
    parg, params = subtree_inputs(g, fr.nb)
    a0arg, ga = fr.trace_gravity(g)
    args = co['args'] + [parg, a0arg, co['offset_args']]
    return Trace(g, 'gravity_kernel', args, joint_torques(fr, trace_gravity(fr, cs, co['x'], params, ga)))


INVERSE_DYNAMICS = Spec('inverse_dynamics', lambda fr: build_inverse_dynamics(fr, False),
                        ('inertia', 'gravity', 'offsets', 'armature'), 'inverse_dynamics', rows_arrays=True,
                        pooled=True)
INVERSE_DYNAMICS_WRENCH = Spec('inverse_dynamics_wrench', lambda fr: build_inverse_dynamics(fr, True),
                               ('inertia', 'gravity', 'offsets', 'armature'), 'inverse_dynamics', rows_arrays=True,
                               pooled=True)
MOMENTUM = Spec('momentum', build_momentum, ('inertia', 'offsets', 'armature'), 'inverse_dynamics',
                rows_arrays=True, pooled=True)
CORIOLIS_TERM = Spec('coriolis_term', build_coriolis_term, ('inertia', 'offsets'), 'inverse_dynamics',
                     rows_arrays=True, pooled=True)
GRAVITY = Spec('gravity', build_gravity, ('subtree', 'gravity', 'offsets'), 'gravity', rows_arrays=True, pooled=True)
