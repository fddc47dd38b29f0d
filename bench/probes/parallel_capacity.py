"""How much two workers can gain on this machine at all: the same batch of inverse dynamics
(the bundled arm, one thread each) timed in one process alone, then in two processes at once.
Two workers' throughput over one worker's is the ceiling of any 2-thread speed-up here (2.0 on
two free physical cores; less where the two CPUs share a core or a busy host):

    python -m bench.probes.parallel_capacity [--states 100000] [--rounds 15]
"""
import argparse
import subprocess
import sys
import time

import numpy as np

START_S = 5.0   # s: both workers imported, built and warm before they start timing


def worker(states, rounds, start_at):
    """Median seconds of one batched call on `states` random states of the bundled arm, timed
    from the wall-clock instant start_at (so that two workers measure at the same time)."""
    import time

    from lie_dynamics import default_urdf_path, load_urdf
    from lie_dynamics.codegen import native

    native.set_threads(1)
    m = load_urdf(default_urdf_path())
    q, qd, qdd = np.random.default_rng(0).uniform(-1, 1, (3, states, m.n))
    out = np.empty((states, m.n))
    m.inverse_dynamics(q, qd, qdd, out=out)   # built and warm
    time.sleep(max(0.0, start_at - time.time()))
    times = []
    for _ in range(rounds):
        t0 = time.perf_counter()
        m.inverse_dynamics(q, qd, qdd, out=out)
        times.append(time.perf_counter() - t0)
    return float(np.median(times))


def _spawn(states, rounds, start_at):
    code = f'from bench.probes.parallel_capacity import worker; print(worker({states}, {rounds}, {start_at!r}))'
    return subprocess.Popen([sys.executable, '-c', code], stdout=subprocess.PIPE, text=True)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('--states', type=int, default=100_000)
    ap.add_argument('--rounds', type=int, default=15)
    args = ap.parse_args(argv)
    alone = float(_spawn(args.states, args.rounds, 0.0).communicate()[0])
    start_at = time.time() + START_S
    pair = [_spawn(args.states, args.rounds, start_at) for _ in range(2)]
    both = [float(p.communicate()[0]) for p in pair]
    gain = 2 * alone / max(both)
    print(f'one process alone: {alone * 1e3:.2f} ms per call; two at once: '
          f'{both[0] * 1e3:.2f} and {both[1] * 1e3:.2f} ms')
    print(f'throughput of two workers / one worker: {gain:.2f}x (the ceiling of a 2-thread speed-up here)')


if __name__ == '__main__':
    main()
