"""Where the dynamics node's gravity comes from, and who compensates it, in plain Python (no rclpy
import).

`GravitySource` follows a gravity vector from a topic (`gravity_topic`, geometry_msgs/Vector3Stamped
in the URDF root frame: a mobile or tilting base). Each message is checked (`check_vector`: finite,
norm at most GRAVITY_NORM_MAX, a frame the root frame or a link fixed to it); a valid one is
followed until it is older than `gravity_timeout` (steady clock, injectable). Then the node falls
back to the `gravity` parameter, says so once and in the diagnostics, and follows the topic again
when it returns. Both transitions blend the command (ramp_time), a topic update in between does
not (it follows a slowly turning base). `apply` puts the vector on the model before each command;
its fast path is two comparisons.

`robot_compensates_gravity`: a robot that adds g(q) itself (libfranka torque control, KUKA FRI
torque mode, ...) gets every law evaluated without its gravity term (laws.py, gravity=False: the
law at zero gravity; the trajectory fill likewise). Reading joint_states efforts is
contact.effort_convention's rule: `measured_effort` alone says what they hold (the sensor),
whatever `robot_compensates_gravity` says (the actuator).
"""
import time

import numpy as np

from ..core.diagnostics import clip
from ..core.watchdog import Freshness, fresh

# A gravity vector longer than this (m/s^2, 3 g) is a units or frame error, not a tilted base.
GRAVITY_NORM_MAX = 30.0
# The frame a vector without frame_id is taken to be in.
ROOT_FRAMES = ('',)


def check_vector(vector, frame_id, model):
    """The vector (3,) in the model's root frame, or raise ValueError with the reason. frame_id
    '' is the root frame; a link fixed to the root (world) is rotated into it; anything else is
    refused (a moving frame would need the joint positions of the moment it was measured)."""
    g = np.asarray(vector, dtype=float).reshape(3)
    if not np.all(np.isfinite(g)):
        raise ValueError(f'non-finite gravity vector {clip(str(g.tolist()), 120)}')
    norm = float(np.linalg.norm(g))
    if norm > GRAVITY_NORM_MAX:
        raise ValueError(f'gravity vector norm {norm:.4g} m/s^2 is above {GRAVITY_NORM_MAX:g} (units or frame?)')
    if frame_id in ROOT_FRAMES:
        return g
    place = None if model is None else model.link_frames.get(frame_id)
    if place is None:
        raise ValueError(f"gravity frame_id '{clip(frame_id, 80)}' is not a link of the robot model")
    body, T = place
    if body != -1:
        raise ValueError(f"gravity frame_id '{clip(frame_id, 80)}' moves with the joints: give the vector in the "
                         'URDF root frame')
    return np.asarray(T)[:3, :3] @ g


class GravitySource:
    """The gravity the node follows: the topic's while fresh, else the `gravity` parameter.

    offer(vector, frame_id, model, now) takes one message; apply(core, now) puts the vector in force
    on core.model (times gravity_scale). Events (severity, key, text) queue in `events` for the
    node's throttled log; counters are totals. topic: the resolved topic name ('' = none).
    """

    def __init__(self, topic='', clock=time.monotonic):
        self.topic = topic
        self.clock = clock
        self.vector = None       # last valid vector (root frame), or None
        self.time = None         # when it arrived
        self.seq = 0             # bumped by each valid vector
        self.following = False   # the last apply used the topic's vector
        self.freshness = Freshness('gravity', 'gravity_timeout', 'gravity')   # fallen: a vector came and went stale
        self.received = self.rejected = 0
        self.last_error = ''
        self.events = []
        self._key = None         # what the model's gravity was last set from

    def offer(self, vector, frame_id, model, now=None):
        """One gravity message -> accepted? A rejected one leaves the last valid vector as it was."""
        self.received += 1
        try:
            g = check_vector(vector, frame_id, model)
        except ValueError as exc:
            self.rejected += 1
            self.last_error = f'gravity on {self.topic} rejected: {exc}'   # bounded where it is shown
            self.events.append(('warn', 'gravity:rejected', self.last_error))
            return False
        self.vector = g
        self.time = self.clock() if now is None else now
        self.seq += 1
        return True

    def fresh(self, timeout, now):
        return fresh(self.time, timeout, now)

    def apply(self, core, now=None):
        """Put the gravity in force on core.model: the topic's vector while fresh, else the
        `gravity` parameter; both times gravity_scale. A switch between the two blends the command
        and is said once."""
        model = core.model
        if model is None or not self.topic:
            return
        s = core.settings
        now = self.clock() if now is None else now
        fresh, line = self.freshness.check(self.time, s.gravity_timeout, now, self.topic, never=False)
        if line is not None:   # (never came: the parameter is the gravity, nothing fell back)
            self._say(line, s)
        switched = fresh != self.following
        if switched:
            self.following = fresh
        seq = self.seq if fresh else -1
        k = self._key
        if k is not None and k[0] is model and k[2] is s and k[1] == model.version and k[3] == seq:
            return
        core.use_gravity((self.vector if fresh else np.asarray(s.gravity, dtype=float)) * s.gravity_scale,
                         blend=switched)
        self._key = (model, model.version, s, seq)

    def _say(self, line, s):
        severity, key, text = line
        self.events.append((severity, key, f'{text}: following it' if severity == 'info' else
                            f"{text}: using the gravity parameter {s.gravity}"))

    def report(self, level, message, now=None):
        """(level, message, values) additions for the node's diagnostics."""
        now = self.clock() if now is None else now
        if not self.topic:
            source = 'parameter'
        elif self.following:
            source = f'topic {self.topic}'
        else:
            source = ('parameter (fallback: topic stale)' if self.freshness.fallen else
                      f'parameter (none yet on {self.topic})')
        if self.freshness.fallen and not self.following:
            level = max(level, 1)
            message = f'{message}; gravity topic stale: gravity parameter' if message else 'gravity topic stale'
        values = [('gravity_source', source),
                  ('gravity_topic_age_ms', f'{1e3 * (now - self.time):.1f}' if self.time is not None else 'inf'),
                  ('gravity_received_total', str(self.received)),
                  ('gravity_rejected_total', str(self.rejected)),
                  ('gravity_fallback_events', str(self.freshness.events)),
                  ('gravity_error', self.last_error)]
        return level, message, values
