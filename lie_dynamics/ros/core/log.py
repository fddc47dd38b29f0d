"""The dynamics node's log decisions, in plain Python (no rclpy import): at most one line per
problem class (throttle key) every LOG_THROTTLE_S seconds; what is held back is counted in the
class's next line, or said by `held` once the period is over (the node's timer, and shutdown);
every line at most LOG_TEXT_MAX characters. Writing a line is the caller's `emit(severity, text)`.
"""
import collections
import time

from .diagnostics import LOG_TEXT_MAX, Throttle, clip, held_text

LOG_THROTTLE_S = 2.0
# A paced log writes this many lines per flush: one per node callback. A model swap decides
# several lines at once; with rclpy's Python logger (0.2-1.3 ms per line: it inspects the caller's
# frames; the node now writes through its C call, outputs.py) they delayed the next reply by a
# millisecond or more when written in one joint_states callback.
LOG_LINES_PER_CALLBACK = 1
LOG_QUEUE_MAX = 1000   # lines waiting to be written; beyond it they are counted, not kept
# A paced log writes at most this many lines in any second, whatever the input: a flood that
# touches many problem classes at once (each its one line per LOG_THROTTLE_S) waits in the queue.
LOG_LINES_PER_S = 5


class EventLog:
    """Events (severity, key, text) -> throttled lines through emit(severity, text); key None:
    never throttled. pace None: each line is written as it is decided; else lines wait in order
    and flush(limit) writes them, at most `rate` in any second (None: no bound)."""

    def __init__(self, emit, period=LOG_THROTTLE_S, clock=time.monotonic, pace=None, queue_max=LOG_QUEUE_MAX,
                 rate=None):
        self.emit = emit
        self.period = period
        self.clock = clock
        self.throttle = Throttle(period, clock)
        self.pace = pace
        self.queue_max = queue_max
        self.rate = rate
        self._queue = collections.deque()
        self._written = collections.deque()   # when the last `rate` lines were written
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
        """Everything said (shutdown): the held-back lines, then every waiting one (the rate
        does not apply)."""
        self.held(float('inf'))
        self.flush(rated=False)

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

    def flush(self, limit=None, rated=True):
        """Write up to `limit` waiting lines, oldest first (None: all of them), within the rate
        (rated=False: regardless of it, as at start-up and shutdown); then, with room left, how
        many lines did not fit in the queue."""
        n = 0
        while self._queue and (limit is None or n < limit) and self._room(rated):
            self.emit(*self._queue.popleft())
            n += 1
        if self.dropped and not self._queue and (limit is None or n < limit) and self._room(rated):
            self.emit('warn', f'log lines not written: {self.dropped} (more than {self.queue_max} were waiting)')
            self.dropped = 0

    def _room(self, rated):
        """May one more line be written now (the rate: lines in the last second)? Counts it."""
        if self.rate is None:
            return True
        now = self.clock()
        written = self._written
        while written and now - written[0] >= 1.0:
            written.popleft()
        if rated and len(written) >= self.rate:
            return False
        written.append(now)
        return True


def guarded(callback):
    """A node callback that never lets the node die on input: an unexpected exception is kept
    as the core's last error (`note_error`) and logged (`self.log_event`: the one event queue),
    not raised; a service callback (named _srv*) answers with its response as it stands."""
    def wrapper(self, *args):
        try:
            return callback(self, *args)
        except Exception as exc:  # noqa: BLE001 - last line of defence
            text = self.core.note_error(f'{callback.__name__}: {type(exc).__name__}: {exc}')
            self.log_event('error', 'internal:' + callback.__name__, f'internal error in {text}')
            return args[-1] if callback.__name__.startswith('_srv') else None
    wrapper.__name__ = callback.__name__
    return wrapper
