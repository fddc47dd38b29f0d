"""The process shell shared by the package's nodes: arguments, init, spin, stop cleanly on SIGINT/SIGTERM.

rclpy's own signal handler raises KeyboardInterrupt wherever the process happens to be
(a second Ctrl-C inside destroy_node leaves DDS shared-memory files behind), so signals
only set a flag here and the spin loop ends in its own time.

Bad arguments or parameters end in one line on stderr and exit status 2, never in a
traceback: malformed --ros-args (`<node>: error: ...`), arguments outside --ros-args that
the node's parser refuses (`<node>: error: ... (see --help)`), and a node that cannot be
built from its parameters (`<node>: invalid configuration: ...`).
"""
import gc
import os
import signal
import sys

import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.signals import SignalHandlerOptions
from rclpy.utilities import remove_ros_args

from ..cli import CliParser, one_line

PARAMETERS_HELP = ('parameters (--ros-args -p name:=value ..., or --ros-args --params-file file.yaml;\n'
                   'doubles need a decimal point: 1.0, not 1; arrays: "name:=[0.0,1.5]"), defaults shown:')


def _literal(value):
    """A parameter value the way `-p name:=value` writes it."""
    if isinstance(value, bool):
        return 'true' if value else 'false'
    if isinstance(value, (list, tuple)):
        return '[' + ','.join(_literal(v) for v in value) + ']'
    if isinstance(value, str):
        return value if value else "''"
    return repr(value)


def node_parser(name, description, parameters, example):
    """The --help of a node: description, its ROS parameters and an example.

    parameters: (name, default, meaning) rows, the node's declaration table. The parser
    accepts no argument of its own: everything else goes after --ros-args.
    """
    lines = [PARAMETERS_HELP]
    for pname, default, meaning in parameters:
        setting = f'  {pname}:={_literal(default)}'
        lines.append(f'{setting:<34}{meaning}' if len(setting) < 34 else f'{setting}\n{"":34}{meaning}')
    epilog = '\n'.join(lines) + '\nexample:\n' + '\n'.join('  ' + e for e in example.strip().splitlines()) + '\n'
    return CliParser(name, prog=name, description=description, epilog=epilog,
                     usage='%(prog)s [-h] [--ros-args [-p NAME:=VALUE ...] [--params-file FILE] ...]')


# Which executor spins the package's nodes: rclpy's EventsExecutor (measured here: a third of the
# default executor's CPU and a lower p99 at 1 kHz, bench/node_latency.py) unless the environment
# asks for the default one. Its spin() was seen busy-looping, so it is driven by spin_once.
EXECUTOR_ENV = 'LIE_DYNAMICS_EXECUTOR'
EXECUTORS = ('events', 'single_threaded')


def make_executor(choice=None):
    """(executor, name): `choice` (default: $LIE_DYNAMICS_EXECUTOR, else 'events'); falls back to
    the SingleThreadedExecutor when the EventsExecutor is missing or refuses to start."""
    choice = choice or os.environ.get(EXECUTOR_ENV) or 'events'
    if choice not in EXECUTORS:
        raise ValueError(f'{EXECUTOR_ENV} must be one of {", ".join(EXECUTORS)}, got {choice!r}')
    if choice == 'events':
        try:
            from rclpy.experimental import EventsExecutor
            return EventsExecutor(), 'events'
        except Exception:  # noqa: BLE001 - an rclpy without it, or one that cannot create it
            pass
    return SingleThreadedExecutor(), 'single_threaded'


STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)


def _stopping():
    """The process is stopping: a repeated stop request (Ctrl-C again, a launcher escalating)
    changes nothing, up to the very end. Ignored rather than left to the flag's handler: the
    interpreter's exit puts a Python handler back to the default action, and a signal in its
    last moments would kill a process that stopped cleanly (-2). SIGKILL still ends a hung one."""
    for sig in STOP_SIGNALS:
        signal.signal(sig, signal.SIG_IGN)


def _refuse(name, what, exc):
    print(f'{name}: {what}: {one_line(exc)}', file=sys.stderr)
    return 2


def run(make_node, name, args=None, done=None, on_stop=None, parser=None):
    """Spin make_node() on the chosen executor (make_executor) until a signal, done(node) or rclpy
    shutdown.

    args: the command line, program name first (default sys.argv). parser (node_parser):
    prints --help and refuses arguments outside --ros-args; without one they are ignored.
    Malformed ROS arguments, and a node that cannot be built (invalid parameters), exit with
    code 2 and one line saying why. on_stop(node) runs once before the node is destroyed
    (e.g. a last safe command).
    """
    argv = list(sys.argv if args is None else args)
    try:
        # rcl parses here without logging; rclpy.init would log an error and raise a long message
        rest = remove_ros_args(argv)
    except RuntimeError as exc:
        if type(exc).__name__ == 'UnknownROSArgsError':  # its message is just the list of arguments
            exc = ValueError(f'unknown ROS arguments {exc} (see --help)')
        return _refuse(name, 'error', exc)
    if parser is not None:
        parser.parse_args(rest[1:])  # --help: prints and exits 0; anything else: one line, exit 2
    try:
        rclpy.init(args=argv, signal_handler_options=SignalHandlerOptions.NO)
    except RuntimeError as exc:  # e.g. an invalid ROS_DOMAIN_ID
        return _refuse(name, 'error', exc)
    stop = []

    def on_stop_signal(*_):
        # Ignore further requests first, then note this one in a list (no lock): a flood of
        # signals otherwise nests this handler until RecursionError, and an Event's set()
        # interrupted by its own handler waits on its own lock.
        _stopping()
        stop.append(True)
    for sig in STOP_SIGNALS:
        signal.signal(sig, on_stop_signal)
    executor = None
    try:
        executor, kind = make_executor()
        node = make_node()
    except Exception as exc:  # noqa: BLE001 - any failure to build the node: refuse to start, say why
        _stopping()
        if executor is not None:   # its threads must not outlive the context (abort at exit)
            executor.shutdown()
        rclpy.try_shutdown()
        return _refuse(name, 'invalid configuration', exc)
    executor.add_node(node)
    if hasattr(node, 'note_executor'):  # shown in the node's diagnostics
        node.note_executor(kind)
    if kind == 'events' and hasattr(node, 'defer_to'):  # its tasks are cheap: they run the work after a command
        node.defer_to(executor)
    if hasattr(node, 'settle'):   # its helper processes join the ROS graph before it serves
        node.settle(cancel=lambda: bool(stop))
    # Everything built so far lives as long as the process: move it out of the collector's
    # reach, so the hot path's garbage collections scan only what the callbacks allocate.
    gc.collect()
    gc.freeze()
    try:
        while not stop and rclpy.ok() and not (done and done(node)):
            executor.spin_once(timeout_sec=0.1)
        _stopping()
        if on_stop is not None:
            on_stop(node)
    finally:
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown()
    return 0
