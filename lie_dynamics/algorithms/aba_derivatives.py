"""Derivatives of forward dynamics from those of inverse dynamics.

Forward dynamics qdd = FD(q, qd, tau) solves ID(q, qd, qdd) = tau. Differentiating the
identity ID(q, qd, FD(q, qd, tau)) = tau gives, with M = dID/dqdd,

    dqdd/dq = -M^-1 dID/dq,   dqdd/dqd = -M^-1 dID/dqd,   dqdd/dtau = M^-1,

the partials of ID evaluated at qdd = FD(q, qd, tau) (rnea_derivatives.py). M^-1 is
applied by Cholesky solves, and returned as dqdd/dtau (it is that derivative).

Without wrenches, models of up to KERNEL_MAX_BODIES bodies run all of it as one generated
kernel (codegen.py): the Cholesky forward dynamics of aba.py, the derivative recursion of
rnea_derivatives.py at that qdd, and the 3n triangular solves, on Python floats for one
state and small batches and on numpy rows for large ones.
"""
import numpy as np

from . import aba, crba, rnea
from ..codegen import runtime
from ..codegen.render import kernel
from ..codegen.tracer import Graph
from . import rnea_derivatives as rd
from .aba import cho_solve, cholesky
from .rnea_derivatives import inverse_dynamics_derivatives

KERNEL_MAX_BODIES = rd.KERNEL_MAX_BODIES
# Batches: the float kernel state by state below _LOOP_BELOW states, numpy rows from _ROWS_FROM,
# the general (vectorised) path in between (measured crossovers on the arm: ~8 and ~80).
_LOOP_BELOW = 8
_ROWS_FROM = 80


def forward_dynamics_derivatives(model, q, qd, tau, wrenches=None):
    """(dqdd/dq, dqdd/dqd, dqdd/dtau) at qdd = forward_dynamics(q, qd, tau, wrenches).

    Single state (n,) -> three (n, n) arrays; batch (N, n) -> three (N, n, n) arrays
    (Pinocchio's computeABADerivatives: ddq_dq, ddq_dv, Minv).
    """
    n = model.n
    if not wrenches:
        a, b, c = runtime.is_fast_single(q, n), runtime.is_fast_single(qd, n), runtime.is_fast_single(tau, n)
        if a is not None and b is not None and c is not None:
            out = _kernel_single(model, a, b, c)
            if out is not None:
                return out[0], out[1], out[2]
    single = np.ndim(q) == 1
    q, qd, tau = model.check_states(q=q, qd=qd, tau=tau)
    N = q.shape[0]
    if not wrenches:
        out = _kernel_states(model, q, qd, tau)
        if out is not None:
            return tuple(o[0] for o in out) if single else out
    # the general path; it also reports a mass matrix that is not positive definite
    if single:   # one state: the kernel paths and 2-D LAPACK calls (no batch axis to carry)
        q, qd, tau = q[0], qd[0], tau[0]
        M = crba.mass_matrix(model, q)
        L = cholesky(M[None])[0]
        h = rnea.inverse_dynamics(model, q, qd, np.zeros_like(qd), wrenches)
        Lt = L.T
        qdd = np.linalg.solve(Lt, np.linalg.solve(L, tau - h))
        dq, dv = inverse_dynamics_derivatives(model, q, qd, qdd, wrenches)
        sol = np.linalg.solve(Lt, np.linalg.solve(L, np.concatenate([dq, dv, np.eye(n)], axis=1)))
        return -sol[:, :n], -sol[:, n:2 * n], sol[:, 2 * n:]
    M = crba.mass_matrix(model, q)
    L = cholesky(M)
    h = rnea.inverse_dynamics(model, q, qd, np.zeros_like(qd), wrenches)
    qdd = cho_solve(L, tau - h)
    dq, dv = inverse_dynamics_derivatives(model, q, qd, qdd, wrenches)
    rhs = np.concatenate([dq, dv, np.broadcast_to(np.eye(n), (N, n, n))], axis=-1)
    sol = cho_solve(L, rhs)
    return -sol[..., :n], -sol[..., n:2 * n], sol[..., 2 * n:]


# ---------------------------------------------------------------------------- generated kernel
def _build_kernel(fr):
    """Trace qdd (aba.trace_forward_dynamics), dtau/dq and dtau/dqd at that qdd
    (rnea_derivatives.trace_derivatives) and the solves with the same Cholesky factor.

    Outputs dqdd/dq, dqdd/dqd, M^-1 (row-major), then the pivots and diag(M) for the
    positive-definiteness check (as aba's Cholesky kernel).
    """
    g = Graph()
    co, args, params, ga, taus = aba.trace_inputs(fr, g)
    qdd, M, L, inv_d, pivots = aba.trace_forward_dynamics(fr, g, co['x'], co['xd'], params, ga, taus)
    n, nb = fr.n, fr.nb
    xdd = [sum((float(fr.E[b, j]) * qdd[j] for j in range(n) if fr.E[b, j] != 0), 0.0) for b in range(nb)]
    dq, dv = rd.trace_derivatives(fr, g, co['x'], co['xd'], xdd, params, ga)
    cols = []
    for D, sign in ((dq, -1.0), (dv, -1.0)):
        cols += [[sign * v for v in aba.trace_cho_solve(L, inv_d, [D[r][c] for r in range(n)])] for c in range(n)]
    cols += [aba.trace_cho_solve(L, inv_d, [1.0 if r == c else 0.0 for r in range(n)]) for c in range(n)]
    outputs = []
    for k in range(3):
        outputs += [cols[k * n + c][r] for r in range(n) for c in range(n)]
    outputs += pivots + [M[j][j] for j in range(n)]
    return kernel(g, 'forward_dynamics_derivatives_kernel', args, outputs)


def _kernel(model):
    if model.nb > KERNEL_MAX_BODIES:
        return False
    return runtime.compiled(model, 'forward_dynamics_derivatives', _build_kernel)


def _kernel_single(model, q, qd, tau):
    """One state (lists of floats) on Python floats: a (3, n, n) array, or None (no kernel, or
    the mass matrix fails the positive-definiteness test)."""
    k = _kernel(model)
    if not k:
        return None
    fr, fn, _ = k
    P, E0, A0 = runtime.model_params(model, fr, gravity=True)
    n = model.n
    vals = aba.single_checked(fn, (P, A0, E0), q, qd, tau, 3 * n * n)
    return None if vals is None else np.fromiter(vals, float, 3 * n * n).reshape(3, n, n)


def _kernel_states(model, q, qd, tau, mode=None):
    """Kernel path for validated (N, n) arrays, without wrenches.

    mode: 'loop' (Python floats, state by state), 'rows' (numpy rows) or None (by batch size).
    Returns three (N, n, n) arrays, or None when there is no kernel, the batch size is one
    where the general path is faster, or some mass matrix fails the positive-definiteness
    test (the general path then reports it).
    """
    N = q.shape[0]
    if mode is None:
        mode = 'loop' if N < _LOOP_BELOW else 'rows' if N >= _ROWS_FROM else None
    k = _kernel(model) if mode else False
    if not k:
        return None
    fr, fn, _ = k
    P, E0, A0 = runtime.model_params(model, fr, gravity=True)
    n = q.shape[1]
    vals = aba.run_checked(fn, (P, A0, E0), q, qd, tau, 3 * n * n, mode == 'rows')
    if vals is None:
        return None
    out = vals.reshape(N, 3, n, n)
    return out[:, 0], out[:, 1], out[:, 2]
