"""Native kernels: compile time of each kernel family at first use, load time from the cache,
and the call time beside Pinocchio, kernels cut into parts (crender.py) against one function.

    python -m bench.compile [--quick] [--parts 250,500,500:-O2,none:-O2] [--robots arm7,ur5] [--out DIR]
    python -m bench.compile --chains 8,12,16      (derivative kernels of random chains)
    python -m bench --only compile

For the bundled arm, the Panda (fingers folded), UR5 and Talos left arm, each family is built
in a fresh temporary cache: `first use` is the first runtime.native call (trace, render,
compile, load), `compile` the C compiler's wall time in it (native.compile_seconds). `load`
is the same call in a new process that finds the library cached (the model already loaded).
The same families are then built as before the cut (one function each, -O2:
THRESHOLDS['native_part'] = None), and the two bound kernels and Pinocchio are timed per
call, one state, in interleaved rounds (ratios: medians of per-round ratios); --parts
compares other part sizes and optimisation levels the same way. --quick: the arm only, no
build before the cut. --chains: compile time against kernel size beyond the arm (what THRESHOLDS['native_nodes']
rests on), and the native kernel against the Python kernels per state. The 1-minute load
average is printed (2 cores: above ~0.5 the wall times include waiting for other work; the
compiler's CPU time much less so).
"""
import argparse
import json
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time
import warnings

import numpy as np

from bench import common

FAMILIES = ('inverse_dynamics', 'gravity', 'mass_matrix', 'forward_dynamics', 'aba', 'regressor',
            'inverse_dynamics_derivatives', 'coriolis', 'forward_dynamics_derivatives')
ROBOTS = ('arm7', 'panda', 'ur5', 'talos_arm')
_CONFIGURED = {}   # the kernel flags as configured, before any variant changed them


def _restore_cache_dir(saved):
    """$LIE_DYNAMICS_CACHE_DIR as it was before a measurement (None: unset)."""
    if saved is None:
        os.environ.pop('LIE_DYNAMICS_CACHE_DIR', None)
    else:
        os.environ['LIE_DYNAMICS_CACHE_DIR'] = saved


def _specs():
    from lie_dynamics.codegen.traced import aba, cholesky, crba, derivatives, regressor, rnea
    return {'inverse_dynamics': rnea.INVERSE_DYNAMICS, 'gravity': rnea.GRAVITY, 'mass_matrix': crba.MASS_MATRIX,
            'forward_dynamics': cholesky.FORWARD_DYNAMICS, 'aba': aba.ABA, 'regressor': regressor.REGRESSOR,
            'inverse_dynamics_derivatives': derivatives.INVERSE_DYNAMICS_DERIVATIVES,
            'coriolis': derivatives.CORIOLIS, 'forward_dynamics_derivatives': derivatives.FORWARD_DYNAMICS_DERIVATIVES}


def _robot(label):
    """(xml, load_urdf keywords, Pinocchio model of the same joints)."""
    import pinocchio as pin
    from bench import robots
    if label == 'arm7':
        xml = common.arm_xml()
        return xml, {}, pin.buildModelFromXML(xml)
    rel = {'panda': robots.ROBOTS[0], 'ur5': robots.ROBOTS[1], 'talos_arm': robots.ROBOTS[2]}[label]
    with open(os.path.join(robots.robot_dir(), rel), encoding='utf-8') as fh:
        xml = fh.read()
    pm = pin.buildModelFromXML(xml)
    if label != 'panda':
        return xml, {}, pm
    locked = [pm.getJointId(j) for j in robots.FINGERS]
    return xml, dict(joints=robots.PANDA_ARM), pin.buildReducedModel(pm, locked, pin.neutral(pm))


def _load(xml, kw):
    from lie_dynamics import load_urdf
    with warnings.catch_warnings():
        warnings.simplefilter('ignore')   # vendor inertias are warned about
        return load_urdf(xml, **kw)


def _cpu():
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def _build(model):
    """{family: (bound kernel, first-use s, compile s, compiler CPU s)} in the current cache folder."""
    from lie_dynamics.codegen import native, runtime
    out = {}
    for fam, spec in _specs().items():
        c0, u0, t0 = native.compile_seconds(), _cpu(), time.perf_counter()
        fn = runtime.native(model, spec)
        out[fam] = (fn, time.perf_counter() - t0, native.compile_seconds() - c0, _cpu() - u0)
    return out


