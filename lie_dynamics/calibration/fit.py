"""Physically consistent calibration: every body's mass, CoM and inertia valid, friction and
armature >= 0, the prior (the URDF) kept along the directions the data do not see.

The measured efforts are linear in the calibration parameters (regressor.py), but a plain
least-squares fit can return a negative mass or an inertia no body has. Here every body's
parameters are written through its pseudo-inertia (Rucker & Wensing 2022, "Smooth
parameterization of rigid-body inertia"),

    P = [[Sigma, h], [h^T, m]] = U U^T,   Sigma = tr(I)/2 1 - I,   h = m c,

with I the inertia about the body frame and U upper triangular,

    U = e^alpha [[e^d1, s12, s13, t1], [0, e^d2, s23, t2], [0, 0, e^d3, t3], [0, 0, 0, 1]].

P is positive definite exactly when the body is physically valid (m > 0, inertia about the
CoM positive definite, triangle inequality strict), and every real theta = (alpha, d1, d2,
d3, s12, s23, s13, t1, t2, t3) gives one, so the fit is an unconstrained least-squares
problem in theta (scipy.optimize.least_squares), with armature, viscous and Coulomb friction
as bounded variables (>= 0) and the offsets free.

The cost is |W (Y pi(x) - tau)|^2 + lambda |N^T D (pi(x) - pi_prior)|^2: the (weighted) effort
residual, solved in the p + 1 rows of its QR form (regressor.reduce, so a long recording costs
one QR), plus a regularisation towards the prior that acts only along N, the directions the
data do not see (D the column scaling): along the seen directions the data alone decide.

Standard deviations come from the Jacobian of the effort residual at the solution (the
stacked regressor), scaled by the residual variance: sigma^2 (Y^T W^2 Y)^+ for the parameters
the data determine alone; the others have none (NaN) and say where their value comes from.
"""
import warnings
from dataclasses import dataclass

import numpy as np

from ..algorithms.identification import UnidentifiableWarning, least_squares
from ..laws import COULOMB_VELOCITY_EPSILON
from . import regressor as creg

__all__ = ['UnidentifiableWarning', 'fit', 'FitResult', 'parameters_to_theta', 'theta_to_parameters']

# Which joint terms are >= 0 (armature, viscous, Coulomb); offsets are free.
_NONNEGATIVE = {'armature': True, 'viscous': True, 'coulomb': True, 'offset': False}
# Upper-triangular entries of U holding s12, s23, s13, t1, t2, t3 (theta[4:]).
_OFF = ((0, 1), (1, 2), (0, 2), (0, 3), (1, 3), (2, 3))


def _pseudo_inertia(pi):
    """P (4, 4) of one body's parameters (m, h, Ixx, Ixy, Iyy, Ixz, Iyz, Izz)."""
    m, h = pi[0], pi[1:4]
    xx, xy, yy, xz, yz, zz = pi[4:]
    I = np.array([[xx, xy, xz], [xy, yy, yz], [xz, yz, zz]])
    P = np.empty((4, 4))
    P[:3, :3] = 0.5 * np.trace(I) * np.eye(3) - I
    P[:3, 3] = P[3, :3] = h
    P[3, 3] = m
    return P


def _parameters_of(P):
    """Inverse of _pseudo_inertia (linear): (..., 10) parameters of P (..., 4, 4)."""
    S = P[..., :3, :3]
    tr = np.trace(S, axis1=-2, axis2=-1)
    return np.stack([P[..., 3, 3], P[..., 0, 3], P[..., 1, 3], P[..., 2, 3], tr - S[..., 0, 0], -S[..., 0, 1],
                     tr - S[..., 1, 1], -S[..., 0, 2], -S[..., 1, 2], tr - S[..., 2, 2]], axis=-1)


_DIAG = (0, 1, 2)
_ROWS, _COLS = np.array(_OFF).T


def _factor(theta):
    """U (..., 4, 4) of theta (..., 10), one per body."""
    theta = np.asarray(theta)
    U = np.zeros(theta.shape[:-1] + (4, 4))
    U[..., _DIAG, _DIAG] = np.exp(theta[..., 1:4])
    U[..., 3, 3] = 1.0
    U[..., _ROWS, _COLS] = theta[..., 4:]
    return np.exp(theta[..., 0])[..., None, None] * U


def theta_to_parameters(theta):
    """(nb, 10) log-Cholesky coordinates -> (nb, 10) inertial parameters (always physically valid)."""
    U = _factor(np.atleast_2d(theta))
    return _parameters_of(U @ np.swapaxes(U, -1, -2))


def parameters_to_theta(pi):
    """(nb, 10) inertial parameters with a positive-definite pseudo-inertia -> log-Cholesky
    coordinates; ValueError naming the body where P is not positive definite."""
    out = []
    E = np.eye(4)[::-1]
    for i, p in enumerate(np.atleast_2d(pi)):
        try:
            L = np.linalg.cholesky(E @ _pseudo_inertia(p) @ E)
        except np.linalg.LinAlgError:
            raise ValueError(f'body {i}: the parameters are not strictly physically valid '
                             '(pseudo-inertia not positive definite)') from None
        U = E @ L @ E
        a = U[3, 3]
        U = U / a
        out.append(np.concatenate([[np.log(a)], np.log(np.diag(U)[:3]), [U[i, j] for i, j in _OFF]]))
    return np.array(out)


