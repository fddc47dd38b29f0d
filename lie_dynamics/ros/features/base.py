"""Per-sample features of the dynamics node: the one interface the node loops over, in plain
Python (no rclpy import).

A feature is something the node does around the torque command of each joint_states message:
publish dynamics terms, run the momentum observer, follow gravity from a topic, record for a
payload identification. The node makes each registered feature once (`DynamicsNode` in
node.py: `FEATURES`, one line each, made as `cls(node)`; topics and services it makes come
from the one table, interfaces.py) and then calls, through `Features`:

  * `check(settings, model)` on every parameter change (on-set) and at start-up: ValueError with
    the reason refuses the change (the old values stay) or the start-up (exit 2);
  * `kernels(settings)`: the warm-up calls of the generated kernels its on_sample calls under
    these settings, each a tuple (function, *args) run as function(model, *args)
    (loading/models.py: warm_up; `at_rest(model, method, states)` calls a Model method at rest),
    once for a new model where it is built and in the loading thread, so that their code is
    never generated on the control path. They travel to the build process pickled one by one
    (loading/models.py: portable): a module-level function of a module it imports (best one
    without rclpy: the feature's plain part, or at_rest) compiles there too, any other call only
    in the loading thread;
  * `configure(settings, model, derived)` when the settings or the model object changed (before
    the next sample; derived: core.settings.Derived, None without a model). The model's own
    setters (gravity, locked values) bump `model.version` instead, which the sample carries;
  * `before_command(core)` only for a feature that steers the command (it defines the method):
    before every command, asking the core through its public methods (`Compensator.use_gravity`);
  * `on_sample(sample)` with each accepted core.sample.SampleResult, once, in order, after the
    command went out, while `active` (nothing is called per sample for an inactive feature);
    through `steps(sample)`: the same work as callables run in order (by default one, calling
    on_sample). A feature marked `later` (its work only publishes: the observer, the dynamics
    topics) may have its steps run by the node in executor tasks after the command, so that a
    newer state's command goes out between two of them (the others run at once, in order); one
    also marked `coalesce` (its work for a state is worth nothing once a newer state's is queued:
    the dynamics topics) has its queued steps replaced by the newer state's;
  * `report(level, message)` -> (level, message, [(key, value string)]): its part of the
    node's one diagnostics status (registration order; `Features.report` bounds every text);
  * `events`: (severity, throttle key, text) log lines, appended to the node's one event queue
    (the same list for the core and every feature, given at registration: `use_events`) that the
    node drains through its throttled, paced log; a feature never writes a log line itself;
  * `stop()` when the node goes (worker threads, helper nodes).
"""
import functools

from ..core.diagnostics import DIAG_TEXT_MAX, clip


class Feature:
    """Base of a per-sample feature (see the module docstring); every hook does nothing."""

    name = 'feature'
    active = False
    later = False      # its steps may run in executor tasks after the command (steps)
    coalesce = False   # its queued steps of a state are dropped when a newer state's come (steps)

    def __init__(self):
        self.events = []

    def use_events(self, queue):
        """Append log lines to `queue` from now on (Features.add: the node's one queue). A feature
        whose plain part queues lines itself hands the queue on here."""
        self.events = queue

    def check(self, settings, model):
        """Validation of a planned change that needs the model (None: not loaded yet)."""

    def kernels(self, settings):
        """Warm-up calls (function, *args) of the kernels on_sample calls under `settings`
        (loading/models.py: warm_up)."""
        return ()

    def configure(self, settings, model, derived):
        """The settings or the model changed."""

    def on_sample(self, sample):
        """One new accepted sample (only while `active`)."""

    def steps(self, sample):
        """on_sample(sample)'s work as callables run in order (by default: one, on_sample)."""
        return (functools.partial(self.on_sample, sample),)

    def report(self, level, message):
        return level, message, []

    def stop(self):
        """The node is being destroyed."""


class Features:
    """The node's features: configured when the settings or the model change, fed each accepted
    sample once, reported in order. events: the one queue (a list) every feature appends to."""

    def __init__(self, features=(), events=None):
        self.events = [] if events is None else events
        self.all, self.steering = [], []
        self._settings = self._model = None
        self._last = None   # the last sample fed
        for f in features:
            self.add(f)

    def add(self, feature):
        """Register `feature` (after those already registered); its events go to the one queue."""
        feature.use_events(self.events)
        self.all.append(feature)
        if callable(getattr(feature, 'before_command', None)):
            self.steering.append(feature)
        self._settings = None   # configured at the next configure_if_changed

    def get(self, name):
        """The feature registered under `name`."""
        for f in self.all:
            if f.name == name:
                return f
        raise KeyError(name)

    def check(self, settings, model):
        for f in self.all:
            f.check(settings, model)

    def kernels(self, settings):
        """The warm-up calls of every feature under `settings`, each once, in order."""
        return tuple(dict.fromkeys(k for f in self.all for k in f.kernels(settings)))

    def changed(self, core):
        """Have core's settings or model changed since the features were last configured?"""
        return core.settings is not self._settings or core.model is not self._model

    def configure_if_changed(self, core):
        """Configure the features if core's settings or model changed since the last call."""
        if self.changed(core):
            self._settings, self._model = core.settings, core.model
            for f in self.all:
                f.configure(core.settings, core.model, core.derived)

    def before_command(self, core):
        """Before each command (joint_states and the timer): the features that steer it."""
        for f in self.steering:
            f.before_command(core)

    def feed(self, core):
        """After the command for a joint_states message: each active feature gets core.result if
        the core accepted it (a rejected message, or the same result again, feeds nothing).
        steps' work, run as it goes (no list of steps to build per sample)."""
        sample = self._new_sample(core)
        if sample is None:
            return
        for f in self.all:
            if f.active:
                if type(f).steps is Feature.steps:   # the default: its one step, without a partial
                    f.on_sample(sample)
                else:
                    for step in f.steps(sample):
                        step()

    def steps(self, core):
        """feed's work, not done: [(feature, step)] in the order feed runs them (each feature's
        `steps`); the features are configured first if core's settings or model changed."""
        sample = self._new_sample(core)
        if sample is None:
            return []
        return [(f, step) for f in self.all if f.active for step in f.steps(sample)]

    def _new_sample(self, core):
        """core.result if it is a new accepted sample (then it is the last fed), else None; the
        features configured first if core's settings or model changed."""
        self.configure_if_changed(core)
        sample = core.result
        if sample is self._last or sample is None or not sample.accepted:
            return None
        self._last = sample
        return sample

    def drain(self):
        """[(severity, key, text)] queued by the core and the features, emptied."""
        out = self.events[:]
        self.events.clear()
        return out

    def report(self, level, message, values):
        """The core's diagnostics (level, message, values) with each feature's part added; the
        message and every value bounded here, once, to DIAG_TEXT_MAX characters."""
        values = list(values)
        for f in self.all:
            level, message, more = f.report(level, message)
            values += more
        return level, clip(message, DIAG_TEXT_MAX), [(k, clip(v, DIAG_TEXT_MAX)) for k, v in values]

    def stop(self):
        for f in self.all:
            f.stop()
