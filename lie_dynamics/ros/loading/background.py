"""The dynamics node's heavy work off the control path, in plain Python (no rclpy import).

Reading a robot description and building its model run in a child process (build_process.py:
the interpreter lock stays with the control path; it also compiles the model's native kernels
into the disk cache), driven by one worker thread (worker.py) that waits for the model without
the lock, then loads its code (a warm-up call: once per robot structure, cached) and checks it
against the settings. The control path (the executor thread: joint_states callbacks and the
timer) calls `collect()`, a plain attribute test while nothing has finished, and swaps a
finished model in there, between two commands: until then the previous model answers every
joint_states message. A description arriving while another one loads replaces the one
waiting, so loads never pile up; the newest always loads last.

Trajectories are taken, filled and published by the trajectory process
(trajectories/process.py): the worker thread answers its questions with the fill of the
running model and settings (or the refusal: more points than max_trajectory_points, no model,
disabled), and `collect()` counts and logs its outcomes.

Cheap refusals happen at once, on the control path: description_update 'none' with a model
running, a description over max_description_bytes or max_description_links, text that is not
XML, a file that does not exist.

Python threads share one interpreter lock: a long call into C that keeps it (parsing XML,
converting or taking a large message) delays the control path by its length. Descriptions are
therefore parsed in another process, trajectories never enter the node's process, and the caps
bound the rest. A build process that dies or hangs is reported like a refused description
(the running model stays) and replaced at the next load.
"""
import contextlib
import ctypes
import functools
import os
import sys
import weakref

from ...codegen import runtime
from .build_process import BuildProcess
from ..core.descriptions import build, read_description, update_refusal
from ..core.diagnostics import clip
from ..core.messages import Rejected
from .models import portable, warm_up
from .sources import open_source, resolve_path, source_label
from ..trajectories.fill import TrajectoryInput
from ..trajectories.process import TrajectoryProcess
from .worker import Worker


# Heavy jobs leave freed memory in the allocator's arenas (the worker thread has its own);
# glibc's malloc_trim hands it back to the system (measured: 309 -> 232 MB after five
# 100,000-point trajectories). Inputs below TRIM_BYTES are not worth the call.
TRIM_BYTES = 1 << 20
try:
    _MALLOC_TRIM = ctypes.CDLL(None).malloc_trim
except (OSError, AttributeError):  # not glibc
    _MALLOC_TRIM = None


# While a job runs, the loader thread hands the interpreter lock over within this time when the
# control path waits for it (Python's default, 5 ms, widened the gaps between replies by as much).
JOB_SWITCH_INTERVAL_S = 0.0005


@contextlib.contextmanager
def short_switch_interval():
    """sys.setswitchinterval(JOB_SWITCH_INTERVAL_S) for the duration (restored after)."""
    old = sys.getswitchinterval()
    sys.setswitchinterval(min(old, JOB_SWITCH_INTERVAL_S))
    try:
        yield
    finally:
        sys.setswitchinterval(old)


def release_memory():
    """Return freed heap memory to the system where the C library can (glibc)."""
    if _MALLOC_TRIM is not None:
        _MALLOC_TRIM(0)


