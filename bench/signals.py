"""Signal preparation for calibration: derivative and effort error against the low-pass cutoff.

    python -m bench.signals [--quick] [--out DIR]

A synthetic recording with known derivatives: every joint of the bundled arm follows a finite
Fourier series (HARMONICS harmonics of BASE Hz, random coefficients decaying as 1/l, seeded), as
an excitation does; joint_states at RATE Hz with stamp jitter, 1 % of the samples lost, positions
quantised by an encoder, no velocity, and efforts = inverse dynamics + white noise. Through
lie_dynamics.calibration.signals.prepare:

  cutoff  the RMS error of q̇, q̈ and of the filtered effort (against the noise-free effort),
          each relative to the signal's RMS, against cutoff / highest harmonic, for a fine
          (17-bit) and a coarse (12-bit) encoder; this picks signals.CUTOFF_FACTOR;
  gap     the largest q̈ error in a window around one dropout of g periods of the cutoff,
          relative to the RMS of q̈ (no split): this picks signals.MAX_GAP_PERIODS;
  ends    the RMS q̈ error in bands of distance from a segment's end, without trimming: this
          picks signals.TRIM_PERIODS;
  velocity  q̇ and q̈ errors when a measured velocity is passed (white noise of 0.1 % of q̇'s RMS,
          delayed by 0, 1 or 5 ms as a drive's own filter delays it) against q̇ derived from the
          17-bit positions (qd=None).

Writes signals.{md,csv,png}.
"""
import argparse
import csv
import os

import numpy as np

from lie_dynamics import default_urdf_path, load_urdf
from lie_dynamics.calibration import signals

RATE = 1000.0
BASE, HARMONICS = 0.1, 5            # Hz: the highest harmonic is 0.5 Hz
DURATION = 30.0
JITTER = 0.2e-3                     # s, uniform +- on each stamp
LOSS = 0.01                         # fraction of samples lost (single dropouts)
ENCODERS = {'17-bit': 2 * np.pi / 2 ** 17, '12-bit': 2 * np.pi / 2 ** 12}
EFFORT_NOISE = 0.02                 # white noise, fraction of each joint's effort RMS
FACTORS = (1.5, 2.0, 3.0, 4.0, 6.0, 8.0, 12.0, 16.0, 24.0)
FACTORS_QUICK = (2.0, 4.0, 8.0)
GAPS = (0.02, 0.05, 0.1, 0.25, 0.5, 1.0)   # periods of the cutoff
ENDS = (0.0, 0.5, 1.0, 2.0, 3.0, 4.0, 6.0)    # band edges, periods of the cutoff from a segment's end


def trajectory(model, t, seed):
    """(q, q̇, q̈) of a Fourier series per joint at times t, within +-0.6 rad of mid-range."""
    rng = np.random.default_rng(seed)
    w = 2 * np.pi * BASE * np.arange(1, HARMONICS + 1)
    a, b = (rng.normal(size=(model.n, HARMONICS)) / np.arange(1, HARMONICS + 1) for _ in range(2))
    S, C = np.sin(np.outer(t, w)), np.cos(np.outer(t, w))
    p, v, acc = S @ a.T + C @ b.T, (C * w) @ a.T - (S * w) @ b.T, -(S * w ** 2) @ a.T - (C * w ** 2) @ b.T
    k = 0.6 / np.abs(p).max(axis=0)
    lo, hi = model.position_lower, model.position_upper
    mid = np.where(np.isfinite(lo) & np.isfinite(hi), 0.5 * (lo + hi), 0.0)
    return mid + k * p, k * v, k * acc


def recording(model, seed, quantum, duration=DURATION, gap=None):
    """(t, q measured, effort measured, truth(t) -> (q, q̇, q̈, effort)) of one synthetic recording."""
    rng = np.random.default_rng(seed + 1000)
    t = np.arange(0.0, duration, 1.0 / RATE)
    t = t + rng.uniform(-JITTER, JITTER, len(t))
    keep = rng.random(len(t)) >= LOSS
    if gap is not None:   # one dropout of `gap` s in the middle
        keep &= ~((t > 0.5 * duration) & (t < 0.5 * duration + gap))
    t = np.sort(t[keep])

    def truth(ts):
        q, qd, qdd = trajectory(model, ts, seed)
        return q, qd, qdd, model.inverse_dynamics(q, qd, qdd)

    q, _, _, tau = truth(t)
    sigma = EFFORT_NOISE * np.sqrt(np.mean(tau ** 2, axis=0))
    return t, np.round(q / quantum) * quantum, tau + rng.normal(size=tau.shape) * sigma, truth


