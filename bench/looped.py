"""Looped against straight-line native kernels, beside Pinocchio: where THRESHOLDS looped_from lies.

    python -m bench.looped [--robots chain8,chain16,...]
                           [--families mass_matrix,aba,forward_dynamics,regressor,jacobian,jacobian_dot,
                                       inverse_dynamics_derivatives,coriolis,forward_dynamics_derivatives]
                           [--rounds 7] [--out DIR]

For each robot (random revolute chains and binary trees, bench.common.robot_urdf; or a label of
bench.native_sizes) and family, in a fresh temporary kernel cache: the straight-line native kernel
(every looped_from off; the native caps as THRESHOLDS has them: above them, `–`, the vectorised
reference runs), the looped one (looped_from 1) and Pinocchio's call on the same URDF, one state,
interleaved rounds (ratios: medians of per-round ratios). `forward_dynamics` is method='cholesky':
straight-line, the Cholesky kernel; looped, the looped ABA that method takes from looped_from.
`inverse_dynamics_derivatives` against Pinocchio's computeRNEADerivatives, `coriolis` (the
recursive C, the dtau/dqd half of the same kernel) against computeCoriolisMatrix,
`forward_dynamics_derivatives` against computeABADerivatives.
First use: the first runtime.native call (trace or step tracing, render, compile, load). The
frame Jacobians (`jacobian`, `jacobian_dot`: J̇q̇) have no looped form (an O(depth) source): their
straight-line kernel of the deepest body's link, 'world_aligned', with its native cap lifted,
through the Model's method beside pin.computeFrameJacobian (J̇q̇: pin.forwardKinematics then
getFrameClassicalAcceleration); first use is the method's first call. The 1-minute load average
is printed (2 cores: above ~0.5 the wall times include waiting).
"""
import functools
import os
import shutil
import tempfile
import time
import warnings

import numpy as np

from bench import common
from bench.compile import _restore_cache_dir
from bench.native_sizes import _arguments, pin_peer, robot_xml

ROBOTS = ('chain8', 'chain16', 'chain24', 'chain32', 'chain48', 'chain64', 'chain100', 'chain200',
          'tree16', 'tree32', 'tree64', 'tree100', 'tree200')
FAMILIES = ('mass_matrix', 'aba', 'forward_dynamics', 'regressor', 'jacobian', 'jacobian_dot',
            'inverse_dynamics_derivatives', 'coriolis', 'forward_dynamics_derivatives')
LIMITS = {'mass_matrix': 'mass_matrix', 'aba': 'aba', 'forward_dynamics': 'aba', 'regressor': 'regressor',
          'jacobian': 'jacobian', 'jacobian_dot': 'jacobian',
          'inverse_dynamics_derivatives': 'inverse_dynamics_derivatives', 'coriolis': 'inverse_dynamics_derivatives',
          'forward_dynamics_derivatives': 'forward_dynamics_derivatives'}
JACOBIANS = ('jacobian', 'jacobian_dot')


def _specs(model, fam):
    """(straight-line spec, looped spec) of a family for this model."""
    from lie_dynamics.codegen.traced import aba, cholesky, crba, derivatives, regressor
    if fam == 'mass_matrix':
        return crba.MASS_MATRIX, crba.MASS_MATRIX
    if fam == 'regressor':
        return regressor.REGRESSOR, regressor.REGRESSOR
    if fam == 'inverse_dynamics_derivatives':
        return derivatives.INVERSE_DYNAMICS_DERIVATIVES, derivatives.INVERSE_DYNAMICS_DERIVATIVES
    if fam == 'coriolis':
        return derivatives.CORIOLIS, derivatives.CORIOLIS
    if fam == 'forward_dynamics_derivatives':
        return derivatives.FORWARD_DYNAMICS_DERIVATIVES, derivatives.FORWARD_DYNAMICS_DERIVATIVES
    if fam == 'aba':
        return aba.spec(model), aba.spec(model)
    return cholesky.FORWARD_DYNAMICS, aba.spec(model)


def _first(model, spec):
    """(bound native kernel or None, first-use seconds)."""
    from lie_dynamics.codegen import runtime
    t0 = time.perf_counter()
    fn = runtime.native(model, spec)
    return fn, time.perf_counter() - t0


