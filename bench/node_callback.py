"""The dynamics node's joint_states callback, this tree against another checkout, in one process.

    python -m bench.node_callback BEFORE_SRC [--rounds R] [--quick]

BEFORE_SRC is the root of another checkout (as for bench.probes.ab, whose loader imports it as
`lie_dynamics_before`). Both nodes run in one rclpy context, with real publishers (no DDS
reader), on the bundled arm in gravity mode, with the observer on (its default) and off, and
this tree's node once more with all four dynamics topics at every state (dynamics.publish:
gravity, coriolis, mass_matrix, jacobian; dynamics.rate: 0; the last row, against this tree
with them off). Each
one gets what its subscription delivers for the same serialized messages: a checkout whose
node subscribes raw is given the bytes; one that subscribes typed is timed for rclpy's
deserialization plus its callback, which is what its executor runs per message. Rounds are
interleaved (the order rotates); the table shows per-message medians and the median, over
rounds, of after/before. This is a benchmark, not a test: read the ratios.
"""
import argparse
import inspect
import sys

import numpy as np

from bench.probes.ab import load_before
from bench.common import time_interleaved
from lie_dynamics import default_urdf_path

JOINTS = [f'joint{i}' for i in range(1, 8)]


def messages(n, seed=0):
    """n serialized JointStates of the arm: positions in range at rest, efforts g(q); no stamp
    (the messages are sent round and round: a stamp would go back in time and be refused)."""
    from rclpy.serialization import serialize_message
    from sensor_msgs.msg import JointState
    from lie_dynamics import load_urdf
    model = load_urdf(default_urdf_path())
    lo, hi = np.maximum(model.position_lower, -3.0), np.minimum(model.position_upper, 3.0)
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        q = rng.uniform(lo, hi)   # at rest, efforts holding it: no collision is flagged
        m = JointState(name=JOINTS, position=q.tolist(), velocity=[0.0] * 7, effort=model.gravity(q).tolist())
        out.append(bytes(serialize_message(m)))
    return out


def _takes_bytes(node_cls):
    """Does this version's joint_states subscription deliver serialized messages? (Its table of
    interfaces says, or, in a version without one, the line that subscribes.)"""
    table = getattr(sys.modules[node_cls.__module__], 'interfaces', None)
    if table is not None:
        return table.INTERFACES['joint_states'].raw
    return 'raw=True' in inspect.getsource(node_cls._start).split("'joint_states'")[1].split('\n')[0]


def _timed(cls, name, ctx, msgs, nodes, params):
    """A callable feeding this tree's node `name` the serialized messages round and round."""
    node = cls(name, context=ctx, parameter_overrides=params)
    nodes.append(node)
    state = {'k': 0}

    def fn():
        node.on_joint_state(msgs[state['k'] % len(msgs)])
        state['k'] += 1
    return fn


def run(before_src, rounds=31, quick=False):
    import rclpy
    from rclpy.parameter import Parameter
    from rclpy.serialization import deserialize_message
    from sensor_msgs.msg import JointState

    from lie_dynamics.ros.node import DynamicsNode
    before = load_before(before_src)
    from lie_dynamics_before.ros.node import DynamicsNode as BeforeNode   # noqa: E402 - loaded just above
    msgs = messages(200 if quick else 1000)
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    nodes, fns = [], {}
    try:
        for observer in (True, False):
            for label, cls in (('before', BeforeNode), ('after', DynamicsNode)):
                params = [Parameter('urdf_path', value=default_urdf_path()), Parameter('stale_timeout', value=60.0),
                          Parameter('observer.enabled', value=observer)]
                node = cls(f'callback_bench_{label}_{int(observer)}', context=ctx, parameter_overrides=params)
                nodes.append(node)
                state = {'k': 0}
                if _takes_bytes(cls):
                    def fn(node=node, state=state):
                        node.on_joint_state(msgs[state['k'] % len(msgs)])
                        state['k'] += 1
                else:
                    def fn(node=node, state=state):
                        node.on_joint_state(deserialize_message(msgs[state['k'] % len(msgs)], JointState))
                        state['k'] += 1
                fns[(observer, label)] = fn
        fns[('topics', 'after')] = _timed(DynamicsNode, 'callback_bench_topics', ctx, msgs, nodes, [
            Parameter('urdf_path', value=default_urdf_path()), Parameter('stale_timeout', value=60.0),
            Parameter('dynamics.publish', value=['gravity', 'coriolis', 'mass_matrix', 'jacobian']),
            Parameter('dynamics.rate', value=0.0)])
        for fn in fns.values():   # warm-up: kernels, name maps
            for _ in range(50):
                fn()
        times = time_interleaved(fns, 5 if quick else rounds, 0.02, rotate=True, pause_gc=True)
        accepted = {key: n.core.count.accepted for key, n in zip(fns, nodes)}
    finally:
        for node in nodes:
            node.destroy_node()
        rclpy.shutdown(context=ctx)
    del before
    rows = []
    for observer in (True, False, 'topics'):
        b, a = (times[(True, 'after')], times[('topics', 'after')]) if observer == 'topics' else \
            (times[(observer, 'before')], times[(observer, 'after')])
        ratios = a / b
        rows.append({'observer': observer, 'before_us': float(np.median(b) * 1e6),
                     'after_us': float(np.median(a) * 1e6),
                     'ratio_median': float(np.median(ratios)), 'ratio_p10': float(np.percentile(ratios, 10)),
                     'ratio_p90': float(np.percentile(ratios, 90)),
                     'accepted': (accepted[(True, 'after')] if observer == 'topics' else accepted[(observer, 'before')],
                                  accepted[(observer, 'after')])})
    return rows


def markdown(rows):
    lines = ['| observer | before µs/msg | after µs/msg | after/before (median, p10-p90 of rounds) | accepted |',
             '|---|---|---|---|---|']
    for r in rows:
        what = ('on; before = this tree, after = the same + 4 dynamics topics at every state'
                if r['observer'] == 'topics' else 'on' if r['observer'] else 'off')
        lines.append(f"| {what} | {r['before_us']:.1f} | {r['after_us']:.1f} | "
                     f"{r['ratio_median']:.3f} ({r['ratio_p10']:.3f}-{r['ratio_p90']:.3f}) | {r['accepted']} |")
    return '\n'.join(lines)


def main(argv=None):
    p = argparse.ArgumentParser(prog='python -m bench.node_callback', description=__doc__.splitlines()[0])
    p.add_argument('before_src')
    p.add_argument('--rounds', type=int, default=31)
    p.add_argument('--quick', action='store_true')
    a = p.parse_args(argv)
    print(markdown(run(a.before_src, a.rounds, a.quick)))
    return 0


if __name__ == '__main__':
    sys.exit(main())
