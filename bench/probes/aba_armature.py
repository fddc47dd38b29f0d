"""What the armature costs the ABA kernel while it is all zero: the traced graph's size and the
call time beside Pinocchio's aba, with the rigid variant (the armature the constant 0.0,
traced_aba.ABA_RIGID, what forward_dynamics(method='aba') runs while Model.armature is zero)
and with the armature kernel (traced_aba.ABA: the armature a parameter).

    python -m bench.probes.aba_armature [--rounds R]

Ratios are medians over interleaved rounds in one process (absolute times are noise on a loaded
machine). Bundled arm and the 12-joint chain of the benchmarks.
"""
import argparse
import time

import numpy as np


def _graph_size(spec, model):
    from lie_dynamics.codegen import runtime
    t = spec.build(runtime.frames(model))
    ops = [op for op, _ in t.graph.nodes]
    return len(ops), sum(op == 'mul' for op in ops)


def _per_call(f, k):
    t0 = time.perf_counter_ns()
    for _ in range(k):
        f()
    return (time.perf_counter_ns() - t0) / k


def run(rounds=21, calls=2000):
    import pinocchio as pin

    from lie_dynamics import default_urdf_path, load_urdf
    from lie_dynamics.algorithms import aba
    from lie_dynamics.codegen import runtime
    from lie_dynamics.codegen.traced import aba as traced_aba

    model = load_urdf(default_urdf_path())
    pm = pin.buildModelFromUrdf(default_urdf_path())
    pd = pm.createData()
    rng = np.random.default_rng(0)
    q, qd, tau = rng.uniform(-1, 1, (3, model.n))
    rigid = runtime.native(model, traced_aba.ABA_RIGID)
    full = runtime.native(model, traced_aba.ABA)
    assert traced_aba.spec(model) is traced_aba.ABA_RIGID
    lines = []
    for name, spec in (('rigid (armature 0.0 folded)', traced_aba.ABA_RIGID), ('armature parameter', traced_aba.ABA)):
        nodes, muls = _graph_size(spec, model)
        lines.append(f'{name:28s} graph nodes {nodes}, products {muls}')
    if rigid is None or full is None:
        lines.append('no native kernels (no C compiler or LIE_DYNAMICS_NATIVE=0): no timing')
        return '\n'.join(lines)
    ref = aba.forward_dynamics(model, q, qd, tau, method='aba')
    assert np.allclose(rigid(q, qd, tau), ref, rtol=1e-12, atol=1e-12)
    assert np.allclose(full(q, qd, tau), ref, rtol=1e-12, atol=1e-12)
    r_rigid, r_full, r_api = [], [], []
    for _ in range(rounds):
        p = _per_call(lambda: pin.aba(pm, pd, q, qd, tau), calls)
        r_rigid.append(_per_call(lambda: rigid(q, qd, tau), calls) / p)
        r_full.append(_per_call(lambda: full(q, qd, tau), calls) / p)
        r_api.append(_per_call(lambda: model.forward_dynamics(q, qd, tau, method='aba'), calls) / p)
        p2 = _per_call(lambda: pin.aba(pm, pd, q, qd, tau), calls)
        r_rigid[-1], r_full[-1], r_api[-1] = (x * p / (0.5 * (p + p2)) for x in (r_rigid[-1], r_full[-1], r_api[-1]))
    rigid_m, full_m = np.median(r_rigid), np.median(r_full)
    lines.append(f'native kernel / pin.aba, median of {rounds} rounds: rigid {rigid_m:.3f}, armature parameter '
                 f'{full_m:.3f} (rigid / armature {rigid_m / full_m:.3f}); '
                 f'model.forward_dynamics(method=\'aba\') / pin.aba {np.median(r_api):.3f}')
    return '\n'.join(lines)


def main(argv=None):
    ap = argparse.ArgumentParser(prog='python -m bench.probes.aba_armature', description=__doc__.split('\n')[0])
    ap.add_argument('--rounds', type=int, default=21)
    args = ap.parse_args(argv)
    print(run(args.rounds))
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
