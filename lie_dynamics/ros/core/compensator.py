"""Decision logic of the dynamics node, in plain Python (no rclpy import).

`Compensator` turns joint_states messages into effort commands. It wires the pieces
(messages.py: reading and checking input; lie_dynamics.laws: torque laws, friction, the
clamp; watchdog.py; ramp.py: safe transitions; settings.py; models.py: description updates;
trajectories.py; diagnostics.py) and owns the state between messages: model and settings, the
last valid desired state (`on_desired`) and the fallback to gravity without one, the stale
action (`tick`), the enable state. The ROS node only moves messages in and out and logs the
`events` queued here, each with a throttle key (its problem class). Time comes from `clock`
(injectable, steady by default; every entry point also takes an explicit `now`).

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
changes, before the clamp; a new model must pass `description_update`, what changed is logged.

Settings and models change in two steps: `plan` validates (a parameter change, a new model,
or both) without changing anything, `apply` makes a plan current; `update` and `set_model`
do both. `load` applies `inertia_policy`; the model's physical_consistency() report is logged
once per load (at most INERTIA_LOG_LINES lines) and kept for the diagnostics.
"""
import copy
import math
import time
import warnings

import numpy as np

from ...laws import LAWS, clamp, gravity_law, uses_velocity
from ..loading.build_process import build
from .diagnostics import (DIAG_TEXT_MAX, ERROR, INERTIA_LOG_LINES, INERTIA_TEXT_MAX, OK, WARN, Counters, Throttle,
                          Window, clip, names_text, report)
from .messages import JointStateReader, NameMap, Rejected, read_desired
from ..loading.models import model_changes, update_refusal
from .params import check_value, defaults
from .ramp import Ramp
from .sample import SampleResult
from .settings import (BLEND_KEYS, PAYLOAD_KEYS, Plan, check_payload_pair, derive, gains, payload_link,
                       place_payload)
from ..trajectories.fill import TrajectoryInput
from .watchdog import Watchdog, fresh

# OK/WARN/ERROR, Throttle and the text bounds live in diagnostics.py; offered here as well.
__all__ = ['Compensator', 'Plan', 'Throttle', 'OK', 'WARN', 'ERROR', 'DIAG_TEXT_MAX', 'INERTIA_LOG_LINES',
           'INERTIA_TEXT_MAX']


