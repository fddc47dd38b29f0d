"""Derivatives of forward dynamics from those of inverse dynamics.

Forward dynamics qdd = FD(q, qd, tau) solves ID(q, qd, qdd) = tau. Differentiating the
identity ID(q, qd, FD(q, qd, tau)) = tau gives, with M = dID/dqdd,

    dqdd/dq = -M^-1 dID/dq,   dqdd/dqd = -M^-1 dID/dqd,   dqdd/dtau = M^-1,

the partials of ID evaluated at qdd = FD(q, qd, tau) (rnea_derivatives.py). M^-1 is
applied by Cholesky solves, and returned as dqdd/dtau (it is that derivative).

Without wrenches, a generated kernel runs all of it (codegen/traced/derivatives.py): the
Cholesky forward dynamics, the derivative recursion at that qdd, and the 3n triangular
solves. Validate, then that kernel where codegen.runtime.route says so (and its pivots pass
the positive-definiteness test), else the vectorised reference.
"""
import numpy as np

from . import crba, rnea
from .cholesky import cho_solve, cholesky
from ..codegen import runtime
from ..codegen.traced import derivatives as traced
from .rnea_derivatives import inverse_dynamics_derivatives_validated


def forward_dynamics_derivatives(model, q, qd, tau, wrenches=None):
    """(dqdd/dq, dqdd/dqd, dqdd/dtau) at qdd = forward_dynamics(q, qd, tau, wrenches).

    Single state (n,) -> three (n, n) arrays; batch (N, n) -> three (N, n, n) arrays
    (Pinocchio's computeABADerivatives: ddq_dq, ddq_dv, Minv).
    """
    n = model.n
    # the fast path (its kernel takes no wrenches): the result, or None
    out = None if wrenches else runtime.fast(model, traced.FORWARD_DYNAMICS_DERIVATIVES)(q, qd, tau)
    if out is None:
        out = runtime.call(model, _DERIVATIVES, (q, qd, tau), None, (wrenches,))
    out = out.reshape(out.shape[:-1] + (3, n, n))
    return out[..., 0, :, :], out[..., 1, :, :], out[..., 2, :, :]


def _full(model, arrays, wrenches=None):
    """call's full path on validated (N, n) arrays: the three derivatives as one (N, 3 n n)
    array, as the kernel's outputs."""
    q, qd, tau = arrays
    out = None if wrenches else runtime.run(model, traced.FORWARD_DYNAMICS_DERIVATIVES, arrays)
    if out is None:
        out = np.concatenate([d.reshape(len(q), -1) for d in _vectorized(model, q, qd, tau, wrenches)], axis=1)
    return out


_DERIVATIVES = runtime.Entry(('q', 'qd', 'tau'), None, _full)


def forward_dynamics_derivatives_kernel(model, q, qd, tau, mode=None):
    """forward_dynamics_derivatives (no wrenches) from the generated Python kernel: mode 'loop'
    (Python floats, state by state), 'rows' (numpy rows) or None (as route decides). None
    when there is no kernel or a mass matrix fails the positive-definiteness test."""
    (q, qd, tau), single = model.validate(('q', 'qd', 'tau'), (q, qd, tau))
    out = _kernel(model, q, qd, tau, mode, native_first=False)
    return out if out is None or not single else tuple(o[0] for o in out)


def _kernel(model, q, qd, tau, mode=None, native_first=True):
    vals = runtime.run(model, traced.FORWARD_DYNAMICS_DERIVATIVES, [q, qd, tau], mode, native_first)
    if vals is None:
        return None
    n = model.n
    out = vals.reshape(len(q), 3, n, n)
    return out[:, 0], out[:, 1], out[:, 2]


def forward_dynamics_derivatives_vectorized(model, q, qd, tau, wrenches=None):
    """forward_dynamics_derivatives without its generated kernel: M, h and the derivatives of
    inverse dynamics by their own dispatch, then batched Cholesky solves."""
    (q, qd, tau), single = model.validate(('q', 'qd', 'tau'), (q, qd, tau))
    out = _vectorized(model, q, qd, tau, wrenches)
    return tuple(o[0] for o in out) if single else out


def _vectorized(model, q, qd, tau, wrenches):
    """On validated (N, n) arrays, by the validated paths of M, h and the derivatives of
    inverse dynamics; also reports a mass matrix that is not positive definite."""
    n = model.n
    N = q.shape[0]
    M = crba.mass_matrix_validated(model, q)
    h = rnea.inverse_dynamics_validated(model, [q, qd, np.zeros_like(qd)], wrenches)
    if N == 1:   # one state: 2-D LAPACK calls (no batch axis to carry)
        L = cholesky(M)[0]
        Lt = L.T
        qdd = np.linalg.solve(Lt, np.linalg.solve(L, tau[0] - h[0]))
        dq, dv = inverse_dynamics_derivatives_validated(model, [q, qd, qdd[None]], wrenches)
        sol = np.linalg.solve(Lt, np.linalg.solve(L, np.concatenate([dq[0], dv[0], np.eye(n)], axis=1)))
        return -sol[None, :, :n], -sol[None, :, n:2 * n], sol[None, :, 2 * n:]
    L = cholesky(M)
    qdd = cho_solve(L, tau - h)
    dq, dv = inverse_dynamics_derivatives_validated(model, [q, qd, qdd], wrenches)
    rhs = np.concatenate([dq, dv, np.broadcast_to(np.eye(n), (N, n, n))], axis=-1)
    sol = cho_solve(L, rhs)
    return -sol[..., :n], -sol[..., n:2 * n], sol[..., 2 * n:]
