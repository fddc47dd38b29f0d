"""Inertial-parameter identification (calibration) by least squares on the regressor.

Rigid-body torques are linear in the 10 inertial parameters of every body (regressor.py):
tau = Y(q, qd, qdd) pi. Stacking measured torques along a trajectory gives an
overdetermined linear system; its solution is only unique up to the null space of the
stacked regressor. Part of that null space is structural (the first link of an arm
turns about one fixed axis, so only its inertia about that axis matters; some
parameters only act in combinations), part comes from a trajectory that does not excite
the robot enough. `identify` therefore

  1. scales the columns of the stacked regressor (parameters have different units),
  2. finds its numerical rank r by SVD (relative threshold `rcond`),
  3. picks r independent columns by QR with column pivoting: the *base parameters*
     beta = pi_B + K pi_D (every dependent column is a combination of the chosen ones,
     Y_D = Y_B K), which the data determine uniquely,
  4. solves for beta by least squares, and returns as full parameter vector the one closest
     to a prior (default 0, i.e. the minimum-norm solution in scaled units) that fits the
     data; directions the data cannot see keep the prior's value,
  5. warns (UnidentifiableWarning) with the count of unidentifiable directions instead of
     returning an arbitrary full vector silently; result.fully_identifiable is the flag.

Only the rigid-body parameters are identified: on a real robot, add regressor columns for
joint friction (sign(qd), qd) and rotor inertia (qdd), and filter the measured signals.

`python -m lie_dynamics.identification [--quick]` runs the calibration example on the bundled
arm (its command line lives in lie_dynamics/identification.py, beside the package's other
commands).
"""
import warnings
from dataclasses import dataclass

import numpy as np

from .regressor import regressor_validated


class UnidentifiableWarning(UserWarning):
    """Some inertial-parameter directions are not determined by the data."""


@dataclass
class IdentificationResult:
    """Outcome of `identify`.

    parameters: (10 nb,) full estimate: fits the data, equals the prior along the
        unidentifiable directions (the minimum-norm solution for prior 0).
    base_parameters: (r,) beta = base_matrix @ pi, uniquely determined by the data.
    base_columns: (r,) indices of the parameters chosen as base (pivoted QR order).
    base_matrix: (r, 10 nb) K with beta = K pi (identity on base_columns).
    base_std: (r,) standard deviation of beta from the residual variance.
    rank, n_parameters, n_unidentifiable, fully_identifiable: the rank test.
    condition_number: of the column-scaled base regressor (large: poor excitation).
    residual_rms: (n,) rms torque residual per joint on the training data.
    """
    parameters: np.ndarray
    base_parameters: np.ndarray
    base_columns: np.ndarray
    base_matrix: np.ndarray
    base_std: np.ndarray
    rank: int
    n_parameters: int
    n_unidentifiable: int
    fully_identifiable: bool
    condition_number: float
    residual_rms: np.ndarray

    def predict(self, model, q, qd, qdd):
        """Torques predicted by the identified parameters (unaffected by the prior), with the
        model's armature term (Model.armature, known, not identified)."""
        return model.regressor(q, qd, qdd) @ self.parameters + np.asarray(qdd, dtype=float) * model.armature

    def base_of(self, pi):
        """Base parameters of a full parameter vector (e.g. the true one, for comparison)."""
        return self.base_matrix @ np.asarray(pi, dtype=float)


def _pivoted_columns(R, r):
    """Indices of r independent columns of R (QR with column pivoting, Businger-Golub)."""
    A = np.array(R, dtype=float, copy=True)
    chosen = []
    norms = np.sum(A * A, axis=0)
    for _ in range(r):
        norms[chosen] = -1.0
        j = int(np.argmax(norms))
        chosen.append(j)
        v = A[:, j] / np.linalg.norm(A[:, j])
        A -= np.outer(v, v @ A)
        norms = np.sum(A * A, axis=0)
    return np.array(chosen)


