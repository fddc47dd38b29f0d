"""Composite rigid body algorithm: the mass matrix in O(n^2).

The recursive counterpart of the closed form M = S^T G^T J G S (lagrangian.py, eq 39).
Grouping the sum over bodies in eq 29 by the deepest body involved,

    m_kj = A_k^T Jc_j A_j        for k <= j (k is j or an ancestor of j), m_jk = m_kj,
    m_kj = 0                      when neither is an ancestor of the other,

where A_j = Ad_{T_j} S_j is joint j's screw in the root frame and
Jc_j = sum_{j <= p} Ad_{T_p}^-T J_p Ad_{T_p}^-1 is the composite inertia of the subtree of
body j about the root frame. The backward recursion Jc_parent += Jc_child is one product
with the constant ancestor matrix (subtree sums), then M is a masked product of the
screws with the composite momenta Jc_j A_j: O(n^2) work, vectorised over bodies and states.

The same algorithm also exists as generated straight-line code (codegen/traced/crba.py), in
body frames: composite inertias carried to the parent as 10 parameters, the joint wrench
F = Jc_j S_j carried to every ancestor. `mass_matrix` validates, then runs that kernel
where codegen.runtime.route says it is faster, else the vectorised form.
"""
import numpy as np

from ..codegen import runtime
from ..codegen.traced import crba as traced
from ..spatial import transpose
from .common import body_matrices, kinematic_state, subtree_sum, world_inertias


def _crba(model, x):
    _, AdinvT, A = kinematic_state(model, x)
    Jc = subtree_sum(model, world_inertias(model, AdinvT))      # backward recursion
    F = (Jc @ A[..., None])[..., 0]                              # Jc_j A_j
    U = (A @ transpose(F)) * model.ancestors.T                   # m_kj for k <= j
    return U + transpose(U) - U * np.eye(model.nb)


def mass_matrix(model, q, out=None):
    """M(q) by the composite rigid body algorithm. q: (n,) or (N, n) -> (n, n) or (N, n, n).
    out: optional float64 array of the result's shape, written and returned."""
    M = runtime.fast(model, traced.MASS_MATRIX)(q, out)
    if M is not None:
        return M
    n = model.n
    (q,), single = model.validate(('q',), (q,))
    runtime.check_out(out, (n, n) if single else (len(q), n, n))
    vals = runtime.run(model, traced.MASS_MATRIX, [q])
    M = mass_matrix_vectorized(model, q) if vals is None else vals.reshape(len(q), n, n)
    return runtime.deliver(M[0] if single else M, out)


def mass_matrix_kernel(model, q, mode=None):
    """M(q) from the generated Python kernel: mode 'loop' (Python floats, state by state),
    'rows' (numpy rows) or None (as route decides). None without a kernel (or where route
    says the vectorised form is faster)."""
    (q,), single = model.validate(('q',), (q,))
    vals = runtime.run(model, traced.MASS_MATRIX, [q], mode, native_first=False)
    if vals is None:
        return None
    M = vals.reshape(len(q), model.n, model.n)
    return M[0] if single else M


def mass_matrix_vectorized(model, q):
    """M(q) by the vectorised composite rigid body algorithm (numpy over bodies and states)."""
    nb = model.nb
    return body_matrices(model, q, _crba, 150 * nb + nb * nb)
