"""Stale-input detection on an injectable clock, in plain Python (no rclpy import)."""
import time


def fresh(since, timeout, now):
    """The one freshness rule of the node's inputs (joint_states, the desired state, the gravity
    topic): an input that arrived at `since` (None: never) is fresh at `now` while it is at most
    `timeout` seconds old; older, its user falls back."""
    return since is not None and now - since <= timeout


class Freshness:
    """An input used while fresh (`fresh`) with a fallback while stale (the desired state, the
    gravity topic; joint_states has the Watchdog): the one flag, counter and pair of log lines of
    the change between the two. `check` at each use says a change once each way."""

    def __init__(self, what, timeout_name, key):
        self.what, self.timeout_name, self.key = what, timeout_name, key
        self.fallen = False   # stale at the last check (after a change said): the fallback is in use
        self.events = 0       # changes to stale so far

    def check(self, since, timeout, now, topic, never=True):
        """(fresh, line): fresh as `fresh(since, timeout, now)`; line None, or (severity, key,
        text) when the state just changed: fresh again ('<key>:resumed'), stale ('<key>:stale',
        with the input's age and the timeout), or stale without any input yet ('<key>:none';
        never=False: no change, nothing was followed). The user adds its fallback to the text."""
        if fresh(since, timeout, now):
            if self.fallen:
                self.fallen = False
                return True, ('info', f'{self.key}:resumed', f'{self.what} on {topic} fresh again')
            return True, None
        if self.fallen or (since is None and not never):
            return False, None
        self.fallen = True
        self.events += 1
        if since is None:
            return False, ('warn', f'{self.key}:none', f'no {self.what} received yet on {topic}')
        return False, ('warn', f'{self.key}:stale', f'no valid {self.what} on {topic} for {now - since:.3f} s '
                                                    f'({self.timeout_name} {timeout} s)')

    def reset(self):
        """Forget a fallback: the next stale check is said again."""
        self.fallen = False


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

    def expire(self, now=None):
        """The input is taken for stopped (shutdown): stale from now on, counted as a stale
        period. Returns the seconds since the last valid input, or None when there was none or
        it is stale already."""
        if self.stale or self.last_valid_time is None:
            return None
        now = self.clock() if now is None else now
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
