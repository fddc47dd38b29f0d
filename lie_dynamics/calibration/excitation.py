"""Excitation design: a finite Fourier series per joint, optimised for the condition number of
the base calibration regressor, at rest at a home pose at its start and end, within limits.

Per joint j, with w_l = 2 pi l f0 (f0 = 1 / duration: one period),

    q_j(t) = home_j + sum_l a_jl sin(w_l t) + b_jl (cos(w_l t) - 1),

so q_j(0) = q_j(T) = home_j; the coefficients are restricted to sum_l a_jl w_l = 0 and
sum_l b_jl w_l^2 = 0 (a basis of that subspace), so qd and qdd are 0 at both ends too. The
objective is log cond of the column-scaled base calibration regressor (the structural base
columns, regressor.structural_base) along the trajectory, plus a penalty on the limits
(positions within a margin, a fraction of the velocity limits, an acceleration bound, a fraction
of the effort limits predicted by the model's inverse dynamics); scipy's L-BFGS-B minimises it
with the gradient in closed form (the singular values' derivatives, chained with the regressor's
at perturbed states: _objective). log cond = log s_max - log s_min is not smooth where the extreme
singular values cross, which stalls L-BFGS-B; so the optimisation runs in stages (STAGES) on the
smooth surrogate log |s|_p + log |1/s|_p (p-norms of the singular values and of their inverses,
log cond as p grows), p = 4 then 16, and ends on log cond itself, each stage starting where the
last stopped. The grid of the optimisation has SAMPLES_PER_PERIOD samples per period of the
highest harmonic (at least LEAST_SAMPLES). The free coefficients are velocity amplitudes
(a_jl w_l, b_jl w_l: every harmonic weighs alike on the velocity), in units of the start's
largest (L-BFGS-B's first step has unit length); see _Series. The start is the best conditioned
of a few random series, each scaled up or down to the limits; the result is checked on the
sampled trajectory and, where a limit is still exceeded, shrunk towards home until none is (the
stiff penalty leaves little to shrink).
"""
import numpy as np

from ..laws import COULOMB_VELOCITY_EPSILON
from . import regressor as creg


def condition_number(model, q, qd, qdd, eps=COULOMB_VELOCITY_EPSILON, columns=None, scaled=True):
    """Condition number of the column-scaled calibration regressor along (q, qd, qdd), on the
    given columns (default: the robot's structural base columns); scaled=False: unscaled. inf when
    a column is zero."""
    if columns is None:
        columns = creg.structural_base(model, eps).base_columns
    Y = creg.stack(model, q, qd, qdd)[:, columns] if eps == COULOMB_VELOCITY_EPSILON else \
        creg.calibration_regressor(model, q, qd, qdd, eps).reshape(-1, creg.n_parameters(model))[:, columns]
    if scaled:
        norms = np.linalg.norm(Y, axis=0)
        if np.any(norms == 0):
            return np.inf
        Y = Y / norms
    s = np.linalg.svd(Y, compute_uv=False)
    return float(s[0] / s[-1]) if s[-1] > 0 else np.inf


def _basis(w, power):
    """Orthonormal basis (H, H - 1) of the coefficient vectors c with sum c_l w_l^power = 0."""
    v = (w ** power)[:, None]
    return np.linalg.svd(v.T)[2][1:].T


