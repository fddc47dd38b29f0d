"""Inertial-parameter identification on a simulated robot: the calibration example.

`python -m lie_dynamics.identification [--quick]`: an exciting trajectory (finite Fourier series
inside the joint limits), simulated noisy torques, identification, and the torque prediction
error on held-out data. The library's calls (`identify`, `excitation_trajectory`,
`IdentificationResult`, `UnidentifiableWarning`) live in lie_dynamics.algorithms.identification
and are re-exported here, at their documented path `lie_dynamics.identification`.
"""
import warnings

import numpy as np

from . import default_urdf_path, load_urdf
from .algorithms.identification import IdentificationResult, UnidentifiableWarning, excitation_trajectory, identify
from .cli import CliParser, number, run_cli

__all__ = ['IdentificationResult', 'UnidentifiableWarning', 'excitation_trajectory', 'identify', 'main']


EXAMPLES = """\
what it does: simulates an exciting trajectory (a Fourier series inside the joint limits,
  sampled at 100 Hz) on the robot, adds Gaussian noise to the inverse-dynamics torques,
  identifies the inertial parameters by least squares, then predicts the torques of a
  second, held-out trajectory and prints the errors. Nothing is written to disk.
input: any URDF the library loads; the noise scales with each joint's effort limit
  (joints without a limit: 100 N m).
examples:
  python -m lie_dynamics.identification --quick
  python -m lie_dynamics.identification --urdf config/arm7.urdf --noise 0.01 --duration 60 --seed 3
"""


def main(argv=None):
    """Calibration example on the bundled arm; prints what was recovered."""
    ap = CliParser('lie_dynamics.identification', description=__doc__.split('\n')[0], epilog=EXAMPLES)
    ap.add_argument('--urdf', default=default_urdf_path(), help='robot (default: the bundled 7-DoF arm)')
    ap.add_argument('--noise', type=number(low=0, strict=True), default=0.002,
                    help='torque noise std as a fraction of each joint effort limit, > 0 (default 0.002)')
    ap.add_argument('--duration', type=number(low=0, strict=True), default=30.0,
                    help='training trajectory length, s, > 0 (default 30)')
    ap.add_argument('--seed', type=number(int, low=0), default=1, help='random seed, >= 0 (default 1)')
    ap.add_argument('--quick', action='store_true', help='5 s trajectories, ignores --duration (smoke test)')
    return run_cli(ap, _example, argv)


def _example(args):
    model = load_urdf(args.urdf)
    pi_true = model.inertial_parameters()
    rng = np.random.default_rng(args.seed)
    duration = 5.0 if args.quick else args.duration
    effort = np.where(np.isfinite(model.effort_limits), model.effort_limits, 100.0)
    sigma = args.noise * effort

    def measured(seed, T):
        _, q, qd, qdd = excitation_trajectory(model, duration=T, rate=100.0, seed=seed)
        tau = model.inverse_dynamics(q, qd, qdd)
        return q, qd, qdd, tau, tau + rng.normal(size=tau.shape) * sigma

    q, qd, qdd, _, tau_noisy = measured(args.seed, duration)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter('always', UnidentifiableWarning)
        res = identify(model, q, qd, qdd, tau_noisy, weights=1.0 / sigma)
    for w in caught:
        print(f'warning: {w.message}')
    print(f'robot {model.name}: {model.n} joints, {res.n_parameters} inertial parameters, '
          f'{len(q)} training samples, torque noise {args.noise:.1%} of the effort limits')
    print(f'rank {res.rank} (base parameters), {res.n_unidentifiable} unidentifiable directions, '
          f'condition number {res.condition_number:.3g}')
    beta_true = res.base_of(pi_true)
    rel = np.abs(res.base_parameters - beta_true) / np.maximum(np.abs(beta_true), 1e-9)
    within = np.abs(res.base_parameters - beta_true) <= 3 * res.base_std + 1e-12
    big = np.abs(beta_true) > 10 * res.base_std
    print(f'base parameters: {within.mean():.0%} within 3 standard deviations of the true value; '
          f'the {int(big.sum())} larger than 10 std have median relative error {np.median(rel[big]):.2e}')
    print('mass per body, true vs identified (not separately identifiable where it is only '
          'seen in combinations):')
    width = max(len('body (link)'), *(len(name) for name in model.body_link_names))
    print(f'  {"body (link)":{width}s} {"true kg":>10s} {"identified kg":>14s}')
    for i, name in enumerate(model.body_link_names):
        print(f'  {name:{width}s} {pi_true[10 * i]:10.4f} {res.parameters[10 * i]:14.4f}')
    qh, qdh, qddh, tau_h, tau_h_noisy = measured(args.seed + 100, 5.0 if args.quick else 10.0)
    pred = res.predict(model, qh, qdh, qddh)
    rms_true = np.sqrt(np.mean((pred - tau_h) ** 2, axis=0))
    rms_noisy = np.sqrt(np.mean((pred - tau_h_noisy) ** 2, axis=0))
    scale = np.sqrt(np.mean(tau_h ** 2, axis=0))
    print('held-out trajectory, torque prediction rms error per joint (Nm):')
    print('  vs noise-free torques:', np.array2string(rms_true, precision=4))
    print('  vs measured torques:  ', np.array2string(rms_noisy, precision=4), '(noise std',
          np.array2string(sigma, precision=3) + ')')
    print('  rms torque of the held-out trajectory:', np.array2string(scale, precision=3))
    print(f'  noise-free error / rms torque: {np.max(rms_true / scale):.2e} (worst joint)')
    return res


if __name__ == '__main__':
    main()