class Compensator(TrajectoryInput):
    """Gravity/feedforward compensation state machine, independent of ROS.

    Inputs: `load` / `set_model`, `update` (or `plan` + `apply`), `on_joint_state`,
    `on_desired`, `on_trajectory`, `tick`, `set_enabled`.
    Outputs: command arrays (None = publish nothing) and `events`, a list of
    (severity, throttle_key, text) the caller drains and logs. Totals are in `count`
    (diagnostics.Counters), the stale state in `watchdog`.
    """

    def __init__(self, settings=None, clock=time.monotonic):
        self.clock = clock
        s = defaults()
        for k, v in (settings or {}).items():
            s[k] = check_value(k, v)
        check_payload_pair(s)
        self.settings = s
        self.layout = list(s['joints']) or None  # command joint order, fixed once known
        if self.layout is not None:
            gains(s['kp'], len(self.layout), 'kp')
            gains(s['kd'], len(self.layout), 'kd')
        self.model = None
        self.model_info = ''          # where the current model came from
        self.loading = ''             # what is being loaded in the background (note_context)
        self.executor = ''            # which executor spins the node (note_context)
        self.inertia_report = []      # physical_consistency() of the current model
        self.inertia_repaired = 0     # entries of it with repaired=True
        self.events = []
        self.count = Counters()
        self.window = Window(self.count, clock())
        self.watchdog = Watchdog(s['stale_timeout'], clock)
        self.reader = None            # JointStateReader of the current model
        self.known_locked = {}        # last measured value of each locked joint, kept across models
        self.derived = None           # settings.Derived of (model, settings)
        self.limits = None            # laws.EffortLimits
        self.friction = None          # laws.Friction or None (off)
        self.kp = self.kd = None      # per-joint gains or None (0)
        self.needs_velocity = {}      # mode -> does its law read the measured velocity
        self.last_q = None            # positions of the last valid joint_states (the stale action holds them)
        self.last_stamp = 0           # stamp (ns) of the last accepted joint_states; 0: none
        self.result = None            # sample.SampleResult of the last joint_states message
        self.clamped = None           # joints clamped in the last command
        # transitions: while silent nothing is published (disabled and ramped down)
        self.ramp = Ramp(s['ramp_time'], 1.0 if s['enabled'] else 0.0)
        self.silent = not s['enabled']
        self.published = False        # a command went out since the node last fell silent
        self.last_cmd = None          # the last command returned for publishing
        self.held = None              # while disabling without input: the command being ramped down
        # desired state (controlled order) and its fallback state
        self.desired_topic = s['desired_topic']   # the resolved name: note_context
        self.desired_map = NameMap()
        self.desired = None           # (q_d, qd_d, qdd_d)
        self.desired_time = None
        self.desired_fallback = False  # the last command used the gravity law instead of `mode`
        self.law = None                # torque law of the last command ('gravity (fallback)' if it fell back)
        self.last_error = ''
        self.description_error = ''

    def _event(self, severity, key, text):
        self.events.append((severity, key, text))

    def _error(self, text):
        self.last_error = clip(text, DIAG_TEXT_MAX)
        return self.last_error

    def note_error(self, text):
        """Keep `text` as the last error (diagnostics); returns it as kept (bounded)."""
        return self._error(text)

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

    # ------------------------------------------------------------------ configuration
    def plan(self, changes=None, model=None, info=''):
        """Validate parameter `changes` and/or a new `model` (its joint_names must equal the
        fixed layout, and description_update must let it replace the running one) without
        making them current. Returns a Plan for `apply`; raises ValueError with the reason.
        Only a new model is touched (configured with the settings); a payload on the current
        model is tried on a scratch copy of it."""
        changes = dict(changes or {})
        new = dict(self.settings)
        for k, v in changes.items():
            new[k] = check_value(k, v)
        if new['joints'] != self.settings['joints']:
            raise ValueError('joints cannot change at run time')
        check_payload_pair(new)
        derived = None
        if model is not None:
            if self.layout is not None and list(model.joint_names) != self.layout:
                raise ValueError(f'the model controls {names_text(model.joint_names)}, but the command layout is '
                                 f'{names_text(self.layout)}')
            refusal = update_refusal(new['description_update'], self.model, model)
            if refusal:
                raise ValueError(refusal)
            derived = derive(model, new)
            # a new model carries at most a payload an earlier plan put there (current settings)
            place_payload(model, new, payload_link(self.settings))
        elif self.model is not None:
            derived = derive(self.model, new)
            if payload_link(new) and any(new[k] != self.settings[k] for k in PAYLOAD_KEYS):
                place_payload(copy.deepcopy(self.model), new, payload_link(self.settings))
        elif self.layout is not None:  # gains are checked against the layout early
            gains(new['kp'], len(self.layout), 'kp')
            gains(new['kd'], len(self.layout), 'kd')
        report = None
        if model is not None:
            report = (model_changes(self.model, model) if self.model is not None else [], model.physical_consistency())
        return Plan(new, changes, model, info, derived, (self.model, self.settings), report)

    def apply(self, plan, now=None):
        """Make `plan` current. Returns the command to publish once (the zero command when it
        disables without a ramp), or None. A plan made before another change is checked again
        (ValueError)."""
        if plan.base[0] is not self.model or plan.base[1] is not self.settings:
            plan = self.plan(plan.changes, plan.model, plan.info)
        now = self.clock() if now is None else now
        old = self.settings
        if plan.model is None and self.model is not None:
            place_payload(self.model, plan.settings, payload_link(old))
        self.settings = s = plan.settings
        self.ramp.set_duration(s['ramp_time'])
        if plan.model is not None:
            self._install(plan.model, plan.info, plan.report)
        if plan.derived is not None:
            self._adopt(plan.derived)
        self.watchdog.timeout = s['stale_timeout']
        if plan.model is not None or any(s[k] != old[k] for k in BLEND_KEYS):
            self.ramp.switch()
        if s['mode'] != old['mode']:
            self.desired_fallback = False  # a later stale desired state is reported again
            self._event('info', 'mode', f"mode: {s['mode']}")
        if s['enabled'] != old['enabled']:
            return self._sent(self._on_enabled_changed(now))
        return None

    def _adopt(self, derived):
        self.derived = derived
        self.limits, self.friction, self.kp, self.kd = derived.limits, derived.friction, derived.kp, derived.kd
        if self.reader is not None:
            self.reader.bounds = derived.bounds
        vt = self.settings['include_velocity_terms']
        self.needs_velocity = {mode: uses_velocity(mode, self.kd, self.friction, vt) for mode in LAWS}

    def _install(self, model, info, report):
        """report: the plan's (model_changes against the running model, physical_consistency)."""
        self.model = model
        self.layout = list(model.joint_names)
        self.model_info = info
        self.reader = JointStateReader(model, self.known_locked)
        self.description_error = ''
        self._event('info', 'model', f"model '{model.name}' loaded{' from ' + info if info else ''}: "
                                     f'{model.n} controlled joints {names_text(model.joint_names)}, '
                                     f'locked {names_text(model.locked_joint_names)}')
        for k, (severity, text) in enumerate(report[0]):
            self._event(severity, f'model:change:{k}', f'model update: {text}')
        lim = np.asarray(model.effort_limits)
        unlimited = [j for j, e in zip(model.joint_names, lim, strict=True) if not np.isfinite(e)]
        if unlimited:
            self._event('warn', 'model:unlimited', f'no URDF effort limit for {names_text(unlimited)}: not clamped')
        self._note_inertia(report[1])

    def update(self, changes):
        """Validate and apply parameter changes atomically (plan + apply). Raises ValueError with
        the reason; returns the command to publish once, or None."""
        return self.apply(self.plan(changes))

    def set_model(self, model, info=''):
        """Make `model` current (its joint_names must equal the fixed layout). Raises ValueError
        and keeps the previous model if the new one does not fit the settings."""
        self.apply(self.plan(None, model, info))

    def build_model(self, source, inertia=None, builder=None):
        """load_urdf(source) for the command layout with the configured gravity and inertia
        policy (`inertia` overrides `inertia_policy`); not made current. Raises ValueError (also
        for a strict refusal). builder: build_process.build (the default: in this process) or
        another callable with its signature (BuildProcess.build: in a child process)."""
        policy = check_value('inertia_policy', self.settings['inertia_policy'] if inertia is None else inertia)
        # InertiaWarnings are recorded: set_model reports the model's own report once per link;
        # a model description_update refuses is refused where it is built (plan checks it again)
        running = None if self.model is None else (self.settings['description_update'], self.model.name)
        model, other = (builder or build)(source, joints=self.layout, gravity=self.settings['gravity'],
                                          inertia=policy, running=running)
        for message, category, filename, lineno in other:  # other warnings are not ours to swallow
            warnings.warn_explicit(message, category, filename, lineno)
        return model

    def load(self, source, info='', inertia=None):
        """build_model, then set_model. Raises ValueError and keeps the previous model."""
        model = self.build_model(source, inertia)
        self.set_model(model, info)
        return model

    def _note_inertia(self, report_):
        """Keep the model's inertia report; one warn event per offending link (this load only)."""
        self.inertia_report = list(report_)
        self.inertia_repaired = sum(bool(r['repaired']) for r in self.inertia_report)
        for k, item in enumerate(self.inertia_report[:INERTIA_LOG_LINES]):
            self._event('warn', f'inertia:{k}', clip(f"inertia: {item['message']}", INERTIA_TEXT_MAX))
        more = len(self.inertia_report) - INERTIA_LOG_LINES
        if more > 0:
            self._event('warn', 'inertia:more', f'inertia: ... and {more} more links with inconsistent inertia')

    def note_description_error(self, text):
        """Record a refused description; returns the text as kept (bounded)."""
        text = clip(text, DIAG_TEXT_MAX)  # e.g. a strict refusal listing thousands of links
        self.description_error = text
        self.last_error = text
        kept = f" (keeping model '{self.model.name}')" if self.model is not None else ''
        self._event('error', 'description', f'robot description rejected: {text}{kept}')
        return text

    def set_enabled(self, flag):
        return self.update({'enabled': bool(flag)})

    def _on_enabled_changed(self, now):
        ramp = self.ramp
        if self.settings['enabled']:
            self.silent = False
            self.held = None
            ramp.set_target(1.0, now)
            self._event('info', 'enabled', 'enabled: publishing commands' +
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
            ramp.level_time = now
        self._event('info', 'enabled', f'disabling: ramping the command down to zero over {ramp.duration} s')
        return None

    def _fall_silent(self, why, zero=True):
        """Go silent; returns the one zero command to publish (zero=True), else None."""
        self.silent = True
        self.published = False
        self.held = None
        self.ramp.level = 0.0
        self.ramp.offset = None
        self._event('info', 'enabled', why)
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
        self.last_error = clip(f'joint_states rejected: {text}', DIAG_TEXT_MAX)
        self._event('warn', 'reject:' + kind, self.last_error)
        self.result = SampleResult.reject(stamp, kind, self.last_error)
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
        self._event('warn', 'desired:malformed', self._error(f'desired state rejected: malformed message: {text}'))
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
        if stamp and stamp < self.last_stamp and not self.watchdog.stale:
            return self._reject('old', f'stamp {stamp * 1e-9:.9f} s is older than the last accepted state '
                                       f'({self.last_stamp * 1e-9:.9f} s)', stamp)
        try:
            q = reader.positions(names, position, velocity, effort)
        except Rejected as exc:
            return self._reject(exc.kind, exc.text, stamp)
        s = self.settings
        now = self.clock() if now is None else now
        law = s['mode']
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
                        s['include_velocity_terms'], gravity=not s['robot_compensates_gravity'])
        ramp = self.ramp
        if ramp.idle:
            ramp.last = tau
        else:
            tau = ramp.shape(tau, now)
        tau = self._limit(tau)
        if tau is None:
            return self._reject('nonfinite_output', f'non-finite torque computed at q={clip(str(q.tolist()), 300)}',
                                stamp)
        count.accepted += 1
        self.last_q = q
        self.result = SampleResult.accept(stamp, q, self.model, self.layout, reader.map.idx, velocity, effort)
        if stamp:
            self.last_stamp = stamp
        if self.watchdog.feed(now):
            self._event('info', 'resumed', 'joint_states valid again: compensation resumed')
        if self.silent:
            return None
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
            self._event('warn', 'clamp', f'effort clamped to limit x {self.settings["effort_limit_scale"]}'
                                         f' for {names_text(self.clamped)} (total {self.count.clamp_count})')
        return tau

    def _desired_fresh(self, now):
        """Is the desired state usable at `now`? Queues the fallback / recovery log lines."""
        t = self.desired_time
        if self.desired_is_fresh(now):
            if self.desired_fallback:
                self.desired_fallback = False
                self._event('info', 'desired:recovered',
                            f"desired state on {self.desired_topic} fresh again: mode {self.settings['mode']}"
                            ' resumed')
            return True
        if not self.desired_fallback:
            self.desired_fallback = True
            self.count.fallback_events += 1
            if t is None:
                key, why = 'desired:none', f'no desired state received yet on {self.desired_topic}'
            else:
                key, why = 'desired:stale', (f'no valid desired state on {self.desired_topic} for {now - t:.3f} s '
                                             f"(desired_timeout {self.settings['desired_timeout']} s)")
            self._event('warn', key, f"mode {self.settings['mode']}: {why}: gravity compensation at the measured "
                                     'state')
        return False

    # ------------------------------------------------------------------ desired state
    def desired_is_fresh(self, now=None):
        now = self.clock() if now is None else now
        return fresh(self.desired_time, self.settings['desired_timeout'], now)

    def on_desired(self, names, points, now=None):
        """One desired-state message (JointTrajectory joint_names and points) -> accepted?

        Checks: messages.read_desired. A rejected message leaves the last valid desired state
        (and its age) as it was.
        """
        self.count.desired_received += 1
        if self.layout is None:  # no model and no `joints` yet: nothing to map to
            return False
        try:
            value = read_desired(names, points, self.layout, self.desired_map, self.desired_topic)
        except Rejected as exc:
            self.count.desired_rejected += 1
            self._event('warn', 'desired:' + exc.kind, self._error(f'desired state rejected: {exc.text}'))
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
        action = self.settings['stale_action']
        self._event('warn', 'stale', f'no valid joint_states for {age:.3f} s '
                                     f'(stale_timeout {self.watchdog.timeout} s): {action}')
        model = self.model
        if self.silent or model is None:
            return None
        if (action == 'zero' or self.settings['robot_compensates_gravity'] or self.last_q is None
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
        self.watchdog.expired(math.inf)
        return self._stale(now - self.watchdog.last_valid_time, now)

    # ------------------------------------------------------------------ diagnostics
    def record_compute_time(self, seconds):
        self.window.add_time(seconds)

    def diagnostics(self, now=None):
        """(level, message, [(key, value-string)]) for the window since the last call; resets it."""
        now = self.clock() if now is None else now
        out = report(self, self.window, now)
        self.window.restart(now)
        return out
