"""Calibration: held-out torque prediction error against effort noise and recording length, and
the run time of the identify_dynamics command.

    python -m bench.calibration [--quick] [--out DIR] [--identify-time]

A robot that differs from its URDF: the bundled arm with masses +-15 %, CoMs moved by 1-3 cm,
inertias about the CoM scaled with the mass, armature, viscous and Coulomb friction (the node's
smooth form) and effort offsets of its own (`true_parameters`, seeded). Every joint follows a
finite Fourier series (bench/signals.py: 5 harmonics of 0.1 Hz, +-0.6 rad about mid-range);
joint_states at RATE Hz with +-0.2 ms stamp jitter, 1 % of the samples lost, positions quantised
by a 17-bit encoder, no velocity, and efforts = the true robot's torque + white noise of a given
fraction of each joint's torque RMS. Each recording goes through
lie_dynamics.calibration.identify_dynamics (filter, fit on the first 80 %); the held-out error is
the calibrated model's torque prediction on the last 20 %, at the true states, against the true
torque: RMS per joint as a fraction of that joint's torque RMS (the worst joint is reported, and
all joints pooled). Median over seeds.

  noise     effort noise 0-10 % of the torque RMS, 60 s recordings;
  length    recordings of 10-120 s with the documented noise (NOISE: 2 %);
  step      the decimation after filtering (signals.OVERSAMPLE): error and fit time against the
            samples kept per period of the cutoff, 60 s with the documented noise.

Gate: with the documented noise and 60 s, the worst joint's held-out error <= GATE (3 %).

--identify-time: the `identify_dynamics` command (a subprocess, as a user runs it) on a 60 s,
1 kHz recording of the 7-joint arm written by this command to a temporary folder (a trajectory
CSV with efforts and an mcap rosbag2 folder; removed afterwards): wall time, median of 3.

Writes calibration.{md,csv,png}.
"""
import argparse
import csv
import os
import shutil
import subprocess
import sys
import tempfile
import time

import numpy as np

from bench.signals import ENCODERS, JITTER, LOSS, RATE, trajectory
from lie_dynamics import default_urdf_path, load_urdf
from lie_dynamics.laws import COULOMB_VELOCITY_EPSILON, friction_torque

NOISE = 0.02                                   # the documented effort noise: 2 % of each joint's torque RMS
# absolute effort noise, N m per joint: the calibration demo's simulated sensors (0.1 on the
# shoulder and elbow joints, 0.03 on the wrist), 0.6-7.4 % of this trajectory's torque RMS
NOISE_DEMO = (0.1, 0.1, 0.1, 0.1, 0.03, 0.03, 0.03)
DURATION = 60.0                                # s
NOISES = (0.0, 0.005, 0.01, 0.02, 0.05, 0.1)
NOISES_QUICK = (0.0, 0.02)
DURATIONS = (10.0, 20.0, 40.0, 60.0, 120.0)
DURATIONS_QUICK = (20.0,)
OVERSAMPLES = (None, 100.0, 50.0, 25.0, 10.0, 5.0)   # samples kept per period of the cutoff (None: all)
GATE = 0.03
ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def true_parameters(model, seed=0):
    """Calibration parameters (regressor.parameter_names order) of a robot that differs from
    its URDF: masses +-15 %, CoMs moved by 1-3 cm, inertias about the CoM scaled with the mass;
    armature 0.05-0.3, viscous 0.1-1, Coulomb 0.1-0.8, offsets +-1 (SI units)."""
    rng = np.random.default_rng(seed)
    out = []
    for b in model.inertial_parameters().reshape(model.nb, 10):
        m, c = b[0], b[1:4] / b[0]
        I = np.array([[b[4], b[5], b[7]], [b[5], b[6], b[8]], [b[7], b[8], b[9]]])
        Ic = I - m * (c @ c * np.eye(3) - np.outer(c, c))
        f = 1 + rng.uniform(-0.15, 0.15)
        c2 = c + rng.choice([-1, 1], 3) * rng.uniform(0.01, 0.03, 3) / np.sqrt(3)
        m2 = m * f
        I2 = Ic * f + m2 * (c2 @ c2 * np.eye(3) - np.outer(c2, c2))
        out += [m2, *(m2 * c2), I2[0, 0], I2[0, 1], I2[1, 1], I2[0, 2], I2[1, 2], I2[2, 2]]
    n = model.n
    joints = np.stack([rng.uniform(0.05, 0.3, n), rng.uniform(0.1, 1.0, n), rng.uniform(0.1, 0.8, n),
                       rng.uniform(-1.0, 1.0, n)], axis=1)
    return np.concatenate([out, joints.reshape(-1)])


