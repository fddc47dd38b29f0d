"""identify_dynamics: a recording of the robot in, calibration.yaml (and a report, a corrected
URDF) out.

Library: `identify_dynamics(model, t, q, effort, qd=None, ...)` prepares the signals
(calibration.signals.prepare: a uniform grid, one zero-phase low-pass for positions and
efforts, then q̇ and q̈), keeps the last `holdout` fraction of the time aside, fits the
physically consistent calibration (fit.py) on the rest, and returns a CalibrationResult whose
`report` holds the held-out check: the torque prediction RMS per joint before (the URDF with
its <dynamics> friction, no armature, no offsets) and after calibration. With qd and qdd
both given (exact states, e.g. from a simulation) the signals are used as they are.

Command line: `identify_dynamics RECORDING --urdf URDF -o calibration.yaml [--joints a,b,...]
[--topic T] [--report DIR] [--urdf-out corrected.urdf]`.
"""
import os

import numpy as np

from ..laws import COULOMB_VELOCITY_EPSILON
from . import fit as cfit
from . import regressor as creg
from .result import from_fit, rewrite_urdf

HOLDOUT = 0.2


def identify_dynamics(model, t, q, effort, qd=None, *, qdd=None, holdout=HOLDOUT, eps=COULOMB_VELOCITY_EPSILON,
                      weights=None, prior=None, signals=None, **fit_options):
    """CalibrationResult from a recording: t (N,) s; q, effort (N, n) in model.joint_names order;
    qd (N, n) measured velocities or None. qdd: with qd, exact accelerations (no filtering).
    holdout: the last fraction of the time kept out of the fit for the before/after check
    (0: none). signals: options for calibration.signals.prepare (cutoff, harmonic, rate, ...;
    oversample defaults to signals.OVERSAMPLE, None keeps every grid sample). The smooth Coulomb
    sign is low-passed with the efforts (prepare's `terms`).
    fit_options: for fit.fit (regularization, rcond, min_motion, ...). Warns
    UnidentifiableWarning as fit.fit does; ValueError names bad input."""
    if not (0 <= holdout < 1):
        raise ValueError(f'holdout must be in [0, 1), got {holdout}')
    t = np.asarray(t, dtype=float).reshape(-1)
    if qdd is not None:
        if qd is None:
            raise ValueError('qdd needs qd (exact states); without them the signals are filtered and differentiated')
        q, qd, qdd, effort = model.check_states(q=q, qd=qd, qdd=qdd, effort=effort)
        if len(t) != len(q):
            raise ValueError(f't has {len(t)} stamps for {len(q)} samples')
        segment = np.zeros(len(t), dtype=int)
        coulomb = None
        info = {'rate': float(1.0 / np.median(np.diff(t))) if len(t) > 1 else float('nan'), 'cutoff': None}
    else:
        s = prepare_recording(t, q, effort, qd, eps=eps, signals=signals)
        t, q, qd, qdd, effort, segment, coulomb = s.t, s.q, s.qd, s.qdd, s.effort, s.segment, s.terms
        q, qd, qdd, effort = model.check_states(q=q, qd=qd, qdd=qdd, effort=effort)
        info = {'rate': s.rate * s.step, 'step': s.step, 'cutoff': s.cutoff, 'dropped': s.dropped,
                'segments': s.segments}
    split = t[0] + (1 - holdout) * (t[-1] - t[0]) if holdout > 0 else np.inf
    train = t < split
    test = ~train
    if holdout > 0 and test.sum() < 2:
        raise ValueError(f'the held-out last {holdout:.0%} of the recording has {int(test.sum())} samples')
    fitted = cfit.fit(model, q[train], qd[train], qdd[train], effort[train], eps=eps, weights=weights, prior=prior,
                      coulomb=None if coulomb is None else coulomb[train], **fit_options)
    result = from_fit(model, fitted)
    report = dict(info, samples=int(len(t)), train_samples=int(train.sum()), holdout=holdout)
    if test.any():
        Y = creg.calibration_regressor(model, q[test], qd[test], qdd[test], eps,
                                       None if coulomb is None else coulomb[test])
        before = Y @ fitted.prior
        after = Y @ fitted.parameters
        meas = effort[test]
        report.update(t=t[test], measured=meas, before=before, after=after,
                      rms_before=np.sqrt(np.mean((before - meas) ** 2, axis=0)),
                      rms_after=np.sqrt(np.mean((after - meas) ** 2, axis=0)),
                      rms_effort=np.sqrt(np.mean(meas ** 2, axis=0)))
    report['segment'] = segment
    result.report = report
    return result