class Background:
    """Loads for a Compensator `core`, whose running model's source `sources` (sources.Sources)
    tracks, and the trajectory process: `trajectories` is its start configuration
    (trajectories/process.py; None: no trajectories served). kernels(settings): the keys of the
    kernels the node's features call (features/base.py), warmed with every new model."""

    def __init__(self, core, sources, trajectories=None, kernels=None):
        self.core = core
        self.sources = sources
        self.kernels = kernels or (lambda settings: ())
        self.worker = Worker('lie_dynamics_loader', slots=('model', 'trajectory', 'kernels'))
        self._later = {}   # (id(model), kernel name) -> (model ref, spec): builds the control path deferred
        self._failed = {}   # the same, for builds that raised
        self.builds_deferred = 0   # kernels the control path lacked (not warmed with their model)
        self._deferring = runtime.deferred(self._request_build)
        self.process = BuildProcess()   # its child starts with the first load (expect_description: at start-up)
        self.running_xml = None         # the description text of the running model
        self.trajectories = None
        self.trajectory_input = TrajectoryInput(core)   # the checks and counts of the fills
        if trajectories is not None:
            self.trajectories = TrajectoryProcess(trajectories, self._on_ask)
            self.trajectories.start()

    # ------------------------------------------------------------------ robot descriptions
    def expect_description(self):
        """No model yet: the first one comes from a topic or a parameter, built in the build
        process, which starts now (its start-up overlaps the wait instead of delaying the model)."""
        self.process.prestart()

    def precheck(self, kind, text, settings=None):
        """Why the description (kind, text) is refused before it is read, or None."""
        s = self.core.settings if settings is None else settings
        refusal = update_refusal(s.description_update, self.core.model)
        if refusal:
            return refusal
        cap = s.max_description_bytes
        if kind == 'file':
            path = resolve_path(text)
            if not os.path.isfile(path):
                return f'URDF file not found: {clip(repr(path), 300)}'
            size = os.path.getsize(path)
        else:
            if not text.lstrip().startswith('<'):
                return 'not URDF XML'
            size = len(text) if len(text) > cap or text.isascii() else len(text.encode('utf-8', 'replace'))
        if size > cap:
            return f'{size} bytes, more than max_description_bytes ({cap})'
        return None

    def _build(self, kind, text, inertia, remote=True):
        """The Plan of a new model (worker thread): read and build (in the build process when
        remote, else here: start-up), configure, warm up. (A build here records load_urdf's
        warnings with warnings.catch_warnings, which acts on the whole process while it runs.)"""
        core = self.core
        s = core.settings
        source, label = open_source(kind, text)
        caps = (kind == 'file', s.max_description_bytes, s.max_description_links)
        xml = read_description(source, caps) if kind == 'file' else text   # what a repeat is compared with
        keys = self.kernels(s)
        builder = (functools.partial(self.process.build, caps=caps, warm=portable(keys)) if remote
                   else functools.partial(build, caps=caps))
        try:
            with short_switch_interval():
                model = core.build_model(source, inertia, builder=builder)
                plan = core.plan(None, model, label)
                warm_up(model, keys)
        finally:
            if not remote and len(source) > TRIM_BYTES:
                release_memory()
        return plan, xml

    def request(self, kind, text, inertia=None, settings=None, skip_identical=False):
        """Load a description in the background (it replaces a load still waiting). Returns
        None, or the reason it is refused at once (also logged and kept for the diagnostics).
        skip_identical: the text of the running model's description only becomes its source (a
        robot_description topic repeating the file the node started from): rebuilding the same
        model would only replace the model object, which ends a payload recording."""
        if (skip_identical and inertia is None and text == self.running_xml and self.core.model is not None
                and self.worker.busy('model') is None):   # (a load under way: the newest still loads last)
            self.sources.current = (kind, text)
            return None
        label = source_label(kind, text)
        try:
            err = self.precheck(kind, text, settings)
        except ValueError as exc:
            err = str(exc)
        if err:
            return self.core.note_description_error(f'{label}: {err}')
        self.worker.submit('model', (kind, text, label), lambda: self._build(kind, text, inertia))
        self.core.note_context(loading=label)
        return None

    def load_now(self, kind, text, inertia=None):
        """Load a description in this thread (start-up). Returns None or the error text."""
        label = source_label(kind, text)
        try:
            err = self.precheck(kind, text)
            if err is None:
                return self._install((kind, text, label), self._build(kind, text, inertia, remote=False), None)
        except Exception as exc:  # noqa: BLE001 - any bad input: log, keep the previous model, never die
            err = str(exc) or type(exc).__name__
        return self.core.note_description_error(f'{label}: {err}')

    def _install(self, tag, built, error):
        kind, text, label = tag
        if error is None:
            try:
                plan, xml = built
                self.core.apply(plan)
                self.sources.current = (kind, text)
                self.running_xml = xml
                return None
            except ValueError as exc:  # the state moved while it loaded and the model no longer fits
                error = exc
        return self.core.note_description_error(f'{label}: {str(error) or type(error).__name__}')

    # ------------------------------------------------------------------ kernels
    def deferred(self):
        """The control path's context: it builds no kernel code (codegen.runtime.deferred); a
        kernel it lacks (a feature turned on at run time, on a structure whose kernels no cache
        holds) is built in the loader thread, and until then the reference answers."""
        return self._deferring

    def _request_build(self, model, spec):
        key = (id(model), spec.name)
        asked = self._later.get(key) or self._failed.get(key)
        if asked is None or asked[0]() is not model:   # (a failed build is not asked for again)
            self._later[key] = (weakref.ref(model), spec)
            self.builds_deferred += 1
            try:
                self.worker.submit('kernels', 'kernels', self._build_later)
            except RuntimeError:   # the node is stopping
                pass

    def _build_later(self):
        """(worker thread) The kernels the control path asked for; the first error is raised
        (reported once) after the others are built, and a failed one is not asked for again."""
        error = None
        with short_switch_interval():
            for key, (ref, spec) in list(self._later.items()):
                model = ref()
                try:
                    if model is not None:
                        runtime.build(model, spec)
                except Exception as exc:  # noqa: BLE001 - reported by collect
                    error = error or exc
                    self._failed[key] = (ref, spec)
                self._later.pop(key, None)
        if error is not None:
            raise error

    # ------------------------------------------------------------------ trajectories
    def _on_ask(self, child, seq, points):
        """The trajectory process has a trajectory of `points` points (its reader thread)."""
        try:
            self.worker.submit('trajectory', 'trajectory', lambda: self._answer(child, seq, points))
        except RuntimeError:   # the node is stopping (and the child with it)
            pass

    def _start_trajectories(self):
        """(worker thread: the child dies with it) A new trajectory process, unless started too recently."""
        self.trajectories.start()

    def _answer(self, child, seq, points):
        """(worker thread) Answer the trajectory process: the fill of the running model and
        settings, or a refusal, returned as (text, kind) for the control path to count."""
        cap = self.core.settings.max_trajectory_points
        job = self.trajectory_input.job(points)
        refused = isinstance(job, Rejected)
        try:
            with short_switch_interval():   # pickling a large model: milliseconds, in Python in part
                self.trajectories.answer(child, seq, None if refused else job, cap)
        except Exception:
            self.trajectories.answer(child, seq, None, cap)   # it must not wait: refused, counted here
            raise
        return (job.text, job.kind) if refused else None

    # ------------------------------------------------------------------ control path
    def swap_in(self):
        """Take the finished jobs' outcomes: a finished model swaps in (control path, before a
        command; an attribute test while nothing finished)."""
        worker, core = self.worker, self.core
        if worker.has_outcomes:
            for out in worker.outcomes():
                if out.slot == 'model':
                    self._install(out.tag, out.value, out.error)
                elif out.slot == 'kernels':
                    if out.error is not None:
                        core.event('warn', 'kernels', f'a kernel could not be built: '
                                                      f'{type(out.error).__name__}: {out.error}')
                elif out.error is not None:   # the trajectory process was not answered: it waits for a fill
                    self.trajectory_input.done(f'{type(out.error).__name__}: {out.error}')
                elif out.value is not None:   # refused: counted here
                    self.trajectory_input.done(out.value[0], kind=out.value[1])

    def collect(self):
        """swap_in, then account for finished fills and the loader's state (control path, cheap;
        the joint_states callback calls it after the command)."""
        self.swap_in()
        worker, core = self.worker, self.core
        busy = worker.busy('model')
        core.note_context(loading=busy[2] if busy is not None else '')
        tp = self.trajectories
        if tp is None:
            return
        for msg in tp.collect():
            if msg[0] == 'done':
                self.trajectory_input.done(msg[1], msg[2], kind=msg[3] or 'malformed')
            elif msg[2]:   # a child lost during a fill: that trajectory is rejected
                self.trajectory_input.done(msg[1] + ' while filling', kind='process')
            else:
                core.event('warn', 'trajectory:process', f'{msg[1]}; a new one starts')
        if not tp.running and worker.busy('trajectory') is None:
            worker.submit('trajectory', 'start', self._start_trajectories)

    def stop_trajectories(self):
        """Tell the trajectory process to leave the ROS graph and exit, without waiting for it
        (stop() does): none starts again."""
        if self.trajectories is not None:
            self.trajectories.stop(wait=False)

    def stop(self, timeout=2.0):
        """End the child processes and the loader thread (no job of it touches the node's ROS
        entities). The trajectory process is waited for before the loader thread ends: a child
        that thread started gets SIGKILL when it ends, before leaving the ROS graph."""
        self.stop_trajectories()   # first: none starts again
        self.process.stop()   # first: a build waited for ends at once, and none starts after
        if self.trajectories is not None:
            self.trajectories.stop()
        self.worker.stop(timeout)
        if self.trajectories is not None:
            self.trajectories.stop()