def _rel(err, ref):
    return float(np.sqrt(np.mean(err ** 2)) / np.sqrt(np.mean(ref ** 2)))


def cutoff_sweep(model, factors, seeds):
    rows = []
    harmonic = BASE * HARMONICS
    for name, quantum in ENCODERS.items():
        for f in factors:
            errs = []
            for seed in seeds:
                t, q, e, truth = recording(model, seed, quantum)
                s = signals.prepare(t, q, e, cutoff=f * harmonic, trim=2.0 / harmonic)  # >= 3 periods of every cutoff
                q0, qd0, qdd0, tau0 = truth(s.t)
                errs.append((_rel(s.qd - qd0, qd0), _rel(s.qdd - qdd0, qdd0), _rel(s.effort - tau0, tau0)))
            qd_e, qdd_e, eff_e = np.median(errs, axis=0)
            rows.append({'sweep': 'cutoff', 'encoder': name, 'x': f, 'qd_rel': qd_e, 'qdd_rel': qdd_e,
                         'effort_rel': eff_e})
    return rows


def gap_sweep(model, seeds):
    rows = []
    harmonic = BASE * HARMONICS
    cutoff = signals.CUTOFF_FACTOR * harmonic
    for g in GAPS:
        errs = []
        for seed in seeds:
            t, q, e, truth = recording(model, seed, ENCODERS['17-bit'], gap=g / cutoff)
            s = signals.prepare(t, q, e, cutoff=cutoff, max_gap=np.inf)
            _, _, qdd0, _ = truth(s.t)
            near = np.abs(s.t - 0.5 * DURATION) < 1.0 / cutoff + g / cutoff
            errs.append(np.abs(s.qdd - qdd0)[near].max() / np.sqrt(np.mean(qdd0 ** 2)))
        rows.append({'sweep': 'gap', 'encoder': '17-bit', 'x': g, 'qd_rel': '', 'qdd_rel': float(np.median(errs)),
                     'effort_rel': ''})
    return rows


def ends_sweep(model, seeds):
    rows = []
    harmonic = BASE * HARMONICS
    cutoff = signals.CUTOFF_FACTOR * harmonic
    errs = {k: [] for k in range(len(ENDS) - 1)}
    for seed in seeds:
        t, q, e, truth = recording(model, seed, ENCODERS['17-bit'])
        s = signals.prepare(t, q, e, cutoff=cutoff, trim=0.0)
        _, _, qdd0, _ = truth(s.t)
        d = np.minimum(s.t - s.t[0], s.t[-1] - s.t) * cutoff   # periods from the nearer end
        for k in errs:
            band = (d >= ENDS[k]) & (d < ENDS[k + 1])
            errs[k].append(_rel(s.qdd[band] - qdd0[band], qdd0))
    for k, v in errs.items():
        rows.append({'sweep': 'ends', 'encoder': '17-bit', 'x': f'{ENDS[k]:g}-{ENDS[k + 1]:g}', 'qd_rel': '',
                     'qdd_rel': float(np.median(v)), 'effort_rel': ''})
    return rows


def velocity_sweep(model, seeds):
    rows = []
    harmonic = BASE * HARMONICS
    for lag in (None, 0.0, 1e-3, 5e-3):
        errs = []
        for seed in seeds:
            t, q, e, truth = recording(model, seed, ENCODERS['17-bit'])
            qd = None
            if lag is not None:
                _, v, _ = trajectory(model, t - lag, seed)
                v = v + 1e-3 * np.sqrt(np.mean(v ** 2)) * np.random.default_rng(seed + 7).normal(size=v.shape)
                qd = v
            s = signals.prepare(t, q, e, qd, harmonic=harmonic)
            _, qd0, qdd0, _ = truth(s.t)
            errs.append((_rel(s.qd - qd0, qd0), _rel(s.qdd - qdd0, qdd0)))
        qd_e, qdd_e = np.median(errs, axis=0)
        rows.append({'sweep': 'velocity', 'encoder': '17-bit', 'x': 'derived' if lag is None else
                     f'measured, {lag * 1e3:g} ms late', 'qd_rel': qd_e, 'qdd_rel': qdd_e, 'effort_rel': ''})
    return rows


