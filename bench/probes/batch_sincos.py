"""Two costs of a native batch of inverse dynamics, measured apart (xArm7, N states of
bench.common.random_states, angles within the joint limits, +-2 pi on four joints):

    python -m bench.probes.batch_sincos [--states 10000] [--rounds 15]

1. The C library's sincos on the batch's joint angles, ns a call: in the batch's order, grouped
   as a native batch computes them (native_call.c sincos_grouped: a counting sort by the
   branches the library takes, its cost included), and sorted (every branch predicted, the
   floor). The values are the same in every order.
2. The upper halves of the vector registers: 1,000 one-state calls of our inverse dynamics (the
   one-state kernel is SSE code) and a Pinocchio loop over 1,000 states, timed right after the
   AVX2 form across states was called bare (ctypes; it returns with them in use, gcc emitting no
   vzeroupper below -O2) and right after `model.inverse_dynamics` on a batch, whose call path
   clears them: the ratio is what the SSE instructions after the bare form paid.
Interleaved rounds, medians; the 1-minute load average is printed with the figures.
"""
import argparse
import ctypes
import os
import sys
import time
import warnings

import numpy as np

from bench import calls, common


def _best(f, repeats=3):
    best = np.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        f()
        best = min(best, time.perf_counter() - t0)
    return best


def run(states=10000, rounds=15):
    from lie_dynamics.codegen import native, runtime
    from lie_dynamics.codegen.spec import parameters
    from lie_dynamics.codegen.traced import rnea as t_rnea

    name, rel, joints = next(r for r in calls.ROBOTS if r[0] == 'xArm7')
    with warnings.catch_warnings():
        warnings.simplefilter('ignore')
        pin, model, pm = calls._models(rel, joints)
    q, qd, qdd = (np.ascontiguousarray(x) for x in common.random_states(model, states, seed=2))
    x = np.ascontiguousarray(q.reshape(-1))
    xs = np.sort(x)
    mod = native.module()
    s0, c0 = mod.sincos_batch(x, False)
    s1, c1 = mod.sincos_batch(x, True)
    assert np.array_equal(s0, s1) and np.array_equal(c0, c1)

    # the bare form across states on 4 states (the kernel's own layout; clanes.py)
    spec = t_rnea.INVERSE_DYNAMICS
    lib = runtime.kernel(model, spec).native()
    P = [np.ascontiguousarray(p, dtype=float).reshape(-1) if len(p) else np.zeros(1) for p in parameters(model, spec)]
    par = (ctypes.c_void_p * len(P))(*[p.ctypes.data for p in P])
    n_sc = len(lib.lanes_sincos) // 2
    sc = np.zeros((2, 4, max(n_sc, 1)))
    ins = (ctypes.c_void_p * 5)(q.ctypes.data, qd.ctypes.data, qdd.ctypes.data, sc[0].ctypes.data, sc[1].ctypes.data)
    blk = np.empty((4, model.n))
    bare = ctypes.CFUNCTYPE(ctypes.c_int, ctypes.c_void_p, ctypes.c_void_p, ctypes.c_void_p)(lib.lanes_address)
    out = np.empty((states, model.n))
    pd = pm.createData()
    M = min(1000, states)

    o1 = np.empty(model.n)

    def pin_loop():
        for i in range(M):
            pin.rnea(pm, pd, q[i], qd[i], qdd[i])

    def our_loop():
        for i in range(M):
            model.inverse_dynamics(q[i], qd[i], qdd[i], out=o1)

    loops = {'ours, one state': our_loop, 'pin.rnea': pin_loop}
    t = {k: [] for k in ('in order', 'grouped', 'sorted')}
    for _ in range(rounds):
        t['in order'].append(_best(lambda: mod.sincos_batch(x, False)) / x.size)
        t['grouped'].append(_best(lambda: mod.sincos_batch(x, True)) / x.size)
        t['sorted'].append(_best(lambda: mod.sincos_batch(xs, False)) / x.size)
        for loop, f in loops.items():
            for key, before in (('bare', lambda: bare(ins, par, blk.ctypes.data)),
                                ('call path', lambda: model.inverse_dynamics(q[:64], qd[:64], qdd[:64],
                                                                             out=out[:64]))):
                best = np.inf
                for _ in range(3):
                    before()
                    t0 = time.perf_counter()
                    f()
                    best = min(best, time.perf_counter() - t0)
                t.setdefault((loop, key), []).append(best / M)
    sincos = {k: float(np.median(t[k])) * 1e9 for k in ('in order', 'grouped', 'sorted')}
    after = {loop: dict(bare=float(np.median(t[loop, 'bare'])) * 1e9,
                        call_path=float(np.median(t[loop, 'call path'])) * 1e9,
                        ratio=float(np.median(np.array(t[loop, 'bare']) / np.array(t[loop, 'call path']))))
             for loop in loops}
    return dict(robot=name, states=states, rounds=rounds, load=os.getloadavg()[0], sincos_ns=sincos, after=after)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--states', type=int, default=10000)
    ap.add_argument('--rounds', type=int, default=15)
    a = ap.parse_args(argv)
    load0 = os.getloadavg()[0]
    r = run(a.states, a.rounds)
    s = r['sincos_ns']
    print(f"{r['robot']}, {r['states']:,} states, {r['rounds']} rounds, load average {load0:.1f} -> {r['load']:.1f}")
    print(f"sincos, ns a call: in order {s['in order']:.1f}, grouped {s['grouped']:.1f}, sorted {s['sorted']:.1f}")
    for loop, p in r['after'].items():
        print(f"{loop} in a Python loop, ns a state: after the bare AVX2 form {p['bare']:.0f}, "
              f"after the call path {p['call_path']:.0f} (ratio {p['ratio']:.2f})")
    return 0


if __name__ == '__main__':
    sys.exit(main())
