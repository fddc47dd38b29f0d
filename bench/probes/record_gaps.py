"""~/record beside the control path: the joint_states callback's time while the node records and
while it writes the recording, in one process.

    python -m bench.probes.record_gaps [--seconds S] [--rate HZ] [--rounds R]

A DynamicsNode on the bundled arm (gravity mode, observer on: its defaults) in one rclpy context,
fed serialized, stamped joint_states with efforts by direct calls of its callback (what its
executor runs per message), paced at RATE Hz of wall time; ~/record is called through a real
client from another thread. Phases, in R interleaved rounds (a shared machine's load drifts):
`idle` (no recording, S/R s), `recording` (S/R s of states), and `writing`: from the `false` call
until its answer, while the writer child serializes and writes the S/R x RATE messages and the
callback keeps running. Per phase over the rounds: calls, the callback's median, p99 and largest
time. This is a benchmark, not a test: read the columns side by side.
"""
import argparse
import os
import shutil
import tempfile
import threading
import time

import numpy as np

from lie_dynamics import default_urdf_path, load_urdf

JOINTS = [f'joint{i}' for i in range(1, 8)]


def run(seconds=10.0, rate=1000.0, rounds=5):
    import rclpy
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.parameter import Parameter
    from rclpy.serialization import serialize_message
    from sensor_msgs.msg import JointState
    from std_srvs.srv import SetBool

    from lie_dynamics.ros.node import DynamicsNode

    model = load_urdf(default_urdf_path())
    rng = np.random.default_rng(0)
    lo, hi = np.maximum(model.position_lower, -3.0), np.minimum(model.position_upper, 3.0)
    pool = [(q, model.gravity(q)) for q in rng.uniform(lo, hi, (200, 7))]
    folder = tempfile.mkdtemp(prefix='lie_dynamics_record_gaps_')
    ctx = Context()
    rclpy.init(context=ctx)
    ex = SingleThreadedExecutor(context=ctx)
    tester = rclpy.create_node('record_gaps_client', context=ctx)
    ex.add_node(tester)
    spinner = threading.Thread(target=ex.spin, daemon=True)
    spinner.start()
    with open(default_urdf_path()) as fh:
        xml = fh.read()
    node = DynamicsNode(context=ctx, parameter_overrides=[
        Parameter('robot_description', value=xml), Parameter('recording_dir', value=folder),
        Parameter('recording_max_s', value=3600.0), Parameter('stale_timeout', value=60.0)])
    client = tester.create_client(SetBool, '/dynamics_node/record')
    client.wait_for_service(timeout_sec=30.0)
    period = 1.0 / rate
    state = {'k': 0}
    times = {}

    def feed(phase, until):
        """Call the callback at `rate` until until() is true; the times go to times[phase]."""
        out = times.setdefault(phase, [])
        start = time.perf_counter()
        n = 0
        while not until(n):
            k = state['k']
            q, g = pool[k % len(pool)]
            msg = JointState(name=JOINTS, position=q.tolist(), velocity=[0.0] * 7, effort=g.tolist())
            msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(1_000_000_000 + k * int(1e9 * period), 10 ** 9)
            data = bytes(serialize_message(msg))
            wait = start + n * period - time.perf_counter()
            if wait > 0:
                time.sleep(wait)
            t0 = time.perf_counter()
            node.on_joint_state(data)
            out.append(time.perf_counter() - t0)
            state['k'] += 1
            n += 1

    count = max(1, int(seconds * rate / rounds))
    try:
        for _ in range(rounds):
            feed('idle', lambda n: n >= count)
            assert client.call(SetBool.Request(data=True)).success
            feed('recording', lambda n: n >= count)
            fut = client.call_async(SetBool.Request(data=False))
            feed('writing', lambda n: fut.done())
            answer = fut.result()
            written = answer.message if answer.success else f'failed: {answer.message}'
    finally:
        node.destroy_node()
        ex.shutdown(timeout_sec=2.0)
        rclpy.shutdown(context=ctx)
        shutil.rmtree(folder, ignore_errors=True)
    rows = [(phase, len(v), 1e6 * np.median(v), 1e6 * np.percentile(v, 99), 1e6 * np.max(v))
            for phase, v in times.items()]
    return rows, os.path.basename(written.split(' (')[0]) if answer.success else written


def markdown(rows, note, seconds, rate, rounds):
    lines = [f'~/record: the joint_states callback per phase ({seconds:g} s at {rate:g} Hz recorded in {rounds} '
             f'rounds; the last written: {note})', '', '| phase | calls | median (µs) | p99 (µs) | max (µs) |',
             '|---|---:|---:|---:|---:|']
    lines += [f'| {p} | {n} | {m:.0f} | {p99:.0f} | {mx:.0f} |' for p, n, m, p99, mx in rows]
    return '\n'.join(lines)


def main(argv=None):
    ap = argparse.ArgumentParser(prog='python -m bench.probes.record_gaps', description=__doc__.split('\n')[0])
    ap.add_argument('--seconds', type=float, default=10.0)
    ap.add_argument('--rate', type=float, default=1000.0)
    ap.add_argument('--rounds', type=int, default=5)
    args = ap.parse_args(argv)
    rows, note = run(args.seconds, args.rate, args.rounds)
    print(markdown(rows, note, args.seconds, args.rate, args.rounds))
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
