"""One background thread for the node's heavy work, in plain Python (no rclpy import).

Jobs are submitted to named slots ('model', 'trajectory'). Each slot holds at most one job
waiting: a newer submission replaces it (the replaced job never runs, so work cannot pile
up). A running job always finishes and its outcome is delivered: under a steady stream of
submissions the newest one still runs next, and nothing starves. Outcomes wait in a
lock-protected list; the control path checks `has_outcomes` (a plain attribute read) and
takes them with `outcomes()`.
"""
import threading
from typing import Any, NamedTuple, Optional


class Outcome(NamedTuple):
    slot: str
    tag: Any                       # what the submitter attached (e.g. the source being loaded)
    value: Any                     # the job's return value (None if it raised)
    error: Optional[BaseException]


class Worker:
    def __init__(self, name='worker', slots=('model', 'trajectory')):
        self._name = name
        self._slots = tuple(slots)      # earlier slots run first
        self._cv = threading.Condition()
        self._waiting = {}              # slot -> (tag, job)
        self._done = []
        self._thread = None
        self._stopping = False
        self.running = None             # (slot, tag) of the job in progress
        self.has_outcomes = False
        self.replaced = {s: 0 for s in self._slots}   # jobs that never ran (a newer one came first)

    def submit(self, slot, tag, job):
        """Queue job() in `slot`, replacing a job still waiting there (returns its tag, else None)."""
        with self._cv:
            if self._stopping:
                raise RuntimeError('worker stopped')
            old = self._waiting.pop(slot, None)
            if old is not None:
                self.replaced[slot] += 1
            self._waiting[slot] = (tag, job)
            if self._thread is None:
                self._thread = threading.Thread(target=self._run, name=self._name, daemon=True)
                self._thread.start()
            self._cv.notify()
        return None if old is None else old[0]

    def waiting(self, slot):
        """Tag of the job waiting in `slot`, or None."""
        item = self._waiting.get(slot)
        return None if item is None else item[0]

    def busy(self, slot):
        """Tag of the job of `slot` that runs or waits (the running one first), or None."""
        running = self.running
        if running is not None and running[0] == slot:
            return running[1]
        return self.waiting(slot)

    def outcomes(self):
        """The outcomes delivered since the last call, oldest first."""
        with self._cv:
            out, self._done = self._done, []
            self.has_outcomes = False
        return out

    def stop(self, timeout=2.0):
        """Drop waiting jobs and end the thread (a running job is waited for up to `timeout` s;
        the thread is a daemon, so one that takes longer cannot keep the process alive)."""
        with self._cv:
            self._stopping = True
            self._waiting.clear()
            self._cv.notify()
        if self._thread is not None:
            self._thread.join(timeout)

    def _next(self):
        with self._cv:
            while not self._stopping and not self._waiting:
                self._cv.wait()
            if self._stopping:
                return None
            slot = next(s for s in self._slots if s in self._waiting)
            tag, job = self._waiting.pop(slot)
            self.running = (slot, tag)
            return slot, tag, job

    def _run(self):
        while True:
            item = self._next()
            if item is None:
                return
            slot, tag, job = item
            try:
                out = Outcome(slot, tag, job(), None)
            except Exception as exc:  # noqa: BLE001 - delivered to the control path, which reports it
                out = Outcome(slot, tag, None, exc)
            with self._cv:
                self.running = None
                self._done.append(out)
                self.has_outcomes = True
