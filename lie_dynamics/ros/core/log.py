"""The dynamics node's log decisions, in plain Python (no rclpy import): at most one line per
problem class (throttle key) every LOG_THROTTLE_S seconds; what is held back is counted in the
class's next line, or said by `held` once the period is over (the node's timer, and shutdown);
every line at most LOG_TEXT_MAX characters. Writing a line is the caller's `emit(severity, text)`.
"""
import time

from .diagnostics import DIAG_TEXT_MAX, LOG_TEXT_MAX, Throttle, clip, held_text

LOG_THROTTLE_S = 2.0


class EventLog:
    """Events (severity, key, text) -> throttled lines through emit(severity, text); key None:
    never throttled."""

    def __init__(self, emit, period=LOG_THROTTLE_S, clock=time.monotonic):
        self.emit = emit
        self.period = period
        self.throttle = Throttle(period, clock)

    def event(self, severity, key, text):
        """One line, at most one per `key` every `period` s."""
        if key is not None:
            held = self.throttle.check(key, payload=(severity, text))
            if held is None:
                return
            text = held_text(text, held, self.period)
        self.emit(severity, clip(text, LOG_TEXT_MAX))

    def events(self, events):
        for severity, key, text in events:
            self.event(severity, key, text)

    def held(self, now=None):
        """Classes whose period ended with lines held back: their newest line, with how many more."""
        for (severity, text), more in self.throttle.due(now):
            self.emit(severity, clip(held_text(text, more, self.period), LOG_TEXT_MAX))


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
