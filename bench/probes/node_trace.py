"""The dynamics node with its joint_states callback timed, for bench.node_loads --trace.

    LIE_DYNAMICS_NODE_TRACE=FILE python -m bench.probes.node_trace --ros-args ...

Runs `lie_dynamics.dynamics_node` unchanged but for a wrapper around each joint_states callback
that records, per call, its start (time.monotonic), its wall time, its thread's CPU time and the
time the thread waited for a CPU while ready (Linux /proc schedstat; 0 elsewhere), and around
each log line written, its wall time. At exit FILE gets them as JSON ({'callbacks': [[start,
wall, cpu, wait], ...], 'lines': [[start, wall], ...]}). A callback whose wall time is mostly
waiting was delayed by the machine's scheduler; one whose CPU time is long did the work itself.
"""
import json
import os
import sys
import threading
import time


def _waited():
    """Seconds this thread has waited on a run queue (schedstat's second field), or 0."""
    try:
        with open(f'/proc/self/task/{threading.get_native_id()}/schedstat') as fh:
            return int(fh.read().split()[1]) * 1e-9
    except (OSError, IndexError, ValueError):
        return 0.0


def main():
    from lie_dynamics.ros import node as node_module
    from lie_dynamics.ros.outputs import Outputs
    path = os.environ['LIE_DYNAMICS_NODE_TRACE']
    calls, lines = [], []
    on_joint_state, log_line = node_module.DynamicsNode.on_joint_state, Outputs.log_line

    def timed_callback(self, msg):
        t0, c0, w0 = time.monotonic(), time.thread_time(), _waited()
        try:
            return on_joint_state(self, msg)
        finally:
            calls.append((t0, time.monotonic() - t0, time.thread_time() - c0, _waited() - w0))

    def timed_line(self, severity, text):
        t0 = time.monotonic()
        try:
            return log_line(self, severity, text)
        finally:
            lines.append((t0, time.monotonic() - t0))
    node_module.DynamicsNode.on_joint_state = timed_callback   # before the node subscribes with it
    Outputs.log_line = timed_line
    try:
        return node_module.main()
    finally:
        with open(path, 'w') as fh:
            json.dump({'callbacks': calls, 'lines': lines}, fh)


if __name__ == '__main__':
    sys.exit(main())
