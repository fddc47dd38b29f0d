"""The calibration regressor: rigid-body inertial parameters plus the joints' own terms.

The measured effort of joint j is modelled as

    tau_meas_j = (Y(q, qd, qdd) pi)_j + a_j qdd_j + b_j qd_j + fc_j tanh(qd_j / eps) + o_j,

with Y the inertial regressor (algorithms/regressor.py: 10 columns per body, Pinocchio's
order), a_j the armature (rotor inertia reflected to the joint), b_j viscous and fc_j Coulomb
friction in the smooth form of `laws.friction_torque` (the node's friction compensation), and
o_j the effort sensor's offset (measured effort = true effort + offset). It is linear in all
10 nb + 4 n parameters, so the calibration regressor is Y with 4 columns per joint appended.

Not every parameter is determined by data, whatever the trajectory: the first link turns
about one axis, so only its inertia about that axis counts, and that inertia adds to the
first joint's armature; other parameters act only in combinations. `base_parameters` finds
the combinations the data determine (QR with column pivoting, the engine of
algorithms/identification.py) and names which physical parameters are identified alone,
which only in combination, and which not at all.
"""
from dataclasses import dataclass

import numpy as np

from ..algorithms.identification import least_squares
from ..laws import COULOMB_VELOCITY_EPSILON
from ..model.inertia import PARAMETER_NAMES

# The joint terms, in their column order after the inertial columns (4 per joint, joint by joint).
JOINT_TERMS = ('armature', 'viscous', 'coulomb', 'offset')


def n_parameters(model):
    """Number of calibration parameters: 10 per body and 4 per controlled joint."""
    return 10 * model.nb + len(JOINT_TERMS) * model.n


def parameter_names(model):
    """Names of the calibration parameters in column order: '<link>.<m|mcx|...|Izz>' per body
    (the body's child link; the values are the body's totals, fixed children included), then
    '<joint>.<armature|viscous|coulomb|offset>' per controlled joint."""
    return ([f'{link}.{p}' for link in model.body_link_names for p in PARAMETER_NAMES]
            + [f'{joint}.{t}' for joint in model.joint_names for t in JOINT_TERMS])


def joint_columns(qd, qdd, eps=COULOMB_VELOCITY_EPSILON, coulomb=None):
    """The joint terms' columns for validated (N, n) qd, qdd: (N, n, 4 n), non-zero only on the
    joint's own row (armature qdd, viscous qd, Coulomb tanh(qd / eps), offset 1). coulomb: (N, n)
    the Coulomb column's values instead of tanh(qd / eps) (the smooth sign low-passed like
    filtered efforts: signals.prepare's `terms`)."""
    N, n = qd.shape
    Z = np.zeros((N, n, n, len(JOINT_TERMS)))
    j = np.arange(n)
    Z[:, j, j, 0] = qdd
    Z[:, j, j, 1] = qd
    Z[:, j, j, 2] = np.tanh(qd / eps) if coulomb is None else coulomb
    Z[:, j, j, 3] = 1.0
    return Z.reshape(N, n, n * len(JOINT_TERMS))


def calibration_regressor(model, q, qd, qdd, eps=COULOMB_VELOCITY_EPSILON, coulomb=None):
    """(n, 10 nb + 4 n) or (N, n, 10 nb + 4 n): [model.regressor(q, qd, qdd) | joint_columns],
    so that the modelled measured effort is this times `prior_parameters`-shaped vectors.
    coulomb: (N, n) values of the Coulomb columns (joint_columns) instead of tanh(qd / eps)."""
    if not (np.isfinite(eps) and eps > 0):
        raise ValueError(f'eps (the Coulomb velocity scale) must be > 0, got {eps}')
    (q, qd, qdd), single = model.validate(('q', 'qd', 'qdd'), (q, qd, qdd))
    if coulomb is not None:
        coulomb = model.check_batch('coulomb', coulomb, len(q))
    Y = np.concatenate([model.regressor(q, qd, qdd), joint_columns(qd, qdd, eps, coulomb)], axis=2)
    return Y[0] if single else Y


def prior_parameters(model, armature=None, viscous=None, coulomb=None, offset=None):
    """The model's own calibration parameters (the prior): its bodies' inertial parameters,
    its armature (`Model.armature` where the model has one, else 0), viscous friction from
    the URDF's <dynamics damping>, Coulomb from <dynamics friction>, offsets 0. Any of the
    joint terms can be given instead (one value or one per joint)."""
    n = model.n
    default = {'armature': getattr(model, 'armature', None), 'viscous': model.damping,
               'coulomb': model.friction, 'offset': None}
    given = {'armature': armature, 'viscous': viscous, 'coulomb': coulomb, 'offset': offset}
    cols = []
    for term in JOINT_TERMS:
        v = given[term] if given[term] is not None else default[term]
        v = np.zeros(n) if v is None else np.broadcast_to(np.asarray(v, dtype=float), (n,))
        cols.append(v)
    return np.concatenate([model.inertial_parameters(), np.stack(cols, axis=1).reshape(-1)])