class _Series:
    """Positions, velocities, accelerations of the constrained series on a time grid. The free
    coefficients are velocity amplitudes: a_l = c_l / w_l (likewise b), so every harmonic moves the
    velocity alike. Position amplitudes would let the highest harmonics' accelerations (w_l^2 a_l)
    dominate: the random start, shrunk to the acceleration bound, then barely moves, and L-BFGS-B
    sees variables whose effects differ by w_H^2 / w_1^2 (225 with 15 harmonics), which it crosses
    slowly or not at all (its line search failed at once on the bundled arm with 15 harmonics)."""

    def __init__(self, t, w):
        self.S, self.C = np.sin(np.outer(t, w)), np.cos(np.outer(t, w))
        self.w = w
        # sum a_l w_l = sum c_l = 0 and sum b_l w_l^2 = sum c_l w_l = 0 (at rest at both ends)
        self.Ba, self.Bb = _basis(w, 0) / w[:, None], _basis(w, 1) / w[:, None]

    def coefficients(self, x, n):
        x = x.reshape(n, 2, -1)
        return x[:, 0] @ self.Ba.T, x[:, 1] @ self.Bb.T        # (n, H) each

    def __call__(self, x, n):
        a, b = self.coefficients(x, n)
        S, C, w = self.S, self.C, self.w
        p = S @ a.T + (C - 1) @ b.T
        v = (C * w) @ a.T - (S * w) @ b.T
        acc = -(S * w ** 2) @ a.T - (C * w ** 2) @ b.T
        return p, v, acc


def _limits(model, home, margin, velocity_fraction, acceleration, effort_fraction, joints):
    n = model.n
    lo = np.where(np.isfinite(model.position_lower), model.position_lower, -np.pi)
    hi = np.where(np.isfinite(model.position_upper), model.position_upper, np.pi)
    span = hi - lo
    lo, hi = lo + margin * span, hi - margin * span
    vmax = np.where(np.isfinite(model.velocity_limits) & (model.velocity_limits > 0),
                    model.velocity_limits, np.inf) * velocity_fraction
    amax = np.broadcast_to(np.asarray(acceleration, dtype=float), (n,)).copy()
    emax = np.where(np.isfinite(model.effort_limits) & (model.effort_limits > 0),
                    model.effort_limits, np.inf) * effort_fraction
    for j in range(n):
        name = model.joint_names[j]
        if not lo[j] < hi[j]:
            raise ValueError(f"position limit of joint '{name}': no room inside [{lo[j]:.6g}, {hi[j]:.6g}] "
                             f'with the margin {margin:g}')
        if not (lo[j] <= home[j] <= hi[j]):
            raise ValueError(f"position limit of joint '{name}': home {home[j]:.6g} is outside "
                             f'[{lo[j]:.6g}, {hi[j]:.6g}] (the limits less the margin {margin:g} of the range)')
    g = model.gravity(home)
    for j in range(n):
        if abs(g[j]) >= emax[j]:
            raise ValueError(f"effort limit of joint '{model.joint_names[j]}': gravity alone at home needs "
                             f'{abs(g[j]):.6g}, above {effort_fraction:g} of the limit ({emax[j]:.6g})')
    moving = np.zeros(n, dtype=bool)
    moving[joints] = True
    return lo, hi, vmax, amax, emax, moving


def _violation(model, home, lo, hi, vmax, amax, emax, p, v, a):
    """Per-sample excess over each limit, relative to the limit: four (N, n) arrays."""
    q = home + p
    span = hi - lo
    ep = np.maximum(np.maximum(q - hi, lo - q), 0.0) / span
    ev = np.maximum(np.abs(v) - vmax, 0.0) / vmax
    ea = np.maximum(np.abs(a) - amax, 0.0) / amax
    tau = model.inverse_dynamics(q, v, a)
    ee = np.maximum(np.abs(tau) - emax, 0.0) / np.where(np.isfinite(emax), emax, 1.0)
    return ep, ev, ea, ee


# Default harmonics: the highest at about HIGHEST_HARMONIC_HZ whatever the duration, and at least
# LEAST_HARMONICS. A longer excitation with the same harmonics only moves the same way more slowly
# (velocities and accelerations scale with 1 / duration); more harmonics keep its pace and add independent
# motion. A short one needs more than that pace gives: at 10 s on the bundled arm 15 harmonics (1.5 Hz,
# at most 0.06 rad under 5 rad/s^2) reach a condition number of 5.4; 5 harmonics (0.5 Hz) reached 8.4
# with position amplitudes as the coefficients (bench/calibration_excitation.py, docs/benchmarks.md).
HIGHEST_HARMONIC_HZ = 0.25
LEAST_HARMONICS = 15


