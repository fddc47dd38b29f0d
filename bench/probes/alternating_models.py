"""What calling several models in turn costs a C method (codegen/native_method.c): each of
Model.gravity, mass_matrix, forward_dynamics and jacobian called on one model alone, and on
two and five copies of it in turn (a robot and its calibrated copy; more models than the
method holds). Per call, median of interleaved rounds, as a ratio to the call on one model.

    python -m bench.probes.alternating_models [--rounds R] [--robot arm7|talos_reduced]
"""
import argparse
import copy
import os
import warnings

import numpy as np

from bench import common


def _model(name):
    from lie_dynamics import load_urdf
    if name == 'arm7':
        return load_urdf(common.default_urdf())
    from bench.robots import robot_dir
    with warnings.catch_warnings():
        warnings.simplefilter('ignore')
        return load_urdf(os.path.join(robot_dir(), 'talos_data/robots/talos_reduced.urdf'))


def run(robot='talos_reduced', rounds=15):
    m = _model(robot)
    models = [m] + [copy.deepcopy(m) for _ in range(4)]
    rng = np.random.default_rng(0)
    q, qd, qdd = (rng.uniform(-1, 1, m.n) for _ in range(3))
    tau = m.inverse_dynamics(q, qd, qdd)
    link = m.body_link_names[int(np.argmax(m.depth))]
    calls = {'gravity': lambda x: x.gravity(q), 'mass_matrix': lambda x: x.mass_matrix(q),
             'forward_dynamics': lambda x: x.forward_dynamics(q, qd, tau), 'jacobian': lambda x: x.jacobian(q, link)}
    rows = []
    for name, f in calls.items():
        fns = {'one model': lambda f=f: (f(m), f(m)),
               'two in turn': lambda f=f: (f(models[0]), f(models[1])),
               'five in turn': lambda f=f: [f(x) for x in models]}
        t = common.time_interleaved(fns, rounds, 0.01, rotate=True)
        per = {'one model': t['one model'] / 2, 'two in turn': t['two in turn'] / 2,
               'five in turn': t['five in turn'] / 5}
        rows.append((name, float(np.median(per['one model'])) * 1e6,
                     float(np.median(per['two in turn'] / per['one model'])),
                     float(np.median(per['five in turn'] / per['one model']))))
    print(f'| {robot} | one model, µs per call | two in turn / one | five in turn / one |\n|---|---:|---:|---:|')
    for name, us, two, five in rows:
        print(f'| {name} | {us:.2f} | {two:.2f} | {five:.2f} |')
    print(f'(load average {os.getloadavg()[0]:.1f})')
    return rows


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--rounds', type=int, default=15)
    ap.add_argument('--robot', default='talos_reduced', choices=('arm7', 'talos_reduced'))
    a = ap.parse_args(argv)
    run(a.robot, a.rounds)
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