def run(quick=False, out=None):
    model = load_urdf(default_urdf_path())
    seeds = (0,) if quick else (0, 1, 2)
    rows = cutoff_sweep(model, FACTORS_QUICK if quick else FACTORS, seeds)
    rows += gap_sweep(model, seeds) + ends_sweep(model, seeds) + velocity_sweep(model, seeds)
    if out is not None:
        write(rows, out)
    return rows


def _fmt(x):
    return f'{x:.3g}' if isinstance(x, float) else str(x)


def markdown(rows):
    lines = ['# Signal preparation: error against cutoff, gap and distance from the ends', '',
             f'{HARMONICS} harmonics of {BASE} Hz (highest {BASE * HARMONICS:g} Hz), {RATE:g} Hz with '
             f'+-{JITTER * 1e3:g} ms jitter and {100 * LOSS:g} % lost samples, effort noise '
             f'{100 * EFFORT_NOISE:g} % of RMS; errors relative to the true signal RMS (median over seeds).', '',
             '| sweep | encoder | x | q̇ error | q̈ error | effort error |', '|---|---|---:|---:|---:|---:|']
    lines += [f"| {r['sweep']} | {r['encoder']} | {_fmt(r['x'])} | {_fmt(r['qd_rel'])} | {_fmt(r['qdd_rel'])} | "
              f"{_fmt(r['effort_rel'])} |" for r in rows]
    return '\n'.join(lines) + '\n'


def chart(rows, path):
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2))
    ax = axes[0]
    for name, style in zip(ENCODERS, ('-', '--')):
        sel = [r for r in rows if r['sweep'] == 'cutoff' and r['encoder'] == name]
        x = [r['x'] for r in sel]
        for key, color, label in (('qd_rel', 'C0', 'q̇'), ('qdd_rel', 'C1', 'q̈'), ('effort_rel', 'C2', 'effort')):
            ax.loglog(x, [r[key] for r in sel], style, color=color, marker='o', ms=3, label=f'{label}, {name}')
    ax.axvline(signals.CUTOFF_FACTOR, color='k', lw=0.8, ls=':')
    factors = sorted({r['x'] for r in rows if r['sweep'] == 'cutoff'})
    ax.set_xticks(factors, [f'{f:g}' for f in factors])
    ax.minorticks_off()
    ax.set_xlabel('cutoff / highest harmonic')
    ax.set_ylabel('RMS error / RMS signal')
    ax.set_title('error against cutoff (dotted: the default)')
    ax.legend(fontsize=7, ncol=2)
    ax.grid(True, which='both', alpha=0.3)
    ax = axes[1]
    sel = [r for r in rows if r['sweep'] == 'gap']
    ax.loglog([r['x'] for r in sel], [r['qdd_rel'] for r in sel], 'o-', color='C1')
    ax.axvline(signals.MAX_GAP_PERIODS, color='k', lw=0.8, ls=':')
    ax.set_xlabel('dropout length, periods of the cutoff')
    ax.set_ylabel('largest q̈ error near it / RMS q̈')
    ax.set_title('one dropout bridged (dotted: the longest bridged)')
    ax.grid(True, which='both', alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def write(rows, out):
    os.makedirs(out, exist_ok=True)
    with open(os.path.join(out, 'signals.md'), 'w', encoding='utf-8') as fh:
        fh.write(markdown(rows))
    with open(os.path.join(out, 'signals.csv'), 'w', newline='', encoding='utf-8') as fh:
        w = csv.DictWriter(fh, fieldnames=['sweep', 'encoder', 'x', 'qd_rel', 'qdd_rel', 'effort_rel'])
        w.writeheader()
        w.writerows(rows)
    chart(rows, os.path.join(out, 'signals.png'))


def main(argv=None):
    ap = argparse.ArgumentParser(prog='python -m bench.signals', description=__doc__.split('\n')[0])
    ap.add_argument('--quick', action='store_true')
    ap.add_argument('--out', default=os.path.join(os.path.dirname(os.path.abspath(__file__)), 'out'))
    args = ap.parse_args(argv)
    rows = run(quick=args.quick, out=args.out)
    print(markdown(rows))
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