def prepare_recording(t, q, effort, qd=None, *, eps=COULOMB_VELOCITY_EPSILON, signals=None):
    """A recording's signals as identify_dynamics fits them (calibration.signals.Signals): resampled,
    low-passed, differentiated, decimated to signals.OVERSAMPLE per cutoff period; `.terms` holds
    the Coulomb columns to pass to calibration_regressor. signals: options for signals.prepare."""
    from .signals import OVERSAMPLE, prepare   # scipy.signal: imported where it is used

    # the smooth Coulomb sign is low-passed like the efforts: the filter rounds off its steps
    # in the measured efforts, and tanh of the filtered q̇ would keep them sharp
    options = dict({'oversample': OVERSAMPLE}, **(signals or {}))
    return prepare(t, q, effort, qd, terms=lambda q_, qd_, qdd_: np.tanh(qd_ / eps), **options)


def write_report(result, folder, joint_names=None):
    """The report of `identify_dynamics` in `folder`: report.txt (condition number, base
    parameters and their combinations, the held-out torque RMS per joint before and after) and
    torques.png (measured against predicted torques per joint on the held-out part). matplotlib
    is a development dependency only: it is imported here, and without it the PNG is skipped
    (said in report.txt). Returns the paths written."""
    os.makedirs(folder, exist_ok=True)
    names = joint_names or result.joint_names
    rep = result.report
    lines = [f'robot {result.robot}: {len(names)} joints, {len(result.parameters)} calibration parameters',
             f"samples: {rep.get('samples')} ({rep.get('train_samples')} fitted, the last "
             f"{rep.get('holdout', 0):.0%} held out); grid rate {rep.get('rate', float('nan')):.6g} Hz, "
             f"low-pass cutoff {rep.get('cutoff')} Hz, decimated by {rep.get('step', 1)} after filtering",
             f'condition number of the base regressor (column-scaled): {result.condition_number:.6g}']
    base = result.base
    if base is not None:
        lines.append(f'base parameters: {base.rank}')
        for k, (b, v, s) in enumerate(zip(base.base_columns, base.values, base.std)):
            lines.append(f'  beta_{k:<3d} {base.names[b]:24s} {v: .6g} +- {s:.3g}')
        lines.append('combinations (beta_k = its base column plus the dependent ones):')
        lines += ['  ' + c for c in base.combinations]
        for status in ('combination', 'unidentified'):
            lines.append(f'{status}: ' + ', '.join(base.names_with(status)))
    paths = []
    if 'rms_after' in rep:
        lines.append('held-out torque prediction RMS per joint (N m): before calibration (URDF), after, '
                     'RMS of the measured effort')
        for j, name in enumerate(names):
            lines.append(f"  {name:16s} {rep['rms_before'][j]:10.4g} {rep['rms_after'][j]:10.4g} "
                         f"{rep['rms_effort'][j]:10.4g}")
        png = os.path.join(folder, 'torques.png')
        try:
            _plot(rep, names, png)
            paths.append(png)
        except ImportError:
            lines.append('torques.png not written: matplotlib is not installed (a development dependency)')
    txt = os.path.join(folder, 'report.txt')
    with open(txt, 'w') as fh:
        fh.write('\n'.join(lines) + '\n')
    return [txt] + paths


def _plot(rep, names, path):
    import matplotlib   # a development dependency only
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    n = len(names)
    fig, axes = plt.subplots(n, 1, figsize=(10, 1.8 * n + 0.8), sharex=True, squeeze=False)
    for j, ax in enumerate(axes[:, 0]):
        ax.plot(rep['t'], rep['measured'][:, j], color='0.3', lw=1.2, label='measured')
        ax.plot(rep['t'], rep['before'][:, j], color='tab:red', lw=0.9, ls='--',
                label=f"URDF (RMS {rep['rms_before'][j]:.3g})")
        ax.plot(rep['t'], rep['after'][:, j], color='tab:blue', lw=0.9,
                label=f"calibrated (RMS {rep['rms_after'][j]:.3g})")
        ax.set_ylabel(f'{names[j]}\nN m')
        ax.legend(loc='upper right', fontsize=7, ncol=3)
    axes[-1, 0].set_xlabel('time, s (held-out part of the recording)')
    fig.suptitle('measured against predicted joint torques')
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


