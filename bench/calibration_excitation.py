"""Excitation design: condition number of the optimised excitation against the random one.

    python -m bench.calibration_excitation [--quick] [--iterations N] [--jobs N] [--out DIR]

For each robot and duration: the condition number of the column-scaled structural base
calibration regressor (calibration.excitation.condition_number) along
  random     the library's random Fourier excitation (excitation_trajectory, optimize=False, seed 0:
             5 harmonics of 0.1 Hz, filling the position limits less a 10 % margin, under 0.9 of the
             velocity limits), as it comes;
  random in limits  the same series shrunk about its centre until it also meets the optimised
             excitation's limits (0.8 of the velocity limits, 5 rad/s^2, 0.8 of the effort limits);
  optimised  excitation_trajectory(optimize=True, seed 0) with its defaults (the CLI's: 2,500 L-BFGS-B
             iterations or --iterations, harmonics growing with the duration), limits checked on its 100 Hz samples;
  uniform states  1000 states drawn uniformly over the box the limits allow (positions less the
             margin, 0.8 of the velocity limits, 5 rad/s^2), free of any trajectory: what spreading
             the samples alone gives (efforts not checked);
their ratios (optimised / random, and optimised / random in limits: the issue's target, <= 0.2 of the
random excitation at the same duration and limits, is on the latter) and the optimiser's wall time (a
loaded machine: indicative only). Robots: the bundled arm and example-robot-data's UR5 when installed.

Writes calibration_excitation.{md,csv,png}.
"""
import argparse
import csv
import glob
import os
import sys
import time

import numpy as np

from lie_dynamics import default_urdf_path, load_urdf
from lie_dynamics.algorithms.identification import excitation_trajectory
from lie_dynamics.calibration.excitation import condition_number

RATE = 100.0
DURATIONS = (10.0, 20.0, 60.0)
DURATIONS_QUICK = (4.0,)
LIMITS = dict(margin=0.1, velocity_fraction=0.8, acceleration=5.0, effort_fraction=0.8)
TARGET = 0.2


def robots(quick):
    out = {'arm7 (bundled)': default_urdf_path()}
    if quick:
        return out
    share = glob.glob(os.path.join(sys.prefix, 'lib', 'python3*', 'site-packages', 'cmeel.prefix', 'share',
                                   'example-robot-data', 'robots'))
    if share:
        out['UR5'] = os.path.join(share[0], 'ur_description', 'urdf', 'ur5_robot.urdf')
    return out


def excess(model, q, qd, qdd):
    """Largest relative excess of the sampled trajectory over LIMITS (<= 0: within them)."""
    lo, hi = model.position_lower, model.position_upper
    lo = np.where(np.isfinite(lo), lo, -np.pi)
    hi = np.where(np.isfinite(hi), hi, np.pi)
    span = hi - lo
    m = LIMITS['margin'] * span
    tau = model.inverse_dynamics(q, qd, qdd)
    return max(float(np.max(np.maximum(lo + m - q, q - hi + m) / span)),
               float(np.max(np.abs(qd) / (LIMITS['velocity_fraction'] * model.velocity_limits))) - 1,
               float(np.max(np.abs(qdd))) / LIMITS['acceleration'] - 1,
               float(np.max(np.abs(tau) / (LIMITS['effort_fraction'] * model.effort_limits))) - 1)


def within_limits(model, q, qd, qdd):
    """The random series shrunk about its centre (bisection) until excess <= 0."""
    c = 0.5 * (q.max(axis=0) + q.min(axis=0))

    def at(s):
        return c + s * (q - c), s * qd, s * qdd
    if excess(model, *at(1.0)) <= 0:
        return at(1.0)
    good, bad = 0.0, 1.0
    for _ in range(40):
        mid = 0.5 * (good + bad)
        good, bad = (mid, bad) if excess(model, *at(mid)) <= 0 else (good, mid)
    return at(good)


def uniform_states(model, count=1000, seed=0):
    rng = np.random.default_rng(seed)
    lo = np.where(np.isfinite(model.position_lower), model.position_lower, -np.pi)
    hi = np.where(np.isfinite(model.position_upper), model.position_upper, np.pi)
    m = LIMITS['margin'] * (hi - lo)
    u = rng.random((3, count, model.n))
    return (lo + m + (hi - lo - 2 * m) * u[0], (2 * u[1] - 1) * LIMITS['velocity_fraction'] * model.velocity_limits,
            (2 * u[2] - 1) * LIMITS['acceleration'])


