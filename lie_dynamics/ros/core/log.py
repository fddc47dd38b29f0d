"""The dynamics node's log decisions, in plain Python (no rclpy import): at most one line per
problem class (throttle key) every LOG_THROTTLE_S seconds; what is held back is counted in the
class's next line, or said by `held` once the period is over (the node's timer, and shutdown);
every line at most LOG_TEXT_MAX characters. Writing a line is the caller's `emit(severity, text)`.
"""
import collections
import time

from .diagnostics import DIAG_TEXT_MAX, LOG_TEXT_MAX, Throttle, clip, held_text

LOG_THROTTLE_S = 2.0
# A paced log writes this many lines per flush: one per node callback. A model swap decides
# several lines at once; with rclpy's Python logger (0.2-1.3 ms per line: it inspects the caller's
# frames; the node now writes through its C call, outputs.py) they delayed the next reply by a
# millisecond or more when written in one joint_states callback.
LOG_LINES_PER_CALLBACK = 1
LOG_QUEUE_MAX = 1000   # lines waiting to be written; beyond it they are counted, not kept


class EventLog:
    """Events (severity, key, text) -> throttled lines through emit(severity, text); key None:
    never throttled. pace None: each line is written as it is decided; else lines wait in order
    and flush(limit) writes them."""

    def __init__(self, emit, period=LOG_THROTTLE_S, clock=time.monotonic, pace=None, queue_max=LOG_QUEUE_MAX):
        self.emit = emit
        self.period = period
        self.throttle = Throttle(period, clock)
        self.pace = pace
        self.queue_max = queue_max
        self._queue = collections.deque()
        self.dropped = 0
        self._samples = None   # the caller's message count at the last tick

    def event(self, severity, key, text):
        """One line, at most one per `key` every `period` s."""
        if key is not None:
            held = self.throttle.check(key, payload=(severity, text))
            if held is None:
                return
            text = held_text(text, held, self.period)
        self._write(severity, text)

    def events(self, events):
        for severity, key, text in events:
            self.event(severity, key, text)

    def held(self, now=None):
        """Classes whose period ended with lines held back: their newest line, with how many more."""
        for (severity, text), more in self.throttle.due(now):
            self._write(severity, held_text(text, more, self.period))

    def tick(self, samples, now=None):
        """(a timer) The held-back lines that are due (held), then the waiting lines: all of them
        when no message came since the last tick (`samples`, a count the caller keeps), else
        one pace."""
        self.held(now)
        idle, self._samples = samples == self._samples, samples
        self.flush(None if idle or self.pace is None else self.pace)

    def close(self):
        """Everything said (shutdown): the held-back lines, then every waiting one."""
        self.held(float('inf'))
        self.flush()

    def _write(self, severity, text):
        text = clip(text, LOG_TEXT_MAX)
        if self.pace is None:
            self.emit(severity, text)
        elif len(self._queue) < self.queue_max:
            self._queue.append((severity, text))
        else:
            self.dropped += 1

    @property
    def waiting(self):
        """Lines decided and not yet written (a paced log)."""
        return len(self._queue)

    def flush(self, limit=None):
        """Write up to `limit` waiting lines, oldest first (None: all of them); then, with room
        left, how many lines did not fit in the queue."""
        n = 0
        while self._queue and (limit is None or n < limit):
            self.emit(*self._queue.popleft())
            n += 1
        if self.dropped and not self._queue and (limit is None or n < limit):
            self.emit('warn', f'log lines not written: {self.dropped} (more than {self.queue_max} were waiting)')
            self.dropped = 0


def guarded(callback):
    """A node callback that never lets the node die on input: an unexpected exception is kept
    as the core's last_error and logged (`self.log_event`), not raised; a service callback
    (named _srv*) answers with its response as it stands."""
    def wrapper(self, *args):
        try:
            return callback(self, *args)
        except Exception as exc:  # noqa: BLE001 - last line of defence
            text = clip(f'{callback.__name__}: {type(exc).__name__}: {exc}', DIAG_TEXT_MAX)
            self.core.last_error = text
            self.log_event('error', 'internal:' + callback.__name__, f'internal error in {text}')
            return args[-1] if callback.__name__.startswith('_srv') else None
    wrapper.__name__ = callback.__name__
    return wrapper
