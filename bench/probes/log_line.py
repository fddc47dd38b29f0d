"""What one log line costs the node: rclpy's Python logger (node.get_logger().warning) against the
node's own path (Outputs.log_line: rclpy's C logging call), timed in the same process in
interleaved rounds; both write the same console line and /rosout record.

    python -m bench.probes.log_line [--rounds R] [--lines N]

Console output goes to /dev/null while timing (a terminal would add its own cost to both).
Prints medians and p90 per line and their ratio. A benchmark, not a test.
"""
import argparse
import os
import sys
import time

import numpy as np


def _timed(fn, n):
    out = []
    for i in range(n):
        t = time.perf_counter()
        fn(i)
        out.append(time.perf_counter() - t)
    return out


def run(rounds=5, lines=200):
    import rclpy
    from rclpy.node import Node

    from lie_dynamics.ros.outputs import Outputs
    saved = os.dup(2)
    null = os.open(os.devnull, os.O_WRONLY)
    rclpy.init()
    node = Node('log_line_bench')
    outputs = Outputs(node, '/log_line_bench/commands')
    logger = node.get_logger()
    python = {'name': "rclpy's Python logger", 'fn': lambda i: logger.warning(f'line {i}: ' + 'x' * 100), 't': []}
    ours = {'name': 'Outputs.log_line (C call)', 'fn': lambda i: outputs.log_line('warn', f'line {i}: ' + 'x' * 100),
            't': []}
    try:
        os.dup2(null, 2)
        for _ in range(rounds):
            for c in (python, ours):
                c['t'] += _timed(c['fn'], lines)
    finally:
        os.dup2(saved, 2)
        os.close(null)
        os.close(saved)
        outputs.close()
        node.destroy_node()
        rclpy.try_shutdown()
    rows = []
    for c in (python, ours):
        median, p90 = np.percentile(c['t'], (50, 90))
        rows.append({'path': c['name'], 'median_us': 1e6 * median, 'p90_us': 1e6 * p90})
    return rows


def markdown(rows):
    out = ['| path | median µs per line | p90 µs | median against the Python logger |', '|---|---|---|---|']
    for r in rows:
        out.append(f"| {r['path']} | {r['median_us']:.1f} | {r['p90_us']:.1f} | "
                   f"{r['median_us'] / rows[0]['median_us']:.3f}× |")
    return '\n'.join(out)


def main(argv=None):
    ap = argparse.ArgumentParser(prog='python -m bench.probes.log_line', description=__doc__.split('\n')[0])
    ap.add_argument('--rounds', type=int, default=5)
    ap.add_argument('--lines', type=int, default=200, help='lines per path per round')
    a = ap.parse_args(argv)
    print(markdown(run(a.rounds, a.lines)))
    return 0


if __name__ == '__main__':
    sys.exit(main())
