"""In-process before/after benchmark: the old and the new lie_dynamics timed in the same rounds.

    python -m bench.probes.ab BEFORE_SRC [--rounds R] [--quick] [--out DIR] [--threshold 5]

Why. `python -m bench.compare` pairs two separate benchmark runs, one per checkout. On a
shared 2-core machine the load changes between those runs, so even unchanged code moves by
10-20 % per row. Here both versions live in ONE process: BEFORE_SRC (the root of another
checkout of this repository, the folder that holds `lie_dynamics/`) is imported under the
module name `lie_dynamics_before`, the current tree is the ordinary `import lie_dynamics`,
and every row times before, after and Pinocchio in interleaved rounds (the order rotates
each round). A busy second hits the three alike, and each round's after/before ratio
compares calls made milliseconds apart.

Typical use, comparing the working tree against a commit:

    git worktree add /tmp/before <commit>
    python -m bench.probes.ab /tmp/before [--quick]
    git worktree remove /tmp/before

Rows: on the bundled arm every public call that exists in both versions (inverse dynamics,
gravity, mass matrix, Coriolis matrix by Christoffel symbols and recursively, the Christoffel
symbols, forward dynamics by Cholesky and ABA, the derivatives of inverse and forward
dynamics, the regressor), for one state and a batch of N = 1000 states (inverse dynamics and
gravity also 100 and 10 000); on real robots of example-robot-data (Panda with its fingers
fixed, UR5, Talos left arm) one state of inverse dynamics, gravity, mass matrix and forward
dynamics. Both versions get the same URDF text and the same states. Before anything is timed,
both versions' outputs are compared: a call the old version lacks (AttributeError, TypeError,
an unknown method name) is skipped with a note, and a row whose outputs differ is reported
and not timed (exit status 1).

Timing: each sample repeats the call until it takes ~2.5-5 ms (bench.common.calibrate);
rounds take one sample of before, after and Pinocchio (a Python loop over the states for
batches, outputs not copied); the tables show medians over rounds, in µs per state, and
the medians of per-round ratios, with the 10-90 % range of after/before. Rows whose median
after/before exceeds 1 + threshold/100 are marked slower. Single-threaded BLAS.

Writes DIR/ab.md, DIR/ab.json and DIR/ab.png (after/before per row with its range; default
DIR bench/out) and prints the table.
"""
import argparse
import importlib.util
import os
import platform
import subprocess
import sys
import time
import types
import warnings

# Single-threaded BLAS, as in bench/lagrangian.py: a multi-threaded OpenBLAS on a shared 2-core
# machine makes small products vary by 10-100x from call to call.
for _var in ('OPENBLAS_NUM_THREADS', 'OMP_NUM_THREADS', 'MKL_NUM_THREADS'):
    os.environ.setdefault(_var, '1')

import numpy as np  # noqa: E402

import lie_dynamics as after_pkg  # noqa: E402
from bench import common  # noqa: E402
from bench.common import HERE, ROOT  # noqa: E402  (bench/ and the repository root)
BEFORE_NAME = 'lie_dynamics_before'
VERSIONS = ('before', 'after', 'pinocchio')
TARGET = 0.0025          # seconds per sample: calibrate doubles the repeat count up to 2.5-5 ms
TARGET_QUICK = 0.001
ROUNDS = 61
ROUNDS_QUICK = 5
AGREE_RTOL = 1e-8        # max |after - before| / max |before|
SKIP = (AttributeError, TypeError, ValueError, NotImplementedError)