def default_harmonics(duration):
    """Harmonics of the optimised excitation by default: round(duration * HIGHEST_HARMONIC_HZ), at least
    LEAST_HARMONICS."""
    return max(LEAST_HARMONICS, int(round(duration * HIGHEST_HARMONIC_HZ)))


# (p, share of the iterations): the smooth surrogates log |s|_p + log |1/s|_p, then log cond (None)
STAGES = ((4.0, 0.25), (16.0, 0.25), (None, 0.5))

# L-BFGS-B iterations of all stages by default, and the grid of the optimisation: samples per period of
# the highest harmonic, at least LEAST_SAMPLES. The regressor's rows hold products of the motion's harmonics
# (qd^2, trigonometric functions of q), so on a coarse grid the optimiser exploits the gaps between samples.
# On the bundled arm at 10 s (docs/benchmarks.md, "Excitation: condition number"; the target there is
# 5.03, 0.2 of the random excitation in the same limits): 1,500 iterations on 10 samples per period reach
# 5.58, on 20 5.08; 2,000 on 20 4.89 and 2,500 4.83, every stage ending on its budget. With the gradient's
# cost cut (_objective, _perturbations), 2,500 iterations on 20 samples per period take 1.15 times the CPU
# time 1,500 on 10 took before (2,000 about 0.92 times, with less margin on the target).
ITERATIONS = 2500
SAMPLES_PER_PERIOD = 20
LEAST_SAMPLES = 200
# The start: a random series scaled to this fraction of the largest scale within the limits. At the
# limits (1.0) a start can sit on a penalty's kink, where L-BFGS-B's line search fails within a few
# iterations (the bundled arm, seed 1: the optimised excitation came out 4.7x worse than the random one).
START_SCALE = 0.8
LIMIT_NAMES = ('position limit', 'velocity limit', 'acceleration bound', 'effort limit')


