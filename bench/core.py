"""Core benchmark: inverse dynamics and gravity of lie_dynamics next to Pinocchio and Modern Robotics.

    python -m bench.core [--quick] [--json] [--urdf PATH] [--out DIR]

For one arm (the bundled config/arm7.urdf by default) and N = 1, 100, 10 000 states it times
  * lie_dynamics (single state for N = 1, one batched call otherwise),
  * lie_dynamics' vectorised root-frame path (the implementation before the generated kernels),
  * Pinocchio (pin.rnea / pin.computeGeneralizedGravity; a Python loop for batches),
  * Modern Robotics (mr.InverseDynamics / mr.GravityForces in a loop; ~2 ms per state, so
    large batches are timed on a subset of states and scaled, marked "est."),
after checking that all of them give the same torques. The machine is shared and noisy:
every implementation is timed once per round, rounds are interleaved, and the table shows
medians over rounds; ratios are medians of per-round ratios, so all come from the same run.

Writes bench/out/core.{md,csv,json,png}; `--json` also prints the JSON. `run()` returns
the same dict for an aggregating "make bench".
"""
import argparse
import json
import os
import platform
import sys

import numpy as np

from bench import common

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
SIZES = (1, 100, 10_000)
IMPLS = ('lie_dynamics', 'lie_dynamics_python', 'lie_dynamics_vectorised', 'pinocchio', 'modern_robotics')
LABELS = {'lie_dynamics': 'lie_dynamics (native C kernels)', 'lie_dynamics_python': 'lie_dynamics (Python kernels)',
          'lie_dynamics_vectorised': 'lie_dynamics vectorised (before)',
          'pinocchio': 'Pinocchio', 'modern_robotics': 'Modern Robotics'}


# Shared with the other benchmarks (bench/common.py); the names stay importable from here.
default_urdf = common.default_urdf
modern_robotics_lists = common.modern_robotics_lists
_calibrate = common.calibrate


def _build(model, urdf_xml, op, N, rng, mr_states):
    """Callables for every implementation: impl -> (fn, states timed per call), and the outputs."""
    import modern_robotics as mr
    import pinocchio as pin
    from lie_dynamics.algorithms import rnea

    py = common.python_kernels(model)
    pm = pin.buildModelFromXML(urdf_xml)
    pm.gravity.linear = model.gravity_vector
    pd = pm.createData()
    if pm.nq != model.n or pm.nv != model.n:
        raise ValueError('the benchmark robot must have one revolute/prismatic Pinocchio joint per joint')
    lo = np.where(np.isfinite(model.position_lower), model.position_lower, -np.pi)
    hi = np.where(np.isfinite(model.position_upper), model.position_upper, np.pi)
    q = rng.uniform(lo, hi, (N, model.n))
    qd = rng.uniform(-1.5, 1.5, (N, model.n))
    qdd = rng.uniform(-3, 3, (N, model.n))
    Mlist, Glist, Slist = modern_robotics_lists(model)
    g = model.gravity_vector
    k = min(N, mr_states)

    if op == 'inverse_dynamics':
        args = (q[0], qd[0], qdd[0]) if N == 1 else (q, qd, qdd)
        ours = lambda: model.inverse_dynamics(*args)  # noqa: E731
        ours_py = lambda: py.inverse_dynamics(*args)  # noqa: E731

        def vect():
            return rnea.inverse_dynamics_vectorized(model, *args)
        if N == 1:
            pino = lambda: pin.rnea(pm, pd, q[0], qd[0], qdd[0])  # noqa: E731
        else:
            def pino():
                return [pin.rnea(pm, pd, q[i], qd[i], qdd[i]).copy() for i in range(N)]

        def mrob():
            return [mr.InverseDynamics(q[i], qd[i], qdd[i], g, np.zeros(6), Mlist, Glist, Slist) for i in range(k)]
    else:
        args = q[0] if N == 1 else q
        ours = lambda: model.gravity(args)  # noqa: E731
        ours_py = lambda: py.gravity(args)  # noqa: E731

        def vect():
            return rnea.gravity_vectorized(model, args)
        if N == 1:
            pino = lambda: pin.computeGeneralizedGravity(pm, pd, q[0])  # noqa: E731
        else:
            def pino():
                return [pin.computeGeneralizedGravity(pm, pd, q[i]).copy() for i in range(N)]

        def mrob():
            return [mr.GravityForces(q[i], g, Mlist, Glist, Slist) for i in range(k)]
    fns = {'lie_dynamics': (ours, N), 'lie_dynamics_python': (ours_py, N),
           'lie_dynamics_vectorised': (vect, N), 'pinocchio': (pino, N),
           'modern_robotics': (mrob, k)}
    # same torques from everyone (MR on its subset) before anything is timed
    ref = np.array(pino()).reshape(N, model.n)
    worst = {}
    for impl, (fn, states) in fns.items():
        out = np.array(fn()).reshape(states, model.n)
        err = np.max(np.abs(out - ref[:states])) / max(1.0, np.max(np.abs(ref)))
        if err > 1e-9:
            raise AssertionError(f'{impl} {op} disagrees with Pinocchio: relative error {err:.2e}')
        worst[impl] = float(err)
    return fns, worst


