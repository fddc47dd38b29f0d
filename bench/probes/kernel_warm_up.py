"""Where the kernels of a new robot structure are generated: in the node's process (its loader
thread, before) or in the build process (after: it compiles them into the disk cache and the
node only loads them).

    python -m bench.probes.kernel_warm_up [--joints 7,14] [--rounds 3]

For each round and size, two random chains no cache has seen (a temporary cache folder,
removed at the end): "in the node" runs models.warm_up (the gravity and inverse-dynamics
kernels the node calls) on a model loaded here, as the loader thread did; "from the build
process" builds the model with build_process.BuildProcess (which warms the native cache there)
and then runs the same warm_up here. Reported per case: the wall time of that warm_up here and
this thread's CPU time in it (Python work that holds the interpreter lock; the C compiler
runs in a process of its own either way), medians over the rounds. Without a C compiler (or
with LIE_DYNAMICS_NATIVE=0) both cases generate the Python kernels here.
This is a benchmark, not a test: the numbers depend on the machine and its load.
"""
import argparse
import os
import shutil
import sys
import tempfile
import time

import numpy as np

from bench.common import robot_urdf


def _timed(fn):
    w, c = time.perf_counter(), time.thread_time()
    fn()
    return time.perf_counter() - w, time.thread_time() - c


def run(joints=(7, 14), rounds=3):
    tmp = tempfile.mkdtemp(prefix='lie_dynamics_warm_up_')
    os.environ['LIE_DYNAMICS_CACHE_DIR'] = tmp   # read at each call; inherited by the build process
    from lie_dynamics import load_urdf
    from lie_dynamics.ros.loading.build_process import BuildProcess
    from lie_dynamics.ros.loading.models import warm_up
    proc = BuildProcess()
    rows = []
    try:
        seed = 1000
        for n in (2, *joints):   # the first: compiles the call module once, outside the figures
            here, there = [], []
            for _ in range(1 if n == 2 else rounds):
                seed += 2
                model = load_urdf(robot_urdf(n, seed=seed))
                here.append(_timed(lambda m=model: warm_up(m)))
                model = proc.build(robot_urdf(n, seed=seed + 1))[0]
                there.append(_timed(lambda m=model: warm_up(m)))
            if n != 2:
                for case, t in (('in the node', here), ('from the build process', there)):
                    rows.append({'joints': n, 'case': case, 'wall_ms': 1e3 * float(np.median([w for w, _ in t])),
                                 'cpu_ms': 1e3 * float(np.median([c for _, c in t])), 'rounds': len(t)})
    finally:
        proc.stop()
        shutil.rmtree(tmp, ignore_errors=True)
    return rows


def markdown(rows):
    lines = ['| joints | kernels generated | warm_up in the node: wall ms | its CPU ms (interpreter lock) | rounds |',
             '|---|---|---|---|---|']
    for r in rows:
        lines.append(f"| {r['joints']} | {r['case']} | {r['wall_ms']:.1f} | {r['cpu_ms']:.1f} | {r['rounds']} |")
    return '\n'.join(lines)


def main(argv=None):
    ap = argparse.ArgumentParser(prog='python -m bench.probes.kernel_warm_up', description=__doc__.split('\n')[0])
    ap.add_argument('--joints', default='7,14', help='chain sizes, comma-separated')
    ap.add_argument('--rounds', type=int, default=3)
    a = ap.parse_args(argv)
    print(markdown(run(tuple(int(x) for x in a.joints.split(',')), a.rounds)))
    return 0


if __name__ == '__main__':
    sys.exit(main())
