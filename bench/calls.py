"""One call and batches on the arms, beside Pinocchio in the same process.

    python -m bench.calls [--quick] [--out DIR]      (also: python -m bench --only calls)

Robots: UR5, xArm7, the Talos arm and the Panda (arm joints; fingers locked) of
example-robot-data. For each, interleaved rounds, each the best of REPEATS measurements of
every candidate (a measurement preempted on a loaded machine drops out), medians of per-round
ratios:
  * one state: inverse dynamics and gravity, allocating and with `out=`, over pin.rnea and
    pin.computeGeneralizedGravity; and the floor of any Python -> C call with arrays, a numpy
    ufunc with out= (np.add of two (n,) arrays), over pin.rnea;
  * batched inverse dynamics per state at N = 100 and 10,000: over a Pinocchio loop
    (pin.rnea state by state, copied out) and over pin.rneaInParallel with one thread (ours:
    the plain call, the process set to one thread); with
    lie_dynamics.codegen.native.set_threads(2) around the call over one thread of ours and over
    rneaInParallel with two threads (N = 10,000).
Writes DIR/calls.{md,csv,json}.
"""
import gc
import os
import sys
import time
import warnings

import numpy as np

from bench import common

REPEATS = 3

ROBOTS = (('UR5', 'ur_description/urdf/ur5_robot.urdf', None),
          ('xArm7', 'xarm_description/urdf/xarm7.urdf', None),
          ('Talos arm', 'talos_data/robots/talos_left_arm.urdf', None),
          ('Panda', 'panda_description/urdf/panda.urdf', [f'panda_joint{k}' for k in range(1, 8)]))


def _timed(fns, rounds, target):
    """{key: seconds per call, one per round}: rounds interleaved, each the best of REPEATS (the
    garbage collector off while timing, as timeit)."""
    calls = {k: common.calibrate(f, target / REPEATS) for k, f in fns.items()}
    t = {k: np.empty(rounds) for k in fns}
    for r in range(rounds):
        keys = list(fns)[r % len(fns):] + list(fns)[:r % len(fns)]
        for k in keys:
            f, n = fns[k], calls[k]
            best = np.inf
            gc.disable()   # as timeit
            try:
                for _ in range(REPEATS):
                    t0 = time.perf_counter()
                    for _ in range(n):
                        f()
                    best = min(best, time.perf_counter() - t0)
            finally:
                gc.enable()
            t[k][r] = best / n
    return t


def _models(rel, joints):
    import pinocchio as pin
    from bench.robots import robot_dir
    from lie_dynamics import load_urdf
    with open(os.path.join(robot_dir(), rel), encoding='utf-8') as fh:
        xml = fh.read()
    with warnings.catch_warnings():
        warnings.simplefilter('ignore')   # vendor inertias are warned about
        model = load_urdf(xml, joints=joints)
    pm = pin.buildModelFromXML(xml)
    if joints:   # the other joints locked at zero, as load_urdf does
        pm = pin.buildReducedModel(pm, [pm.getJointId(j) for j in pm.names[1:] if j not in joints], pin.neutral(pm))
    pm.gravity.linear = model.gravity_vector
    return pin, model, pm


def _one_state(pin, model, pm, rounds, target):
    pd = pm.createData()
    q, qd, qdd = (x[0].copy() for x in common.random_states(model, 1, seed=1))
    out = np.empty(model.n)
    a, b, c = np.ones(model.n), np.ones(model.n), np.empty(model.n)
    assert common.rel_err(model.inverse_dynamics(q, qd, qdd), pin.rnea(pm, pd, q, qd, qdd)) < 1e-10
    fns = {'pin_rnea': lambda: pin.rnea(pm, pd, q, qd, qdd),
           'pin_gravity': lambda: pin.computeGeneralizedGravity(pm, pd, q),
           'inverse_dynamics': lambda: model.inverse_dynamics(q, qd, qdd),
           'inverse_dynamics_out': lambda: model.inverse_dynamics(q, qd, qdd, out=out),
           'gravity': lambda: model.gravity(q),
           'gravity_out': lambda: model.gravity(q, out=out),
           'ufunc_out': lambda: np.add(a, b, out=c)}
    t = _timed(fns, rounds, target)
    rows = []
    for k in fns:
        if k.startswith('pin'):
            continue
        base = t['pin_gravity'] if k.startswith('gravity') else t['pin_rnea']
        rows.append(dict(case=k, N=1, us=float(np.median(t[k]) * 1e6), ratio=float(np.median(t[k] / base)),
                         versus='pin.computeGeneralizedGravity' if k.startswith('gravity') else 'pin.rnea'))
    return rows


