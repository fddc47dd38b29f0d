"""Derivatives of forward dynamics from those of inverse dynamics.

Forward dynamics qdd = FD(q, qd, tau) solves ID(q, qd, qdd) = tau. Differentiating the
identity ID(q, qd, FD(q, qd, tau)) = tau gives, with M = dID/dqdd,

    dqdd/dq = -M^-1 dID/dq,   dqdd/dqd = -M^-1 dID/dqd,   dqdd/dtau = M^-1,

the partials of ID evaluated at qdd = FD(q, qd, tau) (rnea_derivatives.py). M^-1 is
applied by Cholesky solves, and returned as dqdd/dtau (it is that derivative).
"""
import numpy as np

from . import crba, rnea
from .aba import cho_solve, cholesky
from .rnea_derivatives import inverse_dynamics_derivatives


def forward_dynamics_derivatives(model, q, qd, tau, wrenches=None):
    """(dqdd/dq, dqdd/dqd, dqdd/dtau) at qdd = forward_dynamics(q, qd, tau, wrenches).

    Single state (n,) -> three (n, n) arrays; batch (N, n) -> three (N, n, n) arrays
    (Pinocchio's computeABADerivatives: ddq_dq, ddq_dv, Minv).
    """
    single = np.ndim(q) == 1
    q, qd, tau = model._states(q=q, qd=qd, tau=tau)
    N = q.shape[0]
    n = model.n
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