def _theta_jacobian(theta):
    """d pi / d theta (nb, 10, 10), one block per body, analytic: dP = dU U^T + U dU^T, pi linear
    in P; dU/d theta_0 = U, dU/d theta_k = U_kk on the diagonal entry (k = 1..3), and e^alpha on
    the off-diagonal entry of theta_k (k = 4..9)."""
    theta = np.atleast_2d(theta)
    U = _factor(theta)
    dU = np.zeros(theta.shape[:-1] + (10, 4, 4))
    dU[..., 0, :, :] = U
    for k in _DIAG:
        dU[..., k + 1, k, k] = U[..., k, k]
    dU[..., 4 + np.arange(6), _ROWS, _COLS] = np.exp(theta[..., 0])[..., None]
    dP = dU @ np.swapaxes(U, -1, -2)[..., None, :, :]
    return np.swapaxes(_parameters_of(dP + np.swapaxes(dP, -1, -2)), -1, -2)


def _nearest_valid(pi, floor):
    """A strictly valid body near pi (for a start point): mass at least `floor`, the pseudo-
    inertia's eigenvalues raised to a small positive floor."""
    P = _pseudo_inertia(pi)
    w, V = np.linalg.eigh(P)
    w = np.maximum(w, floor * max(w.max(), 1e-12))
    P = (V * w) @ V.T
    return _parameters_of(P)


@dataclass
class FitResult:
    """Outcome of `fit`.

    parameters: (p,) calibration parameters (regressor.parameter_names order): every body
        physically valid, armature, viscous and Coulomb >= 0.
    std: (p,) standard deviations; NaN where the data do not determine the value alone.
    source: (p,) 'identified' (the data determine it), 'combination' (the data determine it
        only in combination with others: its value also leans on the prior) or 'prior' (kept).
    base: regressor.BaseParameters of the data (rank, combinations, condition number).
    residual_rms: (n,) rms effort residual per joint on the data. eps: the Coulomb velocity scale.
    still_joints: joints that never moved (their friction and armature kept from the prior).
    """
    parameters: np.ndarray
    std: np.ndarray
    source: list
    base: object
    residual_rms: np.ndarray
    eps: float
    still_joints: list
    prior: np.ndarray
    cost: float