def _batch(pin, model, pm, N, rounds, target):
    from lie_dynamics.codegen import native
    pd = pm.createData()
    q, qd, qdd = (np.ascontiguousarray(x) for x in common.random_states(model, N, seed=2))
    out = np.empty((N, model.n))
    pool = pin.ModelPool(pm, 2)
    tau = np.zeros((N, model.n)).T   # Pinocchio's (n, N), column-major: no copy of the result
    pin.rneaInParallel(1, pool, q.T, qd.T, qdd.T, tau)
    assert common.rel_err(model.inverse_dynamics(q, qd, qdd), tau.T) < 1e-10

    def two_threads():
        previous = native.set_threads(2)
        try:
            model.inverse_dynamics(q, qd, qdd, out=out)
        finally:
            native.set_threads(previous)
    # one thread: the plain call under the process's setting (1 while timing). Switching the
    # setting around each call, as the 2-thread candidate does, costs ~2.5 us (two Python calls),
    # a fifth of a 100-state batch, and is no part of the call rneaInParallel is compared with.
    fns = {'ours_1': lambda: model.inverse_dynamics(q, qd, qdd, out=out), 'ours_2': two_threads,
           'pin_parallel_1': lambda: pin.rneaInParallel(1, pool, q.T, qd.T, qdd.T, tau),
           'pin_parallel_2': lambda: pin.rneaInParallel(2, pool, q.T, qd.T, qdd.T, tau)}
    fns['pin_loop'] = lambda: [pin.rnea(pm, pd, q[i], qd[i], qdd[i]).copy() for i in range(N)]
    previous = native.set_threads(1)
    try:
        t = _timed(fns, rounds, target)
    finally:
        native.set_threads(previous)
    med = lambda a, b: float(np.median(t[a] / t[b]))  # noqa: E731
    row = dict(case='batched inverse_dynamics', N=N, ns_per_state=float(np.median(t['ours_1']) / N * 1e9),
               vs_rnea_in_parallel_1=med('ours_1', 'pin_parallel_1'),
               two_threads_speedup=med('ours_1', 'ours_2'),
               vs_rnea_in_parallel_2=med('ours_2', 'pin_parallel_2'),
               pin_parallel_speedup=med('pin_parallel_1', 'pin_parallel_2'))
    row['vs_pin_loop'] = med('ours_1', 'pin_loop')
    return row


def run(quick=False, out=None, robots=ROBOTS):
    """Every robot's one-state and batch rows; written to out/calls.* when out is given."""
    rounds = 5 if quick else 15
    target = 0.004 if quick else 0.02
    result = {'one_state': [], 'batches': [], 'meta': dict(rounds=rounds, quick=quick)}
    for name, rel, joints in robots[:2] if quick else robots:
        pin, model, pm = _models(rel, joints)
        for r in _one_state(pin, model, pm, rounds, target):
            result['one_state'].append(dict(robot=name, n=model.n, **r))
        for N in ((100,) if quick else (100, 10_000)):
            result['batches'].append(dict(robot=name, n=model.n, **_batch(pin, model, pm, N, rounds, target)))
    if out:
        common.write_tables(out, 'calls', markdown(result), result, result['one_state'])
    return result


def markdown(result):
    lines = ['### One state: ours / Pinocchio (median of per-round ratios)', '',
             '| robot (joints) | ID | ID out= | gravity | gravity out= | ufunc out= (floor) |',
             '|---|---|---|---|---|---|']
    by = {}
    for r in result['one_state']:
        by.setdefault((r['robot'], r['n']), {})[r['case']] = r['ratio']
    for (robot, n), c in by.items():
        lines.append(f"| {robot} ({n}) | {c['inverse_dynamics']:.2f} | {c['inverse_dynamics_out']:.2f} | "
                     f"{c['gravity']:.2f} | {c['gravity_out']:.2f} | {c['ufunc_out']:.2f} |")
    lines += ['', '### Batched inverse dynamics, per state', '',
              '| robot | N | ns/state | / Pinocchio loop | / rneaInParallel(1) | 2 threads: speed-up '
              '| 2 threads / rneaInParallel(2) | rneaInParallel speed-up |', '|---|---|---|---|---|---|---|---|']
    for r in result['batches']:
        lines.append(f"| {r['robot']} | {r['N']:,} | {r['ns_per_state']:.0f} | {r['vs_pin_loop']:.3f} "
                     f"| {r['vs_rnea_in_parallel_1']:.2f} "
                     f"| {r['two_threads_speedup']:.2f}x | {r['vs_rnea_in_parallel_2']:.2f} | "
                     f"{r['pin_parallel_speedup']:.2f}x |")
    return '\n'.join(lines) + '\n'


def main(argv=None):
    return common.section_main(argv, __doc__, run, markdown)


if __name__ == '__main__':
    sys.exit(main())