def optimized_excitation(model, duration=10.0, rate=100.0, harmonics=None, home=None, joints=None, margin=0.1,
                         velocity_fraction=0.8, acceleration=5.0, effort_fraction=0.8, seed=0,
                         eps=COULOMB_VELOCITY_EPSILON, iterations=ITERATIONS, samples=None, starts=1):
    """(t, q, qd, qdd) of the optimised excitation (module docstring): q, qd, qdd (N, n).

    home: the pose it starts and ends at, at rest ((n,), default the middle of the position
    limits). joints: names of the joints that move (default all; the others stay at home).
    margin: fraction of each joint's range kept free at both ends. velocity_fraction,
    effort_fraction: of the URDF's limits; acceleration: rad/s^2 (m/s^2), one or per joint.
    harmonics: of the series (default default_harmonics(duration): more for a longer one).
    iterations: of L-BFGS-B, all stages together (STAGES: a quarter each on the surrogates with
    p = 4 and 16, half on log cond); samples: grid of the optimisation (default SAMPLES_PER_PERIOD
    per period of the highest harmonic, at least LEAST_SAMPLES); starts: random series tried as the start, each scaled
    to the limits, the best conditioned kept; seed: theirs (fixed: the result is deterministic). The limits hold on the
    returned samples (checked); ValueError names the binding limit where they cannot (home
    outside the limits, gravity at home above the effort fraction, a bound that leaves no
    motion: a moving joint sweeping less than 1e-3 of its range, with the joint).
    """
    from scipy.optimize import minimize   # scipy: imported where it is used

    n = model.n
    if harmonics is None and duration > 0:
        harmonics = default_harmonics(duration)
    if not (duration > 0 and rate > 0 and harmonics >= 2 and 0 <= margin < 0.5):
        raise ValueError('duration and rate must be > 0, harmonics >= 2, margin in [0, 0.5)')
    for name, value in (('velocity_fraction', velocity_fraction), ('effort_fraction', effort_fraction)):
        if not (0 < value <= 1):
            raise ValueError(f'{name} must be in (0, 1], got {value}: no motion is possible')
    if not np.all(np.asarray(acceleration, dtype=float) > 0):
        raise ValueError(f'acceleration bound must be > 0, got {acceleration}: no motion is possible')
    if joints is None:
        cols = np.arange(n)
    else:
        unknown = [j for j in joints if j not in model.joint_names]
        if unknown:
            raise ValueError(f'unknown joints {unknown}; the model has {model.joint_names}')
        cols = np.array([model.joint_names.index(j) for j in joints], dtype=int)
    lo0 = np.where(np.isfinite(model.position_lower), model.position_lower, -np.pi)
    hi0 = np.where(np.isfinite(model.position_upper), model.position_upper, np.pi)
    home = 0.5 * (lo0 + hi0) if home is None else np.asarray(model.check_batch('home', home)[0])
    lo, hi, vmax, amax, emax, moving = _limits(model, home, margin, velocity_fraction, acceleration,
                                               effort_fraction, cols)

    w = 2 * np.pi / duration * np.arange(1, harmonics + 1)
    m = samples or max(LEAST_SAMPLES, SAMPLES_PER_PERIOD * harmonics)
    t_opt = np.arange(m) * (duration / m)
    t = np.arange(0.0, duration + 0.5 / rate, 1.0 / rate)
    t = t[t <= duration + 1e-12]
    opt, fine = _Series(t_opt, w), _Series(t, w)
    columns = creg.structural_base(model, eps).base_columns
    mask = np.repeat(moving, 2 * (harmonics - 1))

    def trajectory(series, x, s=1.0):
        p, v, a = series(x * mask, n)
        return s * p, s * v, s * a

    bases = _derivative_bases(opt, n)
    limits = (lo, hi, vmax, amax, emax)

    def cost(x, weight=1e3, gradient=True, power=None):
        p, v, a = trajectory(opt, x)
        return _objective(model, home, p, v, a, columns, eps, limits, weight, bases if gradient else None, mask,
                          power=power)

    # the start: the best conditioned of `starts` random series, each scaled up or down to the limits
    rng = np.random.default_rng(seed)
    best = None
    for _ in range(max(1, starts)):
        x0 = rng.normal(size=(n, 2, harmonics - 1)).reshape(-1)
        x0 *= START_SCALE * _shrink(model, home, lo, hi, vmax, amax, emax, lambda s, x0=x0: trajectory(opt, x0, s), 1e3)
        c0 = cost(x0, 0.0, False)[0]
        if best is None or c0 < best[0]:
            best = (c0, x0)
    # L-BFGS-B's first step has unit length: it works on the coefficients in units of the start's
    # largest, so that step stays near the limits instead of far beyond them (its line search failed)
    unit = float(np.abs(best[1]).max())

    def scaled_cost(y, weight=1e3, gradient=True, power=None):
        f, g = cost(unit * y, weight, gradient, power)
        return f, (None if g is None else unit * g)
    y = y0 = best[1] / unit
    for power, share in STAGES:
        budget = max(1, int(round(share * iterations)))
        best_f = np.inf
        while budget > 0:
            with np.errstate(divide='ignore', invalid='ignore', over='ignore'):
                res = minimize(scaled_cost, y, jac=True, method='L-BFGS-B', args=(1e3, True, power),
                               options={'maxiter': budget})
            budget -= max(1, res.nit)
            if not (np.isfinite(res.fun) and res.fun < best_f):
                break
            y, best_f = res.x, res.fun
            # a failed line search (status 2: the Coulomb columns' tanh and the limits' kinks make the
            # objective stiff in places) ends L-BFGS-B early; its memory restarted, it goes on
            if res.status != 2:
                break
    # the exact objective decides: a stage that made it worse than the start is not kept
    x = unit * (y if scaled_cost(y, gradient=False)[0] <= scaled_cost(y0, gradient=False)[0] else y0)
    s = _shrink(model, home, lo, hi, vmax, amax, emax, lambda s: trajectory(fine, x, s), 1.0)
    p, v, a = trajectory(fine, x, s)
    worst = [float(e.max()) for e in _violation(model, home, lo, hi, vmax, amax, emax, p, v, a)]
    if max(worst) > 0:
        raise ValueError(f'the limits leave no exciting motion: the {LIMIT_NAMES[int(np.argmax(worst))]} binds')
    _check_motion(model, home, lo, hi, vmax, amax, emax, p, v, a, moving)
    q = np.where(moving, home + p, home)
    return t, q, np.where(moving, v, 0.0), np.where(moving, a, 0.0)