def true_torque(model, true, q, qd, qdd, eps=COULOMB_VELOCITY_EPSILON):
    """The true robot's measured effort without noise: rigid body + armature + friction + offset."""
    n, ni = model.n, 10 * model.nb
    a, b, fc, off = true[ni:].reshape(n, 4).T
    plant = model.with_inertial_parameters(true[:ni])
    return plant.inverse_dynamics(q, qd, qdd) + a * qdd + friction_torque(qd, b, fc, eps) + off


def recording(model, true, duration, noise, seed, rate=RATE):
    """(t, q, effort) joint_states of the true robot: jitter, lost samples, a 17-bit encoder,
    effort noise of `noise` x each joint's torque RMS (a tuple: N m per joint)."""
    rng = np.random.default_rng(seed + 2000)
    t = np.arange(0.0, duration, 1.0 / rate)
    t = np.sort(t + rng.uniform(-JITTER, JITTER, len(t)))
    t = t[rng.random(len(t)) >= LOSS]
    q, qd, qdd = trajectory(model, t, seed)
    tau = true_torque(model, true, q, qd, qdd)
    quantum = ENCODERS['17-bit']
    sigma = np.array(noise) if isinstance(noise, tuple) else noise * np.sqrt(np.mean(tau ** 2, axis=0))
    return t, np.round(q / quantum) * quantum, tau + sigma * rng.normal(size=tau.shape)


def one(model, noise, duration, seed, oversample=False):
    """Held-out errors of one calibration: per joint after and before (the URDF), relative."""
    import warnings

    from lie_dynamics.calibration import identify_dynamics
    from lie_dynamics.calibration import regressor as creg

    true = true_parameters(model, seed)
    t, q, effort = recording(model, true, duration, noise, seed)
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter('ignore')   # a short recording warns what it cannot see: measured anyway
        c = identify_dynamics(model, t, q, effort, signals=None if oversample is False else {'oversample': oversample})
    seconds = time.perf_counter() - t0
    ts = c.report['t']
    qs, qds, qdds = trajectory(model, ts, seed)
    tau = true_torque(model, true, qs, qds, qdds)
    Y = creg.calibration_regressor(model, qs, qds, qdds, c.eps)
    rms = np.sqrt(np.mean(tau ** 2, axis=0))
    err = (lambda p: np.sqrt(np.mean((Y @ p - tau) ** 2, axis=0)) / rms)   # noqa: E731
    pooled = (lambda p: float(np.sqrt(np.mean((Y @ p - tau) ** 2)) / np.sqrt(np.mean(tau ** 2))))  # noqa: E731
    prior = creg.prior_parameters(model)
    return dict(after=err(c.parameters), before=err(prior), pooled=pooled(c.parameters),
                pooled_before=pooled(prior), seconds=seconds, samples=len(c.report['segment']),
                cutoff=c.report['cutoff'], step=c.report.get('step', 1))


def _row(sweep, x, runs):
    med = (lambda k: float(np.median([np.max(r[k]) if np.ndim(r[k]) else r[k] for r in runs])))  # noqa: E731
    return dict(sweep=sweep, x=x, worst=med('after'), pooled=med('pooled'), worst_before=med('before'),
                pooled_before=med('pooled_before'), seconds=med('seconds'), samples=int(med('samples')),
                cutoff=med('cutoff'),
                joints=np.median([r['after'] for r in runs], axis=0))


