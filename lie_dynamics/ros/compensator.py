"""Decision logic of the dynamics node, in plain Python (no rclpy import).

`Compensator` turns joint_states messages into effort commands. It wires the pieces:
    messages.py     name maps and the checks of joint_states / desired-state messages
    lie_dynamics.laws  the torque laws, friction compensation and the effort clamp
    watchdog.py     stale-input detection
    diagnostics.py  counters and the /diagnostics status
and owns the state between messages: the model and settings, the last valid desired state
(`on_desired`), the fallback to gravity without one, and the stale action (`tick`). It also
fills trajectories with feedforward efforts (`on_trajectory`). The ROS node (node.py) only
moves messages in and out and logs the `events` queued here. Time comes from `clock`
(injectable; every entry point also takes an explicit `now`).

Torque law: setting `mode` (gravity, feedforward, computed_torque, pd; formulas in
lie_dynamics.laws), command order = controlled joints, q and qd measured, the desired state
the last valid one. g uses gravity * gravity_scale (and the payload). A mode other than
gravity without a desired state younger than desired_timeout (or none yet) uses the gravity
law instead, says so once (throttled) and in the diagnostics, and resumes by itself with the
next valid desired state. The result is clamped to +-effort_limit*effort_limit_scale
(laws.clamp, the one clamp of commands, the stale action and trajectory efforts); a
non-finite result is never published. Velocity-dependent terms use the measured velocity; a
NaN/inf (or absent) velocity of a joint counts as unavailable and is used as 0. Locked joints
are treated as stationary at their measured value (desired values for them are ignored).
Commands are computed for joint_states messages only: a desired message updates the
set-point, it does not trigger a command.

Settings and models change in two steps: `plan` validates (a parameter change, a new model,
or both) without changing anything, `apply` makes a plan current; `update` and `set_model`
do both at once.

Inertia: `load` applies `inertia_policy` (load_urdf's `inertia`). The loaded model's
physical_consistency() report is logged once per load (one line per offending link, at most
INERTIA_LOG_LINES) and kept for the diagnostics (WARN while it is non-empty).
"""
import copy
import math
import time
import warnings
from typing import NamedTuple, Optional

import numpy as np

from .. import InertiaWarning, load_urdf
from ..laws import LAWS, add_friction, clamp, effort_limits, gravity_law, make_friction, uses_velocity
from ..trajectory import fill_trajectory_efforts
from .diagnostics import (DIAG_TEXT_MAX, ERROR, INERTIA_LOG_LINES, INERTIA_TEXT_MAX, OK, WARN, Counters, Throttle,
                          Window, clip, report)
from .messages import JointStateReader, NameMap, Rejected, read_desired
from .params import check_value, defaults
from .trajectory_msgs import trajectory_arrays
from .watchdog import Watchdog

# OK/WARN/ERROR, Throttle and the text bounds live in diagnostics.py; offered here as well.
__all__ = ['Compensator', 'Plan', 'Throttle', 'OK', 'WARN', 'ERROR', 'DIAG_TEXT_MAX', 'INERTIA_LOG_LINES',
           'INERTIA_TEXT_MAX']

PAYLOAD_KEYS = ('payload.link', 'payload.mass', 'payload.com', 'payload.inertia')


def _per_joint(values, urdf_values, n, name):
    """Friction coefficients: [] -> URDF, [c] -> every joint, n values -> per joint. None when all 0."""
    if len(values) == 0:
        out = np.asarray(urdf_values, dtype=float).copy()
    elif len(values) == 1:
        out = np.full(n, float(values[0]))
    elif len(values) == n:
        out = np.asarray(values, dtype=float)
    else:
        raise ValueError(f'{name} must have 0, 1 or {n} values (one per controlled joint), got {len(values)}')
    if not np.all(np.isfinite(out)) or np.any(out < 0):
        raise ValueError(f'{name} must be finite and >= 0, got {out.tolist()}')
    return out if np.any(out != 0) else None


