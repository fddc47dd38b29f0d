"""The pipe protocol of the node's child processes (the build process, loading/build_process.py,
and the trajectory process, trajectories/process.py), in plain Python (no rclpy import): objects
pickled with their length first (`send`, `receive`), the child started with exec, not a fork of
a process with DDS threads (`start_child`), and what a child does first (`child_setup`).
"""
import ctypes
import os
import pickle
import select
import signal
import struct
import subprocess
import sys

from ... import SOURCE_ROOT

_LEN = struct.Struct('<Q')
_CHUNK = 1 << 20
_PR_SET_PDEATHSIG = 1
# Children yield the CPU to the node: on a machine with fewer free cores than busy threads, a
# child working at the node's priority took time slices from the control path.
CHILD_NICE = 5


def send(fd, obj):
    """Write obj to fd, pickled, with its length first."""
    data = pickle.dumps(obj, protocol=pickle.HIGHEST_PROTOCOL)
    view = memoryview(_LEN.pack(len(data)) + data)
    while view:
        view = view[os.write(fd, view):]


TIMEOUT = object()   # what receive returns when its deadline passes


def receive(fd, deadline=None, clock=None):
    """The next object on fd; None at end of input, TIMEOUT when `deadline` (clock()) passes."""
    buf = bytearray()
    need = _LEN.size
    size = None
    while len(buf) < need:
        if deadline is not None:
            left = deadline - clock()
            if left <= 0 or not select.select([fd], [], [], left)[0]:
                return TIMEOUT
        chunk = os.read(fd, min(_CHUNK, need - len(buf)))
        if not chunk:
            return None
        buf += chunk
        if size is None and len(buf) >= _LEN.size:
            size = _LEN.unpack_from(buf)[0]
            need = _LEN.size + size
    return pickle.loads(memoryview(buf)[_LEN.size:])


def start_child(module):
    """`python -m module <this pid>` with pipes on its stdin and stdout (exec, not a fork of a
    process with DDS threads); the child calls child_setup first. The package's source root
    leads its path, so that a source tree runs its own code."""
    env = dict(os.environ)
    env['PYTHONPATH'] = os.pathsep.join(p for p in (SOURCE_ROOT, env.get('PYTHONPATH')) if p)
    return subprocess.Popen([sys.executable, '-m', module, str(os.getpid())], stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, env=env, close_fds=True)


def child_setup(parent=None):
    """A child of start_child: dies with the thread that started it (Linux: SIGKILL), ignores
    SIGINT (a terminal's Ctrl-C goes to the parent, which stops it), runs CHILD_NICE steps
    nicer than the node, sends stray prints to stderr. Returns the descriptor its answers go to,
    or None when the parent already died."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        ctypes.CDLL(None).prctl(_PR_SET_PDEATHSIG, signal.SIGKILL)
    except (OSError, AttributeError):   # not Linux: end of input still ends the child
        pass
    if parent is not None and os.getppid() != parent:   # the parent died before prctl
        return None
    try:
        os.nice(CHILD_NICE)
    except OSError:
        pass
    out = os.dup(1)
    os.dup2(2, 1)   # stray prints go to stderr, never into the answers
    return out