def identify(model, q, qd, qdd, tau, prior=None, weights=None, rcond=1e-8):
    """Least-squares inertial parameters from torques measured along a trajectory.

    q, qd, qdd, tau: (N, n) samples (n controlled joints). prior: optional (10 nb,) parameter
    vector (e.g. CAD values) kept along unidentifiable directions. weights: optional (n,)
    per-joint weights (1 / noise std). rcond: singular values below rcond * largest count as
    zero (directions the data do not determine). The model's armature (Model.armature) is
    taken as known: its torque is subtracted before the fit.
    Returns an IdentificationResult; warns UnidentifiableWarning when rank < 10 nb.
    """
    q, qd, qdd, tau = model.check_states(q=q, qd=qd, qdd=qdd, tau=tau)   # the one validation
    N = q.shape[0]
    n, p = model.n, 10 * model.nb
    if N * n < p:
        warnings.warn(f'{N} samples x {n} joints = {N * n} equations for {p} parameters: '
                      'use a longer trajectory', UnidentifiableWarning, stacklevel=2)
    if prior is None:
        prior = np.zeros(p)
    prior = np.asarray(prior, dtype=float)
    if prior.shape != (p,) or not np.all(np.isfinite(prior)):
        raise ValueError(f'prior must be a finite vector of shape ({p},), got {prior.shape}')
    w = np.ones(n) if weights is None else np.asarray(weights, dtype=float)
    if w.shape != (n,) or not np.all(np.isfinite(w)) or np.any(w <= 0):
        raise ValueError(f'weights must be {n} finite positive numbers (one per joint)')
    if not (0.0 < rcond < 1.0):
        raise ValueError(f'rcond must be in (0, 1), got {rcond}')

    Y = (regressor_validated(model, [q, qd, qdd]) * w[None, :, None]).reshape(N * n, p)
    y = ((tau - qdd * model.armature) * w).reshape(N * n)   # the model's armature is known, not fitted
    fit = least_squares(Y, y, prior, rcond)
    r, pi, resid = fit['rank'], fit['parameters'], fit['residual']
    if r == 0:
        raise ValueError('the stacked regressor is zero: the trajectory moves no mass')

    missing = p - r
    if missing:
        what = 'the minimum-norm' if not np.any(prior) else 'the prior-closest'
        warnings.warn(f'{missing} of {p} inertial-parameter directions are not identifiable from these data '
                      f'(structural or not excited); identified {r} base parameters and returned '
                      f'{what} full parameter vector (result.fully_identifiable is False)',
                      UnidentifiableWarning, stacklevel=2)
    rms = np.sqrt(np.mean((resid.reshape(N, n) / w) ** 2, axis=0))
    return IdentificationResult(parameters=pi, base_parameters=fit['base_parameters'], base_columns=fit['base_columns'],
                                base_matrix=fit['base_matrix'], base_std=fit['base_std'], rank=r, n_parameters=p,
                                n_unidentifiable=missing, fully_identifiable=missing == 0,
                                condition_number=fit['condition_number'], residual_rms=rms)


def least_squares(Y, y, prior, rcond=1e-8):
    """The least-squares engine of `identify` (steps 1-4 of the module docstring) on a stacked
    regressor Y (rows, p) and measurements y (rows,): a dict with rank, base_columns,
    base_matrix, base_parameters, base_std, condition_number, parameters (closest to `prior`
    along the unidentifiable directions), residual, determined (p,) booleans (a parameter the
    data fix on its own: no null-space direction moves it), scale (p,) the column scaling and
    null_space (p - rank, p) the directions the data do not see, in scaled units."""
    p = Y.shape[1]
    scale = np.sqrt(np.sum(Y * Y, axis=0))
    seen = scale > 1e-12 * max(scale.max(), 1e-300)
    scale = np.where(seen, scale, 1.0)
    Ys = Y / scale
    Ys[:, ~seen] = 0.0
    U, s, Vt = np.linalg.svd(Ys, full_matrices=False)
    r = int(np.sum(s > rcond * s[0])) if s.size and s[0] > 0 else 0
    if r == 0:
        return dict(rank=0, parameters=np.array(prior, dtype=float), residual=np.array(y, dtype=float),
                    determined=np.zeros(p, dtype=bool))
    # base parameters: r independent columns; dependent columns are combinations of them
    B = _pivoted_columns(np.diag(s[:r]) @ Vt[:r], r)
    D = np.setdiff1d(np.arange(p), B)
    KD = np.linalg.lstsq(Ys[:, B], Ys[:, D], rcond=None)[0]         # Ys_D = Ys_B KD
    Ks = np.zeros((r, p))
    Ks[np.arange(r), B] = 1.0
    Ks[:, D] = KD
    base_matrix = Ks * (1.0 / scale[B])[:, None] * scale[None, :]   # beta = K pi (unscaled)
    YB = Ys[:, B]
    zB, *_ = np.linalg.lstsq(YB, y, rcond=None)
    resid = y - YB @ zB
    sigma2 = float(resid @ resid) / max(len(y) - r, 1)
    sB = np.linalg.svd(YB, compute_uv=False)
    cov_z = sigma2 * np.linalg.pinv(YB.T @ YB)
    # full vector: closest to the prior (in scaled units) among the solutions
    zp = prior * scale
    dz = Vt[:r].T @ ((U[:, :r].T @ (y - Ys @ zp)) / s[:r])
    pi = (zp + dz) / scale
    pi[~seen] = prior[~seen]
    null = Vt[r:]  # the directions the data do not see (scaled units)
    determined = seen & (np.linalg.norm(null, axis=0) < 1e-6 if len(null) else np.ones(p, dtype=bool))
    return dict(rank=r, base_columns=B, base_matrix=base_matrix, base_parameters=zB / scale[B],
                base_std=np.sqrt(np.clip(np.diag(cov_z), 0, None)) / scale[B],
                condition_number=float(sB[0] / sB[-1]) if sB[-1] > 0 else np.inf, parameters=pi,
                residual=resid, determined=determined, scale=scale, null_space=null)


