"""Payload identification: error against torque noise and against recording length.

    python -m bench.payload [--quick] [--out DIR]

The node's pipeline without ROS (lie_dynamics.ros.features.payload_service): the bundled arm carries the
demo's load (2 kg on tool0, CoM off the axis, full inertia) along the identification excitation
trajectory; joint_states at RATE Hz with efforts = inverse dynamics of the loaded arm + white
torque noise of standard deviation sigma, pushed through the node's bounded Recording (at most
4,000 samples: long recordings are decimated), q̈ from the node's smoothing derivative of q̇
(`dynamic`), or the same poses held still (`static`: q̇ = q̈ = 0, mass and CoM only). Errors:
|m - m_true| / m_true, |c - c_true| (mm), and for the inertia the largest error of its six
entries relative to the largest true entry; median over seeds, with how many fits the node
refused (identify.max_residual_ratio 0.3 by default: the residual would be too large a part of
the payload torque). Writes payload.{md,csv,json,png}.
"""
import os
import time

import numpy as np

from bench import common

RATE = 500.0
LINK, MASS, COM = 'tool0', 2.0, np.array([0.03, -0.02, 0.08])
INERTIA = np.array([0.012, 0.0, 0.0, 0.014, 0.0, 0.008])
NOISES = (0.0, 0.01, 0.03, 0.1, 0.3, 1.0, 3.0)          # N m
NOISES_QUICK = (0.0, 0.1, 1.0)
DURATIONS = (0.5, 1.0, 2.0, 5.0, 10.0, 20.0, 40.0)      # s
DURATIONS_QUICK = (1.0, 5.0)
DURATION_NOISE = 0.3                                    # N m: the noise of the duration sweep
NOISE_DURATION = 10.0                                   # s: the duration of the noise sweep
MAX_RATIO = 0.3


def one(model, mode, sigma, duration, seed):
    """Errors of one identification (None where refused) and what the fit said."""
    from lie_dynamics.algorithms.identification import excitation_trajectory
    from lie_dynamics.ros.features.payload_service import Recording, fit
    t, q, qd, qdd = excitation_trajectory(model, duration=duration, rate=RATE, seed=seed)
    if mode == 'static':
        qd, qdd = np.zeros_like(qd), np.zeros_like(qdd)
    loaded = model.with_body_inertias(model.J_links)
    loaded.set_payload(LINK, MASS, COM, INERTIA)
    tau = loaded.inverse_dynamics(q, qd, qdd) + sigma * np.random.default_rng(seed + 1000).normal(size=q.shape)
    rec = Recording(model.n, duration=np.inf)
    for k in range(len(t)):
        rec.add(t[k], q[k], qd[k], tau[k])
    t0 = time.perf_counter()
    try:
        res, _, _ = fit(model, LINK, *rec.arrays(), mode, 'total', MAX_RATIO)
    except ValueError as exc:
        return dict(refused=str(exc)[:120], seconds=time.perf_counter() - t0, samples=rec.size)
    out = dict(refused='', seconds=time.perf_counter() - t0, samples=rec.size,
               mass_err=abs(res.mass - MASS) / MASS, com_err_mm=1e3 * float(np.linalg.norm(res.com - COM)),
               inertia_err=(float(np.max(np.abs(res.inertia - INERTIA)) / np.max(np.abs(INERTIA)))
                            if res.inertia is not None else float('nan')),
               determined=int(sum(res.determined.values())), repaired=bool(res.repaired))
    return out


def _summary(runs):
    ok = [r for r in runs if not r['refused']]
    med = (lambda k: float(np.median([r[k] for r in ok])) if ok else float('nan'))  # noqa: E731
    return dict(mass_err=med('mass_err'), com_err_mm=med('com_err_mm'), inertia_err=med('inertia_err'),
                refused=len(runs) - len(ok), fits=len(runs), seconds=med('seconds'),
                samples=int(np.median([r['samples'] for r in runs])),
                determined=int(np.median([r['determined'] for r in ok])) if ok else 0)


