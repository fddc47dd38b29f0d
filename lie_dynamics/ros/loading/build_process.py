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
import subprocess
import sys
import threading
import time

from ...codegen import native
from ..core.descriptions import build, read_description
from ..core.pipe import TIMEOUT, child_setup, receive, send, start_child
from .models import warm_up

BUILD_TIMEOUT_S = 120.0   # a build that takes longer is taken for hung (a 5,000-link chain: ~3 s)


class BuildLost(RuntimeError):
    """The build process died or did not answer in time (it has been killed)."""


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