def row(name, path, duration, quick=False, iterations=None):
    """One robot and duration: the table's row."""
    model = load_urdf(path)
    _, qr, qdr, qddr = excitation_trajectory(model, duration=duration, rate=RATE, seed=0)
    c_random = condition_number(model, qr, qdr, qddr)
    c_within = condition_number(model, *within_limits(model, qr, qdr, qddr))
    c_uniform = condition_number(model, *uniform_states(model))
    t0 = time.perf_counter()
    _, q, qd, qdd = excitation_trajectory(model, duration=duration, rate=RATE, optimize=True, seed=0,
                                          **{k: v for k, v in LIMITS.items() if k != 'margin'},
                                          **({'iterations': 10} if quick else {}),
                                          **({'iterations': iterations} if iterations else {}))
    seconds = time.perf_counter() - t0
    c_opt = condition_number(model, q, qd, qdd)
    out = {'robot': name, 'duration': duration, 'random': c_random, 'random_in_limits': c_within,
           'optimised': c_opt, 'uniform_states': c_uniform, 'ratio': c_opt / c_random,
           'ratio_in_limits': c_opt / c_within, 'excess': excess(model, q, qd, qdd), 'seconds': seconds}
    print(out, flush=True)
    return out


def run(quick=False, out=None, iterations=None, jobs=1):
    """The rows of every robot and duration; jobs > 1: that many processes at once (the same
    figures, each optimiser's time then shares the machine with the others)."""
    tasks = [(name, path, duration, quick, iterations) for name, path in robots(quick).items()
             for duration in (DURATIONS_QUICK if quick else DURATIONS)]
    if jobs > 1:
        from concurrent.futures import ProcessPoolExecutor
        with ProcessPoolExecutor(jobs) as pool:
            rows = list(pool.map(row, *zip(*tasks)))
    else:
        rows = [row(*task) for task in tasks]
    if out is not None:
        write(rows, out)
    return rows


def markdown(rows):
    lines = ['# Excitation: condition number, optimised against random', '',
             f'Column-scaled structural base calibration regressor, {RATE:g} Hz samples, seed 0; limits: '
             f'{LIMITS}; target: optimised / random in limits <= {TARGET:g}.', '',
             '| robot | duration (s) | random | random in limits | optimised | optimised / random | '
             'optimised / random in limits | uniform states | largest limit excess | optimiser time (s) |',
             '|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|']
    lines += [f"| {r['robot']} | {r['duration']:g} | {r['random']:.3g} | {r['random_in_limits']:.3g} | "
              f"{r['optimised']:.3g} | {r['ratio']:.3f} | {r['ratio_in_limits']:.3f} | {r['uniform_states']:.3g} | "
              f"{r['excess']:.2g} | "
              f"{r['seconds']:.0f} |" for r in rows]
    return '\n'.join(lines) + '\n'


def chart(rows, path):
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(figsize=(10, 4.4))
    for i, name in enumerate(dict.fromkeys(r['robot'] for r in rows)):
        sel = [r for r in rows if r['robot'] == name]
        d = [r['duration'] for r in sel]
        ax.plot(d, [r['random'] for r in sel], 's--', color=f'C{i}', label=f'{name}: random')
        ax.plot(d, [r['random_in_limits'] for r in sel], '^:', color=f'C{i}', label=f'{name}: random in limits')
        ax.plot(d, [r['optimised'] for r in sel], 'o-', color=f'C{i}', label=f'{name}: optimised')
        ax.plot(d, [r['uniform_states'] for r in sel], 'x', color=f'C{i}', label=f'{name}: uniform states')
        ax.plot(d, [TARGET * r['random_in_limits'] for r in sel], '-', color=f'C{i}', lw=0.8, alpha=0.7,
                label=f'{name}: target ({TARGET:g} x random in limits)')
    ax.set_yscale('log')
    ax.set_xlabel('duration (s)')
    ax.set_ylabel('condition number (column-scaled base regressor)')
    ax.set_title('excitation: optimised against random')
    ax.legend(fontsize=7, loc='upper left', bbox_to_anchor=(1.01, 1.0))
    ax.grid(True, which='both', alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def write(rows, out):
    os.makedirs(out, exist_ok=True)
    with open(os.path.join(out, 'calibration_excitation.md'), 'w', encoding='utf-8') as fh:
        fh.write(markdown(rows))
    with open(os.path.join(out, 'calibration_excitation.csv'), 'w', newline='', encoding='utf-8') as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    chart(rows, os.path.join(out, 'calibration_excitation.png'))


def main(argv=None):
    ap = argparse.ArgumentParser(prog='python -m bench.calibration_excitation', description=__doc__.split('\n')[0])
    ap.add_argument('--quick', action='store_true')
    ap.add_argument('--iterations', type=int, default=None, help='L-BFGS-B iterations (default: the library\'s)')
    ap.add_argument('--jobs', type=int, default=1, help='rows computed at once, in processes (default 1)')
    ap.add_argument('--out', default=os.path.join(os.path.dirname(os.path.abspath(__file__)), 'out'))
    args = ap.parse_args(argv)
    print(markdown(run(quick=args.quick, out=args.out, iterations=args.iterations, jobs=args.jobs)))
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
