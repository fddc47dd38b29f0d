"""Forward dynamics qdd = M^-1 (tau - h) by a Cholesky factorisation, traced.

M from the traced CRBA (traced/crba.py), the bias h = C qd + g from the traced RNEA with
qdd = 0 (traced/rnea.py), then M = L L^T and two triangular solves, all straight-line for
the model's tree (algorithms/aba.py, method='cholesky'). The kernels end their outputs
with the pivots d_j^2 and diag(M): callers test positive definiteness with them
(algorithms/cholesky.py), blind to the scale of the masses.
"""
from ..kernel import Trace
from ..runtime import Spec
from ..thresholds import PD_RTOL
from ..tracer import Graph
from .crba import trace_mass_matrix
from .rnea import trace_inverse_dynamics, trig


def trace_inputs(fr, g):
    """Symbols of a forward-dynamics kernel: (coordinates, argument lists (Q, QD, TAU, P, A0,
    E0), inertia parameters, -g, joint torques)."""
    co = fr.trace_coordinates(g, rates=1)
    parg, params = fr.trace_params(g)
    a0arg, ga = fr.trace_gravity(g)
    n = fr.n
    taus = [g.input(f'u{j}') for j in range(n)]
    args = co['args'] + [('TAU', [f'u{j}' for j in range(n)]), parg, a0arg, co['offset_args']]
    return co, args, params, ga, taus


def trace_forward_dynamics(fr, g, x, xd, params, a0, taus):
    """qdd = M^-1 (tau - h) traced: CRBA, the RNEA bias with qdd = 0, Cholesky and two
    triangular solves. Returns (qdd, M, L, 1 / diag(L), pivots)."""
    n = fr.n
    X = [fr.joint_transform(g, b, x[b]) for b in range(fr.nb)]
    M = trace_mass_matrix(fr, g, params, X)
    tau_b = trace_inverse_dynamics(fr, trig(fr, g, x), x, xd, [0.0] * fr.nb, params, a0)
    h = [sum((float(fr.E[b, j]) * tau_b[b] for b in range(fr.nb) if fr.E[b, j] != 0), 0.0) for j in range(n)]
    L, inv_d, pivots = trace_cholesky(g, M)
    return trace_cho_solve(L, inv_d, [taus[j] - h[j] for j in range(n)]), M, L, inv_d, pivots


def trace_cholesky(g, M):
    """M = L L^T traced (M: nested n x n list). Returns (L, 1 / diag(L), pivots d_j^2); a
    negative pivot makes sqrt fail on floats, and the caller tests the pivots (PD check)."""
    n = len(M)
    L = [[0.0] * n for _ in range(n)]
    inv_d, pivots = [0.0] * n, [0.0] * n
    for j in range(n):
        s = M[j][j]
        for k in range(j):
            s = s - L[j][k] * L[j][k]
        pivots[j] = s
        d = g.sqrt(s)
        inv_d[j] = g.inv(d)
        L[j][j] = d
        for i in range(j + 1, n):
            s = M[i][j]
            for k in range(j):
                s = s - L[i][k] * L[j][k]
            L[i][j] = s * inv_d[j]
    return L, inv_d, pivots


def trace_cho_solve(L, inv_d, b):
    """x with L L^T x = b, traced: forward then backward substitution."""
    n = len(b)
    y = [0.0] * n
    for i in range(n):
        s = b[i]
        for k in range(i):
            s = s - L[i][k] * y[k]
        y[i] = s * inv_d[i]
    z = [0.0] * n
    for i in reversed(range(n)):
        s = y[i]
        for k in range(i + 1, n):
            s = s - L[k][i] * z[k]
        z[i] = s * inv_d[i]
    return z


def build_forward_dynamics(fr):
    """k(Q, QD, TAU, P, A0, E0) -> qdd, then the Cholesky pivots d_j^2 and the diagonal of M
    (a negative pivot makes sqrt fail on floats)."""
    g = Graph()
    co, args, params, ga, taus = trace_inputs(fr, g)
    z, M, L, inv_d, pivots = trace_forward_dynamics(fr, g, co['x'], co['xd'], params, ga, taus)
    outputs = z + pivots + [M[j][j] for j in range(fr.n)]
    return Trace(g, 'forward_dynamics_kernel', args, outputs)


FORWARD_DYNAMICS = Spec('forward_dynamics', build_forward_dynamics, ('inertia', 'gravity', 'offsets'),
                        'forward_dynamics', checked=True, result=lambda model: ((model.n,), PD_RTOL))
