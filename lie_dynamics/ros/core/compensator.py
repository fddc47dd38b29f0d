"""Decision logic of the dynamics node, in plain Python (no rclpy import).

`Compensator` turns joint_states messages into effort commands. It wires the pieces
(messages.py: reading and checking input; lie_dynamics.laws: torque laws, friction, the
clamp; watchdog.py; ramp.py: safe transitions; settings.py; diagnostics.py) and owns the state
between messages: the last valid desired state (`on_desired`) and the fallback to gravity
without one, the stale action (`tick`), the enable state. Its settings and models, planned and
applied, built and loaded, are its base `configuration.Configuration`. The ROS node only moves
messages in and out and logs the `events` queued here, each with a throttle key (its problem
class). Time comes from `clock` (injectable, steady by default; every entry point also takes an
explicit `now`).

Torque law: setting `mode` (formulas in lie_dynamics.laws), command order = controlled joints,
q and qd measured, the desired state the last valid one; a mode other than gravity without a
desired state younger than desired_timeout uses the gravity law instead (said once, in the
diagnostics too) and resumes by itself. Every command goes through laws.clamp (+-effort limit
x effort_limit_scale; never a non-finite value). Unavailable (NaN/inf/absent) velocities count
as 0. Locked joints are stationary at their measured value. Commands are computed for
joint_states messages only.

Safety: joint_states older than the last accepted one (non-zero stamps) are refused while the
input is live (after a stale period any stamp starts a new stream: a restarted simulator);
implausible positions are refused like non-finite ones; nothing is published before the first
valid joint_states, disable included; `ramp_time` ramps enable / disable and blends law
changes, before the clamp.
"""
import time

import numpy as np

from ...laws import LAWS, clamp, gravity_law
from .configuration import Configuration
from .diagnostics import (DIAG_TEXT_MAX, ERROR, INERTIA_LOG_LINES, INERTIA_TEXT_MAX, OK, WARN, Throttle, Window, clip,
                          names_text, report)
from .messages import NameMap, Rejected, read_desired
from .ramp import Ramp
from .sample import SampleResult
from .settings import BLEND_KEYS, Plan
from .watchdog import Freshness, Watchdog, fresh

# OK/WARN/ERROR, Throttle and the text bounds live in diagnostics.py; offered here as well.
__all__ = ['Compensator', 'Plan', 'Throttle', 'OK', 'WARN', 'ERROR', 'DIAG_TEXT_MAX', 'INERTIA_LOG_LINES',
           'INERTIA_TEXT_MAX']


