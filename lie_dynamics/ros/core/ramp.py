"""Safe transitions of the command over `ramp_time`, in plain Python (no rclpy import).

Two mechanisms, both on the compensator's clock (steady time) and both before the clamp:
* level, in [0, 1], scales the law's command. It moves toward `target` (1: enabled,
  0: disabled) at 1/duration per second, counted from the first command computed after the
  change (while no command is computed, e.g. before the first joint_states, it does not move).
* blend (bumpless transfer): after `switch()` the next command continues from the previous
  output, and the difference between them decays linearly to zero over `duration`:
      out(t) = law_new(x) + (1 - w) (out_prev - law_new(x_0)),  w = (t - t_0) / duration.
  At a constant state this is exactly (1 - w) law_old + w law_new; a switch during a blend
  starts from where the command is, so switches never step the command. Unlike evaluating the
  old law beside the new one, it costs nothing per command and needs no copy of the old model.
duration 0 turns both off: the level jumps to its target, switches take effect at once.
"""
import numpy as np


class Ramp:
    def __init__(self, duration, level=1.0):
        self.duration = float(duration)
        self.level = float(level)
        self.target = float(level)
        self.level_time = None   # when the level last moved (None: it starts at the next command)
        self.offset = None       # decaying difference of a blend (law space), or None
        self.offset_time = None
        self.switched = False    # a blend starts at the next command
        self.last = None         # the last command before the level (where a blend starts from)
        self.idle = True         # nothing to do: the command is the law's (hot-path test)

    def _update(self):
        self.idle = not self.switched and self.offset is None and self.level == 1.0 and self.target == 1.0

    def set_duration(self, duration):
        self.duration = float(duration)
        if self.duration <= 0:
            self.level, self.offset, self.switched = self.target, None, False
        self._update()

    def set_target(self, target, now):
        """Ramp toward `target` (1 or 0), from the current level: a ramp in motion turns around
        in time; one from rest starts at the next command."""
        if self.level_time is not None and self.level != self.target:
            self.advance(now)
        else:
            self.level_time = None
        self.target = float(target)
        if self.duration <= 0:
            self.level = self.target
        self._update()

    def switch(self):
        """The law changes: blend from the previous command to it (no-op when duration is 0)."""
        if self.duration > 0 and self.last is not None:
            self.switched = True
            self._update()

    def restart(self, command):
        """The command became `command` outside the law (the stale action): full level, and the
        next command blends from it."""
        self.level = self.target = 1.0
        self.level_time = self.offset = None
        self.last = command
        self.switched = False
        self.switch()

    def start(self, now):
        """The level moves from `now` on (not from the next command: the timer drives a ramp
        without input)."""
        self.level_time = now

    def stop(self):
        """Ramped down and silent: level 0 at target 0, no blend under way."""
        self.level = self.target = 0.0
        self.offset = None
        self._update()

    def note(self, command):
        """A command that went out unshaped (idle): a later blend starts from it."""
        self.last = command

    def advance(self, now):
        """Move the level to time `now`; returns it."""
        if self.level_time is None or self.duration <= 0:
            self.level_time = now
            if self.duration <= 0:
                self.level = self.target
        else:
            step = (now - self.level_time) / self.duration
            self.level_time = now
            if self.target > self.level:
                self.level = min(self.level + step, self.target)
            elif self.target < self.level:
                self.level = max(self.level - step, self.target)
        self._update()
        return self.level

    def shape(self, tau, now):
        """The command for law torque `tau` at `now` (before the clamp)."""
        if self.switched:
            self.switched = False
            d = None if self.last is None else self.last - tau
            if d is not None and np.all(np.isfinite(d)):
                self.offset, self.offset_time = d, now
        out = tau
        if self.offset is not None:
            w = (now - self.offset_time) / self.duration if self.duration > 0 else 1.0
            if w >= 1.0:
                self.offset = None
            else:
                out = tau + (1.0 - w) * self.offset
        self.last = out
        if self.level != 1.0 or self.target != 1.0:
            level = self.advance(now)
            if level != 1.0:
                out = out * level
        self._update()
        return out

    @property
    def down(self):
        """Ramped down completely to 0 (a disable has finished)."""
        return self.target == 0.0 and self.level == 0.0