def _gains(values, n, name):
    """PD gains: [] -> 0, [k] -> every joint, n values -> per joint. None when all 0."""
    if len(values) not in (0, 1, n):
        raise ValueError(f'{name} must have 1 or {n} values (one per controlled joint), got {len(values)}')
    out = np.zeros(n) + np.asarray(values or [0.0], dtype=float)
    if not np.all(np.isfinite(out)) or np.any(out < 0):
        raise ValueError(f'{name} must be finite and >= 0, got {out.tolist()}')
    return out if np.any(out != 0) else None


def _check_payload_pair(s):
    if s['payload.mass'] > 0 and not s['payload.link']:
        raise ValueError('payload.mass > 0 needs payload.link')


def _payload_link(s):
    """The link that carries the payload of settings s ('' for none)."""
    return s['payload.link'] if s['payload.mass'] > 0 else ''


def _place_payload(model, s, prev_link):
    """Payload and gravity of settings s on `model` (whose payload, if any, is on prev_link).
    Raises ValueError, leaving the model's payload and gravity unchanged."""
    link, mass = s['payload.link'], s['payload.mass']
    if link and mass > 0:
        if link not in model.link_frames:
            raise ValueError(f"payload.link '{link}' is not a link of robot '{model.name}'")
        model.set_payload(link, mass, s['payload.com'], s['payload.inertia'] or None)  # validates first
        if prev_link and prev_link != link:
            model.clear_payload(prev_link)
    elif prev_link:
        model.clear_payload(prev_link)
    model.gravity_vector = np.asarray(s['gravity'], dtype=float) * s['gravity_scale']


class Plan(NamedTuple):
    """A validated change (Compensator.plan), made current by Compensator.apply."""
    settings: dict             # all settings after the change
    changes: dict              # the requested changes (to check again if the state moved meanwhile)
    model: Optional[object]    # a new model, already configured with `settings`; None: keep the current one
    info: str                  # where the new model comes from
    derived: Optional[tuple]   # (EffortLimits, Friction or None, kp, kd) for the model after the change
    base: tuple                # (model, settings) the plan was made against


