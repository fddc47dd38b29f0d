"""The dynamics node's work per joint_states message with every feature on, step by step, in
process (no DDS transport, no executor: the features' steps run right after the command, each
timed where the node would queue it):

    python -m bench.probes.node_steps [--robot arm7|talos_reduced] [--states 3000] [--defaults]

The node as bench.node_latency's every-feature candidate configures it (the four dynamics topics
at every state, ~/commanded_efforts, the observer and its topics; --defaults: the node's own
defaults, observer on, no dynamics topics), fed serialized joint_states of random postures as a
driver's messages are (one layout, its padding bytes fixed, velocities 0, efforts g(q): no
contact). Prints per message the median and p90 of the whole callback and of each feature's steps,
how many commands the fused command path made and how many of the states were clamped; then
C(q, qd) qd by its own kernel (`Model.coriolis_term`) against inverse dynamics at qdd = 0 without
gravity, one state, timeit minima. A probe, not a test: say the load average beside its figures.
"""
import argparse
import collections
import gc
import os
import sys
import time
import timeit

import numpy as np


def _messages(model, joints, count):
    """Serialized joint_states of bench.node_latency's postures, one layout with fixed padding
    (cdr.joint_state_template, as the fused command path's test writes them), at rest."""
    from bench.node_latency import postures
    from lie_dynamics.ros.core.cdr import joint_state_template
    t, stamp_at, slots = joint_state_template(joints)
    return [t.fill(slots, (q, np.zeros(model.n), model.gravity(q)), stamp_at, 0) for q in postures(model, count)]


def run(robot='arm7', states=3000, defaults=False):
    import rclpy
    from rclpy.parameter import Parameter

    from bench.node_latency import streamed_robot
    from lie_dynamics.ros.node import DynamicsNode
    path, joints, model, _ = streamed_robot(robot)
    msgs = _messages(model, joints, 300)
    params = {'urdf_path': path, 'joints': joints, 'stale_timeout': 60.0}
    if not defaults:
        params.update({'dynamics.publish': ['gravity', 'coriolis', 'mass_matrix', 'jacobian'], 'dynamics.rate': 0.0,
                       'publish_commanded_efforts': True})
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    node = DynamicsNode('node_steps_probe', context=ctx,
                        parameter_overrides=[Parameter(k, value=v) for k, v in params.items()])
    try:
        core = node.core
        times = collections.defaultdict(list)
        clock = time.perf_counter

        def timed(features):   # the node's _after_command without an executor, each feature's steps timed
            spent = collections.defaultdict(float)
            for f, step in features.steps(core):
                t0 = clock()
                step()
                spent[f.name] += clock() - t0
            for name, t in spent.items():
                times[name].append(t)
        node._after_command = timed
        for k in range(600):   # warm-up: kernels, writers, the fused command
            node.on_joint_state(msgs[k % len(msgs)])
        times.clear()
        taken, clamps = node.fused.taken, core.count.clamp_count
        gc.disable()
        try:
            for k in range(states):
                t0 = clock()
                node.on_joint_state(msgs[k % len(msgs)])
                times['callback, all of it'].append(clock() - t0)
        finally:
            gc.enable()
        rows = {name: (np.median(v) * 1e6, np.percentile(v, 90) * 1e6) for name, v in times.items()}
        counts = (node.fused.taken - taken, core.count.clamp_count - clamps)
    finally:
        node.destroy_node()
        rclpy.shutdown(context=ctx)
    q, qd = np.full(model.n, 0.3), np.full(model.n, 0.2)
    zeros = np.zeros(model.n)
    call = {'coriolis_term': lambda: model.coriolis_term(q, qd),
            'inverse_dynamics at qdd = 0 without gravity': lambda: model.inverse_dynamics(q, qd, zeros,
                                                                                           with_gravity=False)}
    per_call = {k: min(timeit.repeat(f, number=5000, repeat=5)) / 5000 * 1e6 for k, f in call.items()}
    return rows, counts, per_call


def main(argv=None):
    ap = argparse.ArgumentParser(prog='python -m bench.probes.node_steps', description=__doc__.split('\n')[0])
    ap.add_argument('--robot', choices=('arm7', 'talos_reduced'), default='arm7')
    ap.add_argument('--states', type=int, default=3000)
    ap.add_argument('--defaults', action='store_true')
    a = ap.parse_args(argv)
    rows, (taken, clamps), per_call = run(a.robot, a.states, a.defaults)
    print(f'{a.robot}, {"its defaults" if a.defaults else "every feature on"}, {a.states} states '
          f'(load average {os.getloadavg()[0]:.2f})')
    print('| per message | median µs | p90 µs |\n|---|---:|---:|')
    for name, (p50, p90) in rows.items():
        print(f'| {name} | {p50:.1f} | {p90:.1f} |')
    print(f'fused command path: {taken} of {a.states} commands; clamped: {clamps}')
    for name, us in per_call.items():
        print(f'{name}: {us:.2f} µs')
    return 0


if __name__ == '__main__':
    sys.exit(main())
