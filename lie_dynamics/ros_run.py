"""The process shell shared by the package's nodes: init, spin, stop cleanly on SIGINT/SIGTERM.

rclpy's own signal handler raises KeyboardInterrupt wherever the process happens to be
(a second Ctrl-C inside destroy_node leaves DDS shared-memory files behind), so signals
only set a flag here and the spin loop ends in its own time.
"""
import signal
import sys
import threading

import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.signals import SignalHandlerOptions


def run(make_node, name, args=None, done=None, on_stop=None):
    """Spin make_node() on a SingleThreadedExecutor until a signal, done(node) or rclpy shutdown.

    A node that cannot be built (invalid parameters) exits with code 2 and says why.
    on_stop(node) runs once before the node is destroyed (e.g. a last safe command).
    """
    rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    try:
        node = make_node()
    except Exception as exc:  # invalid configuration: refuse to start, say why
        print(f'{name}: invalid configuration: {exc}', file=sys.stderr)
        rclpy.try_shutdown()
        return 2
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    try:
        while not stop.is_set() and rclpy.ok() and not (done and done(node)):
            executor.spin_once(timeout_sec=0.1)
        if on_stop is not None:
            on_stop(node)
    finally:
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown()
    return 0
