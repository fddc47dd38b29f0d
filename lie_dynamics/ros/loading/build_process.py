"""Robot models built in a separate process, in plain Python (no rclpy import).

Parsing a description and building its model is seconds of pure Python for a large robot; in
the node's process it would hold the interpreter lock that the control path needs (a
5,000-link description stalled replies by 120-133 ms). `BuildProcess` runs it in a child
interpreter instead (`python -m lie_dynamics.ros.loading.build_process`, started with exec: no fork of
a process with DDS threads), speaking pickle over a pipe: the request is the description text
or path with the caps and the build options, the answer the finished Model (it pickles its
constant data) and the warnings to re-issue, or the error text. Before it answers, the child
compiles the model's native kernels into the on-disk cache (`warm_native`), so that the node
loads them instead of tracing and rendering them under its interpreter lock. The node's loader
thread waits on the pipe without the lock.

A child that dies or does not answer within `timeout` s is killed and reported by a
`BuildLost` error (the caller keeps its model); the next build starts a new child. The child
dies with the node: it exits on end of input, ignores SIGINT (a terminal's Ctrl-C goes to the
node, which stops it), and asks the kernel for SIGKILL when the thread that started it ends
(Linux), so a killed node leaves no orphan.
"""
import ctypes
import os
import pickle
import select
import signal
import struct
import subprocess
import sys
import threading
import time
import warnings

from ... import InertiaWarning, load_urdf
from ... import SOURCE_ROOT
from ...codegen import native
from .models import update_refusal, warm_up

BUILD_TIMEOUT_S = 120.0   # a build that takes longer is taken for hung (a 5,000-link chain: ~3 s)
_LEN = struct.Struct('<Q')
_CHUNK = 1 << 20
_PR_SET_PDEATHSIG = 1
# Children yield the CPU to the node: on a machine with fewer free cores than busy threads, a
# child working at the node's priority took time slices from the control path.
CHILD_NICE = 5


class BuildLost(RuntimeError):
    """The build process died or did not answer in time (it has been killed)."""


def read_description(source, caps=None):
    """The URDF text of `source` within caps = (is_file, max_bytes, max_links): a file is read
    up to max_bytes + 1 characters; more than max_links `<link` tags (an upper bound: comments
    count too) raises ValueError before parsing. Without caps: source unchanged."""
    if caps is None:
        return source
    is_file, max_bytes, max_links = caps
    if is_file:
        with open(source, encoding='utf-8') as fh:
            source = fh.read(max_bytes + 1)
    links = source.count('<link')
    if links > max_links:
        raise ValueError(f'{links} <link> elements, more than max_description_links ({max_links})')
    return source


def build(source, caps=None, *, joints=None, gravity=(0.0, 0.0, -9.81), inertia='warn', running=None):
    """(model, other warnings) of a description: read_description, then load_urdf with its
    InertiaWarnings recorded (the model's physical_consistency() report carries them; the
    caller logs that once) and any other warning returned as (message, category, filename,
    lineno) for the caller to re-issue. running: None, or (description_update, the running
    robot's name): a model that policy refuses is refused here (models.update_refusal), so a
    child never sends back a model (thousands of bodies, perhaps) only to have it refused.
    Raises ValueError."""
    text = read_description(source, caps)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter('always', InertiaWarning)
        model = load_urdf(text, joints=joints, gravity=gravity, inertia=inertia)
    if running is not None:
        refusal = update_refusal(running[0], _Running(running[1]), model)
        if refusal:
            raise ValueError(refusal)
    other = [(str(w.message), w.category, w.filename, w.lineno) for w in caught
             if not issubclass(w.category, InertiaWarning)]
    return model, other


class _Running:
    """What update_refusal reads of the running model."""
    __slots__ = ('name',)

    def __init__(self, name):
        self.name = name


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