def run(quick=False, out=None, seeds=None):
    from lie_dynamics.calibration import signals

    model = load_urdf(default_urdf_path())
    seeds = range(seeds or (1 if quick else 3))
    rows = []
    for noise in (NOISES_QUICK if quick else NOISES) + (NOISE_DEMO,):
        rows.append(_row('noise', noise, [one(model, noise, DURATION, s) for s in seeds]))
    for duration in (DURATIONS_QUICK if quick else DURATIONS):
        rows.append(_row('length', duration, [one(model, NOISE, duration, s) for s in seeds]))
    if not quick:
        for k in OVERSAMPLES:
            rows.append(_row('step', k, [one(model, NOISE, DURATION, s, oversample=k) for s in seeds]))
    gated = [r for r in rows if r['sweep'] == 'noise' and r['x'] in (NOISE, NOISE_DEMO)]
    worst = max(r['worst'] for r in gated)
    figures = ', '.join(f"{100 * r['worst']:.2f} %" for r in gated)
    status = (f"gate: with {100 * NOISE:g} % effort noise and with the demo's (N m: {NOISE_DEMO}), {DURATION:g} s, "
              f"the worst joint's held-out error is {figures} of its "
              f"torque RMS (target <= {100 * GATE:g} %): {'PASS' if worst <= GATE else 'FAIL'}; default decimation "
              f"OVERSAMPLE = {signals.OVERSAMPLE:g}")
    if out is not None:
        write(rows, status, out)
    return rows, status, worst <= GATE


def markdown(rows, status):
    lines = ['# Calibration: held-out torque prediction error against noise and length', '',
             'Bundled arm, true parameters off the URDF; 1 kHz joint_states, 17-bit encoder, jitter, 1 % lost; '
             'fit on the first 80 %, error on the last 20 % (the calibrated model at the true states against the '
             'true torque), RMS relative to the torque RMS, median over seeds.', '',
             '| sweep | x | worst joint | all joints | URDF: worst | URDF: all | fit s | samples fitted |',
             '|---|---:|---:|---:|---:|---:|---:|---:|']
    unit = {'noise': lambda x: 'demo (0.1/0.03 N m)' if isinstance(x, tuple) else f'{100 * x:g} %',
            'length': lambda x: f'{x:g} s',
            'step': lambda x: 'all' if x is None else f'{x:g}/period'}
    for r in rows:
        lines.append(f"| {r['sweep']} | {unit[r['sweep']](r['x'])} | {100 * r['worst']:.3g} % | "
                     f"{100 * r['pooled']:.3g} % | {100 * r['worst_before']:.3g} % | "
                     f"{100 * r['pooled_before']:.3g} % | "
                     f"{r['seconds']:.2f} | {r['samples']} |")
    return '\n'.join(lines) + '\n\n' + status + '\n'


def chart(rows, path):
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    sweeps = [s for s in ('noise', 'length', 'step') if any(r['sweep'] == s for r in rows)]
    fig, axes = plt.subplots(1, len(sweeps), figsize=(5.2 * len(sweeps), 4.0), squeeze=False)
    labels = {'noise': 'effort noise, % of torque RMS (60 s)', 'length': 'recording length, s (2 % noise)',
              'step': 'samples kept per period of the cutoff (60 s, 2 % noise)'}
    for ax, s in zip(axes[0], sweeps):
        sel = [r for r in rows if r['sweep'] == s and not isinstance(r['x'], tuple)]
        x = np.array([RATE / r['cutoff'] if r['x'] is None else r['x'] for r in sel]) * (100 if s == 'noise' else 1)
        for key, style, label in (('worst', 'o-', 'calibrated, worst joint'), ('pooled', 's-', 'calibrated, all'),
                                  ('worst_before', 'o--', 'URDF, worst joint')):
            ax.plot(x, [100 * r[key] for r in sel], style, ms=4, label=label)
        ax.axhline(100 * GATE, color='k', lw=0.8, ls=':')
        ax.set_yscale('log')
        if s == 'step':
            ax.set_xscale('log')
        ax.set_xlabel(labels[s])
        ax.set_ylabel('held-out torque error, % of torque RMS')
        ax.grid(True, which='both', alpha=0.3)
        ax.legend(fontsize=7)
    fig.suptitle('calibration: held-out torque prediction error (dotted: the 3 % target)')
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def write(rows, status, out):
    os.makedirs(out, exist_ok=True)
    with open(os.path.join(out, 'calibration.md'), 'w', encoding='utf-8') as fh:
        fh.write(markdown(rows, status))
    keys = ['sweep', 'x', 'worst', 'pooled', 'worst_before', 'pooled_before', 'seconds', 'samples']
    with open(os.path.join(out, 'calibration.csv'), 'w', newline='', encoding='utf-8') as fh:
        w = csv.DictWriter(fh, fieldnames=keys + ['joints'])
        w.writeheader()
        for r in rows:
            w.writerow({**{k: r[k] for k in keys}, 'joints': ' '.join(f'{v:.4g}' for v in r['joints'])})
    chart(rows, os.path.join(out, 'calibration.png'))