def fit(model, q, qd, qdd, effort, eps=COULOMB_VELOCITY_EPSILON, weights=None, prior=None,
        regularization=0.0, rcond=1e-8, min_motion=1e-3, tol=1e-14, max_nfev=200, start_floor=1e-3, coulomb=None):
    """Physically consistent calibration parameters from measured efforts along (q, qd, qdd).

    q, qd, qdd, effort: (N, n) in model.joint_names order. weights: (n,) per-joint weights
    (1 / noise std; default 1). prior: (p,) calibration parameters to keep where the data are
    blind (default regressor.prior_parameters(model): the URDF's inertias, <dynamics> damping and
    friction, the model's armature, offsets 0). regularization: weight of the pull towards the
    prior along the unseen directions, relative to the data's largest singular value squared.
    min_motion: a joint whose position range and peak speed are both below it (rad, rad/s)
    never moved. coulomb: (N, n) the Coulomb columns' values (regressor.calibration_regressor;
    default tanh(qd / eps)). Warns UnidentifiableWarning (naming the joints and parameters, which keep
    their prior values) when the recording is too short, a joint never moves, or the data
    determine fewer combinations than the robot's structure allows. Returns FitResult.
    """
    q, qd, qdd, effort = model.check_states(q=q, qd=qd, qdd=qdd, effort=effort)
    N, n = q.shape
    nb = model.nb
    names = creg.parameter_names(model)
    p = len(names)
    ni = 10 * nb
    prior = creg.prior_parameters(model) if prior is None else np.asarray(prior, dtype=float)
    if prior.shape != (p,) or not np.all(np.isfinite(prior)):
        raise ValueError(f'prior must be {p} finite calibration parameters, got shape {prior.shape}')
    if not (0 <= regularization < 1):
        raise ValueError(f'regularization must be in [0, 1), got {regularization}')

    moved = (np.ptp(q, axis=0) >= min_motion) | (np.abs(qd).max(axis=0) >= min_motion)
    still = [model.joint_names[j] for j in range(n) if not moved[j]]
    Y, y = creg.stack(model, q, qd, qdd, effort, eps, weights, coulomb)
    # a still joint's own terms are not fitted: its qd, qdd columns would be noise
    fixed = np.zeros(p, dtype=bool)
    for j in np.flatnonzero(~moved):
        fixed[ni + 4 * j: ni + 4 * j + 3] = True
    y = y - Y[:, fixed] @ prior[fixed]
    Y = np.where(fixed[None, :], 0.0, Y)
    R, c, rows = creg.reduce(Y, y)
    base = creg.base_parameters(R, c, names, rows, rcond)
    _warn_unidentifiable(model, base, still, N, eps, rcond)

    scale = base.scale
    Rs = R / scale
    smax = np.linalg.norm(Rs, 2)
    Nt = base.null_space * (np.sqrt(regularization) * smax)      # (p - r, p), scaled units
    free = ~fixed
    free[:ni] = False
    jf = np.flatnonzero(free)                                    # joint terms that are variables
    terms = creg.JOINT_TERMS
    lower = np.array([0.0 if _NONNEGATIVE[terms[(k - ni) % 4]] else -np.inf for k in jf])

    # start: the least-squares solution closest to the prior, each body moved into validity
    ls = least_squares(R, c, prior, rcond)['parameters']
    start = np.array([_nearest_valid(b, start_floor) for b in ls[:ni].reshape(nb, 10)])
    x0 = np.concatenate([parameters_to_theta(start).reshape(-1), np.maximum(ls[jf], lower)])
    lb = np.concatenate([np.full(ni, -np.inf), lower])
    z0 = prior * scale

    def full(x):
        pi = prior.copy()
        pi[:ni] = theta_to_parameters(x[:ni].reshape(nb, 10)).reshape(-1)
        pi[jf] = x[ni:]
        return pi

    def residual(x):
        z = full(x) * scale
        return np.concatenate([Rs @ z - c, Nt @ (z - z0)])

    def jacobian(x):
        D = np.zeros((p, len(x)))
        blocks = _theta_jacobian(x[:ni].reshape(nb, 10))
        for b in range(nb):
            D[10 * b:10 * b + 10, 10 * b:10 * b + 10] = blocks[b]
        D[jf, ni + np.arange(len(jf))] = 1.0
        D *= scale[:, None]
        return np.vstack([Rs @ D, Nt @ D])

    from scipy.optimize import least_squares as solve   # scipy: imported where it is used

    # The optimum often lies where a body is at the edge of validity (the prior's projection is
    # not valid), which log-Cholesky reaches only at infinity: the iteration count then bounds it.
    # Steps by lsmr, not an SVD of the Jacobian per iteration ('exact'): with OpenBLAS's threads
    # on a loaded 2-core machine each 128 x 98 SVD took 75-240 ms (4 ms on one thread), and
    # identify_dynamics on 60 s at 1 kHz took 50 s instead of 12 s (3.6 s and 4.6 s with one BLAS
    # thread; bench/calibration.py --identify-time measures the command).
    with np.errstate(over='ignore', invalid='ignore'):   # trial steps too far: trf shrinks them
        sol = solve(residual, x0, jac=jacobian, bounds=(lb, np.full(len(x0), np.inf)), method='trf',
                    x_scale='jac', tr_solver='lsmr', ftol=tol, xtol=tol, gtol=tol, max_nfev=max_nfev)
    pi = full(sol.x)

    # standard deviations: sigma^2 (Ys^T Ys)^+ in scaled units, for what the data determine alone
    r = base.rank
    data_res = Rs @ (pi * scale) - c
    sigma2 = float(data_res @ data_res) / max(rows - r, 1)
    cov = sigma2 * np.linalg.pinv(Rs.T @ Rs, rcond=rcond ** 2, hermitian=True)
    std = np.sqrt(np.clip(np.diag(cov), 0.0, None)) / scale
    source = [{'identified': 'identified', 'combination': 'combination', 'unidentified': 'prior'}[s]
              for s in base.status]
    for k in np.flatnonzero(fixed):
        source[k] = 'prior'
    std = np.where(np.array(source) == 'identified', std, np.nan)
    resid = Y @ pi - y
    w = np.ones(n) if weights is None else np.asarray(weights, dtype=float)
    rms = np.sqrt(np.mean((resid.reshape(N, n) / w) ** 2, axis=0))
    return FitResult(parameters=pi, std=std, source=source, base=base, residual_rms=rms, eps=float(eps),
                     still_joints=still, prior=prior, cost=float(sol.cost))


def _warn_unidentifiable(model, base, still, N, eps, rcond):
    """UnidentifiableWarning naming what the data miss that the robot's structure would allow."""
    p = len(base.names)
    struct = creg.structural_base(model, eps, rcond=rcond)
    problems = []
    if N * model.n < p:
        problems.append(f'recording too short: {N} samples x {model.n} joints = {N * model.n} equations '
                        f'for {p} parameters')
    if still:
        problems.append(f'joints that never move: {", ".join(still)} (their armature, viscous and Coulomb '
                        'friction keep their prior values)')
    if base.rank < struct.rank:
        rank = {'identified': 2, 'combination': 1, 'unidentified': 0}
        lost = [nm for nm, s, t in zip(base.names, base.status, struct.status) if rank[s] < rank[t]]
        problems.append(f'the data determine {base.rank} of the {struct.rank} base parameters; kept from the '
                        f'prior or only in combination: {", ".join(lost) if lost else "(combinations only)"}')
    if problems:
        warnings.warn('; '.join(problems), UnidentifiableWarning, stacklevel=3)