# (key, Model method, keyword arguments, argument names, Pinocchio function, its argument names)
OPS = {
    'inverse_dynamics': ('inverse_dynamics', {}, ('q', 'qd', 'qdd'), 'rnea', ('q', 'qd', 'qdd')),
    'gravity': ('gravity', {}, ('q',), 'computeGeneralizedGravity', ('q',)),
    'mass_matrix': ('mass_matrix', {}, ('q',), 'crba', ('q',)),
    'coriolis_matrix (christoffel)': ('coriolis_matrix', {'method': 'christoffel'}, ('q', 'qd'),
                                      'computeCoriolisMatrix', ('q', 'qd')),
    'coriolis_matrix (recursive)': ('coriolis_matrix', {'method': 'recursive'}, ('q', 'qd'),
                                    'computeCoriolisMatrix', ('q', 'qd')),
    'christoffel': ('christoffel', {}, ('q',), 'computeCoriolisMatrix', ('q', 'qd')),
    'forward_dynamics (cholesky)': ('forward_dynamics', {'method': 'cholesky'}, ('q', 'qd', 'tau'),
                                    'aba', ('q', 'qd', 'tau')),
    'forward_dynamics (aba)': ('forward_dynamics', {'method': 'aba'}, ('q', 'qd', 'tau'), 'aba', ('q', 'qd', 'tau')),
    'inverse_dynamics_derivatives': ('inverse_dynamics_derivatives', {}, ('q', 'qd', 'qdd'),
                                     'computeRNEADerivatives', ('q', 'qd', 'qdd')),
    'forward_dynamics_derivatives': ('forward_dynamics_derivatives', {}, ('q', 'qd', 'tau'),
                                     'computeABADerivatives', ('q', 'qd', 'tau')),
    'regressor': ('regressor', {}, ('q', 'qd', 'qdd'), 'computeJointTorqueRegressor', ('q', 'qd', 'qdd')),
}
BATCH = 1000
ARM_ROWS = [(op, (1, 100, BATCH, 10_000) if op in ('inverse_dynamics', 'gravity') else (1, BATCH)) for op in OPS]
ARM_ROWS_QUICK = [('inverse_dynamics', (1, 100)), ('gravity', (1,)), ('mass_matrix', (1,)),
                  ('forward_dynamics (aba)', (1,))]
ROBOT_OPS = ('inverse_dynamics', 'gravity', 'mass_matrix', 'forward_dynamics (cholesky)')
ROBOT_OPS_QUICK = ('inverse_dynamics',)


# ------------------------------------------------------------------ the two packages
def load_before(src, name=BEFORE_NAME):
    """The lie_dynamics package of the checkout at `src`, imported as module `name`.

    The math core imports its own modules relatively, so the copy binds to itself; checked
    here (distinct module objects) and again after the run by `check_isolated`.
    """
    pkg_dir = os.path.join(os.path.abspath(src), 'lie_dynamics')
    init = os.path.join(pkg_dir, '__init__.py')
    if not os.path.isfile(init):
        raise FileNotFoundError(f'{src}: no lie_dynamics/__init__.py (give the root of a checkout of this repository)')
    loaded = sys.modules.get(name)
    if loaded is not None and os.path.samefile(getattr(loaded, '__file__', '') or os.devnull, init):
        return loaded
    for key in [k for k in sys.modules if k == name or k.startswith(name + '.')]:
        del sys.modules[key]   # a copy from another checkout: replace it
    spec = importlib.util.spec_from_file_location(name, init, submodule_search_locations=[pkg_dir])
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    try:
        spec.loader.exec_module(module)
    except BaseException:
        del sys.modules[name]
        raise
    assert module is not after_pkg and module.Model is not after_pkg.Model, 'before and after are the same module'
    assert module.load_urdf.__module__.startswith(name + '.'), module.load_urdf.__module__
    assert os.path.samefile(after_pkg.__file__, os.path.join(ROOT, 'lie_dynamics', '__init__.py')), \
        f'lie_dynamics is imported from {after_pkg.__file__}, not from this tree'
    return module


def check_isolated(before, name=BEFORE_NAME):
    """Every loaded module of the old copy comes from its own folder and holds no object of the
    new package (an absolute `lie_dynamics` import in the old code would mix the versions)."""
    pkg_dir = os.path.dirname(os.path.abspath(before.__file__))
    mods = {k: m for k, m in list(sys.modules.items()) if k == name or k.startswith(name + '.')}
    for key, mod in mods.items():
        path = getattr(mod, '__file__', None)
        if path and not os.path.abspath(path).startswith(pkg_dir + os.sep):
            raise AssertionError(f'{key} was loaded from {path}, outside {pkg_dir}')
        for attr, value in vars(mod).items():
            owner = value.__name__ if isinstance(value, types.ModuleType) else getattr(value, '__module__', None)
            if isinstance(owner, str) and (owner == 'lie_dynamics' or owner.startswith('lie_dynamics.')):
                raise AssertionError(f'{key}.{attr} is {owner} of the new package')
    return len(mods)