def identify_time(repeats=3, duration=60.0, rate=1000.0):
    """Wall time of the identify_dynamics command on a `duration` s, `rate` Hz recording of the
    7-joint arm, read from a trajectory CSV and from an mcap rosbag2 folder, each median of
    `repeats` runs. The recording is written to a temporary folder, removed afterwards."""
    from lie_dynamics.calibration.recordings import write_joint_states

    model = load_urdf(default_urdf_path())
    true = true_parameters(model, 0)
    t, q, effort = recording(model, true, duration, NOISE, 0, rate)
    names = model.joint_names
    folder = tempfile.mkdtemp(prefix='bench_calibration_')
    try:
        csv_path = os.path.join(folder, 'recording.csv')
        header = ','.join(['time'] + [f'{k}.{j}' for k in ('pos', 'eff') for j in names])
        np.savetxt(csv_path, np.column_stack([t, q, effort]), delimiter=',', header=header, comments='', fmt='%.17g')
        bag = os.path.join(folder, 'bag')
        write_joint_states(bag, names, np.round(t * 1e9).astype(np.int64), q, np.full_like(q, np.nan), effort)
        times, cpu = {}, {}
        for label, path in (('csv', csv_path), ('mcap', bag)):
            times[label], cpu[label] = [], []
            for k in range(repeats):
                cmd = [sys.executable, '-m', 'lie_dynamics.calibration.identify', path, '--urdf', default_urdf_path(),
                       '-o', os.path.join(folder, f'calibration_{label}_{k}.yaml')]
                t0, c0 = time.perf_counter(), _children_cpu()
                path_env = ROOT + os.pathsep + os.environ.get('PYTHONPATH', '')
                r = subprocess.run(cmd, capture_output=True, text=True, cwd=folder,
                                   env=dict(os.environ, PYTHONPATH=path_env))
                times[label].append(time.perf_counter() - t0)
                cpu[label].append(_children_cpu() - c0)
                if r.returncode != 0:
                    raise RuntimeError(f'identify_dynamics failed: {r.stderr.strip()}')
        samples = len(t)
    finally:
        shutil.rmtree(folder, ignore_errors=True)
    lines = [f'identify_dynamics on a {duration:g} s, {rate:g} Hz recording of the {model.n}-joint arm '
             f'({samples} samples, {100 * NOISE:g} % effort noise): the command\'s wall time and CPU time '
             f'(user + system, all its threads), median of {repeats} (target <= 10 s):']
    lines += [f"  {label:5s} wall {np.median(times[label]):6.2f} s, CPU {np.median(cpu[label]):6.2f} s  (runs: "
              f"{', '.join(f'{x:.2f}' for x in times[label])} s)" for label in times]
    return '\n'.join(lines), {k: (float(np.median(times[k])), float(np.median(cpu[k]))) for k in times}


def _children_cpu():
    import resource
    u = resource.getrusage(resource.RUSAGE_CHILDREN)
    return u.ru_utime + u.ru_stime


def main(argv=None):
    ap = argparse.ArgumentParser(prog='python -m bench.calibration', description=__doc__.split('\n')[0])
    ap.add_argument('--quick', action='store_true')
    ap.add_argument('--out', default=os.path.join(ROOT, 'bench', 'out'))
    ap.add_argument('--seeds', type=int, help='seeds per point (default 3; --quick: 1)')
    ap.add_argument('--identify-time', action='store_true', help='only time the identify_dynamics command')
    args = ap.parse_args(argv)
    if args.identify_time:
        text, _ = identify_time(repeats=1 if args.quick else 3)
        print(text)
        return 0
    rows, status, ok = run(quick=args.quick, out=args.out, seeds=args.seeds)
    print(markdown(rows, status))
    return 0 if ok else 1


if __name__ == '__main__':
    raise SystemExit(main())