def run(quick=False, out=None, seeds=None):
    from lie_dynamics import default_urdf_path, load_urdf
    model = load_urdf(default_urdf_path())
    seeds = range(seeds or (2 if quick else 5))
    rows = []
    for mode in ('dynamic', 'static'):
        for sigma in (NOISES_QUICK if quick else NOISES):
            rows.append(dict(sweep='noise', mode=mode, noise=sigma, duration=NOISE_DURATION,
                             **_summary([one(model, mode, sigma, NOISE_DURATION, s) for s in seeds])))
    for duration in (DURATIONS_QUICK if quick else DURATIONS):
        rows.append(dict(sweep='duration', mode='dynamic', noise=DURATION_NOISE, duration=duration,
                         **_summary([one(model, 'dynamic', DURATION_NOISE, duration, s) for s in seeds])))
    res = dict(rows=rows, meta=dict(quick=quick, seeds=len(seeds), rate=RATE, link=LINK, mass=MASS, com=COM.tolist(),
                                    inertia=INERTIA.tolist(), max_residual_ratio=MAX_RATIO))
    if out:
        write(res, out)
    return res


def _fmt(x, fmt):
    return '' if x != x else fmt.format(x)   # NaN (nothing identified): empty


def markdown(res):
    m = res['meta']
    L = ['# Payload identification: error against noise and recording length', '',
         f"Bundled arm, {m['mass']} kg on `{m['link']}` (CoM {m['com']} m, inertia {m['inertia']} kg m²), "
         f"joint_states at {m['rate']:g} Hz through the node's recording (≤ 4000 samples) and fit; median over "
         f"{m['seeds']} seeds. Inertia error: largest entry error / largest true entry. `static`: the same poses "
         'held still (mass and CoM only).', '',
         '| sweep | mode | torque noise σ (N m) | duration (s) | samples | mass error | CoM error (mm) | '
         'inertia error | determined (of 10) | refused | fit time (ms) |',
         '|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|']
    for r in res['rows']:
        L.append(f"| {r['sweep']} | {r['mode']} | {r['noise']:g} | {r['duration']:g} | {r['samples']} | "
                 f"{_fmt(100 * r['mass_err'], '{:.3g} %')} | {_fmt(r['com_err_mm'], '{:.3g}')} | "
                 f"{_fmt(100 * r['inertia_err'], '{:.3g} %')} | {r['determined']} | {r['refused']}/{r['fits']} | "
                 f"{_fmt(1e3 * r['seconds'], '{:.0f}')} |")
    return '\n'.join(L) + '\n'


def chart(res, path):
    plt = common.setup_matplotlib()
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.8))
    floor = 1e-12   # noise-free fits are exact to round-off: drawn at the floor of the log axis
    for mode, style in (('dynamic', '-'), ('static', '--')):
        rows = [r for r in res['rows'] if r['sweep'] == 'noise' and r['mode'] == mode and r['noise'] > 0]
        x = [r['noise'] for r in rows]
        for key, label, color in (('mass_err', 'mass (relative)', 'C0'), ('com_err_mm', 'CoM (mm)', 'C1'),
                                  ('inertia_err', 'inertia (relative)', 'C2')):
            y = [max(r[key], floor) for r in rows]
            if not all(v != v for v in y):
                axes[0].loglog(x, y, style, marker='o', ms=3, color=color, label=f'{label}, {mode}')
    axes[0].set_xlabel('torque noise σ (N m)')
    axes[0].set_title(f'error against noise ({NOISE_DURATION:g} s of data)', fontsize=10)
    rows = [r for r in res['rows'] if r['sweep'] == 'duration']
    x = [r['duration'] for r in rows]
    for key, label, color in (('mass_err', 'mass (relative)', 'C0'), ('com_err_mm', 'CoM (mm)', 'C1'),
                              ('inertia_err', 'inertia (relative)', 'C2')):
        axes[1].loglog(x, [max(r[key], floor) for r in rows], marker='o', ms=3, color=color, label=label)
    axes[1].set_xlabel('recording length (s)')
    axes[1].set_title(f'error against recording length (σ = {DURATION_NOISE:g} N m, dynamic)', fontsize=10)
    for ax in axes:
        ax.set_ylabel('median error')
        ax.grid(True, which='both', alpha=0.3)
        ax.legend(fontsize=7)
    fig.tight_layout()
    common.savefig(fig, path)


FIELDS = ['sweep', 'mode', 'noise', 'duration', 'samples', 'mass_err', 'com_err_mm', 'inertia_err', 'determined',
          'refused', 'fits', 'seconds']


def write(res, out):
    common.write_tables(out, 'payload', markdown(res), res, res['rows'], FIELDS)
    chart(res, os.path.join(out, 'payload.png'))


def main(argv=None):
    return common.section_main(argv, __doc__, run, markdown)


if __name__ == '__main__':
    raise SystemExit(main())
