"""What publishing one effort command costs the node: a reused message object (rclpy converts and
serializes it) against its serialized bytes (Outputs.command: a cdr.Writer, rclpy publishes the
bytes), with and without ~/commanded_efforts, and what a bare echo node spends per message
(rclpy's deserialization of the JointState, a new Float64MultiArray, its publish), timed in one
process with real publishers (nobody subscribed) in interleaved rounds.

    python -m bench.probes.command_publish [--rounds R] [--joints N]

Prints medians per call and their ratio to the message-object path. A benchmark, not a test.
"""
import argparse
import array
import sys

import numpy as np

from bench.common import time_interleaved


def run(rounds=31, joints=7):
    import rclpy
    from rclpy.node import Node
    from rclpy.serialization import deserialize_message, serialize_message
    from sensor_msgs.msg import JointState
    from std_msgs.msg import Float64MultiArray

    from lie_dynamics.ros.outputs import Outputs
    names = [f'joint{k}' for k in range(1, joints + 1)]
    tau = np.random.default_rng(0).normal(size=joints)
    js_in = bytes(serialize_message(JointState(name=names, position=tau.tolist(), velocity=[0.0] * joints,
                                               effort=tau.tolist())))
    rclpy.init()
    node = Node('command_publish_bench')
    outputs = []
    try:
        serialized, with_js = Outputs(node, '/command_publish_bench/a'), Outputs(node, '/command_publish_bench/b')
        outputs += [serialized, with_js]
        with_js.joint_state(True)
        pub = node.create_publisher(Float64MultiArray, '/command_publish_bench/c', 10)
        js_pub = node.create_publisher(JointState, '/command_publish_bench/d', 10)
        echo_pub = node.create_publisher(Float64MultiArray, '/command_publish_bench/e', 10)
        msg, js = Float64MultiArray(), JointState(name=names)

        def objects(joint_state=False):   # the node's path before: messages reused, data assigned
            data = array.array('d', tau.tobytes())
            msg.data = data
            pub.publish(msg)
            if joint_state:
                js.header.stamp.sec, js.header.stamp.nanosec = 1, 2
                js.effort = data
                js_pub.publish(js)

        def echo():
            m = deserialize_message(js_in, JointState)
            out = Float64MultiArray()
            out.data = m.position
            echo_pub.publish(out)

        fns = {'command, message object': objects, 'command, serialized (Outputs.command)':
               lambda: serialized.command(tau, names, 5),
               'command + ~/commanded_efforts, message objects': lambda: objects(True),
               'command + ~/commanded_efforts, serialized': lambda: with_js.command(tau, names, 5),
               'echo node callback (deserialize, new message, publish)': echo}
        times = time_interleaved(fns, rounds, 0.02, rotate=True, pause_gc=True)
    finally:
        for out in outputs:   # their publishers' handles, before the node goes
            out.close()
        node.destroy_node()
        rclpy.try_shutdown()
    base = {k: times['command, message object'] for k in list(fns)[:2]}
    base.update({k: times['command + ~/commanded_efforts, message objects'] for k in list(fns)[2:4]})
    base['echo node callback (deserialize, new message, publish)'] = times['command, serialized (Outputs.command)']
    return [{'path': k, 'median_us': 1e6 * float(np.median(v)), 'ratio': float(np.median(v / base[k]))}
            for k, v in times.items()]


def markdown(rows, joints):
    out = [f'{joints} joints. Ratio: to the message-object path of the same row pair; the echo row: to the '
           'serialized command.', '', '| path | median µs per call | ratio (median of rounds) |', '|---|---|---|']
    out += [f"| {r['path']} | {r['median_us']:.2f} | {r['ratio']:.2f} |" for r in rows]
    return '\n'.join(out)


def main(argv=None):
    p = argparse.ArgumentParser(prog='python -m bench.probes.command_publish', description=__doc__.splitlines()[0])
    p.add_argument('--rounds', type=int, default=31)
    p.add_argument('--joints', type=int, default=7)
    a = p.parse_args(argv)
    print(markdown(run(a.rounds, a.joints), a.joints))
    return 0


if __name__ == '__main__':
    sys.exit(main())