def _load_child(label, variant):
    """In a new process with the cache filled: seconds of each family's first runtime.native."""
    from lie_dynamics.codegen import native, runtime
    _with(variant, os.environ['LIE_DYNAMICS_CACHE_DIR'])
    xml, kw, _ = _robot(label)
    model = _load(xml, kw)
    t0 = time.perf_counter()
    native.module()
    res = {'call module': time.perf_counter() - t0}
    for fam, spec in _specs().items():
        c0, t0 = native.compile_count(), time.perf_counter()
        ok = runtime.native(model, spec) is not None
        res[fam] = time.perf_counter() - t0 if ok and native.compile_count() == c0 else None
    print(json.dumps(res))


def _pin_calls(pm, pd, q, qd, qdd, tau):
    import pinocchio as pin
    return {'inverse_dynamics': lambda: pin.rnea(pm, pd, q, qd, qdd),
            'gravity': lambda: pin.computeGeneralizedGravity(pm, pd, q),
            'mass_matrix': lambda: pin.crba(pm, pd, q),
            'forward_dynamics': lambda: pin.aba(pm, pd, q, qd, tau),
            'aba': lambda: pin.aba(pm, pd, q, qd, tau),
            'regressor': lambda: pin.computeJointTorqueRegressor(pm, pd, q, qd, qdd),
            'inverse_dynamics_derivatives': lambda: pin.computeRNEADerivatives(pm, pd, q, qd, qdd),
            'coriolis': lambda: pin.computeCoriolisMatrix(pm, pd, q, qd),
            'forward_dynamics_derivatives': lambda: pin.computeABADerivatives(pm, pd, q, qd, tau)}


def _arguments(fam, q, qd, qdd, tau):
    """The per-state arrays a family's native kernel takes."""
    if fam in ('gravity', 'mass_matrix'):
        return (q,)
    if fam == 'coriolis':
        return (q, qd)
    return (q, qd, tau if fam in ('forward_dynamics', 'aba', 'forward_dynamics_derivatives') else qdd)


def _nodes(model, spec):
    from lie_dynamics.codegen import runtime
    trace = spec.build(runtime.frames(model))
    g, outputs = trace.graph, trace.outputs
    return len(g.live(outputs)[1])


def _parse(variant):
    """'500' or 'none', optionally ':-O2' (another optimisation level) -> (part, level)."""
    part, _, level = str(variant).partition(':')
    return (None if part.strip().lower() == 'none' else int(part)), (level.strip() or None)


def _label(variant):
    part, level = _parse(variant)
    return ('one function' if part is None else f'parts of {part}') + (f', {level}' if level else '')


def _with(variant, cache):
    """Set the part size, the kernels' optimisation level and the cache folder, and forget every
    kernel built so far."""
    from lie_dynamics.codegen import native, runtime
    part, level = _parse(variant)
    os.environ['LIE_DYNAMICS_CACHE_DIR'] = cache
    runtime.THRESHOLDS['native_part'] = part
    base = _CONFIGURED.setdefault('flags', native.KERNEL_FLAGS)
    native.KERNEL_FLAGS = ((level,) + base[1:]) if level else base
    runtime.clear()


def _robot_rows(label, parts, work, rounds, quick):
    """One row per family: first use, compile and load with parts[0]; compile and call time with
    every variant in `parts` (_parse), the calls timed interleaved with Pinocchio."""
    xml, kw, pm = _robot(label)
    builds = {}
    for k, part in enumerate(parts):
        _with(part, os.path.join(work, f'{label}-{k}'))
        builds[part] = _build(_load(xml, kw))
        if k == 0:   # load from this cache in a new process
            env = dict(os.environ, PYTHONPATH=os.pathsep.join([common.ROOT, os.environ.get('PYTHONPATH', '')]))
            r = subprocess.run([sys.executable, '-m', 'bench.compile', '--load-child', label, '--parts', part], env=env,
                               capture_output=True, text=True, check=True)
            loads = json.loads(r.stdout.strip().splitlines()[-1])
    model = _load(xml, kw)
    pm.gravity.linear = model.gravity_vector
    pd = pm.createData()
    q, qd, qdd = (x[0] for x in common.random_states(model, 1, seed=1))
    tau = model.inverse_dynamics(q, qd, qdd)
    peers = _pin_calls(pm, pd, q, qd, qdd, tau)
    rows = []
    for fam, spec in _specs().items():
        fn, first = builds[parts[0]][fam][:2]
        row = dict(robot=label, family=fam, nodes=_nodes(model, spec), first_s=first,
                   load_ms=None if loads[fam] is None else loads[fam] * 1e3, loadavg=os.getloadavg()[0])
        for part in parts:
            row[f'compile_s[{part}]'], row[f'cpu_s[{part}]'] = builds[part][fam][2:]
        if fn is not None:
            args = _arguments(fam, q, qd, qdd, tau)
            fns = {part: (lambda f=builds[part][fam][0]: f(*args)) for part in parts}
            t = common.time_interleaved({**fns, 'pin': peers[fam]}, rounds, 0.002 if quick else 0.02)
            row['us'] = float(np.median(t[parts[0]])) * 1e6
            for part in parts:
                row[f'ratio_pin[{part}]'] = float(np.median(t[part] / t['pin']))
                if part != parts[-1]:
                    row[f'over_last[{part}]'] = float(np.median(t[part] / t[parts[-1]]))
        rows.append(row)
    return rows


