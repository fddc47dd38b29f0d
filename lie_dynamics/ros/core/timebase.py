"""The time of a sample in seconds, in plain Python (no rclpy import): the one rule by which the
node's per-sample features (the observer, the payload recording, the dynamics topics' rate)
turn a header stamp into time.

A stamped sample's time is its header stamp (the robot's clock, the simulated time in lockstep),
counted from the first stamp seen so that float seconds keep sub-microsecond resolution; an
unstamped one (stamp 0) takes the steady clock, counted from its first reading. The two bases are
never mixed: `switched` says that a sample's base differs from the previous sample's (a
simulator's first state is stamped 0), and the caller decides what a switch means for it.
"""
import time


class TimeBase:
    """Sample times in seconds (module docstring); clock: the steady clock (injectable)."""

    def __init__(self, clock=time.monotonic):
        self.clock = clock
        self.stamped = None    # the base of the last sample: header stamps (True) or the clock
        self.switched = False  # the last sample's base differs from the one before (or it is the first)
        self._stamp0 = self._clock0 = None

    def reset(self):
        """Start counting anew: the next sample of each base is its new origin."""
        self.stamped = None
        self._stamp0 = self._clock0 = None

    def seconds(self, stamp, now=None):
        """The time (s) of a sample with header stamp `stamp` (ns; 0: none, then `now` or the clock)."""
        stamped = stamp != 0
        self.switched = stamped != self.stamped
        self.stamped = stamped
        if stamped:
            if self._stamp0 is None:
                self._stamp0 = stamp
            return (stamp - self._stamp0) * 1e-9
        now = self.clock() if now is None else now
        if self._clock0 is None:
            self._clock0 = now
        return now - self._clock0
