"""The one-state call path of the frame Jacobians: the method, its Python path, the bare kernel, Pinocchio.

    python -m bench.probes.jacobian_call [--robots arm7,talos_reduced,tree32,tree64] [--rounds 15]

For each robot (bench.native_sizes.robot_xml labels) and the deepest body's link, 'world_aligned',
one state, in interleaved rounds (order rotating): `model.jacobian(q, link)` (and
`model.jacobian_dot_times_qd(q, qd, link)`), the same through the method's Python form (the
`__wrapped__` function: what the call cost before the method ran its kernel from C, and what it
still runs when the C check declines), the bound native kernel alone (runtime.native(...)(q, X):
the floor of the call) and Pinocchio (pin.computeFrameJacobian; for J̇q̇ pin.forwardKinematics
then getFrameClassicalAcceleration, as bench.looped). Prints medians in µs and medians of
per-round ratios to Pinocchio, with the 1-minute load average (2 cores: above ~0.5 the times
include waiting). The Jacobians' native cap is lifted as bench.looped does.
"""
import argparse
import os
import warnings

import numpy as np

from bench import common
from bench.native_sizes import robot_xml


def rows(label, rounds):
    import pinocchio as pin
    from lie_dynamics import load_urdf
    from lie_dynamics.codegen import runtime
    from lie_dynamics.codegen.traced import jacobian as traced
    from lie_dynamics.model.model import Model
    T = runtime.THRESHOLDS
    saved = T['jacobian']
    T['jacobian'] = saved._replace(native_max=10 ** 6)
    try:
        xml = robot_xml(label)
        with warnings.catch_warnings():
            warnings.simplefilter('ignore')   # vendor inertias are warned about
            model = load_urdf(xml)
        deep = max(range(model.nb), key=lambda b: model.depth[b])
        link = next(nm for nm, (b, _) in model.link_frames.items() if b == deep)
        rng = np.random.default_rng(1)
        q, qd = rng.uniform(-1, 1, (2, model.n))
        pm = pin.buildModelFromXML(xml)
        pd, fid, ref = pm.createData(), pm.getFrameId(link), pin.ReferenceFrame.LOCAL_WORLD_ALIGNED
        pq = pin.randomConfiguration(pm, -np.ones(pm.nq), np.ones(pm.nq))
        v, z = rng.uniform(-1, 1, pm.nv), np.zeros(pm.nv)
        # the Python form of each method (before it ran from C: the method itself)
        py_jac = getattr(Model.jacobian, '__wrapped__', Model.jacobian)
        py_drift = getattr(Model.jacobian_dot_times_qd, '__wrapped__', Model.jacobian_dot_times_qd)
        out = []
        for fam in ('jacobian', 'jacobian_dot'):
            X = np.array(runtime.frames(model).point_params(deep, model.link_frames[link][1]))
            if fam == 'jacobian':
                method, slow = (lambda: model.jacobian(q, link)), (lambda: py_jac(model, q, link))

                def peer():
                    return pin.computeFrameJacobian(pm, pd, pq, fid, ref)
                states = (q,)
            else:
                method = lambda: model.jacobian_dot_times_qd(q, qd, link)   # noqa: E731
                slow = lambda: py_drift(model, q, qd, link)   # noqa: E731

                def peer():
                    pin.forwardKinematics(pm, pd, pq, v, z)
                    return pin.getFrameClassicalAcceleration(pm, pd, fid, ref).vector
                states = (q, qd)
            method()
            nk = runtime.native(model, traced.spec(fam, 'world_aligned', deep))
            if nk is None:
                raise RuntimeError(f'{label} {fam}: no native kernel')
            if not np.array_equal(nk(*states, X), method()) or not np.array_equal(slow(), method()):
                raise RuntimeError(f'{label} {fam}: the paths disagree')
            fns = {'pin': peer, 'method': method, 'python': slow, 'kernel': lambda: nk(*states, X)}
            t = common.time_interleaved(fns, rounds, 0.005, rotate=True)
            out.append(dict(robot=label, n=model.n, family=fam, loadavg=os.getloadavg()[0],
                            **{f'{k}_us': float(np.median(t[k])) * 1e6 for k in fns},
                            **{f'{k}_ratio': float(np.median(t[k] / t['pin'])) for k in fns if k != 'pin'}))
        return out
    finally:
        T['jacobian'] = saved


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('--robots', default='arm7,talos_reduced,tree32,tree64')
    ap.add_argument('--rounds', type=int, default=15)
    a = ap.parse_args(argv)
    print('| robot (n) | family | Pinocchio µs | method µs (/pin) | Python path µs (/pin) | kernel µs (/pin) | load |')
    print('|---|---|---|---|---|---|---|')
    for label in a.robots.split(','):
        for r in rows(label, a.rounds):
            print(f"| {r['robot']} ({r['n']}) | {r['family']} | {r['pin_us']:.2f} | "
                  f"{r['method_us']:.2f} ({r['method_ratio']:.2f}) | {r['python_us']:.2f} ({r['python_ratio']:.2f}) | "
                  f"{r['kernel_us']:.2f} ({r['kernel_ratio']:.2f}) | {r['loadavg']:.1f} |", flush=True)


if __name__ == '__main__':
    main()