def run(quick=False, out=None, rounds=None, parts=None, robots=None):
    """The robots' table (module docstring); parts: variants to compare (_parse; default: the
    configured part size and level, and one function at -O2 as before the cut; --quick: the
    configured one). The first is the one whose first use and load are measured; call times
    are also given relative to the last."""
    from lie_dynamics.codegen import native, runtime
    if native.module() is None:
        print('no working C compiler: nothing to measure')
        return []
    saved = (os.environ.get('LIE_DYNAMICS_CACHE_DIR'), runtime.THRESHOLDS['native_part'], native.KERNEL_FLAGS)
    parts = [str(p) for p in parts or ([saved[1]] if quick else [saved[1], 'none:-O2'])]
    rounds = rounds or (3 if quick else 15)
    load_before = os.getloadavg()[0]
    rows = []
    work = tempfile.mkdtemp(prefix='bench_compile_')
    try:
        for label in robots or (ROBOTS[:1] if quick else ROBOTS):
            rows += _robot_rows(label, parts, work, rounds, quick)
    finally:
        _restore_cache_dir(saved[0])
        runtime.THRESHOLDS['native_part'] = saved[1]
        native.KERNEL_FLAGS = _CONFIGURED.get('flags', saved[2])
        runtime.clear()
        shutil.rmtree(work, ignore_errors=True)
    meta = dict(load_before=load_before, load_after=os.getloadavg()[0], rounds=rounds, quick=quick,
                parts=parts, native_nodes=runtime.THRESHOLDS['native_nodes'], flags=' '.join(native.KERNEL_FLAGS))
    md = markdown(rows, meta)
    print(md)
    if out:
        common.write_tables(out, 'compile', md, dict(rows=rows, meta=meta), rows,
                            fields=list(dict.fromkeys(k for r in rows for k in r)))
    return rows


def markdown(rows, meta):
    def f(v, fmt):
        return '–' if v is None else format(v, fmt)
    parts = meta['parts']
    head = ['robot', 'family', 'nodes', 'first use s', 'load ms'] + \
        [f'{_label(p)}: compile s (CPU s)' for p in parts] + [f'{_label(p)}: kernel / Pinocchio' for p in parts] + \
        [f'{_label(p)} / {_label(parts[-1])}' for p in parts[:-1]]
    L = [f"Native kernels: first use in a fresh cache (trace, render, compile, load; {_label(parts[0])}) and "
         f"load from it in a new process; compile wall time (compiler CPU time); the bound kernel "
         f"called directly (one state, no Model-method checks) against Pinocchio, {meta['rounds']} interleaved "
         f"rounds. Kernel flags {meta['flags']}. 1-minute load average {meta['load_before']:.2f} before, "
         f"{meta['load_after']:.2f} after.", '',
         '| ' + ' | '.join(head) + ' |', '|' + '---|' * 2 + '---:|' * (len(head) - 2)]
    for r in rows:
        cells = [r['robot'], r['family'], str(r['nodes']), f(r['first_s'], '.2f'), f(r['load_ms'], '.1f')]
        cells += [f"{r[f'compile_s[{p}]']:.2f} ({r[f'cpu_s[{p}]']:.2f})" for p in parts]
        cells += [f(r.get(f'ratio_pin[{p}]'), '.2f') for p in parts]
        cells += [f(r.get(f'over_last[{p}]'), '.3f') for p in parts[:-1]]
        L.append('| ' + ' | '.join(cells) + ' |')
    return '\n'.join(L) + '\n'