class Compensator:
    """Gravity/feedforward compensation state machine, independent of ROS.

    Inputs: `load` / `set_model`, `update` (or `plan` + `apply`), `on_joint_state`,
    `on_desired`, `on_trajectory`, `tick`, `set_enabled`.
    Outputs: command arrays (None = publish nothing) and `events`, a list of
    (severity, throttle_key or None, text) the caller drains and logs. Totals are in `count`
    (diagnostics.Counters), the stale state in `watchdog`.
    """

    def __init__(self, settings=None, clock=time.monotonic):
        self.clock = clock
        s = defaults()
        for k, v in (settings or {}).items():
            s[k] = check_value(k, v)
        _check_payload_pair(s)
        self.settings = s
        self.layout = list(s['joints']) or None  # command joint order, fixed once known
        if self.layout is not None:
            _gains(s['kp'], len(self.layout), 'kp')
            _gains(s['kd'], len(self.layout), 'kd')
        self.model = None
        self.model_info = ''          # where the current model came from
        self.inertia_report = []      # physical_consistency() of the current model
        self.inertia_repaired = 0     # entries of it with repaired=True
        self.events = []
        self.count = Counters()
        self.window = Window(self.count, clock())
        self.watchdog = Watchdog(s['stale_timeout'], clock)
        self.reader = None            # JointStateReader of the current model
        self.known_locked = {}        # last measured value of each locked joint, kept across models
        # derived from (model, settings) by _adopt
        self.limits = None            # laws.EffortLimits
        self.friction = None          # laws.Friction or None (off)
        self.kp = self.kd = None      # per-joint gains or None (0)
        self.needs_velocity = {}      # mode -> does its law read the measured velocity
        self.last_q = None            # positions of the last valid joint_states (the stale action holds them)
        self.clamped = None           # joints clamped in the last command
        # desired state (controlled order) and its fallback state
        self.desired_topic = s['desired_topic']   # the node sets the resolved name
        self.desired_map = NameMap()
        self.desired = None           # (q_d, qd_d, qdd_d)
        self.desired_time = None
        self.desired_fallback = False  # the last command used the gravity law instead of `mode`
        self.law = None                # torque law of the last command ('gravity (fallback)' if it fell back)
        self.last_error = ''
        self.description_error = ''

    # ------------------------------------------------------------------ configuration
    def _derive(self, model, s):
        """Per-joint arrays of settings s for `model`. Raises ValueError."""
        n = model.n
        viscous = _per_joint(s['friction.viscous'], model.damping, n, 'friction.viscous')
        coulomb = _per_joint(s['friction.coulomb'], model.friction, n, 'friction.coulomb')
        gains = (_gains(s['kp'], n, 'kp'), _gains(s['kd'], n, 'kd'))
        friction = make_friction(viscous, coulomb, s['friction.coulomb_velocity_epsilon'])
        return (effort_limits(model.effort_limits, s['effort_limit_scale']), friction) + gains

    def plan(self, changes=None, model=None, info=''):
        """Validate parameter `changes` and/or a new `model` (its joint_names must equal the
        fixed layout) without making them current. Returns a Plan for `apply`; raises
        ValueError with the reason. Only a new model is touched (configured with the settings);
        a payload on the current model is tried on a scratch copy of it."""
        changes = dict(changes or {})
        new = dict(self.settings)
        for k, v in changes.items():
            new[k] = check_value(k, v)
        if new['joints'] != self.settings['joints']:
            raise ValueError('joints cannot change at run time')
        _check_payload_pair(new)
        derived = None
        if model is not None:
            if self.layout is not None and list(model.joint_names) != self.layout:
                raise ValueError(f'the model controls {model.joint_names}, but the command layout is {self.layout}')
            derived = self._derive(model, new)
            # a new model carries at most a payload an earlier plan put there (current settings)
            _place_payload(model, new, _payload_link(self.settings))
        elif self.model is not None:
            derived = self._derive(self.model, new)
            if _payload_link(new) and any(new[k] != self.settings[k] for k in PAYLOAD_KEYS):
                _place_payload(copy.deepcopy(self.model), new, _payload_link(self.settings))
        elif self.layout is not None:  # gains are checked against the layout early
            _gains(new['kp'], len(self.layout), 'kp')
            _gains(new['kd'], len(self.layout), 'kd')
        return Plan(new, changes, model, info, derived, (self.model, self.settings))

    def apply(self, plan):
        """Make `plan` current. Returns the command to publish once (the zero command when it
        disables), or None. A plan made before another change is checked again (ValueError)."""
        if plan.base[0] is not self.model or plan.base[1] is not self.settings:
            plan = self.plan(plan.changes, plan.model, plan.info)
        old = self.settings
        if plan.model is None and self.model is not None:
            _place_payload(self.model, plan.settings, _payload_link(old))
        self.settings = s = plan.settings
        if plan.model is not None:
            self._install(plan.model, plan.info)
        if plan.derived is not None:
            self._adopt(*plan.derived)
        self.watchdog.timeout = s['stale_timeout']
        if s['mode'] != old['mode']:
            self.desired_fallback = False  # a later stale desired state is reported again
            self.events.append(('info', None, f"mode: {s['mode']}"))
        if s['enabled'] != old['enabled']:
            return self._on_enabled_changed()
        return None

    def _adopt(self, limits, friction, kp, kd):
        self.limits, self.friction, self.kp, self.kd = limits, friction, kp, kd
        vt = self.settings['include_velocity_terms']
        self.needs_velocity = {mode: uses_velocity(mode, kd, friction, vt) for mode in LAWS}

    def _install(self, model, info):
        self.model = model
        self.layout = list(model.joint_names)
        self.model_info = info
        self.reader = JointStateReader(model, self.known_locked)
        self.description_error = ''
        self.events.append(('info', None, f"model '{model.name}' loaded{' from ' + info if info else ''}: "
                                          f'{model.n} controlled joints {model.joint_names}, '
                                          f'locked {model.locked_joint_names}'))
        lim = np.asarray(model.effort_limits)
        unlimited = [j for j, e in zip(model.joint_names, lim, strict=True) if not np.isfinite(e)]
        if unlimited:
            self.events.append(('warn', None, f'no URDF effort limit for {unlimited}: not clamped'))
        self._note_inertia(model.physical_consistency())

    def update(self, changes):
        """Validate and apply parameter changes atomically (plan + apply). Raises ValueError with
        the reason; returns the command to publish once, or None."""
        return self.apply(self.plan(changes))

    def set_model(self, model, info=''):
        """Make `model` current (its joint_names must equal the fixed layout). Raises ValueError
        and keeps the previous model if the new one does not fit the settings."""
        self.apply(self.plan(None, model, info))

    def build_model(self, source, inertia=None):
        """load_urdf(source) for the command layout with the configured gravity and inertia
        policy (`inertia` overrides `inertia_policy`); not made current. Raises ValueError (also
        for a strict refusal)."""
        policy = check_value('inertia_policy', self.settings['inertia_policy'] if inertia is None else inertia)
        with warnings.catch_warnings(record=True) as caught:
            # set_model reports the model's own report once per link: nothing raw on stderr
            warnings.simplefilter('always', InertiaWarning)
            model = load_urdf(source, joints=self.layout, gravity=self.settings['gravity'], inertia=policy)
        for w in caught:  # other warnings are not ours to swallow
            if not issubclass(w.category, InertiaWarning):
                warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
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
        for item in self.inertia_report[:INERTIA_LOG_LINES]:
            self.events.append(('warn', None, clip(f"inertia: {item['message']}", INERTIA_TEXT_MAX)))
        more = len(self.inertia_report) - INERTIA_LOG_LINES
        if more > 0:
            self.events.append(('warn', None, f'inertia: ... and {more} more links with inconsistent inertia'))

    def note_description_error(self, text):
        """Record a refused description; returns the text as kept (bounded)."""
        text = clip(text, DIAG_TEXT_MAX)  # e.g. a strict refusal listing thousands of links
        self.description_error = text
        self.last_error = text
        kept = f" (keeping model '{self.model.name}')" if self.model is not None else ''
        self.events.append(('error', None, f'robot description rejected: {text}{kept}'))
        return text

    def set_enabled(self, flag):
        return self.update({'enabled': bool(flag)})

    def _on_enabled_changed(self):
        if self.settings['enabled']:
            self.events.append(('info', None, 'enabled: publishing commands'))
            return None
        self.events.append(('info', None, 'disabled: published one zero command, now silent'))
        if self.layout is None:
            return None
        return np.zeros(len(self.layout))

    # ------------------------------------------------------------------ per message
    def _reject(self, kind, text):
        self.count.rejected += 1
        self.last_error = f'joint_states rejected: {text}'
        self.events.append(('warn', 'reject:' + kind, self.last_error))
        return None

    def on_joint_state(self, names, position, velocity=(), effort=(), now=None):
        """One joint_states message -> command (ndarray, command order) or None (publish nothing)."""
        self.clamped = None
        count = self.count
        count.received += 1
        reader = self.reader
        if reader is None:  # no model: the node said once at start-up that it waits for one
            return None
        try:
            q = reader.positions(names, position, velocity, effort)
        except Rejected as exc:
            return self._reject(exc.kind, exc.text)
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
                        s['include_velocity_terms'])
        tau = self._limit(tau)
        if tau is None:
            return self._reject('nonfinite_output', f'non-finite torque computed at q={q.tolist()}')
        count.accepted += 1
        self.last_q = q
        if self.watchdog.feed(now):
            self.events.append(('info', None, 'joint_states valid again: compensation resumed'))
        if not s['enabled']:
            return None
        return tau

    def _limit(self, tau):
        """A command through laws.clamp, counted and logged when clamped. None: non-finite."""
        tau, over = clamp(tau, self.limits)
        if over is not None:
            self.count.clamp_count += 1
            self.clamped = [self.layout[k] for k in np.flatnonzero(over)]
            self.events.append(('warn', 'clamp', f'effort clamped to limit x {self.settings["effort_limit_scale"]}'
                                                 f' for {self.clamped} (total {self.count.clamp_count})'))
        return tau

    def _desired_fresh(self, now):
        """Is the desired state usable at `now`? Queues the fallback / recovery log lines."""
        t = self.desired_time
        if self.desired_is_fresh(now):
            if self.desired_fallback:
                self.desired_fallback = False
                self.events.append(('info', 'desired:recovered',
                                    f"desired state on {self.desired_topic} fresh again: mode {self.settings['mode']}"
                                    ' resumed'))
            return True
        if not self.desired_fallback:
            self.desired_fallback = True
            self.count.fallback_events += 1
            if t is None:
                key, why = 'desired:none', f'no desired state received yet on {self.desired_topic}'
            else:
                key, why = 'desired:stale', (f'no valid desired state on {self.desired_topic} for {now - t:.3f} s '
                                             f"(desired_timeout {self.settings['desired_timeout']} s)")
            self.events.append(('warn', key, f"mode {self.settings['mode']}: {why}: "
                                             'gravity compensation at the measured state'))
        return False

    # ------------------------------------------------------------------ desired state and trajectories
    def desired_is_fresh(self, now=None):
        now = self.clock() if now is None else now
        return self.desired_time is not None and now - self.desired_time <= self.settings['desired_timeout']

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
            self.last_error = f'desired state rejected: {exc.text}'
            self.events.append(('warn', 'desired:' + exc.kind, self.last_error))
            return False
        self.desired = value
        self.desired_time = self.clock() if now is None else now
        self.count.desired_accepted += 1
        return True

    def _reject_trajectory(self, text):
        self.count.trajectories_rejected += 1
        self.last_error = f'trajectory rejected: {text}'
        self.events.append(('warn', 'trajectory:' + text, self.last_error + ' (nothing published)'))
        return None

    def on_trajectory(self, names, points):
        """A planner's trajectory (JointTrajectory joint_names and points) -> efforts (N, k) in the
        message's joint order, or None (rejected: publish nothing).

        Effort of a controlled joint: inverse dynamics at the point (missing velocities /
        accelerations derived, see trajectory.py) + friction compensation at the point's velocity,
        clamped like commands. Joints that are not controlled get 0. Not while disabled.
        """
        model = self.model
        if model is None:
            return self._reject_trajectory('no robot model yet')
        if not self.settings['enabled']:
            return self._reject_trajectory('node disabled')
        try:
            arrays = trajectory_arrays(names, points)
            res = fill_trajectory_efforts(model, arrays)
        except ValueError as exc:
            return self._reject_trajectory(str(exc))
        tau, over = clamp(add_friction(res['efforts'], res['velocities'], self.friction), self.limits)
        if over is not None:
            joints = [self.layout[k] for k in np.flatnonzero(over.any(axis=0))]
            self.events.append(('warn', 'trajectory:clamp', f'trajectory efforts clamped to limit x '
                                f"{self.settings['effort_limit_scale']} at {int(over.any(axis=1).sum())} of "
                                f'{len(over)} points for {joints}'))
        if tau is None:
            return self._reject_trajectory('non-finite effort computed')
        names = list(names)
        efforts = np.zeros((len(tau), len(names)))
        efforts[:, [names.index(j) for j in model.joint_names]] = tau
        self.count.trajectories_filled += 1
        return efforts

    # ------------------------------------------------------------------ watchdog
    def tick(self, now=None):
        """Watchdog; call periodically. Returns the stale command to publish once, or None.

        Stale action: gravity at the last valid state without velocity terms or friction
        (hold_gravity_at_last_state), or zeros; clamped like every command.
        """
        age = self.watchdog.expired(now)
        if age is None:
            return None
        action = self.settings['stale_action']
        self.events.append(('warn', None, f'no valid joint_states for {age:.3f} s '
                                          f'(stale_timeout {self.watchdog.timeout} s): {action}'))
        model = self.model
        if not self.settings['enabled'] or model is None:
            return None
        if action == 'zero' or self.last_q is None or len(self.last_q) != model.n:
            return np.zeros(model.n)
        tau = self._limit(gravity_law(model, self.last_q))
        return np.zeros(model.n) if tau is None else tau

    def final_command(self):
        """The stale_action command for shutdown (as if the input had stopped for good), or None
        when there is nothing to hold: no model, no valid joint_states yet, disabled, already stale."""
        if self.model is None or not self.settings['enabled'] or self.watchdog.waiting:
            return None
        return self.tick(math.inf)

    # ------------------------------------------------------------------ diagnostics
    def record_compute_time(self, seconds):
        self.window.times.append(seconds)

    def diagnostics(self, now=None):
        """(level, message, [(key, value-string)]) for the window since the last call; resets it."""
        now = self.clock() if now is None else now
        out = report(self, self.window, now)
        self.window.restart(now)
        return out