@dataclass
class BaseParameters:
    """What data determine of the calibration parameters (`base_parameters`).

    names: the physical parameters' names (parameter_names). rank: number of base parameters.
    base_columns: (rank,) the parameters chosen as base (pivoted QR order). base_matrix: (rank, p)
    K with beta = K pi (identity on base_columns). values, std: (rank,) the least-squares base
    parameters and their standard deviations. condition_number: of the column-scaled base
    regressor. status: per parameter 'identified' (no direction the data miss moves it),
    'combination' (seen, but only in combination with others: see combinations) or
    'unidentified' (the data do not see it at all). combinations: one readable line per base
    parameter that is a combination, 'beta_k = name + c * name ...'. scale: (p,) the column
    scaling; null_space: (p - rank, p) the directions the data do not see, in scaled units.
    """
    names: list
    rank: int
    base_columns: np.ndarray
    base_matrix: np.ndarray
    values: np.ndarray
    std: np.ndarray
    condition_number: float
    status: list
    combinations: list
    scale: np.ndarray
    null_space: np.ndarray

    def of(self, pi):
        """Base parameters K pi of a full parameter vector (e.g. the true one, to compare)."""
        return self.base_matrix @ np.asarray(pi, dtype=float)

    def names_with(self, status):
        return [n for n, s in zip(self.names, self.status) if s == status]


def reduce(Y, y):
    """The least-squares problem min |Y pi - y| in p + 1 rows with the same solutions, the same
    column norms and the same residual norm: R and c of the QR factorisation of [Y | y], the
    last row carrying the residual no pi can fit. Returns (R (p + 1, p), c (p + 1,), rows of Y)."""
    p = Y.shape[1]
    R = np.linalg.qr(np.column_stack([Y, y]), mode='r')
    out = np.zeros((p + 1, p + 1))
    out[:R.shape[0]] = R
    return out[:, :p], out[:, p], Y.shape[0]


def base_parameters(R, c, names, rows=None, rcond=1e-8, tol=1e-9):
    """Base parameters of the stacked regressor R (r_rows, p) and measurements c by the
    identification engine (algorithms/identification.least_squares: column scaling, rank by SVD,
    QR with column pivoting). (R, c) may be the `reduce`d form of a taller system of `rows`
    rows: the standard deviations then use that system's degrees of freedom. tol: coefficients
    of K below it (relative to the row's largest) are left out of the printed combinations."""
    p = R.shape[1]
    fit = least_squares(R, c, np.zeros(p), rcond)
    r = fit['rank']
    if r == 0:
        raise ValueError('the stacked calibration regressor is zero: the recording moves nothing')
    std = fit['base_std']
    if rows is not None and rows > r:
        std = std * np.sqrt(max(len(c) - r, 1) / (rows - r))
    K = fit['base_matrix']
    seen = np.any(R != 0.0, axis=0) & (np.abs(K).max(axis=0) > tol * np.abs(K).max())
    status = ['identified' if d else ('combination' if s else 'unidentified')
              for d, s in zip(fit['determined'], seen)]
    combos = []
    for k in range(r):
        row = K[k]
        big = np.flatnonzero(np.abs(row) > tol * np.abs(row).max())
        if len(big) > 1:
            b = fit['base_columns'][k]
            terms = ' '.join(f'{"+" if row[j] >= 0 else "-"} {abs(row[j]):.6g} * {names[j]}' for j in big if j != b)
            combos.append(f'beta_{k} = {names[b]} {terms}')
    return BaseParameters(names=list(names), rank=r, base_columns=fit['base_columns'], base_matrix=K,
                          values=fit['base_parameters'], std=std,
                          condition_number=fit['condition_number'], status=status, combinations=combos,
                          scale=fit['scale'], null_space=fit['null_space'])


def stack(model, q, qd, qdd, effort=None, eps=COULOMB_VELOCITY_EPSILON, weights=None, coulomb=None):
    """The stacked (N n, p) calibration regressor and, with effort (N, n), the stacked efforts;
    weights: optional (n,) per-joint weights (1 / noise std) applied to both; coulomb: as in
    calibration_regressor."""
    Y = calibration_regressor(model, q, qd, qdd, eps, coulomb)
    Y = np.atleast_3d(Y) if Y.ndim == 3 else Y[None]
    N, n, p = Y.shape
    w = np.ones(n) if weights is None else np.asarray(weights, dtype=float)
    if w.shape != (n,) or not np.all(np.isfinite(w)) or np.any(w <= 0):
        raise ValueError(f'weights must be {n} finite positive numbers (one per joint)')
    Ys = (Y * w[None, :, None]).reshape(N * n, p)
    if effort is None:
        return Ys
    effort = model.check_batch('effort', effort, N)
    return Ys, (effort * w).reshape(N * n)


def calibration_base(model, q, qd, qdd, effort, eps=COULOMB_VELOCITY_EPSILON, weights=None, rcond=1e-8):
    """base_parameters of the calibration regressor along (q, qd, qdd) with measured efforts."""
    Y, y = stack(model, q, qd, qdd, effort, eps, weights)
    R, c, rows = reduce(Y, y)
    return base_parameters(R, c, parameter_names(model), rows, rcond)


def structural_base(model, eps=COULOMB_VELOCITY_EPSILON, samples=None, seed=0, rcond=1e-8):
    """What any data could determine: base_parameters of the calibration regressor on random
    states (positions inside the limits, +-pi where there are none; velocities of a few eps
    and more; accelerations of order 1), i.e. the robot's structural base parameters."""
    rng = np.random.default_rng(seed)
    n = model.n
    N = samples or max(20, 4 * n_parameters(model) // max(n, 1))
    lo = np.where(np.isfinite(model.position_lower), model.position_lower, -np.pi)
    hi = np.where(np.isfinite(model.position_upper), model.position_upper, np.pi)
    q = lo + (hi - lo) * rng.random((N, n))
    qd = rng.normal(size=(N, n)) * 4 * eps
    qdd = rng.normal(size=(N, n))
    Y = stack(model, q, qd, qdd)
    R, c, rows = reduce(Y, np.zeros(len(Y)))
    return base_parameters(R, c, parameter_names(model), rows, rcond)
