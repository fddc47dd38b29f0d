"""Dense Cholesky factorisation and solves for batches of mass matrices, with the positive
definiteness test shared by every forward-dynamics path (the generated kernels' pivots too:
their Spec.result gives PD_RTOL to codegen.runtime.accepts)."""
import numpy as np

from ..codegen.thresholds import PD_RTOL
from ..spatial import transpose

__all__ = ['PD_RTOL', 'cho_solve', 'cholesky']


def cholesky(M):
    """Lower factor L of M = L L^T for (N, n, n); ValueError if some M is not positive definite."""
    try:
        L = np.linalg.cholesky(M)
    except np.linalg.LinAlgError:
        L = None
    else:
        # LAPACK factors some singular matrices (a zero pivot rounded positive): test each pivot
        # against its own diagonal entry, so the test is blind to scale (graded masses are fine)
        # and sees only near-dependence (a joint that moves no mass of its own)
        d = np.diagonal(L, axis1=-2, axis2=-1)
        if (d * d > PD_RTOL * np.diagonal(M, axis1=-2, axis2=-1)).all():
            return L
    bad = [k for k in range(M.shape[0]) if not _is_pd(M[k])]
    k = int(bad[0])
    ev = np.linalg.eigvalsh(M[k])
    where = f'at state {k} ' if M.shape[0] > 1 else ''
    raise ValueError(f'mass matrix is not positive definite {where}(smallest eigenvalue {ev[0]:.3g}, '
                     f'largest {ev[-1]:.3g}): some joint moves no mass (massless body or chain), '
                     'so forward dynamics is undefined')


def _is_pd(M):
    try:
        L = np.linalg.cholesky(M)
    except np.linalg.LinAlgError:
        return False
    return bool(np.all(np.diagonal(L) ** 2 > PD_RTOL * np.diagonal(M)))


def cho_solve(L, B):
    """Solve L L^T X = B for batches: L (N, n, n), B (N, n) or (N, n, k)."""
    vec = B.ndim == 2
    B = B[..., None] if vec else B
    N, n = L.shape[:2]
    if N > 2 * n:
        # many small systems: substitution, one row for all states at a time
        Y = np.empty(B.shape)
        for j in range(n):
            Y[:, j] = (B[:, j] - np.einsum('ni,nik->nk', L[:, j, :j], Y[:, :j])) / L[:, j, j, None]
        X = np.empty(B.shape)
        for j in range(n - 1, -1, -1):
            X[:, j] = (Y[:, j] - np.einsum('ni,nik->nk', L[:, j + 1:, j], X[:, j + 1:])) / L[:, j, j, None]
    else:
        X = np.linalg.solve(transpose(L), np.linalg.solve(L, B))
    return X[..., 0] if vec else X
