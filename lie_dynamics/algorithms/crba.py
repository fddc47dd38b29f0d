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

For models of up to KERNEL_MAX_BODIES bodies the same algorithm also exists as generated
straight-line code (codegen.py), in body frames: composite inertias carried to the parent
as 10 parameters, the joint wrench F = Jc_j S_j carried to every ancestor. That kernel runs
on Python floats for one state (no numpy call) and on numpy rows for large batches; it is
what `mass_matrix` uses where the measured crossovers say it is faster.
"""
import math

import numpy as np

from ..codegen import algebra as la
from ..codegen import runtime
from ..codegen.render import kernel
from ..codegen.tracer import Graph
from ..spatial import transpose
from .lagrangian import body_matrices, kinematic_state, subtree_sum, world_inertias


def _crba(model, x):
    _, AdinvT, A = kinematic_state(model, x)
    Jc = subtree_sum(model, world_inertias(model, AdinvT))      # backward recursion
    F = (Jc @ A[..., None])[..., 0]                              # Jc_j A_j
    U = (A @ transpose(F)) * model.ancestors.T                       # m_kj for k <= j
    return U + transpose(U) - U * np.eye(model.nb)


def mass_matrix(model, q):
    """M(q) by the composite rigid body algorithm. q: (n,) or (N, n) -> (n, n) or (N, n, n).

    Runs the generated kernel (below) for models of up to KERNEL_MAX_BODIES bodies, else the
    vectorised form.
    """
    if _kernel(model):
        N = 1 if np.ndim(q) == 1 else len(q)
        if N < _LOOP_BELOW or N >= _ROWS_FROM:
            return mass_matrix_kernel(model, q)
    return mass_matrix_vectorized(model, q)


def mass_matrix_vectorized(model, q):
    """M(q) by the vectorised composite rigid body algorithm (numpy over bodies and states)."""
    nb = model.nb
    return body_matrices(model, q, _crba, 150 * nb + nb * nb)


# ---------------------------------------------------------------------------- generated kernel
# Above this many bodies the straight-line source (O(n^2) lines) takes long to compile and the
# vectorised path above is used instead.
KERNEL_MAX_BODIES = 24
# Batches: the float kernel state by state below _LOOP_BELOW states, the kernel on numpy rows
# from _ROWS_FROM states, the vectorised form in between (measured on the arm: the float loop
# beats the vectorised form up to ~40 states, where the in-place rows take over).
_LOOP_BELOW = 40
_ROWS_FROM = 40


def trace_mass_matrix(fr, g, params, X):
    """Traced joint-space M (nested n x n lists) by the composite rigid body algorithm.

    In the primed body frames (see codegen.Frames), with X the traced joint transforms:
    backward, Jc_parent += (inertia of the subtree of b, moved to the parent frame); then for
    each joint b: F = Jc_b S_b, m_bb = S_b^T F, and F carried to every ancestor j
    (F <- Ad*_{f^-1} F) gives m_jb = S_j^T F.
    """
    nb = fr.nb
    ic = list(params)
    for b in reversed(range(nb)):
        p = fr.parent[b]
        if p >= 0:
            m, h, Io = la.inertia_to_parent(ic[b], *X[b])
            mp, hp, Ip = ic[p]
            ic[p] = (mp + m, la.vadd(hp, h), la.vadd(Ip, Io))

    def s_dot(b, F):
        return F[0][2] if fr.revolute[b] else F[1][2]

    Mx = [[0.0] * nb for _ in range(nb)]
    for b in range(nb):
        m, h, Io = ic[b]
        if fr.revolute[b]:
            F = ((Io[2], Io[4], Io[5]), (-h[1], h[0], 0.0))
        else:
            F = ((h[1], -h[0], 0.0), (0.0, 0.0, m))
        Mx[b][b] = s_dot(b, F)
        j = b
        while fr.parent[j] >= 0:
            F = la.wrench_to_parent(F, *X[j])
            j = fr.parent[j]
            Mx[j][b] = Mx[b][j] = s_dot(j, F)
    Mq = fr.project(Mx)
    n = fr.n
    return [[Mq[min(a, c)][max(a, c)] for c in range(n)] for a in range(n)]


def _build_kernel(fr):
    g = Graph()
    co = fr.trace_coordinates(g)
    parg, params = fr.trace_params(g)
    X = [fr.joint_transform(g, b, co['x'][b]) for b in range(fr.nb)]
    M = trace_mass_matrix(fr, g, params, X)
    outputs = [v for row in M for v in row]
    return kernel(g, 'mass_kernel', co['args'] + [parg, co['offset_args']], outputs)


def _kernel(model):
    if model.nb > KERNEL_MAX_BODIES:
        return False
    return runtime.compiled(model, 'crba', _build_kernel)


def mass_matrix_kernel(model, q):
    """M(q) from the generated CRBA kernel, or None when the model has none (too large).

    One state runs on Python floats; batches state by state below _ROWS_FROM states, else on rows.
    """
    k = _kernel(model)
    if not k:
        return None
    fr, fn, _ = k
    P, E0 = runtime.model_params(model, fr)
    n = model.n
    lst = runtime.is_fast_single(q, n)
    if lst is not None:
        return np.array(fn(lst, P, E0, sin=math.sin, cos=math.cos)).reshape(n, n)
    single = np.ndim(q) == 1
    qb = model.check_batch('q', q)
    if single:
        return np.array(fn(qb[0].tolist(), P, E0, sin=math.sin, cos=math.cos)).reshape(n, n)
    N = qb.shape[0]
    if N < _ROWS_FROM:
        vals = np.array([fn(row, P, E0, sin=math.sin, cos=math.cos) for row in qb.tolist()])
    else:
        vals = runtime.run_rows(fn, [qb, P, E0], n * n)
    return vals.reshape(N, n, n)