def excitation_trajectory(model, duration=10.0, rate=100.0, harmonics=None, base_frequency=0.1, seed=0,
                          margin=0.1, optimize=False, **options):
    """A finite Fourier series per joint (periodic, smooth), kept inside the joint limits.

    q_j(t) = q0_j + sum_l a_jl sin(w_l t) + b_jl (1 - cos(w_l t)), w_l = 2 pi l base_frequency,
    l = 1..harmonics (5 by default), with random coefficients decaying as 1/l, scaled into the
    position limits (shrunk by `margin` of their range; +-pi for unlimited joints) and under the
    velocity limits.
    Returns (t, q, qd, qdd) with q, qd, qdd of shape (samples, n).

    optimize=True: the series optimised for the condition number of the base calibration
    regressor, at rest at a home pose at both ends, within position, velocity, acceleration and
    effort limits (calibration.excitation.optimized_excitation, which takes the `options`:
    home, joints, velocity_fraction, acceleration, effort_fraction, ...; its period is the
    duration, so base_frequency is not used; its harmonics by default grow with the duration:
    calibration.excitation.default_harmonics).
    """
    if optimize:
        from ..calibration.excitation import optimized_excitation
        return optimized_excitation(model, duration=duration, rate=rate, harmonics=harmonics, seed=seed,
                                    margin=margin, **options)
    if options:
        raise ValueError(f'options {sorted(options)} need optimize=True')
    harmonics = 5 if harmonics is None else harmonics
    if duration <= 0 or rate <= 0 or harmonics < 1 or base_frequency <= 0:
        raise ValueError('duration, rate, base_frequency must be > 0 and harmonics >= 1')
    rng = np.random.default_rng(seed)
    n = model.n
    t = np.arange(0.0, duration, 1.0 / rate)
    lo = np.where(np.isfinite(model.position_lower), model.position_lower, -np.pi)
    hi = np.where(np.isfinite(model.position_upper), model.position_upper, np.pi)
    lo, hi = lo + margin * (hi - lo), hi - margin * (hi - lo)
    mid, half = 0.5 * (lo + hi), 0.5 * (hi - lo)
    wl = 2 * np.pi * base_frequency * np.arange(1, harmonics + 1)
    a = rng.normal(size=(n, harmonics)) / np.arange(1, harmonics + 1)
    b = rng.normal(size=(n, harmonics)) / np.arange(1, harmonics + 1)
    S, C = np.sin(np.outer(t, wl)), np.cos(np.outer(t, wl))
    p = S @ a.T + (1 - C) @ b.T
    v = (C * wl) @ a.T + (S * wl) @ b.T
    acc = (-S * wl ** 2) @ a.T + (C * wl ** 2) @ b.T
    center = 0.5 * (p.max(axis=0) + p.min(axis=0))
    spread = np.maximum(0.5 * (p.max(axis=0) - p.min(axis=0)), 1e-12)
    k = half / spread
    vmax = np.where(np.isfinite(model.velocity_limits), model.velocity_limits, np.inf)
    k = np.minimum(k, 0.9 * vmax / np.maximum(np.abs(v).max(axis=0), 1e-12))
    q = mid + k * (p - center)
    return t, q, k * v, k * acc
