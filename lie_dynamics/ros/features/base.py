"""Per-sample features of the dynamics node: the small interface the node loops over, in plain
Python (no rclpy import).

A feature is something the node does with every accepted joint_states sample after its command
went out (publish dynamics terms, run an observer, record for an identification). The node:

  * `check(settings, model)` on every parameter change (on-set) and at start-up: ValueError with
    the reason refuses the change (the old values stay) or the start-up (exit 2);
  * `configure(settings, model)` when the settings or the model object changed (before the next
    sample; the model's own setters, gravity from a topic or locked values, bump
    `model.version` instead, which `Accepted.version` carries);
  * `on_sample(accepted)` for each new accepted sample while `active` (nothing at all is called
    per sample for an inactive feature: a feature that is off costs the node nothing);
  * `report()` -> [(key, value string)] appended to the node's diagnostics;
  * `events`: (severity, throttle key, text) log lines the node drains through its one event
    path (`DynamicsNode.log_event`: one line per key every LOG_THROTTLE_S s).

The node's own rclpy objects (publishers) are made by the feature's rclpy side from the node
it is given; everything that decides lives in methods the tests can drive without ROS.
"""
import numpy as np


class Accepted:
    """One accepted joint_states sample, after its command: q (validated positions, model order),
    stamp (ns, 0: none), the model that computed the command and its `version`, `names` (the
    command layout), and on demand, in model order: `velocity` and `effort` as the message gave
    them (NaN where absent: an observer pauses on them), and `qd` (the velocity with absent or
    non-finite entries as 0, as the torque laws use it)."""

    __slots__ = ('q', 'stamp', 'model', 'version', 'names', '_sample', '_idx', '_velocity', '_qd', '_effort')

    def __init__(self, q, stamp, model, names, sample, idx):
        self.q, self.stamp, self.model, self.version, self.names = q, stamp, model, model.version, names
        self._sample, self._idx = sample, idx   # the message's arrays and their map to model order
        self._velocity = self._qd = self._effort = None

    def _mapped(self, values):
        return np.asarray(values, dtype=float)[self._idx] if len(values) else np.full(len(self.q), np.nan)

    @property
    def velocity(self):
        if self._velocity is None:
            self._velocity = self._mapped(self._sample.velocity)
        return self._velocity

    @property
    def qd(self):
        if self._qd is None:
            v = self.velocity
            self._qd = np.where(np.isfinite(v), v, 0.0)
        return self._qd

    @property
    def effort(self):
        if self._effort is None:
            self._effort = self._mapped(self._sample.effort)
        return self._effort


class Feature:
    """Base of a per-sample feature (see the module docstring); every hook does nothing."""

    name = 'feature'
    active = False

    def __init__(self):
        self.events = []

    def check(self, settings, model):
        """Validation of a planned change that needs the model (None: not loaded yet)."""

    def configure(self, settings, model):
        """The settings or the model changed."""

    def on_sample(self, accepted):
        """One new accepted sample (only while `active`)."""

    def report(self):
        return []


class Features:
    """The node's registered features, configured when the settings or the model change and fed
    each new accepted sample. `events` of every feature are collected by `drain`."""

    def __init__(self, features=()):
        self.all = list(features)
        self.active = []
        self._settings = self._model = None
        self._accepted = 0   # core.count.accepted at the last sample fed

    def check(self, settings, model):
        for f in self.all:
            f.check(settings, model)

    def sync(self, core):
        """Configure the features if core's settings or model changed since the last call."""
        if core.settings is not self._settings or core.model is not self._model:
            self._settings, self._model = core.settings, core.model
            for f in self.all:
                f.configure(core.settings, core.model)
            self.active = [f for f in self.all if f.active]

    def feed(self, core, sample, names):
        """After the command for `sample` (cdr.JointStateSample): each active feature gets it if
        the compensator accepted it (a rejected or repeated message feeds nothing)."""
        self.sync(core)
        accepted = core.count.accepted
        fresh, self._accepted = accepted != self._accepted, accepted  # kept up to date while inactive too
        if not fresh or not self.active:
            return
        acc = Accepted(core.last_q, sample.stamp, core.model, names, sample, core.reader.map.idx)
        for f in self.active:
            f.on_sample(acc)

    @property
    def has_events(self):
        return any(f.events for f in self.all)

    def drain(self):
        """[(severity, key, text)] of every feature, emptied."""
        out = []
        for f in self.all:
            if f.events:
                out += f.events
                f.events = []
        return out

    def report(self):
        out = []
        for f in self.all:
            out += f.report()
        return out
