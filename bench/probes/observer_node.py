"""What the external-torque observer costs the dynamics node per joint_states message, in the
forms a running node takes it, beside bench.observer's cost table (message objects, the features'
work at once):

  input    objects: sensor_msgs/JointState (bench.observer's node_cost); serialized: the bytes the
           node's subscription delivers (raw=True), so the fused command path (ros/core/fused.py)
           makes the command
  work     at once: no executor to defer to (bench.observer); deferred: as run.py sets the node up
           under the EventsExecutor (DynamicsNode.defer_to), the features' work queued after the
           command and run in executor tasks, here a stand-in executor whose tasks run right after
           the callback returns

Per message: the callback (on_joint_state) and, deferred, the total (the callback and the tasks
it queued), for the observer off (the peer) and on (bench.observer's CASES), in-process with real
publishers and no DDS transport, interleaved rounds; each case's ratio is the median over rounds
of the per-message median over the peer's of the same form and work, as bench.observer's.
Also each piece of the observer's per-sample work (the monitor: mapping, time base, step,
bookkeeping; the two publishes; isolation) timed in place on the serialized, at-once node.

    python -m bench.probes.observer_node [--rounds 5] [--per-round 300]

A benchmark, not a test: read the ratios between rows of one run, and say the load average.
"""
import argparse
import os
import sys
import time

import numpy as np

from bench.observer import CASES, _messages, bench_node, recording


class _Tasks:
    """The executor's create_task, run by the caller (run_all) right after the callback."""

    def __init__(self):
        self.queued = []

    def create_task(self, fn):
        self.queued.append(fn)

    def run_all(self):
        while self.queued:
            self.queued.pop(0)()


def _split(node, msgs):
    """{piece: median us} of the observer's per-sample work, each piece timed in place around its call."""
    topics = node.features.get('contact')
    times = {}
    clock = time.perf_counter

    def wrap(obj, name, key):
        f = getattr(obj, name)

        def timed(*a, **k):
            t0 = clock()
            out = f(*a, **k)
            times.setdefault(key, []).append(clock() - t0)
            return out
        setattr(obj, name, timed)
    m = topics.monitor
    wrap(m.observer, 'step', 'observer step (kernel call)')
    wrap(m, '_accept', 'estimate bookkeeping (_accept)')
    wrap(m, 'on_sample', 'monitor (mapping, time base, step, bookkeeping)')
    wrap(topics._ext_pub, 'publish', 'publish ~/external_torques')
    wrap(topics._flag_pub, 'publish', 'publish ~/collision')
    wrap(topics.isolation, 'update', 'contact isolation')
    wrap(topics, 'on_sample', 'ContactTopics.on_sample (all of the above)')
    wrap(node.features, 'feed', "the features' work (Features.feed: the above and its call)")
    node.on_joint_state(msgs[0])   # ~/external_torques' writer made for the layout: timed from here
    wrap(topics, '_ext', "the estimate's bytes (cdr.Writer)")
    for msg in msgs[1:]:
        node.on_joint_state(msg)
    return {k: float(np.median(v[len(v) // 10:]) * 1e6) for k, v in times.items()}


def run(rounds=5, per_round=300):
    import rclpy
    from rclpy.serialization import serialize_message
    rec = recording(rounds * per_round * 1e-3 + 0.1)
    model = rec[0]
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    nodes, msgs, tasks, extra_nodes = {}, {}, {}, []
    try:
        for form in ('objects', 'serialized'):
            for work in ('at once', 'deferred'):
                for case, extra in CASES.items():
                    key = (form, work, case)
                    node = nodes[key] = bench_node(model, ctx, f'observer_probe_{len(nodes)}', extra)
                    if work == 'deferred':
                        tasks[key] = _Tasks()
                        node.defer_to(tasks[key])
                    m = _messages(rec, rounds * per_round, extra.get('measured_effort', 'total'))
                    msgs[key] = [bytes(serialize_message(x)) for x in m] if form == 'serialized' else m
        cb = {k: [] for k in nodes}
        total = {k: [] for k in nodes}
        clock = time.perf_counter
        for r in range(rounds):
            for key, node in nodes.items():   # interleaved: a slow phase of the machine hits all alike
                run_tasks = tasks[key].run_all if key in tasks else None
                a, b = [], []
                for msg in msgs[key][r * per_round:(r + 1) * per_round]:
                    t0 = clock()
                    node.on_joint_state(msg)
                    t1 = clock()
                    if run_tasks is not None:
                        run_tasks()
                    a.append(t1 - t0)
                    b.append(clock() - t0)
                cb[key].append(np.array(a[10:]) * 1e6)   # the first ones of a round warm caches
                total[key].append(np.array(b[10:]) * 1e6)
        fused = {k: nodes[k].fused.taken if nodes[k].fused is not None else 0 for k in nodes}
        samples = {k: nodes[k].contact_monitor.samples for k in nodes}
        extra_nodes.append(bench_node(model, ctx, 'observer_probe_split', {}))
        split = _split(extra_nodes[-1], [bytes(serialize_message(x)) for x in _messages(rec, rounds * per_round)])
    finally:
        for node in [*nodes.values(), *extra_nodes]:   # every node destroyed before the context goes
            node.destroy_node()
        rclpy.shutdown(context=ctx)
    peer = next(iter(CASES))
    rows = []
    for key in nodes:
        form, work, case = key
        for what, data in (('callback', cb), ('total', total)):
            if what == 'total' and work == 'at once':
                continue   # the same as the callback
            per, ref = data[key], data[(form, work, peer)]
            ratios = [np.median(x) / np.median(y) for x, y in zip(per, ref, strict=True)]
            rows.append((form, work, case, what, float(np.median(np.concatenate(per))), float(np.median(ratios)),
                         float(np.min(ratios)), float(np.max(ratios)), fused[key], samples[key]))
    print(f'load average {os.getloadavg()[0]:.2f} {os.getloadavg()[1]:.2f}; {rounds} rounds of {per_round} messages')
    print('| input | work | case | timed | median µs | ratio to the peer | range over rounds | fused commands '
          '| observer samples |')
    print('|---' * 9 + '|')
    for form, work, case, what, med, ratio, lo, hi, nf, ns in rows:
        print(f'| {form} | {work} | {case} | {what} | {med:.1f} | {ratio:.2f} | {lo:.2f}-{hi:.2f} | {nf} | {ns} |')
    print('\nThe observer\'s per-sample work, serialized input, at once (median µs, each timed in place):')
    for k, v in split.items():
        print(f'  {k:50s} {v:6.2f}')
    return rows, split


def main(argv=None):
    ap = argparse.ArgumentParser(prog='python -m bench.probes.observer_node', description=__doc__.split('\n')[0])
    ap.add_argument('--rounds', type=int, default=5)
    ap.add_argument('--per-round', type=int, default=300)
    args = ap.parse_args(argv)
    run(args.rounds, args.per_round)
    return 0


if __name__ == '__main__':
    sys.exit(main())
