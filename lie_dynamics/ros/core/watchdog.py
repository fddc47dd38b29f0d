"""Stale-input detection on an injectable clock, in plain Python (no rclpy import)."""
import time


def fresh(since, timeout, now):
    """The one freshness rule of the node's inputs (joint_states, the desired state, the gravity
    topic): an input that arrived at `since` (None: never) is fresh at `now` while it is at most
    `timeout` seconds old; older, its user falls back."""
    return since is not None and now - since <= timeout


class Watchdog:
    """Is the input stream alive? `feed` at every valid input, `expired` periodically.

    Stale = no valid input for more than `timeout` seconds. `expired` reports that once per
    stale period (so the caller acts once); the next `feed` ends the period. Before the first
    valid input nothing is stale (there is nothing to hold). clock: seconds, time.monotonic by
    default; every method also takes an explicit `now`.
    """

    def __init__(self, timeout, clock=time.monotonic):
        self.timeout = timeout
        self.clock = clock
        self.last_valid_time = None
        self.stale = False
        self.stale_events = 0

    def feed(self, now=None):
        """A valid input at `now`. True when it ends a stale period (input is back)."""
        self.last_valid_time = self.clock() if now is None else now
        if self.stale:
            self.stale = False
            return True
        return False

    def expired(self, now=None):
        """Seconds since the last valid input when the input has just become stale, else None."""
        if self.stale or self.last_valid_time is None:
            return None
        now = self.clock() if now is None else now
        if fresh(self.last_valid_time, self.timeout, now):
            return None
        self.stale = True
        self.stale_events += 1
        return now - self.last_valid_time

    @property
    def waiting(self):
        """No valid input yet, or none for longer than the timeout (as last checked)."""
        return self.stale or self.last_valid_time is None


class Every:
    """Due once per `period` seconds of `clock` (the node's diagnostics, from its faster timer);
    a late check keeps no debt (the next is a period after it)."""

    def __init__(self, period, clock=time.monotonic):
        self.period, self.clock = period, clock
        self.next = clock() + period

    def due(self):
        now = self.clock()
        if now < self.next:
            return False
        self.next += self.period
        if self.next <= now:   # more than a period late: one now, the next a period later
            self.next = now + self.period
        return True


def tick_period(stale_timeout, diagnostics_period):
    """The node's one timer serves the watchdog, ramps without input and diagnostics: stale input
    is detected between stale_timeout and 1.5 x stale_timeout. (Each wake-up costs CPU.)"""
    return max(min(stale_timeout / 2.0, diagnostics_period), 0.002)
