"""Where isolation's cost lies in the node's callback while the flag is up: the bundled arm held
and pushed at the tool (bench.contact's 'up' case, isolated at link7), DynamicsNode.on_joint_state
in-process with isolation on beside the same node with it stubbed out (the peer), interleaved
rounds. Per message, median and quartiles (us), by its place after the last checkpoint
(ContactIsolation's, every contact_isolation.SETTLE_STEP time constant): the checkpoint itself, the
message after it (caches the checkpoint's work displaced), and the rest; and the load average.

    python -m bench.probes.contact_checkpoints [--rounds R] [--per-round M]
"""
import argparse
import os
import time

import numpy as np


def measure(rounds=20, per_round=200):
    """{'peer': (N,) us, 'on': (N,) us, 'since': (N,) int (0 = a checkpoint message)}."""
    import rclpy
    from rclpy.parameter import Parameter

    from bench.contact import cost_messages, settings_for
    from lie_dynamics import default_urdf_path, load_urdf
    from lie_dynamics.ros.features.contact_link import Published
    from lie_dynamics.ros.node import DynamicsNode
    model = load_urdf(default_urdf_path())
    s = settings_for(model)
    msgs = cost_messages(model, 100 + rounds * per_round, 'tool')
    params = {'urdf_path': default_urdf_path(), 'friction.viscous': model.damping.tolist(),
              'friction.coulomb': [0.0], 'stale_timeout': 60.0, 'collision.threshold': list(s.collision.threshold)}
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    nodes = []
    try:
        for k in range(2):
            nodes.append(DynamicsNode(f'checkpoint_probe_{k}', context=ctx,
                                      parameter_overrides=[Parameter(p, value=v) for p, v in params.items()]))
        nodes[0].features.get('contact').isolation.update = lambda *a: Published(None, None, None)
        for node in nodes:   # the push rises, the flag rises, isolation decides
            for m in msgs[:100]:
                node.on_joint_state(m)
        settling = nodes[1].features.get('contact').isolation.settling
        times, since, last = ([], []), [], None
        for r in range(rounds):
            batch = msgs[100 + r * per_round:100 + (r + 1) * per_round]
            for i in ((0, 1) if r % 2 else (1, 0)):
                for m in batch:
                    checked = settling.checked
                    t0 = time.perf_counter()
                    nodes[i].on_joint_state(m)
                    times[i].append((time.perf_counter() - t0) * 1e6)
                    if i == 1:
                        last = 0 if settling.checked != checked else (None if last is None else last + 1)
                        since.append(-1 if last is None else last)
    finally:
        for node in nodes:
            node.destroy_node()
        rclpy.shutdown(context=ctx)
    return {'peer': np.array(times[0]), 'on': np.array(times[1]), 'since': np.array(since)}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--rounds', type=int, default=20)
    ap.add_argument('--per-round', type=int, default=200)
    a = ap.parse_args(argv)
    load = os.getloadavg()[0]
    res = measure(a.rounds, a.per_round)
    peer, on, since = res['peer'], res['on'], res['since']
    print(f'load average {load:.2f} -> {os.getloadavg()[0]:.2f}; {len(on)} messages each')
    print('| messages | count | median us | p25-p75 us | median / peer median |')
    print('|---|---:|---:|---:|---:|')
    pm = np.median(peer)
    rows = [('peer (isolation stubbed)', peer), ('isolation on, all', on),
            ('checkpoint', on[since == 0]), ('the one after', on[since == 1]), ('the rest', on[since >= 2])]
    for name, x in rows:
        if x.size:
            lo, hi = np.percentile(x, [25, 75])
            print(f'| {name} | {x.size} | {np.median(x):.1f} | {lo:.1f}-{hi:.1f} | {np.median(x) / pm:.2f} |')


if __name__ == '__main__':
    main()