class BuildProcess:
    """The client side: one child at a time, started on the first build; none after `stop`."""

    def __init__(self, timeout=BUILD_TIMEOUT_S):
        self.timeout = timeout
        self._proc = None
        self.started = 0   # children started so far
        self._lock = threading.Lock()   # a child is started or the client stopped, never both at once
        self._stopped = False

    @property
    def pid(self):
        """The running child's pid, or None."""
        proc = self._proc
        return proc.pid if proc is not None and proc.poll() is None else None

    def _start(self):
        with self._lock:
            if self._stopped:
                raise BuildLost('the model build process was stopped')
            self._proc = start_child(__name__)
            self.started += 1
            return self._proc

    def prestart(self):
        """Start the child now, before its first build: its interpreter's start-up (about 0.5 s
        of CPU, seconds on a loaded machine) then overlaps the wait for a description."""
        if self._proc is None:
            try:
                self._start()
            except BuildLost:   # stopped
                pass

    def build(self, source, caps=None, *, joints=None, gravity=(0.0, 0.0, -9.81), inertia='warn', running=None,
              warm=()):
        """`build` in the child: (model, other warnings); `warm`: the keys of the kernels to
        compile there besides the base ones (models.warm_up). Raises ValueError (the
        description), BuildLost (the child died or timed out: killed; the next call starts another)."""
        proc = self._proc
        if proc is not None and proc.poll() is not None:
            self._end(proc)   # it ended between builds: close its pipes before the next child
            proc = None
        if proc is None:
            proc = self._start()
        try:
            send(proc.stdin.fileno(), (source, caps, joints, gravity, inertia, running, tuple(warm)))
            answer = receive(proc.stdout.fileno(), time.monotonic() + self.timeout, time.monotonic)
        except OSError:   # the pipe broke: the child is gone
            answer = None
        if answer is TIMEOUT:
            self._end(proc, kill=True)
            raise BuildLost(f'the model build process did not answer within {self.timeout:g} s and was killed')
        if answer is None:   # end of its output: it ended
            self._end(proc)
            code = proc.returncode
            why = f'signal {-code}' if code < 0 else f'exit status {code}'
            raise BuildLost(f'the model build process ended ({why}) while building')
        ok, value = answer
        if not ok:
            raise ValueError(value)
        return value

    def _end(self, proc, kill=False):
        for f in (proc.stdin, proc.stdout):
            try:
                f.close()
            except OSError:
                pass
        if kill:
            proc.kill()
        try:
            proc.wait(timeout=1.0)   # one that just ended, or ends on end of input
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        if self._proc is proc:
            self._proc = None

    def stop(self):
        """End the child (killed at once: what it builds is not needed any more). No child starts
        after it: a build still to come (a loader thread that outlived the node's stop) raises
        BuildLost instead of starting an interpreter for a model nobody takes."""
        with self._lock:
            self._stopped = True
            proc = self._proc
        if proc is not None:
            self._end(proc, kill=True)


def warm_native(model, kernels=()):
    """Compile the model structure's C kernels that the node calls (models.warm_up) into the
    on-disk cache (codegen/native.py), here, before the model is sent: tracing the recursion and
    rendering it is pure Python, which in the node would take the interpreter lock from the
    control path; there the kernels then load from the cache. Nothing when the native backend
    is off (the Python kernels are generated where they run)."""
    if native.wanted():
        warm_up(model, kernels)


class Builder:
    """The child's work: a request -> (True, (model, warnings)) or (False, error text). The last
    model built is kept with its description text and options: the same request again (a reload
    of an unchanged file, a description repeated) is answered with it without parsing or building
    (the node still gets a new model object: it unpickles one). `builds` counts the others."""

    def __init__(self):
        self.builds = 0
        self._last = (None, None)   # (key, answer)

    def answer(self, request):
        source, caps, joints, gravity, inertia, running, kernels = request
        try:
            text = read_description(source, caps)   # a file is read again: it may have changed
            key = (text, joints, tuple(gravity), inertia, running, tuple(kernels))
            if self._last[0] == key:
                return self._last[1]
            self.builds += 1
            answer = (True, build(text, None, joints=joints, gravity=gravity, inertia=inertia, running=running))
            warm_native(answer[1][0], kernels)
        except Exception as exc:  # noqa: BLE001 - any bad input: its reason goes back to the node
            return False, str(exc) or type(exc).__name__
        self._last = (key, answer)
        return answer


def serve(parent=None):
    """The child's loop: a request in, Builder's answer out."""
    out = child_setup(parent)
    if out is None:
        return
    native.set_jobs(max(1, native.usable_cores() - 1))   # a core stays with the node's control path
    builder = Builder()
    while True:
        request = receive(0)
        if request is None:
            return
        send(out, builder.answer(request))


if __name__ == '__main__':
    serve(int(sys.argv[1]) if len(sys.argv) > 1 else None)