def _check_motion(model, home, lo, hi, vmax, amax, emax, p, v, a, moving, least=1e-3):
    """ValueError when a moving joint sweeps less than `least` of its URDF range: the limits leave
    no motion that excites anything. It names the limit the motion uses most (the binding one)."""
    lo0 = np.where(np.isfinite(model.position_lower), model.position_lower, -np.pi)
    hi0 = np.where(np.isfinite(model.position_upper), model.position_upper, np.pi)
    still = [j for j in np.flatnonzero(moving) if np.ptp(p[:, j]) < least * (hi0[j] - lo0[j])]
    if not still:
        return
    tau = model.inverse_dynamics(home + p, v, a)
    room = np.maximum(np.minimum(hi - home, home - lo), 1e-300)
    used = np.array([np.abs(p).max(axis=0) / room, np.abs(v).max(axis=0) / vmax, np.abs(a).max(axis=0) / amax,
                     np.abs(tau).max(axis=0) / emax])[:, moving]
    k, j = np.unravel_index(np.argmax(used), used.shape)
    j = np.flatnonzero(moving)[j]
    raise ValueError(f"the limits leave no exciting motion: the {LIMIT_NAMES[k]} of joint '{model.joint_names[j]}' "
                     f"binds (joint '{model.joint_names[still[0]]}' sweeps {np.ptp(p[:, still[0]]):.3g} rad or m)")


def _derivative_bases(series, n):
    """d(p, v, a)/dx for one joint's coefficients x = (x_a, x_b): three (m, 2 (H - 1)) matrices."""
    S, C, w, Ba, Bb = series.S, series.C, series.w, series.Ba, series.Bb
    return (np.hstack([S @ Ba, (C - 1) @ Bb]), np.hstack([(C * w) @ Ba, -(S * w) @ Bb]),
            np.hstack([-(S * w ** 2) @ Ba, -(C * w ** 2) @ Bb]))


def _spread(s, power):
    """log s_max - log s_min (power None) or its smooth surrogate log |s|_p + log |1/s|_p, and its
    derivative in each singular value s (descending, > 0)."""
    if power is None:
        d = np.zeros_like(s)
        d[0], d[-1] = 1 / s[0], -1 / s[-1]
        return float(np.log(s[0] / s[-1])), d
    a, b = (s / s[0]) ** power, (s[-1] / s) ** power          # scaled: no overflow
    A, B = a.sum(), b.sum()
    return float(np.log(s[0] / s[-1]) + (np.log(A) + np.log(B)) / power), (a / A - b / B) / s


def _singular(Z):
    """(U-free) SVD of the tall Z: singular values s (descending) and V, from the eigenvalues of the
    Gram matrix Z^T Z (cols x cols). An SVD of Z itself (m n rows) cost 3 ms on one BLAS thread and
    ~30 ms with two on a busy 2-core machine, most of an iteration; squaring the condition number is
    harmless at the values the optimiser meets, and where it is not (cond above ~1e6) the SVD decides."""
    lam, V = np.linalg.eigh(Z.T @ Z)
    if not lam[0] > 1e-12 * lam[-1]:
        _, s, Vt = np.linalg.svd(Z, full_matrices=False)
        return s, Vt.T
    return np.sqrt(lam[::-1]), V[:, ::-1]