EXAMPLES = """\
RECORDING: a rosbag2 folder (mcap or sqlite3) with sensor_msgs/JointState on --topic (positions
and efforts required, velocities optional), or a trajectory CSV with pos.<joint> and eff.<joint>
columns. Record it while the excitation (excitation_trajectory) plays.
writes: calibration.yaml (-o); with --report DIR: DIR/report.txt and DIR/torques.png; with
--urdf-out: the URDF with <inertial> and <dynamics damping friction> rewritten.
examples:
  identify_dynamics rosbag2_2026_01_01 --urdf robot.urdf -o calibration.yaml --report report/
  identify_dynamics recording.csv --urdf robot.urdf -o calibration.yaml --urdf-out corrected.urdf
"""


def main(argv=None):
    """identify_dynamics: calibrate a robot's dynamics from a recording."""
    from ..cli import CliParser, run_cli

    ap = CliParser('lie_dynamics.calibration.identify', description='identify inertial parameters, friction, '
                   'armature and effort offsets from a recording', epilog=EXAMPLES)
    ap.add_argument('recording', help='rosbag2 folder or trajectory CSV with efforts')
    ap.add_argument('--urdf', required=True, help='the robot description (URDF file): the prior')
    ap.add_argument('-o', '--output', required=True, help='calibration.yaml to write')
    ap.add_argument('--joints', help='comma-separated joints to calibrate (default: all controlled joints)')
    ap.add_argument('--topic', default='/joint_states', help='JointState topic in a bag (default /joint_states)')
    ap.add_argument('--report', metavar='DIR', help='write report.txt and torques.png there')
    ap.add_argument('--urdf-out', metavar='FILE', help='write the corrected URDF there')
    run_cli(ap, _identify, argv)   # nothing returned: a console script exits with main()'s value


def _identify(args):
    import warnings

    from .. import load_urdf
    from .recordings import read_recording

    joints = [j.strip() for j in args.joints.split(',')] if args.joints else None
    model = load_urdf(args.urdf, joints=joints)
    rec = read_recording(args.recording, args.topic)
    missing = [j for j in model.joint_names if j not in rec.joint_names]
    if missing:
        raise ValueError(f'{args.recording}: no samples for the joints {", ".join(missing)} '
                         f'(it has {", ".join(rec.joint_names)})')
    cols = [rec.joint_names.index(j) for j in model.joint_names]
    locked = {j: float(np.median(rec.q[:, k])) for k, j in enumerate(rec.joint_names)
              if j in model.locked_joint_names}
    if locked:
        model.set_locked(locked)
    qd = None if rec.qd is None else rec.qd[:, cols]
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter('always', cfit.UnidentifiableWarning)
        result = identify_dynamics(model, rec.t, rec.q[:, cols], rec.effort[:, cols], qd)
    for w in caught:
        print(f'warning: {" ".join(str(w.message).split())}')
    result.save(args.output)
    print(f'{args.output}: {len(result.body_links)} links, {len(result.joint_names)} joints; condition number '
          f'{result.condition_number:.4g}')
    if 'rms_after' in result.report:
        print('held-out torque RMS per joint, before -> after (N m): ' + ', '.join(
            f'{j} {b:.3g} -> {a:.3g}' for j, b, a in zip(model.joint_names, result.report['rms_before'],
                                                         result.report['rms_after'], strict=True)))
    if args.report:
        for p in write_report(result, args.report, model.joint_names):
            print(f'report: {p}')
    if args.urdf_out:
        with open(args.urdf) as fh:
            text = rewrite_urdf(fh.read(), model, result)
        with open(args.urdf_out, 'w') as fh:
            fh.write(text)
        print(f'{args.urdf_out}: the URDF with the identified <inertial> and <dynamics>')


if __name__ == '__main__':
    main()
