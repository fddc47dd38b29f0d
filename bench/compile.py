"""Native kernels: compile time of each kernel family at first use, load time from the cache,
and the call time beside Pinocchio, kernels cut into parts (crender.py) against one function.

    python -m bench.compile [--quick]        (python -m bench --only compile)

For the bundled arm, the Panda (fingers folded), UR5 and Talos left arm, each family is built
in a fresh temporary cache: `first use` is the first runtime.native call (trace, render,
compile, load), `compile` the C compiler's wall time in it (native.compile_seconds). `load`
is the same call in a new process that finds the library cached (the model already loaded).
The same families are then built as one function each (THRESHOLDS['native_part'] = None:
what every kernel was before the cut), and the two bound kernels and Pinocchio are timed
per call, one state, in interleaved rounds (ratios: medians of per-round ratios). --quick:
the arm only, no one-function build. The 1-minute load average is printed before and after
(2 cores: above ~0.5 the compile times include waiting for the other work).
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


def _load_child(label):
    """In a new process with the cache filled: seconds of each family's first runtime.native."""
    from lie_dynamics.codegen import native, runtime
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
    g, _, outputs = spec.build(runtime.frames(model))[0].trace
    return len(g.live(outputs)[1])


def run(quick=False, out=None, rounds=None):
    from lie_dynamics.codegen import native, runtime
    if native.module() is None:
        print('no working C compiler: nothing to measure')
        return []
    rounds = rounds or (3 if quick else 15)
    load_before = os.getloadavg()[0]
    rows, saved = [], (os.environ.get('LIE_DYNAMICS_CACHE_DIR'), runtime.THRESHOLDS['native_part'])
    work = tempfile.mkdtemp(prefix='bench_compile_')
    try:
        for label in ROBOTS[:1] if quick else ROBOTS:
            xml, kw, pm = _robot(label)
            builds = {}
            for variant, part in (('split', saved[1]), ('one', None))[:1 if quick else 2]:
                os.environ['LIE_DYNAMICS_CACHE_DIR'] = os.path.join(work, f'{label}-{variant}')
                runtime.THRESHOLDS['native_part'] = part
                runtime.clear()
                builds[variant] = _build(_load(xml, kw))
                if variant == 'split':
                    env = dict(os.environ, PYTHONPATH=os.pathsep.join([common.ROOT, os.environ.get('PYTHONPATH', '')]))
                    r = subprocess.run([sys.executable, '-m', 'bench.compile', '--load-child', label], env=env,
                                       capture_output=True, text=True, check=True)
                    loads = json.loads(r.stdout.strip().splitlines()[-1])
            runtime.THRESHOLDS['native_part'] = saved[1]
            model = _load(xml, kw)
            pm.gravity.linear = model.gravity_vector
            pd = pm.createData()
            q, qd, qdd = (x[0] for x in common.random_states(model, 1, seed=1))
            tau = model.inverse_dynamics(q, qd, qdd)
            peers = _pin_calls(pm, pd, q, qd, qdd, tau)
            for fam, spec in _specs().items():
                fn, first, comp, cpu = builds['split'][fam]
                row = dict(robot=label, family=fam, nodes=_nodes(model, spec), first_s=first, compile_s=comp, cpu_s=cpu,
                           load_ms=None if loads[fam] is None else loads[fam] * 1e3)
                if fn is not None:
                    fns = {'split': fn}
                    if 'one' in builds:
                        row.update(compile_one_s=builds['one'][fam][2], cpu_one_s=builds['one'][fam][3])
                        fns['one'] = builds['one'][fam][0]
                    fns['pin'] = peers[fam]
                    args = _arguments(fam, q, qd, qdd, tau)
                    t = common.time_interleaved({k: (lambda f=f: f(*args)) if k != 'pin' else f
                                                 for k, f in fns.items()}, rounds, 0.002 if quick else 0.02)
                    row.update(split_us=float(np.median(t['split'])) * 1e6,
                               ratio_pin=float(np.median(t['split'] / t['pin'])))
                    if 'one' in t:
                        row.update(ratio_pin_one=float(np.median(t['one'] / t['pin'])),
                                   split_over_one=float(np.median(t['split'] / t['one'])))
                rows.append(row)
    finally:
        if saved[0] is None:
            os.environ.pop('LIE_DYNAMICS_CACHE_DIR', None)
        else:
            os.environ['LIE_DYNAMICS_CACHE_DIR'] = saved[0]
        runtime.THRESHOLDS['native_part'] = saved[1]
        runtime.clear()
        shutil.rmtree(work, ignore_errors=True)
    meta = dict(load_before=load_before, load_after=os.getloadavg()[0], rounds=rounds, quick=quick,
                part=saved[1], native_nodes=runtime.THRESHOLDS['native_nodes'])
    md = markdown(rows, meta)
    print(md)
    if out:
        common.write_tables(out, 'compile', md, dict(rows=rows, meta=meta), rows,
                           fields=list(dict.fromkeys(k for r in rows for k in r)))
    return rows


def markdown(rows, meta):
    def f(v, fmt):
        return '–' if v is None else format(v, fmt)
    one = any('compile_one_s' in r for r in rows)
    head = ['robot', 'family', 'nodes', 'first use s', 'compile s (CPU s)'] + \
        (['one function: compile s (CPU s)'] if one else []) + ['load ms', 'kernel / Pinocchio'] + \
        (['one function / Pinocchio', 'cut / one function'] if one else [])
    L = [f"Native kernels, first use in a fresh cache and load from it (parts of at most {meta['part']} nodes; "
         f"1-minute load average {meta['load_before']:.2f} before, {meta['load_after']:.2f} after; "
         f"{meta['rounds']} interleaved rounds per call, one state; kernel: the bound native kernel called "
         "directly, without the Model method's checks).", '',
         '| ' + ' | '.join(head) + ' |', '|' + '---|' * 2 + '---:|' * (len(head) - 2)]
    for r in rows:
        cells = [r['robot'], r['family'], str(r['nodes']), f(r['first_s'], '.2f'),
                 f"{r['compile_s']:.2f} ({r['cpu_s']:.2f})"]
        if one:
            cells.append(f"{r['compile_one_s']:.2f} ({r['cpu_one_s']:.2f})" if 'compile_one_s' in r else '–')
        cells += [f(r['load_ms'], '.1f'), f(r.get('ratio_pin'), '.2f')]
        if one:
            cells += [f(r.get('ratio_pin_one'), '.2f'), f(r.get('split_over_one'), '.3f')]
        L.append('| ' + ' | '.join(cells) + ' |')
    return '\n'.join(L) + '\n'


def main(argv=None):
    ap = argparse.ArgumentParser(prog='python -m bench.compile', description=__doc__.split('\n')[0])
    ap.add_argument('--quick', action='store_true')
    ap.add_argument('--out', default=None, help='also write compile.md/.csv/.json into this folder')
    ap.add_argument('--load-child', metavar='ROBOT', help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.load_child:
        _load_child(args.load_child)
        return
    run(quick=args.quick, out=args.out)


if __name__ == '__main__':
    main()