def run(quick=False, urdf=None, rounds=None, sizes=SIZES, seed=0):
    """Time everything; returns a dict with 'meta' and 'rows' (one row per op, N, impl)."""
    from lie_dynamics import load_urdf

    urdf = urdf or default_urdf()
    with open(urdf, encoding='utf-8') as fh:
        xml = fh.read()
    model = load_urdf(xml)
    rounds = rounds or (5 if quick else 15)
    target = 0.004 if quick else 0.02
    mr_states = 20 if quick else 100
    rng = np.random.default_rng(seed)
    rows, accuracy = [], {}
    for op in ('inverse_dynamics', 'gravity'):
        for N in sizes:
            fns, worst = _build(model, xml, op, N, rng, mr_states)
            accuracy[f'{op} N={N}'] = worst
            # interleaved: each round times every implementation once
            secs = common.time_interleaved({impl: fn for impl, (fn, _) in fns.items()}, rounds, target)
            per_state = {impl: secs[impl] / fns[impl][1] * 1e6 for impl in fns}
            pin_rounds = np.array(per_state['pinocchio'])
            for impl in fns:
                ts = np.array(per_state[impl])
                states = fns[impl][1]
                rows.append(dict(
                    op=op, N=N, impl=impl, us_per_state=float(np.median(ts)),
                    us_per_call=float(np.median(ts) * N),
                    ratio_to_pinocchio=float(np.median(ts / pin_rounds)),
                    spread=float((np.percentile(ts, 75) - np.percentile(ts, 25)) / np.median(ts)),
                    states_timed=states, estimated=states < N))
    import pinocchio as pin
    meta = dict(robot=model.name, urdf=os.path.relpath(urdf, ROOT) if urdf.startswith(ROOT) else os.path.basename(urdf),
                dof=model.n, rounds=rounds, native=_native_on(model), quick=quick, python=platform.python_version(),
                numpy=np.__version__, pinocchio=pin.__version__, machine=platform.machine(),
                cpu_count=os.cpu_count(), max_relative_error_vs_pinocchio=accuracy,
                unit='microseconds (median over rounds); ratio = median of per-round ratios to Pinocchio')
    return dict(meta=meta, rows=rows)


def _native_on(model):
    from lie_dynamics.codegen import runtime
    from lie_dynamics.codegen.traced import rnea
    return runtime.native(model, rnea.INVERSE_DYNAMICS) is not None


# ------------------------------------------------------------------ reports
def _lookup(result):
    return {(r['op'], r['N'], r['impl']): r for r in result['rows']}