def _jacobian_row(xml, model, fam, lim, saved, rounds):
    """A Jacobian family's row: its straight-line kernel (native cap lifted) beside Pinocchio."""
    import pinocchio as pin
    from lie_dynamics.codegen import runtime
    T = runtime.THRESHOLDS
    T[lim] = saved[lim]._replace(native_max=10 ** 6)
    deep = max(range(model.nb), key=lambda b: model.depth[b])
    link = next(nm for nm, (b, _) in model.link_frames.items() if b == deep)
    rng = np.random.default_rng(1)
    q, qd = rng.uniform(-1, 1, (2, model.n))
    call = ((lambda: model.jacobian(q, link)) if fam == 'jacobian'
            else (lambda: model.jacobian_dot_times_qd(q, qd, link)))
    t0 = time.perf_counter()
    call()
    first = time.perf_counter() - t0
    from lie_dynamics.codegen.traced import jacobian
    if runtime.native(model, jacobian.spec(fam, 'world_aligned', deep)) is None:
        raise RuntimeError(f'{fam}: no native kernel for body {deep}')
    pm = pin.buildModelFromXML(xml)
    pm.gravity.linear = model.gravity_vector
    pd, fid, ref = pm.createData(), pm.getFrameId(link), pin.ReferenceFrame.LOCAL_WORLD_ALIGNED
    pq = pin.randomConfiguration(pm, -np.ones(pm.nq), np.ones(pm.nq))
    v, z = rng.uniform(-1, 1, pm.nv), np.zeros(pm.nv)
    if fam == 'jacobian':
        def peer():
            return pin.computeFrameJacobian(pm, pd, pq, fid, ref)
    else:
        def peer():
            pin.forwardKinematics(pm, pd, pq, v, z)
            return pin.getFrameClassicalAcceleration(pm, pd, fid, ref).vector
    t = common.time_interleaved({'pin': peer, 'straight': call}, rounds, 0.005)
    T[lim] = saved[lim]
    return dict(pin_us=float(np.median(t['pin'])) * 1e6, straight_first_s=first,
                straight_us=float(np.median(t['straight'])) * 1e6,
                straight_ratio=float(np.median(t['straight'] / t['pin'])))


def measure(labels, families, rounds=7):
    from lie_dynamics import load_urdf
    from lie_dynamics.codegen import runtime
    T = runtime.THRESHOLDS
    saved = dict(T)
    saved_dir = os.environ.get('LIE_DYNAMICS_CACHE_DIR')
    work = tempfile.mkdtemp(prefix='bench_looped_')
    rows = []
    try:
        for label in labels:
            os.environ['LIE_DYNAMICS_CACHE_DIR'] = os.path.join(work, label)
            xml = robot_xml(label)
            for fam in families:
                runtime.clear()
                with warnings.catch_warnings():
                    warnings.simplefilter('ignore')   # vendor inertias are warned about
                    straight, looped = load_urdf(xml), load_urdf(xml)
                lim = LIMITS[fam]
                if fam in JACOBIANS:
                    row = dict(robot=label, n=straight.n, family=fam, loadavg=os.getloadavg()[0])
                    row.update(_jacobian_row(xml, straight, fam, lim, saved, rounds))
                    rows.append(row)
                    print(_line(row), flush=True)
                    continue
                T[lim] = saved[lim]._replace(looped_from=None)
                s_spec, l_spec = _specs(straight, fam)
                s_fn, s_first = _first(straight, s_spec)
                T[lim] = saved[lim]._replace(looped_from=1)
                l_fn, l_first = _first(looped, l_spec)
                if not runtime.looped(looped, l_spec):   # no looped form (mimic joints): the straight-line ran
                    l_fn = None
                T[lim] = saved[lim]
                rng = np.random.default_rng(1)
                args = _arguments(fam, straight, rng)
                fns = {'pin': pin_peer(xml, straight, fam, rng)}
                if s_fn is not None:
                    fns['straight'] = lambda f=s_fn: f(*args)
                if l_fn is not None:
                    fns['looped'] = lambda f=l_fn: f(*args)
                t = common.time_interleaved(fns, rounds, 0.005)
                row = dict(robot=label, n=straight.n, family=fam, loadavg=os.getloadavg()[0],
                           pin_us=float(np.median(t['pin'])) * 1e6)
                for k, first in (('straight', s_first), ('looped', l_first)):
                    if k in t:
                        row[f'{k}_first_s'] = first
                        row[f'{k}_us'] = float(np.median(t[k])) * 1e6
                        row[f'{k}_ratio'] = float(np.median(t[k] / t['pin']))
                if 'straight' in t and 'looped' in t:
                    row['looped_over_straight'] = float(np.median(t['looped'] / t['straight']))
                rows.append(row)
                print(_line(row), flush=True)
    finally:
        T.update(saved)
        runtime.clear()
        _restore_cache_dir(saved_dir)
        shutil.rmtree(work, ignore_errors=True)
    return rows


def _line(r):
    f = functools.partial(common.cell, r)
    return (f"| {r['robot']} | {r['family']} | {f('straight_first_s', '.2f')} | {f('looped_first_s', '.2f')} | "
            f"{f('straight_ratio', '.2f')} | {f('looped_ratio', '.2f')} | {f('looped_over_straight', '.2f')} | "
            f"{f('pin_us', '.1f')} | {r['loadavg']:.1f} |")


HEAD = ('| robot | family | straight first use s | looped first use s | straight / Pinocchio | looped / Pinocchio '
        '| looped / straight | Pinocchio µs | load |\n|---|---|---:|---:|---:|---:|---:|---:|---:|')


def main(argv=None):
    return common.rows_main(argv, __doc__, 'looped', HEAD, _line, lambda a: measure(a.robots, a.families, a.rounds),
                            ','.join(ROBOTS), ','.join(FAMILIES))


if __name__ == '__main__':
    raise SystemExit(main())