def _perturbations(n, h, s=1e-5):
    """The state offsets of the gradient, (1 + 4 n, 3, n): none, then q_j +-h (central differences),
    then (qd_j +-s, qdd_j +1) together. The regressor is Y = A(q) qdd + B(q)[qd, qd] + g(q) (as are
    the inverse dynamics, Y pi + armature qdd), so of the pair's two offsets the difference is
    4 s B(qd, e_j), exactly d/dqd_j times 2 s, and the sum less twice the unperturbed state is
    2 A e_j + 2 s^2 B(e_j, e_j), d/dqdd_j times 2 to 1e-10 relative: one state fewer per joint than
    separate differences (a fifth of the states, most of the cost)."""
    step = np.zeros((1 + 4 * n, 3, n))
    j = np.arange(n)
    step[1 + 2 * j, 0, j], step[2 + 2 * j, 0, j] = h, -h
    step[1 + 2 * n + 2 * j, 1, j], step[2 + 2 * n + 2 * j, 1, j] = s, -s
    step[1 + 2 * n + 2 * j, 2, j] = step[2 + 2 * n + 2 * j, 2, j] = 1.0
    return step


def _objective(model, home, p, v, a, columns, eps, limits, weight, bases, mask, h=1e-6, s=1e-5, power=None):
    """log cond of the column-scaled base regressor (power None; else the surrogate of _spread)
    + weight * the squared relative excess over the limits, and (bases given) its gradient in the
    coefficients: the singular values' derivatives (d s_i = u_i^T dZ v_i, with the column scaling
    differentiated too) chained with the regressor's derivatives in q, qd, qdd of every sample
    (_perturbations). The value's derivative in the inertial columns and the effort penalty's
    (tau = Y pi + armature qdd) are one weight matrix per sample, contracted with the regressor
    at the perturbed states before differencing: no derivative of the regressor is formed (with
    it, the inverse dynamics at the perturbed states and the SVD of the tall matrix, an objective
    with its gradient took 2.8x as long on the bundled arm)."""
    lo, hi, vmax, amax, emax = limits
    m, n = p.shape
    q = home + p
    # the calibration regressor's two parts, each on its own base columns (a column order cond ignores):
    # the same numbers as calibration_regressor(...)[..., columns], without building the unused columns;
    # the joint columns' derivatives are exact (below), so only the inertial part takes the perturbed states
    inertial = 10 * model.nb
    icols, jcols = columns[columns < inertial], columns[columns >= inertial] - inertial
    Yi = model.regressor(q, v, a)
    Y = np.concatenate([Yi[..., icols], creg.joint_columns(v, a, eps)[..., jcols]], axis=2).reshape(m * n, -1)
    D = np.linalg.norm(Y, axis=0)
    if np.any(D == 0):
        return (50.0, np.zeros(n * len(bases[0][0]))) if bases is not None else (50.0, None)
    Z = Y / D
    sv, V = _singular(Z)
    value, dsv = _spread(sv, power)
    tau = model.inverse_dynamics(q, v, a)
    span = hi - lo
    ep = np.maximum(q - hi, 0.0) / span - np.maximum(lo - q, 0.0) / span        # signed excess
    ev = np.sign(v) * np.maximum(np.abs(v) - vmax, 0.0) / vmax
    ea = np.sign(a) * np.maximum(np.abs(a) - amax, 0.0) / amax
    escale = np.where(np.isfinite(emax), emax, 1.0)
    ee = np.sign(tau) * np.maximum(np.abs(tau) - emax, 0.0) / escale
    value += weight * float(np.sum(ep ** 2) + np.sum(ev ** 2) + np.sum(ea ** 2) + np.sum(ee ** 2))
    if bases is None:
        return value, None
    # d value / dY: dZ through the singular values (U diag(dsv) V^T with U = Z V / s), then Z = Y / |Y columns|
    Gz = Z @ ((V * (dsv / sv)) @ V.T)
    G = (Gz / D - (np.sum(Gz * Y, axis=0) / D ** 3) * Y).reshape(m, n, -1)
    de = 2 * weight * ee / escale                                  # d value / d tau (m, n)
    W = np.zeros((m, n, inertial))                                 # d value / d (inertial regressor)
    W[..., icols] = G[..., :len(icols)]
    W += de[..., None] * model.inertial_parameters()
    # one offset at a time: the regressor of m states stays in cache for its contraction (of all the
    # offsets at once it is 40 MB at 300 samples of a 7-joint arm, and the whole took 1.3x as long)
    W = W.reshape(m, -1)
    f = np.array([np.einsum('sk,sk->s', (Yi if not d.any() else model.regressor(q + d[0], v + d[1], a + d[2]))
                            .reshape(m, -1), W) for d in _perturbations(n, h, s)])
    plus, minus = f[1 + 2 * n::2], f[2 + 2 * n::2]
    gs = np.stack([(f[1:1 + 2 * n:2] - f[2:1 + 2 * n:2]) / (2 * h),      # d value / d state (kind, j, sample)
                   (plus - minus) / (2 * s), 0.5 * (plus + minus) - f[0]])
    # joint j's own columns sit on row j: armature qdd_j, viscous qd_j, Coulomb tanh(qd_j / eps), offset 1
    Gj = np.zeros((m, n, n * len(creg.JOINT_TERMS)))
    Gj[..., jcols] = G[..., len(icols):]
    Gj = Gj.reshape(m, n, n, len(creg.JOINT_TERMS))[:, np.arange(n), np.arange(n)]     # (m, n, 4)
    gs[2] += (Gj[..., 0] + de * model.armature).T
    gs[1] += (Gj[..., 1] + Gj[..., 2] * (1 - np.tanh(v / eps) ** 2) / eps).T
    gs[0] += 2 * weight * (ep / span).T
    gs[1] += 2 * weight * (ev / vmax).T
    gs[2] += 2 * weight * (ea / amax).T
    grad = sum(gs[k] @ bases[k] for k in range(3))                 # (n, 2 (H - 1))
    return value, grad.reshape(-1) * mask