def _commit(path):
    """Short commit hash of the checkout at path (read-only git), or None."""
    try:
        res = subprocess.run(['git', '-C', path, 'rev-parse', '--short', 'HEAD'], capture_output=True, text=True,
                             timeout=10, check=False)
    except (OSError, subprocess.SubprocessError):
        return None
    return res.stdout.strip() or None


# ------------------------------------------------------------------ timing
def _flat(x):
    """One float vector of a call's output (arrays, or tuples of arrays)."""
    if isinstance(x, (tuple, list)):
        return np.concatenate([np.ravel(np.asarray(a, float)) for a in x])
    return np.ravel(np.asarray(x, float))


def _calls(models, pin_setup, op, states, N):
    """{version: callable} of one row: before/after one call (a batch for N > 1), Pinocchio per state."""
    method, kwargs, names, pname, pnames = OPS[op]
    args = tuple(states[a][0] if N == 1 else states[a] for a in names)
    out = {}
    for version in ('before', 'after'):
        fn = getattr(models[version], method)   # AttributeError: the version lacks it
        out[version] = (lambda f=fn: f(*args, **kwargs))
    pin, pm, pd = pin_setup
    pfn = getattr(pin, pname)
    pstates = [tuple(states[a][i] for a in pnames) for i in range(N)]
    if N == 1:
        out['pinocchio'] = (lambda a=pstates[0]: pfn(pm, pd, *a))
    else:
        out['pinocchio'] = (lambda: [pfn(pm, pd, *a) for a in pstates])
    return out


def _row(robot, op, N, models, pin_setup, states, rounds, target, threshold):
    label = f'{robot}: {op}, N = {N}'
    row = dict(label=label, robot=robot, op=op, N=N, status='ok', note='')
    try:
        fns = _calls(models, pin_setup, op, states, N)
        b = _flat(fns['before']())        # also compiles the old version's kernels for this call
    except SKIP as exc:
        row.update(status='skipped', note=f'not in the before version: {type(exc).__name__}: {exc}')
        return row
    try:
        a = _flat(fns['after']())
        fns['pinocchio']()
    except Exception as exc:   # an error of the new version is a finding, reported
        row.update(status='error', note=f'after version failed: {type(exc).__name__}: {exc}')
        return row
    if a.shape != b.shape:
        row.update(status='disagree', note=f'output sizes differ: before {b.shape}, after {a.shape}')
        return row
    err = float(np.max(np.abs(a - b)) / max(np.max(np.abs(b)), np.finfo(float).tiny)) if b.size else 0.0
    row['max_rel_diff'] = err
    if not err <= AGREE_RTOL:
        row.update(status='disagree', note=f'before and after differ: max relative difference {err:.2e}')
        return row
    numbers = {}
    secs = common.time_interleaved(fns, rounds, target, rotate=True, pause_gc=True, numbers=numbers)
    us = {k: secs[k] / N * 1e6 for k in VERSIONS}
    ratio = secs['after'] / secs['before']
    med = float(np.median(ratio))
    row.update(
        before_us=float(np.median(us['before'])), after_us=float(np.median(us['after'])),
        pin_us=float(np.median(us['pinocchio'])),
        ratio=med, ratio_p10=float(np.percentile(ratio, 10)), ratio_p90=float(np.percentile(ratio, 90)),
        before_pin=float(np.median(secs['before'] / secs['pinocchio'])),
        after_pin=float(np.median(secs['after'] / secs['pinocchio'])),
        slower=med > 1 + threshold / 100, faster=med < 1 - threshold / 100,
        calls_per_sample={k: int(v) for k, v in numbers.items()},
        us_per_round={k: [float(x) for x in us[k]] for k in VERSIONS})
    return row


def _states(model, N, seed):
    q, qd, qdd = common.random_states(model, N, seed=seed)
    return dict(q=q, qd=qd, qdd=qdd, tau=model.inverse_dynamics(q, qd, qdd))


def _robots(quick):
    """(label, URDF text) of the real robots (example-robot-data); [] when it is not installed."""
    from bench import robots
    try:
        root = robots.robot_dir()
    except RuntimeError:
        return []
    out = []
    for rel, label in ((robots.ROBOTS[0], 'panda (fingers fixed)'), (robots.ROBOTS[1], 'ur5'),
                       (robots.ROBOTS[2], 'talos left arm')):
        path = os.path.join(root, rel)
        if not os.path.isfile(path):
            continue
        with open(path, encoding='utf-8') as fh:
            xml = fh.read()
        out.append((label, robots.fixed_fingers(xml) if label.startswith('panda') else xml))
    return out[1:2] if quick else out


