"""Native kernels on large robots: where a straight-line kernel stops paying (THRESHOLDS native_max).

    python -m bench.native_sizes [--robots pr2,baxter,talos_reduced,tree32,chain32,tree64,chain64]
                                 [--families mass_matrix,...] [--nodes 400000] [--out DIR]

Every size cap lifted (native_max and native_nodes; nodes above --nodes are skipped: they are
listed with their node count, untimed), each robot's kernels are built in a fresh temporary
cache: `first use` is the first runtime.native call (trace, render, compile, load), `CPU` the
compiler's CPU time in it. The bound kernel is then timed against Pinocchio on the same URDF
(every joint of the file its own Pinocchio joint: the same bodies), one state, interleaved
rounds (ratio: median of per-round ratios). Robots: PR2, Baxter, Talos reduced
(example-robot-data) and random revolute chains and binary trees (bench.common.robot_urdf).
The 1-minute load average is printed (2 cores: above ~0.5 the wall times include waiting).
"""
import functools
import os
import shutil
import tempfile
import time
import warnings

import numpy as np

from bench import common
from bench.compile import _cpu, _nodes, _restore_cache_dir, _specs

REAL = {'pr2': 'pr2_description/urdf/pr2.urdf', 'baxter': 'baxter_description/urdf/baxter.urdf',
        'talos_reduced': 'talos_data/robots/talos_reduced.urdf'}
ROBOTS = ('pr2', 'baxter', 'talos_reduced', 'tree32', 'chain32', 'tree64', 'chain64')


def robot_xml(label):
    """The URDF text of a robot label: a REAL key, arm7 (the bundled arm) or chainN / treeN (random,
    seed N)."""
    from bench import robots
    if label == 'arm7':
        return common.arm_xml()
    if label in REAL:
        with open(os.path.join(robots.robot_dir(), REAL[label]), encoding='utf-8') as fh:
            return fh.read()
    for kind in ('chain', 'tree'):
        if label.startswith(kind):
            n = int(label[len(kind):])
            return common.robot_urdf(n, tree=kind == 'tree', seed=n)
    raise ValueError(f'unknown robot {label!r}')


def pin_peer(xml, model, fam, rng):
    """A Pinocchio call of the same family on the whole URDF (random state), and its model."""
    import pinocchio as pin
    pm = pin.buildModelFromXML(xml)
    pm.gravity.linear = model.gravity_vector
    pd = pm.createData()
    q = pin.randomConfiguration(pm, -np.ones(pm.nq), np.ones(pm.nq))
    v, a = rng.uniform(-1, 1, (2, pm.nv))
    tau = pin.rnea(pm, pd, q, v, a)
    return {'inverse_dynamics': lambda: pin.rnea(pm, pd, q, v, a),
            'gravity': lambda: pin.computeGeneralizedGravity(pm, pd, q),
            'mass_matrix': lambda: pin.crba(pm, pd, q),
            'forward_dynamics': lambda: pin.aba(pm, pd, q, v, tau),
            'aba': lambda: pin.aba(pm, pd, q, v, tau),
            'regressor': lambda: pin.computeJointTorqueRegressor(pm, pd, q, v, a),
            'inverse_dynamics_derivatives': lambda: pin.computeRNEADerivatives(pm, pd, q, v, a),
            'coriolis': lambda: pin.computeCoriolisMatrix(pm, pd, q, v),
            'forward_dynamics_derivatives': lambda: pin.computeABADerivatives(pm, pd, q, v, tau)}[fam]


def lifted(max_nodes):
    """THRESHOLDS with every native cap lifted; returns the saved values for restore()."""
    from lie_dynamics.codegen import runtime
    T = runtime.THRESHOLDS
    saved = {k: v for k, v in T.items()}
    for k, v in saved.items():
        if hasattr(v, 'native_max'):
            T[k] = v._replace(native_max=10 ** 6)
    T['native_nodes'] = max_nodes
    runtime.clear()
    return saved


def restore(saved):
    from lie_dynamics.codegen import runtime
    runtime.THRESHOLDS.update(saved)
    runtime.clear()


def _arguments(fam, model, rng):
    q, qd, qdd = rng.uniform(-1, 1, (3, model.n))
    if fam in ('gravity', 'mass_matrix'):
        return (q,)
    if fam == 'coriolis':
        return (q, qd)
    if fam in ('forward_dynamics', 'aba', 'forward_dynamics_derivatives'):
        return (q, qd, model.inverse_dynamics(q, qd, qdd))
    return (q, qd, qdd)


def measure(labels, families, max_nodes, rounds=7):
    from lie_dynamics import load_urdf
    from lie_dynamics.codegen import native, runtime
    rows = []
    saved_dir = os.environ.get('LIE_DYNAMICS_CACHE_DIR')
    saved = lifted(max_nodes)
    work = tempfile.mkdtemp(prefix='bench_native_sizes_')
    try:
        for label in labels:
            os.environ['LIE_DYNAMICS_CACHE_DIR'] = os.path.join(work, label)
            runtime.clear()
            xml = robot_xml(label)
            with warnings.catch_warnings():
                warnings.simplefilter('ignore')   # vendor inertias are warned about
                model = load_urdf(xml)
            for fam, spec in _specs().items():
                if families and fam not in families:
                    continue
                nodes = _nodes(model, spec)
                row = dict(robot=label, n=model.n, nb=model.nb, family=fam, nodes=nodes, loadavg=os.getloadavg()[0])
                if nodes <= max_nodes:
                    c0, u0, t0 = native.compile_seconds(), _cpu(), time.perf_counter()
                    fn = runtime.native(model, spec)
                    row.update(first_s=time.perf_counter() - t0, compile_s=native.compile_seconds() - c0,
                               cpu_s=_cpu() - u0)
                    if fn is not None:
                        rng = np.random.default_rng(1)
                        args = _arguments(fam, model, rng)
                        t = common.time_interleaved({'ours': lambda: fn(*args), 'pin': pin_peer(xml, model, fam, rng)},
                                                    rounds, 0.01)
                        row.update(us=float(np.median(t['ours'])) * 1e6, pin_us=float(np.median(t['pin'])) * 1e6,
                                   ratio=float(np.median(t['ours'] / t['pin'])))
                rows.append(row)
                print(_line(row), flush=True)
    finally:
        _restore_cache_dir(saved_dir)
        restore(saved)
        shutil.rmtree(work, ignore_errors=True)
    return rows


def _line(r):
    f = functools.partial(common.cell, r)
    return (f"| {r['robot']} ({r['n']} joints, {r['nb']} bodies) | {r['family']} | {r['nodes']} | "
            f"{f('first_s', '.2f')} | {f('cpu_s', '.2f')} | {f('us', '.1f')} | {f('pin_us', '.1f')} | "
            f"{f('ratio', '.2f')} | {r['loadavg']:.1f} |")


HEAD = ('| robot | family | nodes | first use s | compiler CPU s | µs | Pinocchio µs | ratio | load |\n'
        '|---|---|---:|---:|---:|---:|---:|---:|---:|')


def main(argv=None):
    nodes = ('--nodes', dict(type=int, default=400000, help='skip kernels above this many nodes'))
    return common.rows_main(argv, __doc__, 'native_sizes', HEAD, _line,
                            lambda a: measure(a.robots, a.families, a.nodes, a.rounds), ','.join(ROBOTS),
                            options=(nodes,))


if __name__ == '__main__':
    raise SystemExit(main())