def chains(sizes, out=None):
    """Derivative kernels of random chains (bench.common.robot_urdf) with THRESHOLDS['native_nodes']
    lifted: nodes, compile wall and CPU time, and per state the native kernel against the Python
    kernels (the same model with the native backend off) at N = 1 and 1,000."""
    from lie_dynamics import load_urdf
    from lie_dynamics.codegen import native, runtime
    from lie_dynamics.codegen.traced import derivatives as d
    saved = (os.environ.get('LIE_DYNAMICS_CACHE_DIR'), runtime.THRESHOLDS['native_nodes'])
    work = tempfile.mkdtemp(prefix='bench_compile_')
    rows = []
    try:
        runtime.THRESHOLDS['native_nodes'] = 10 ** 9
        for n in sizes:
            _with(runtime.THRESHOLDS['native_part'], os.path.join(work, str(n)))
            model = load_urdf(common.robot_urdf(n))
            py = common.python_kernels(model)
            for fam, spec in (('inverse_dynamics_derivatives', d.INVERSE_DYNAMICS_DERIVATIVES),
                              ('forward_dynamics_derivatives', d.FORWARD_DYNAMICS_DERIVATIVES)):
                c0, u0 = native.compile_seconds(), _cpu()
                if runtime.native(model, spec) is None:
                    continue
                row = dict(n=n, family=fam, nodes=_nodes(model, spec), compile_s=native.compile_seconds() - c0,
                           cpu_s=_cpu() - u0, loadavg=os.getloadavg()[0])
                for N in (1, 1000):
                    q, qd, qdd = common.random_states(model, N, seed=1)
                    if N == 1:
                        q, qd, qdd = q[0], qd[0], qdd[0]
                    if fam.startswith('forward'):
                        tau = model.inverse_dynamics(q, qd, qdd)
                        calls = {m: (lambda m=m: m.forward_dynamics_derivatives(q, qd, tau)) for m in (model, py)}
                    else:
                        calls = {m: (lambda m=m: m.inverse_dynamics_derivatives(q, qd, qdd)) for m in (model, py)}
                    t = common.time_interleaved({'native': calls[model], 'python': calls[py]}, 5, 0.05)
                    row[f'native_us[{N}]'] = float(np.median(t['native'])) / N * 1e6
                    row[f'python_us[{N}]'] = float(np.median(t['python'])) / N * 1e6
                rows.append(row)
                print(json.dumps(row), flush=True)
    finally:
        _restore_cache_dir(saved[0])
        runtime.THRESHOLDS['native_nodes'] = saved[1]
        runtime.clear()
        shutil.rmtree(work, ignore_errors=True)
    L = [f"Derivative kernels of random chains, parts of {runtime.THRESHOLDS['native_part']} nodes "
         "(µs per state: native / Python kernels).", '',
         '| joints | family | nodes | compile s (CPU s) | load avg | N = 1 | N = 1000 |',
         '|---:|---|---:|---:|---:|---:|---:|']
    for r in rows:
        L.append(f"| {r['n']} | {r['family']} | {r['nodes']} | {r['compile_s']:.2f} ({r['cpu_s']:.2f}) | "
                 f"{r['loadavg']:.2f} | {r['native_us[1]']:.1f} / {r['python_us[1]']:.0f} | "
                 f"{r['native_us[1000]']:.1f} / {r['python_us[1000]']:.1f} |")
    md = '\n'.join(L) + '\n'
    print(md)
    if out:
        common.write_tables(out, 'compile_chains', md, dict(rows=rows), rows)
    return rows


def main(argv=None):
    ap = argparse.ArgumentParser(prog='python -m bench.compile', description=' '.join(__doc__.split('\n\n')[0].split()))
    ap.add_argument('--quick', action='store_true', help='the arm only, the configured variant only, 3 rounds')
    ap.add_argument('--out', default=None, help='also write compile.md/.csv/.json into this folder')
    ap.add_argument('--parts', help="variants to compare: part sizes, 'none' for one function, each optionally "
                                    "with another optimisation level, e.g. 500,500:-O2,1000,none:-O2 (default: the "
                                    "configured THRESHOLDS['native_part'], and none:-O2, the kernels before the cut)")
    ap.add_argument('--robots', help=f"comma-separated, from {','.join(ROBOTS)}")
    ap.add_argument('--chains', help='instead: derivative kernels of random chains of these joint counts')
    ap.add_argument('--load-child', metavar='ROBOT', help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.load_child:
        _load_child(args.load_child, args.parts)
    elif args.chains:
        chains([int(n) for n in args.chains.split(',')], out=args.out)
    else:
        parts = args.parts.split(',') if args.parts else None
        run(quick=args.quick, out=args.out, parts=parts, robots=args.robots.split(',') if args.robots else None)


if __name__ == '__main__':
    main()