def _shrink(model, home, lo, hi, vmax, amax, emax, traj, s):
    """Largest scale in (0, s] of the motion about home with no limit exceeded (bisection; the
    effort is not linear in the scale); ValueError naming the limit when there is none."""
    def ok(k):
        return all(float(e.max()) <= 0 for e in _violation(model, home, lo, hi, vmax, amax, emax, *traj(k)))
    if ok(s):
        return s
    good, bad = s * 1e-15, s            # geometric bisection: the scale may be many decades down
    if not ok(good):                    # even a vanishing motion exceeds a limit: name it
        excess = np.array([e.max(axis=0) for e in _violation(model, home, lo, hi, vmax, amax, emax, *traj(good))])
        k, j = np.unravel_index(np.argmax(excess), excess.shape)
        raise ValueError(f"the limits leave no exciting motion: the {LIMIT_NAMES[k]} of joint "
                         f"'{model.joint_names[j]}' binds")
    for _ in range(50):
        mid = np.sqrt(good * bad)
        good, bad = (mid, bad) if ok(mid) else (good, mid)
    return good


def write_csv(path, t, q, qd, qdd, joint_names):
    """The trajectory CSV that fill_trajectory and trajectory_source read:
    time, pos.<joint>..., vel.<joint>..., acc.<joint>... (full precision)."""
    import csv

    header = ['time'] + [f'{k}.{j}' for k in ('pos', 'vel', 'acc') for j in joint_names]
    with open(path, 'w', newline='') as fh:
        w = csv.writer(fh)
        w.writerow(header)
        for row in np.column_stack([t, q, qd, qdd]):
            w.writerow([repr(float(x)) for x in row])