def markdown(result):
    """The table: one line per (op, N), per-state times and ratios to Pinocchio."""
    meta, by = result['meta'], _lookup(result)
    ops = sorted({r['op'] for r in result['rows']}, key=['inverse_dynamics', 'gravity'].index)
    sizes = sorted({r['N'] for r in result['rows']})
    head = ['op', 'N', 'lie_dynamics µs/call', 'lie_dynamics µs/state', 'Pinocchio µs/state',
            'lie_dynamics / Pinocchio', 'Python kernels µs/state', 'Python kernels / Pinocchio',
            'vectorised (before) µs/state', 'before / Pinocchio', 'Modern Robotics µs/state', 'MR / Pinocchio']
    lines = [f"# Core benchmark: {meta['robot']} ({meta['dof']} DoF)", '',
             f"Median over {meta['rounds']} interleaved rounds; ratios are medians of per-round ratios "
             f"(same run). Batches: one lie_dynamics call; Pinocchio and Modern Robotics in a Python loop. "
             f"lie_dynamics: the native C kernels where a C compiler works (else the Python kernels, "
             f"native: {meta.get('native')}); Python kernels: the same model with the native backend off. "
             f"Python {meta['python']}, numpy {meta['numpy']}, Pinocchio {meta['pinocchio']}, "
             f"{meta['cpu_count']} cores.", '',
             '| ' + ' | '.join(head) + ' |', '|' + '---|' * len(head)]
    for op in ops:
        for N in sizes:
            o, y, v, p, m = (by[(op, N, i)] for i in IMPLS)
            est = ' (est.)' if m['estimated'] else ''
            lines.append(f"| {op} | {N} | {o['us_per_call']:.1f} | {o['us_per_state']:.3g} | "
                         f"{p['us_per_state']:.3g} | {o['ratio_to_pinocchio']:.2f} | {y['us_per_state']:.3g} | "
                         f"{y['ratio_to_pinocchio']:.2f} | {v['us_per_state']:.3g} | "
                         f"{v['ratio_to_pinocchio']:.1f} | {m['us_per_state']:.4g}{est} | "
                         f"{m['ratio_to_pinocchio']:.0f} |")
    lines += ['', 'Max relative torque difference to Pinocchio (checked before timing): ' +
              ', '.join(f"{k}: {max(v.values()):.1e}" for k, v in meta['max_relative_error_vs_pinocchio'].items())]
    return '\n'.join(lines) + '\n'


def write(result, out_dir):
    common.write_tables(out_dir, 'core', markdown(result), result, result['rows'])
    plot(result, os.path.join(out_dir, 'core.png'))


def plot(result, path):
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    by = _lookup(result)
    sizes = sorted({r['N'] for r in result['rows']})
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2), sharey=True)
    width = 0.8 / len(IMPLS)
    for ax, op in zip(axes, ('inverse_dynamics', 'gravity')):
        x = np.arange(len(sizes))
        for k, impl in enumerate(IMPLS):
            vals = [by[(op, N, impl)]['us_per_state'] for N in sizes]
            ax.bar(x + (k - (len(IMPLS) - 1) / 2) * width, vals, width, label=LABELS[impl])
        ax.set_xticks(x, [f'N = {N:,}' for N in sizes])
        ax.set_yscale('log')
        ax.set_title(op.replace('_', ' '))
        ax.grid(axis='y', which='both', alpha=0.3)
    axes[0].set_ylabel('µs per state (median)')
    axes[0].legend(fontsize=8)
    fig.suptitle(f"{result['meta']['robot']}: time per state (lower is better)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('--quick', action='store_true', help='fewer rounds and shorter measurements')
    ap.add_argument('--json', action='store_true', help='also print the results as JSON')
    ap.add_argument('--urdf', help='robot to time (default: config/arm7.urdf)')
    ap.add_argument('--out', default=os.path.join(HERE, 'out'), help='output directory')
    args = ap.parse_args(argv)
    result = run(quick=args.quick, urdf=args.urdf)
    write(result, args.out)
    print(markdown(result))
    if args.json:
        print(json.dumps(result))
    return 0


if __name__ == '__main__':
    sys.exit(main())