def _models(before, xml):
    with warnings.catch_warnings():
        warnings.simplefilter('ignore')   # vendor files with odd inertias: warned about, not refused
        return {'before': before.load_urdf(xml), 'after': after_pkg.load_urdf(xml)}


def run(before_src, rounds=None, quick=False, threshold=5.0, log=print):
    """Load both versions, check and time every row; returns dict(meta=..., rows=[...])."""
    import pinocchio as pin

    t_start = time.perf_counter()
    before = load_before(before_src)
    rounds = rounds or (ROUNDS_QUICK if quick else ROUNDS)
    target = TARGET_QUICK if quick else TARGET
    with open(after_pkg.default_urdf_path(), encoding='utf-8') as fh:
        arm = fh.read()
    robots = [('arm7', arm, ARM_ROWS_QUICK if quick else ARM_ROWS)]
    ops = ROBOT_OPS_QUICK if quick else ROBOT_OPS
    robots += [(label, xml, [(op, (1,)) for op in ops]) for label, xml in _robots(quick)]
    rows, notes = [], []
    for robot, xml, plan in robots:
        try:
            models = _models(before, xml)
        except Exception as exc:   # one robot the old parser refuses must not stop the rest
            notes.append(f'{robot}: not loaded by both versions ({type(exc).__name__}: {exc})')
            continue
        model = models['after']
        try:
            pin_setup = common.pinocchio_model(xml, model)
        except ValueError:   # continuous joints or mimics: Pinocchio's coordinates differ from ours
            notes.append(f'{robot}: Pinocchio coordinates differ from ours, skipped')
            continue
        for op, Ns in plan:
            for N in Ns:
                row = _row(robot, op, N, models, pin_setup, _states(model, N, seed=N), rounds, target, threshold)
                rows.append(row)
                if row['status'] == 'ok':
                    log(f"[ab] {row['label']}: after/before {row['ratio']:.3f} "
                        f"({row['ratio_p10']:.2f}-{row['ratio_p90']:.2f})", flush=True)
                else:
                    log(f"[ab] {row['label']}: {row['status']}: {row['note']}", flush=True)
    isolated = check_isolated(before)
    meta = dict(before=os.path.basename(os.path.abspath(before_src).rstrip(os.sep)),
                before_commit=_commit(before_src), after_commit=_commit(ROOT),
                before_modules=isolated, rounds=rounds, target_s=target, threshold_pct=threshold, quick=quick,
                seconds=round(time.perf_counter() - t_start, 1), python=platform.python_version(),
                numpy=np.__version__, pinocchio=pin.__version__, machine=platform.machine(),
                cpu_count=os.cpu_count(), notes=notes,
                unit='µs per state, median over rounds; ratios: medians of per-round ratios')
    return dict(meta=meta, rows=rows)


# ------------------------------------------------------------------ reports
def markdown(result):
    meta, rows = result['meta'], result['rows']
    thr = meta['threshold_pct']
    before = meta['before'] + (f" ({meta['before_commit']})" if meta['before_commit'] else '')
    after = 'this tree' + (f" ({meta['after_commit']} + working changes, if any)" if meta['after_commit'] else '')
    lines = [f'# Before/after, one process: {before} against {after}', '',
             f"{meta['rounds']} interleaved rounds (before, after, Pinocchio; order rotated each round), "
             f"~{meta['target_s'] * 1e3:.1f}-{meta['target_s'] * 2e3:.1f} ms per sample. µs per state, medians over "
             'rounds; ratios are medians of per-round ratios, after/before with its 10-90 % range. '
             f"Marked: after/before above {1 + thr / 100:.2f} (slower) or below {1 - thr / 100:.2f} (faster). "
             f"Python {meta['python']}, numpy {meta['numpy']}, Pinocchio {meta['pinocchio']}, "
             f"{meta['cpu_count']} cores; {meta['seconds']:.0f} s.", '',
             '| row | before µs | after µs | Pinocchio µs | after / before (p10-p90) | before / Pin | after / Pin | |',
             '|---|---:|---:|---:|---:|---:|---:|---|']
    for r in rows:
        if r['status'] != 'ok':
            lines.append(f"| {r['label']} | | | | | | | {r['status']}: {r['note']} |")
            continue
        mark = '**slower**' if r['slower'] else ('faster' if r['faster'] else '')
        lines.append(f"| {r['label']} | {r['before_us']:.3g} | {r['after_us']:.3g} | {r['pin_us']:.3g} | "
                     f"{r['ratio']:.3f} ({r['ratio_p10']:.2f}-{r['ratio_p90']:.2f}) | {r['before_pin']:.2f} | "
                     f"{r['after_pin']:.2f} | {mark} |")
    ok = [r for r in rows if r['status'] == 'ok']
    lines += ['', f"{len(ok)} rows timed, {sum(r['slower'] for r in ok)} slower and {sum(r['faster'] for r in ok)} "
              f"faster by more than {thr:g} %; "
              f"{sum(r['status'] == 'skipped' for r in rows)} skipped, {sum(r['status'] == 'disagree' for r in rows)} "
              f"disagreeing, {sum(r['status'] == 'error' for r in rows)} failing."]
    if ok:
        lines.append(f"Before and after agree on every timed row (max relative difference "
                     f"{max(r['max_rel_diff'] for r in ok):.1e}, tolerance {AGREE_RTOL:g}).")
    lines += [f'- {n}' for n in meta['notes']]
    return '\n'.join(lines) + '\n'