class Compensator(Configuration):
    """Gravity/feedforward compensation state machine, independent of ROS.

    Inputs: `load` / `set_model`, `update` (or `plan` + `apply`), `on_joint_state`,
    `on_desired`, `tick`, `set_enabled`.
    Outputs: command arrays (None = publish nothing) and `events`, a list of
    (severity, throttle_key, text) the caller drains and logs. Totals are in `count`
    (diagnostics.Counters), the stale state in `watchdog`. settings: {parameter: value} over the
    defaults; clock: steady seconds; builder: how `load` builds a model (descriptions.build here
    by default; the node hands its build process per load).
    """

    def __init__(self, settings=None, clock=time.monotonic, builder=None):
        super().__init__(settings, clock, builder)
        s = self.settings
        self.executor = ''            # which executor spins the node (note_context)
        self.window = Window(self.count, clock())
        self.watchdog = Watchdog(s.stale_timeout, clock)
        self.last_q = None            # positions of the last valid joint_states (the stale action holds them)
        self.last_stamp = 0           # stamp (ns) of the last accepted joint_states; 0: none
        self.result = None            # sample.SampleResult of the last joint_states message
        self.clamped = None           # joints clamped in the last command
        # transitions: while silent nothing is published (disabled and ramped down)
        self.ramp = Ramp(s.ramp_time, 1.0 if s.enabled else 0.0)
        self.silent = not s.enabled
        self.published = False        # a command went out since the node last fell silent
        self.last_cmd = None          # the last command returned for publishing
        self.held = None              # while disabling without input: the command being ramped down
        # desired state (controlled order) and its fallback state
        self.desired_topic = s.desired_topic   # the resolved name: note_context
        self.desired_map = NameMap()
        self.desired = None           # (q_d, qd_d, qdd_d)
        self.desired_time = None
        self.desired_state = Freshness('desired state', 'desired_timeout', 'desired')
        self.law = None                # torque law of the last command ('gravity (fallback)' if it fell back)

    def note_context(self, loading=None, executor=None, desired_topic=None):
        """What the node around the core says for the diagnostics and log lines (None: unchanged):
        the description being loaded in the background ('' none), the executor that spins the
        node, the resolved name of the desired-state topic."""
        if loading is not None:
            self.loading = loading
        if executor is not None:
            self.executor = executor
        if desired_topic is not None:
            self.desired_topic = desired_topic

    @property
    def desired_fallback(self):
        """The last command used the gravity law instead of `mode` (no fresh desired state)."""
        return self.desired_state.fallen

    def _applied(self, plan, old, now):
        s = self.settings
        self.ramp.set_duration(s.ramp_time)
        self.watchdog.timeout = s.stale_timeout
        if plan.model is not None or s.differs(old, BLEND_KEYS):
            self.ramp.switch()
        if s.mode != old.mode:
            self.desired_state.reset()  # a later stale desired state is reported again
            self.event('info', 'mode', f"mode: {s.mode}")
        if s.enabled != old.enabled:
            return self._sent(self._on_enabled_changed(now))
        return None

    # ------------------------------------------------------------------ enable and disable
    def set_enabled(self, flag):
        return self.update({'enabled': bool(flag)})

    def _on_enabled_changed(self, now):
        ramp = self.ramp
        if self.settings.enabled:
            self.silent = False
            self.held = None
            ramp.set_target(1.0, now)
            self.event('info', 'enabled', 'enabled: publishing commands' +
                        (f" (ramping up over {ramp.duration} s)" if ramp.duration > 0 else ''))
            return None
        ramp.set_target(0.0, now)
        if self.silent:
            return None
        if not self.published or self.layout is None:  # nothing went out: nothing to release
            return self._fall_silent('disabled: nothing was published, now silent', zero=False)
        if ramp.duration <= 0:
            return self._fall_silent('disabled: published one zero command, now silent')
        if self.watchdog.stale:  # no input to ramp with: the timer ramps the held command down
            self.held = self.last_cmd
            ramp.start(now)
        self.event('info', 'enabled', f'disabling: ramping the command down to zero over {ramp.duration} s')
        return None

    def _fall_silent(self, why, zero=True):
        """Go silent; returns the one zero command to publish (zero=True), else None."""
        self.silent = True
        self.published = False
        self.held = None
        self.ramp.stop()
        self.event('info', 'enabled', why)
        return np.zeros(len(self.layout)) if zero else None

    def _sent(self, cmd):
        """Note a command that goes out."""
        if cmd is not None:
            self.last_cmd = cmd
            if not self.silent:
                self.published = True
        return cmd

    # ------------------------------------------------------------------ per message
    def _reject(self, kind, text, stamp=0):
        self.count.rejected += 1
        self.result = SampleResult.reject(stamp, kind, self.note_problem('reject:' + kind,
                                                                          f'joint_states rejected: {text}'))
        return None

    def on_sample(self, sample, now=None):
        """One joint_states sample (cdr.JointStateSample) -> command or None (on_joint_state);
        what became of it: `result`."""
        return self.on_joint_state(sample.names, sample.position, sample.velocity, sample.effort, now, sample.stamp)

    def refuse_malformed(self, topic, text):
        """A serialized joint_states (topic 'joint_states') or desired-state message that could not
        be read: counted as received and rejected, logged under one problem class per topic."""
        if topic == 'joint_states':
            self.count.received += 1
            return self._reject('malformed', f'malformed message: {text}')
        self.count.desired_received += 1
        self.count.desired_rejected += 1
        self.note_problem('desired:malformed', f'desired state rejected: malformed message: {text}')
        return None

    def on_joint_state(self, names, position, velocity=(), effort=(), now=None, stamp=0):
        """One joint_states message -> command (ndarray, command order) or None (publish nothing).
        stamp: header stamp in ns (0: none); an older one than the last accepted is refused.
        `result` (sample.SampleResult) then says whether it was accepted, and why not."""
        self.clamped = None
        count = self.count
        count.received += 1
        reader = self.reader
        if reader is None:  # no model: the node said once at start-up that it waits for one
            self.result = SampleResult.reject(stamp, 'no_model', 'no robot model loaded')
            return None
        if self.refuses_stamp(stamp):
            return self._reject('old', f'stamp {stamp * 1e-9:.9f} s is older than the last accepted state '
                                       f'({self.last_stamp * 1e-9:.9f} s)', stamp)
        try:
            q = reader.positions(names, position, velocity, effort)
        except Rejected as exc:
            return self._reject(exc.kind, exc.text, stamp)
        s = self.settings
        now = self.clock() if now is None else now
        law = s.mode
        if law != 'gravity' and not self._desired_fresh(now):
            law = 'gravity'
            self.law = 'gravity (fallback)'
        else:
            self.law = law
        qd = None
        if self.needs_velocity[law]:
            qd, complete = reader.velocity(velocity)
            if not complete:
                count.velocity_unavailable += 1
        tau = LAWS[law](self.model, q, qd, self.desired, self.kp, self.kd, self.friction,
                        s.include_velocity_terms, gravity=not s.robot_compensates_gravity)
        ramp = self.ramp
        if ramp.idle:
            ramp.note(tau)
        else:
            tau = ramp.shape(tau, now)
        tau = self._limit(tau)
        if tau is None:
            return self._reject('nonfinite_output', f'non-finite torque computed at q={clip(str(q.tolist()), 300)}',
                                stamp)
        return self._accepted(stamp, q, tau, velocity, effort, now)

    def fast_law(self, now):
        """The law of the next command when the fused command path (fused.py) may compute it:
        the mode's own law (a mode other than gravity with a fresh desired state and no fallback
        to say resumed), the command published as computed (not silent, no ramp under way);
        None otherwise (the Python path decides)."""
        if self.silent or not self.ramp.idle or self.reader is None:
            return None
        s = self.settings
        law = s.mode
        if law != 'gravity' and (self.desired_state.fallen or not fresh(self.desired_time, s.desired_timeout, now)):
            return None
        return law

    def refuses_stamp(self, stamp):
        """Is a joint_states stamp (ns, 0: none) refused: older than the last accepted one while
        the input is live?"""
        return stamp and stamp < self.last_stamp and not self.watchdog.stale

    def on_fast_command(self, law, stamp, q, tau, velocity, effort, now, clamped=False):
        """A command the fused command path computed by law `law` (fast_law at `now`) from a
        joint_states message whose stamp is not refused (refuses_stamp) and whose positions q
        passed the checks; tau as the law computed it, `clamped` if the command is tau clamped
        (the fused path wrote what laws.clamp gives): the bookkeeping of on_joint_state's
        accepted state (after the command went out: nothing in it changes the command)."""
        self.clamped = None
        self.count.received += 1
        self.law = law
        self.ramp.note(tau)
        if clamped:   # counted and logged, and kept, as the Python path does
            tau = self._limit(tau)
        self._accepted(stamp, q, tau, velocity, effort, now)

    def _accepted(self, stamp, q, tau, velocity, effort, now):
        """An accepted joint_states state and its command tau (ramped and clamped): the state
        kept, the result for the features, the watchdog fed; the command to publish or None."""
        self.count.accepted += 1
        self.last_q = q
        self.result = SampleResult.accept(stamp, q, self.model, self.layout, self.reader.map.idx, velocity, effort)
        if stamp:
            self.last_stamp = stamp
        if self.watchdog.feed(now):
            self.event('info', 'resumed', 'joint_states valid again: compensation resumed')
        if self.silent:
            return None
        ramp = self.ramp
        if not ramp.idle:
            self.held = None  # input is back: the ramp runs on it, not on the timer
            if ramp.down:
                return self._sent(self._fall_silent(f'disabled: ramped down to zero over {ramp.duration} s, '
                                                    'now silent'))
        self.published = True
        self.last_cmd = tau
        return tau

    def use_gravity(self, g, blend=False):
        """Put the gravity vector g (root frame, scale applied) on the current model for the next
        command (a feature that follows gravity from elsewhere asks here). blend: the gravity's
        source changed (a topic went stale or came back): once a command went out, the next ones
        blend over ramp_time as for a parameter change."""
        if blend and self.last_cmd is not None:
            self.ramp.switch()
        model = self.model
        if model is not None and not np.array_equal(model.gravity_vector, g):
            model.gravity_vector = g

    def _limit(self, tau):
        """A command through laws.clamp, counted and logged when clamped. None: non-finite."""
        tau, over = clamp(tau, self.limits)
        if over is not None:
            self.count.clamp_count += 1
            self.clamped = [self.layout[k] for k in np.flatnonzero(over)]
            self.event('warn', 'clamp', f'effort clamped to limit x {self.settings.effort_limit_scale}'
                                         f' for {names_text(self.clamped)} (total {self.count.clamp_count})')
        return tau

    def _desired_fresh(self, now):
        """Is the desired state usable at `now`? Queues the fallback / recovery log lines."""
        ok, line = self.desired_state.check(self.desired_time, self.settings.desired_timeout, now,
                                            self.desired_topic)
        if line is not None:
            severity, key, text = line
            mode = self.settings.mode
            if ok:
                self.event(severity, key, f'{text}: mode {mode} resumed')
            else:
                self.count.fallback_events += 1
                self.event(severity, key, f'mode {mode}: {text}: gravity compensation at the measured state')
        return ok

    # ------------------------------------------------------------------ desired state
    def desired_is_fresh(self, now=None):
        now = self.clock() if now is None else now
        return fresh(self.desired_time, self.settings.desired_timeout, now)

    def on_desired(self, names, points, now=None):
        """One desired-state message (JointTrajectory joint_names and points) -> accepted?

        Checks: messages.read_desired. A rejected message leaves the last valid desired state
        (and its age) as it was.
        """
        accepted = self._take_desired(names, points, now)
        # Counted last: a reader (diagnostics, a test on another thread) that sees the message
        # counted also sees whether it was accepted or rejected.
        self.count.desired_received += 1
        return accepted

    def _take_desired(self, names, points, now):
        if self.layout is None:  # no model and no `joints` yet: nothing to map to
            return False
        try:
            value = read_desired(names, points, self.layout, self.desired_map, self.desired_topic)
        except Rejected as exc:
            self.count.desired_rejected += 1
            self.note_problem('desired:' + exc.kind, f'desired state rejected: {exc.text}')
            return False
        self.desired = value
        self.desired_time = self.clock() if now is None else now
        self.count.desired_accepted += 1
        return True

    # ------------------------------------------------------------------ watchdog
    def tick(self, now=None):
        """Watchdog; call periodically. Returns the command to publish once, or None.

        Stale action: gravity at the last valid state without velocity terms or friction
        (hold_gravity_at_last_state), or zeros; clamped like every command, and ramped down
        with the rest during a disable. A disable without input is ramped down here.
        """
        now = self.clock() if now is None else now
        age = self.watchdog.expired(now)
        if age is not None:
            return self._stale(age, now)
        if self.held is not None and not self.silent:
            return self._sent(self._held_command(now))
        return None

    def _stale(self, age, now):
        action = self.settings.stale_action
        self.event('warn', 'stale', f'no valid joint_states for {age:.3f} s '
                                     f'(stale_timeout {self.watchdog.timeout} s): {action}')
        model = self.model
        if self.silent or model is None:
            return None
        if (action == 'zero' or self.settings.robot_compensates_gravity or self.last_q is None
                or len(self.last_q) != model.n):
            cmd = np.zeros(model.n)
        else:
            cmd = self._limit(gravity_law(model, self.last_q))
            cmd = np.zeros(model.n) if cmd is None else cmd
        if self.ramp.target == 0.0:  # disabling: the stale action is ramped down with the rest
            self.held = cmd
            return self._sent(self._held_command(now))
        self.ramp.restart(cmd)  # in full; returning input blends from it
        return self._sent(cmd)

    def _held_command(self, now):
        level = self.ramp.advance(now)
        if level <= 0.0:
            return self._fall_silent(f'disabled: ramped down to zero over {self.ramp.duration} s, now silent')
        return level * self.held

    def final_command(self):
        """The stale_action command for shutdown (as if the input had stopped for good), or None
        when there is nothing to hold: no model, no valid joint_states yet, silent, already stale."""
        if self.model is None or self.silent or self.watchdog.waiting:
            return None
        now = self.clock()
        return self._stale(self.watchdog.expire(now), now)

    # ------------------------------------------------------------------ diagnostics
    def record_compute_time(self, seconds):
        self.window.add_time(seconds)

    def diagnostics(self, now=None):
        """(level, message, [(key, value-string)]) for the window since the last call; resets it."""
        now = self.clock() if now is None else now
        out = report(self, self.window, now)
        self.window.restart(now)
        return out