EXAMPLES = """\
The trajectory starts and ends at rest at --home (default: the middle of the position limits),
keeps --margin of each range free, and stays under the fractions of the URDF's velocity and
effort limits (the effort predicted by the model's inverse dynamics) and under --acceleration.
It is a finite Fourier series per joint optimised for the condition number of the base
calibration regressor; joints not in --joints stay at home.
examples:
  excitation_trajectory config/arm7.urdf -o excitation.csv
  excitation_trajectory robot.urdf -o exc.csv --joints joint1,joint2 --duration 30 --home 0,0.5
"""


def main(argv=None):
    """excitation_trajectory: write an optimised excitation trajectory CSV."""
    from ..cli import CliParser, number, run_cli

    ap = CliParser('lie_dynamics.calibration.excitation', description='write an optimised excitation '
                   'trajectory (time, pos.<joint>, vel.<joint>, acc.<joint>) for calibration', epilog=EXAMPLES)
    ap.add_argument('urdf', help='the robot description (URDF file)')
    ap.add_argument('-o', '--output', required=True, help='the CSV to write')
    ap.add_argument('--joints', help='comma-separated joints that move (default: all controlled joints)')
    ap.add_argument('--duration', type=number(low=0, strict=True), default=20.0, help='seconds, > 0 (default 20)')
    ap.add_argument('--home', help='comma-separated start and end pose, one value per controlled joint')
    ap.add_argument('--rate', type=number(low=0, strict=True), default=100.0, help='samples per second (default 100)')
    ap.add_argument('--harmonics', type=number(int, low=2), default=None,
                    help=f'Fourier harmonics, >= 2 (default: duration x {HIGHEST_HARMONIC_HZ:g} Hz, '
                    f'at least {LEAST_HARMONICS})')
    ap.add_argument('--margin', type=number(low=0), default=0.1, help='fraction of each range kept free (default 0.1)')
    ap.add_argument('--velocity-fraction', type=number(low=0, strict=True), default=0.8,
                    help='fraction of the velocity limits (default 0.8)')
    ap.add_argument('--effort-fraction', type=number(low=0, strict=True), default=0.8,
                    help='fraction of the effort limits (default 0.8)')
    ap.add_argument('--acceleration', type=number(low=0, strict=True), default=5.0,
                    help='acceleration bound, rad/s^2 (default 5)')
    ap.add_argument('--seed', type=number(int, low=0), default=0, help='random start, >= 0 (default 0)')
    ap.add_argument('--iterations', type=number(int, low=1), default=ITERATIONS,
                    help=f'L-BFGS-B iterations of the design, >= 1 (default {ITERATIONS}; fewer: faster, worse '
                    'conditioned)')
    return run_cli(ap, _write, argv)


def _values(text, what):
    try:
        return [float(v) for v in text.split(',')]
    except ValueError:
        raise ValueError(f'{what} must be comma-separated numbers, got {text!r}') from None


def _write(args):
    from .. import load_urdf

    model = load_urdf(args.urdf)
    joints = [j.strip() for j in args.joints.split(',')] if args.joints else None
    home = None
    if args.home is not None:
        home = _values(args.home, '--home')
        if len(home) != model.n:
            raise ValueError(f'--home has {len(home)} values for the {model.n} joints {model.joint_names}')
    t, q, qd, qdd = optimized_excitation(model, duration=args.duration, rate=args.rate, harmonics=args.harmonics,
                                         home=home, joints=joints, margin=args.margin,
                                         velocity_fraction=args.velocity_fraction, acceleration=args.acceleration,
                                         effort_fraction=args.effort_fraction, seed=args.seed,
                                         iterations=args.iterations)
    write_csv(args.output, t, q, qd, qdd, model.joint_names)
    print(f'{args.output}: {len(t)} samples over {t[-1]:.3g} s, condition number '
          f'{condition_number(model, q, qd, qdd):.4g}')


if __name__ == '__main__':
    main()