def plot(result, path):
    plt = common.setup_matplotlib()
    rows = [r for r in result['rows'] if r['status'] == 'ok']
    thr = result['meta']['threshold_pct']
    fig, ax = plt.subplots(figsize=(9, 1.2 + 0.28 * max(1, len(rows))))
    y = np.arange(len(rows))[::-1]
    med = np.array([r['ratio'] for r in rows])
    err = np.array([[r['ratio'] - r['ratio_p10'] for r in rows], [r['ratio_p90'] - r['ratio'] for r in rows]])
    colors = ['tab:red' if r['slower'] else 'tab:green' if r['faster'] else 'tab:gray' for r in rows]
    ax.barh(y, med - 1, left=1, color=colors, height=0.7, xerr=err.reshape(2, -1), ecolor='k', capsize=2)
    for yi, r in zip(y, rows):
        ax.annotate(f"{r['ratio']:.3f}", (max(r['ratio_p90'], 1), yi), xytext=(4, 0), textcoords='offset points',
                    va='center', fontsize=6)
    ax.axvline(1, color='k', lw=1)
    ax.axvline(1 + thr / 100, color='tab:red', ls='--', lw=1, label=f'+{thr:g} %')
    ax.axvline(1 - thr / 100, color='tab:green', ls='--', lw=1, label=f'-{thr:g} %')
    ax.set_yticks(y, [r['label'] for r in rows], fontsize=7)
    ax.set_xlabel('after / before (median of per-round ratios; bars: 10-90 %)')
    ax.set_title(f"{result['meta']['before']} -> this tree, one process ({result['meta']['rounds']} rounds)")
    ax.legend(fontsize=7, loc='lower right')
    ax.grid(axis='x', alpha=0.3)
    fig.tight_layout()
    common.savefig(fig, path)


def write(result, out):
    common.write_tables(out, 'ab', markdown(result), result)
    plot(result, os.path.join(out, 'ab.png'))


def main(argv=None):
    ap = argparse.ArgumentParser(prog='python -m bench.probes.ab', description=__doc__.split('\n')[0])
    ap.add_argument('before', metavar='BEFORE_SRC', help='root of the other checkout (holds lie_dynamics/)')
    ap.add_argument('--rounds', type=int, help=f'interleaved rounds per row (default {ROUNDS}, quick {ROUNDS_QUICK})')
    ap.add_argument('--quick', action='store_true', help='few rounds and rows (a smoke test)')
    ap.add_argument('--out', default=os.path.join(HERE, 'out'), help='output folder (default bench/out)')
    ap.add_argument('--threshold', type=float, default=5.0, help='mark rows slower by more than this, %%')
    args = ap.parse_args(argv)
    result = run(args.before, rounds=args.rounds, quick=args.quick, threshold=args.threshold)
    write(result, args.out)
    print(markdown(result))
    return 1 if any(r['status'] in ('disagree', 'error') for r in result['rows']) else 0


if __name__ == '__main__':
    sys.exit(main())
