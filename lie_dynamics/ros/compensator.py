"""Decision logic of the dynamics node, in plain Python (no rclpy import).

`Compensator` turns joint_states messages into effort commands: it validates each message,
maps joints by name, feeds uncontrolled joints to the model's locked values, applies the
torque law, clamps, and runs the stale-input watchdog. It also keeps the last valid desired
state (`on_desired`) and fills trajectories with feedforward efforts (`on_trajectory`). The
ROS node (dynamics_node.py) only moves messages in and out and logs the `events` queued here.

Torque laws (`mode`; command order = controlled joints; q, qd measured; q_d, qd_d, qdd_d the
last valid desired state; e = q_d - q, de = qd_d - qd; f(v) = b*v + fc*tanh(v/eps) friction):
    gravity          tau = g(q) [+ C(q, qd) qd if include_velocity_terms] + f(qd)
    feedforward      tau = M(q_d) qdd_d + C(q_d, qd_d) qd_d + g(q_d) + f(qd_d) + Kp e + Kd de
    computed_torque  tau = M(q) (qdd_d + Kp e + Kd de) + C(q, qd) qd + g(q) + f(qd)
    pd               tau = Kp e + Kd de
g uses gravity * gravity_scale (and the payload). Each is one inverse-dynamics (RNEA) call.
A mode other than gravity without a desired state younger than desired_timeout (or none yet)
uses the gravity law instead, says so once (throttled) and in the diagnostics, and resumes by
itself with the next valid desired state. The result is clamped to
+-effort_limit*effort_limit_scale; a non-finite result is never published. Velocity-dependent
terms use the measured velocity; a NaN/inf (or absent) velocity of a joint counts as
unavailable and is used as 0. Locked joints are treated as stationary at their measured value
(desired values for them are ignored). Commands are computed for joint_states messages only:
a desired message updates the set-point, it does not trigger a command.

Inertia: `load` applies `inertia_policy` (load_urdf's `inertia`). The loaded model's
physical_consistency() report is logged once per load (one line per offending link, at most
INERTIA_LOG_LINES) and kept for the diagnostics (WARN while it is non-empty).
"""
import time
import warnings

import numpy as np

from .. import InertiaWarning, load_urdf
from .params import check_value, defaults
from .trajectory_msgs import trajectory_arrays
from ..trajectory import fill_trajectory_efforts

NEEDS_DESIRED = ('feedforward', 'computed_torque', 'pd')

# diagnostic_msgs/DiagnosticStatus levels
OK, WARN, ERROR = 0, 1, 2

# Bounds of the inertia report: a URDF with thousands of bad links must not flood the log or
# /diagnostics (log lines per load, characters per line, messages in the diagnostics value).
INERTIA_LOG_LINES = 20
INERTIA_TEXT_MAX = 300
INERTIA_DIAG_MESSAGES = 3
DIAG_TEXT_MAX = 1000


def _clip(text, n):
    return text if len(text) <= n else text[:n - 3] + '...'


class Throttle:
    """At most one `ready(key)` per `period` seconds for each key."""

    def __init__(self, period=1.0, clock=time.monotonic):
        self.period = period
        self.clock = clock
        self._last = {}

    def ready(self, key, now=None):
        now = self.clock() if now is None else now
        last = self._last.get(key)
        if last is not None and now - last < self.period:
            return False
        if len(self._last) > 1000:  # keys may carry message text: forget the expired ones
            self._last = {k: t for k, t in self._last.items() if now - t < self.period}
        self._last[key] = now
        return True


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


class _NameMap:
    """Column indices of the controlled joints in a message's name list (cached per list)."""

    def __init__(self):
        self.names = None
        self.error = None
        self.idx = None

    def build(self, names, controlled):
        self.names = list(names)
        self.error = None
        index = {}
        dup = []
        for i, name in enumerate(names):
            if name in index:
                dup.append(name)
            index[name] = i
        if dup:
            self.error = ('duplicate', f'duplicate joint names {sorted(set(dup))}')
            return
        missing = [j for j in controlled if j not in index]
        if missing:
            other = [j for j in names if j not in set(controlled)]
            hint = f' (it names {other}, which are not controlled joints)' if other else ''
            self.error = ('missing', f'missing controlled joints {missing}{hint}')
            return
        self.idx = np.array([index[j] for j in controlled], dtype=int)


class Compensator:
    """Gravity/feedforward compensation state machine, independent of ROS.

    Inputs: `set_model`, `update`, `on_joint_state`, `tick`, `set_enabled`.
    Outputs: command arrays (None = publish nothing) and `events`, a list of
    (severity, throttle_key or None, text) the caller drains and logs.
    """

    def __init__(self, settings=None, clock=time.monotonic):
        self.clock = clock
        self.settings = defaults()
        for k, v in (settings or {}).items():
            self.settings[k] = check_value(k, v)
        self._check_payload_pair(self.settings)
        self.model = None
        self.layout = list(self.settings['joints']) or None  # command joint order, fixed once known
        if self.layout is not None:
            _gains(self.settings['kp'], len(self.layout), 'kp')
            _gains(self.settings['kd'], len(self.layout), 'kd')
        self.model_info = ''          # where the current model came from
        self.inertia_report = []      # physical_consistency() of the current model
        self.inertia_repaired = 0     # entries of it with repaired=True
        self.events = []
        # derived from (model, settings)
        self._limit = None
        self._limit_finite = None
        self._viscous = None
        self._coulomb = None
        self._need_velocity = False
        self._kp = None
        self._kd = None
        # name-mapping cache
        self._names = None
        self._map_error = None
        self._ctrl_idx = None
        self._lock_idx = None
        self._lock_names = ()
        self._last_locked = None
        self._locked_cache = {}
        # state
        self.last_q = None
        self.last_valid_time = None
        self.stale = False
        self.clamped = None
        # desired state (controlled order) and its fallback state
        self.desired_topic = self.settings['desired_topic']   # the node sets the resolved name
        self._des_map = _NameMap()
        self.desired = None           # (q_d, qd_d, qdd_d)
        self.desired_time = None
        self.desired_fallback = False  # the last command used the gravity law instead of `mode`
        self.law = None                # torque law of the last command ('gravity (fallback)' if it fell back)
        self.desired_received = 0
        self.desired_accepted = 0
        self.desired_rejected = 0
        self.fallback_events = 0
        self.trajectories_filled = 0
        self.trajectories_rejected = 0
        # statistics
        self.received = 0
        self.accepted = 0
        self.rejected = 0
        self.clamp_count = 0
        self.stale_events = 0
        self.velocity_unavailable = 0
        self.last_error = ''
        self.description_error = ''
        self._win_start = clock()
        self._win_accepted = 0
        self._win_rejected = 0
        self._win_clamped = 0
        self._win_desired_rejected = 0
        self._win_times = []

    # ------------------------------------------------------------------ configuration
    @staticmethod
    def _check_payload_pair(s):
        if s['payload.mass'] > 0 and not s['payload.link']:
            raise ValueError('payload.mass > 0 needs payload.link')

    def _configure(self, model, s, prev_link=''):
        """Apply settings `s` to `model` (whose payload, if any, is on `prev_link`); return the
        derived arrays. Raises ValueError, leaving the model's payload and gravity unchanged."""
        n = model.n
        viscous = _per_joint(s['friction.viscous'], model.damping, n, 'friction.viscous')
        coulomb = _per_joint(s['friction.coulomb'], model.friction, n, 'friction.coulomb')
        gains = (_gains(s['kp'], n, 'kp'), _gains(s['kd'], n, 'kd'))
        limit = np.asarray(model.effort_limits, dtype=float) * s['effort_limit_scale']
        limit = np.where(np.isnan(limit), np.inf, limit)  # inf * 0
        self._check_payload_pair(s)
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
        return limit, viscous, coulomb, gains

    def _adopt(self, limit, viscous, coulomb, gains):
        self._limit, self._viscous, self._coulomb = limit, viscous, coulomb
        self._kp, self._kd = gains
        self._limit_finite = np.minimum(limit, np.finfo(float).max)  # so that +-inf fails `<=`
        self._need_velocity = (self.settings['include_velocity_terms'] or viscous is not None
                               or coulomb is not None)

    def load(self, source, info='', inertia=None):
        """load_urdf(source) for the command layout with the configured gravity and inertia
        policy (`inertia` overrides `inertia_policy`), then `set_model`. Raises ValueError (also
        for a strict refusal) and keeps the previous model."""
        policy = check_value('inertia_policy', self.settings['inertia_policy'] if inertia is None else inertia)
        with warnings.catch_warnings(record=True) as caught:
            # set_model reports the model's own report once per link: nothing raw on stderr
            warnings.simplefilter('always', InertiaWarning)
            model = load_urdf(source, joints=self.layout, gravity=self.settings['gravity'], inertia=policy)
        for w in caught:  # other warnings are not ours to swallow
            if not issubclass(w.category, InertiaWarning):
                warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
        self.set_model(model, info)
        return model

    def set_model(self, model, info=''):
        """Make `model` current (its joint_names must equal the fixed layout). Raises ValueError
        and keeps the previous model if the new one does not fit the settings."""
        if self.layout is not None and list(model.joint_names) != self.layout:
            raise ValueError(f'the model controls {model.joint_names}, but the command layout is {self.layout}')
        derived = self._configure(model, self.settings)
        lockable = set(model.locked_joint_names)
        known = {k: v for k, v in self._locked_cache.items() if k in lockable}
        if known:
            model.set_locked(known)
        self.model = model
        self.layout = list(model.joint_names)
        self.model_info = info
        self._adopt(*derived)
        self._names = None  # rebuild the name map
        self._last_locked = None
        self.description_error = ''
        self.events.append(('info', None, f"model '{model.name}' loaded{' from ' + info if info else ''}: "
                                          f'{model.n} controlled joints {model.joint_names}, '
                                          f'locked {model.locked_joint_names}'))
        lim = np.asarray(model.effort_limits)
        unlimited = [j for j, e in zip(model.joint_names, lim) if not np.isfinite(e)]
        if unlimited:
            self.events.append(('warn', None, f'no URDF effort limit for {unlimited}: not clamped'))
        self._note_inertia(model.physical_consistency())

    def _note_inertia(self, report):
        """Keep the model's inertia report; one warn event per offending link (this load only)."""
        self.inertia_report = list(report)
        self.inertia_repaired = sum(bool(r['repaired']) for r in self.inertia_report)
        for item in self.inertia_report[:INERTIA_LOG_LINES]:
            self.events.append(('warn', None, _clip(f"inertia: {item['message']}", INERTIA_TEXT_MAX)))
        more = len(self.inertia_report) - INERTIA_LOG_LINES
        if more > 0:
            self.events.append(('warn', None, f'inertia: ... and {more} more links with inconsistent inertia'))

    def note_description_error(self, text):
        """Record a refused description; returns the text as kept (bounded)."""
        text = _clip(text, DIAG_TEXT_MAX)  # e.g. a strict refusal listing thousands of links
        self.description_error = text
        self.last_error = text
        kept = f" (keeping model '{self.model.name}')" if self.model is not None else ''
        self.events.append(('error', None, f'robot description rejected: {text}{kept}'))
        return text

    def update(self, changes):
        """Validate and apply parameter changes atomically. Raises ValueError with the reason."""
        new = dict(self.settings)
        for k, v in changes.items():
            new[k] = check_value(k, v)
        if new['joints'] != self.settings['joints']:
            raise ValueError('joints cannot change at run time')
        self._check_payload_pair(new)
        enable_changed = new['enabled'] != self.settings['enabled']
        if self.model is None and self.layout is not None:  # gains are checked against the layout early
            _gains(new['kp'], len(self.layout), 'kp')
            _gains(new['kd'], len(self.layout), 'kd')
        mode_changed = new['mode'] != self.settings['mode']
        if self.model is not None:
            old = self.settings
            derived = self._configure(self.model, new, old['payload.link'] if old['payload.mass'] > 0 else '')
            self.settings = new
            self._adopt(*derived)
        else:
            self.settings = new
        if mode_changed:
            self.desired_fallback = False  # a later stale desired state is reported again
            self.events.append(('info', None, f"mode: {new['mode']}"))
        if enable_changed:
            return self._on_enabled_changed()
        return None

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
        self.rejected += 1
        self._win_rejected += 1
        self.last_error = f'joint_states rejected: {text}'
        self.events.append(('warn', 'reject:' + kind, self.last_error))
        return None

    def _build_map(self, names):
        nm = _NameMap()
        nm.build(names, self.layout)  # duplicates and missing controlled joints, one message each
        self._names, self._map_error = nm.names, nm.error
        if nm.error:
            return
        index = {name: i for i, name in enumerate(names)}
        self._ctrl_idx = np.array([index[j] for j in self.model.joint_names], dtype=int)
        self._lock_names = [j for j in self.model.locked_joint_names if j in index]
        self._lock_idx = np.array([index[j] for j in self._lock_names], dtype=int)
        self._last_locked = None

    def on_joint_state(self, names, position, velocity=(), effort=(), now=None):
        """One joint_states message -> command (ndarray, command order) or None (publish nothing)."""
        self.clamped = None
        self.received += 1
        model = self.model
        if model is None:  # the node said once at start-up that it waits for a model
            return None
        n_names = len(names)
        if len(position) != n_names or len(velocity) not in (0, n_names) or len(effort) not in (0, n_names):
            return self._reject('length', f'array lengths differ: {n_names} names, {len(position)} positions, '
                                          f'{len(velocity)} velocities, {len(effort)} efforts')
        if names != self._names:
            self._build_map(names)
        if self._map_error is not None:
            return self._reject(*self._map_error)
        pos = np.asarray(position, dtype=float)
        q = pos[self._ctrl_idx]
        if not np.isfinite(q).all():
            bad = [model.joint_names[k] for k in np.flatnonzero(~np.isfinite(q))]
            return self._reject('nonfinite', f'non-finite positions for {bad}')
        if len(self._lock_idx):
            lv = pos[self._lock_idx]
            if not np.isfinite(lv).all():
                bad = [self._lock_names[k] for k in np.flatnonzero(~np.isfinite(lv))]
                return self._reject('nonfinite', f'non-finite positions for {bad}')
            if self._last_locked is None or not np.array_equal(lv, self._last_locked):
                vals = dict(zip(self._lock_names, lv.tolist()))
                model.set_locked(vals)
                self._locked_cache.update(vals)
                self._last_locked = lv

        s = self.settings
        now = self.clock() if now is None else now
        law = s['mode']
        if law != 'gravity' and not self._desired_fresh(now):
            law = 'gravity'
            self.law = 'gravity (fallback)'
        else:
            self.law = law
        if law == 'gravity':
            need_v = self._need_velocity
        else:
            need_v = law == 'computed_torque' or self._kd is not None
        qd = self._velocity(velocity) if need_v else None
        if law == 'gravity':
            if qd is not None and s['include_velocity_terms']:
                tau = model.inverse_dynamics(q, qd, np.zeros(model.n))
            else:
                tau = model.gravity(q)
            tau = self._add_friction(tau, qd)
        else:
            q_d, qd_d, qdd_d = self.desired
            fb = None  # Kp e + Kd de
            if self._kp is not None:
                fb = self._kp * (q_d - q)
            if self._kd is not None:
                fb = self._kd * (qd_d - qd) if fb is None else fb + self._kd * (qd_d - qd)
            if law == 'feedforward':
                tau = self._add_friction(model.inverse_dynamics(q_d, qd_d, qdd_d), qd_d)
                if fb is not None:
                    tau = tau + fb
            elif law == 'computed_torque':
                tau = self._add_friction(model.inverse_dynamics(q, qd, qdd_d if fb is None else qdd_d + fb), qd)
            else:  # pd
                tau = np.zeros(model.n) if fb is None else fb
        tau = self._clamp(tau)
        if tau is None:
            return self._reject('nonfinite_output', f'non-finite torque computed at q={q.tolist()}')

        self.accepted += 1
        self._win_accepted += 1
        self.last_q = q
        self.last_valid_time = now
        if self.stale:
            self.stale = False
            self.events.append(('info', None, 'joint_states valid again: compensation resumed'))
        if not s['enabled']:
            return None
        return tau

    def _velocity(self, velocity):
        """Measured velocities of the controlled joints; unavailable (absent, NaN/inf) = 0."""
        if not len(velocity):
            self.velocity_unavailable += 1
            return np.zeros(self.model.n)
        qd = np.asarray(velocity, dtype=float)[self._ctrl_idx]
        ok = np.isfinite(qd)
        if not ok.all():
            qd = np.where(ok, qd, 0.0)
            self.velocity_unavailable += 1
        return qd

    def _add_friction(self, tau, v):
        """tau + b*v + fc*tanh(v/eps) (configured friction compensation; v may be a batch)."""
        if self._viscous is not None:
            tau = tau + self._viscous * v
        if self._coulomb is not None:
            tau = tau + self._coulomb * np.tanh(v / self.settings['friction.coulomb_velocity_epsilon'])
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
            self.fallback_events += 1
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

    def _reject_desired(self, kind, text):
        self.desired_rejected += 1
        self._win_desired_rejected += 1
        self.last_error = f'desired state rejected: {text}'
        self.events.append(('warn', 'desired:' + kind, self.last_error))
        return False

    def on_desired(self, names, points, now=None):
        """One desired-state message (JointTrajectory joint_names and points) -> accepted?

        Exactly one point; positions for every name; velocities and accelerations either one
        per name or absent (= 0); the controlled joints present and finite (other names are
        ignored). A rejected message leaves the last valid desired state (and its age) as it was.
        """
        self.desired_received += 1
        if self.layout is None:  # no model and no `joints` yet: nothing to map to
            return False
        if len(points) != 1:
            return self._reject_desired('points', f'{len(points)} points: {self.desired_topic} takes exactly one '
                                                  '(whole trajectories go to ~/trajectory_in)')
        p = points[0]
        n_names = len(names)
        pos, vel, acc = p.positions, p.velocities, p.accelerations
        if len(pos) != n_names or len(vel) not in (0, n_names) or len(acc) not in (0, n_names):
            return self._reject_desired('length', f'array lengths differ: {n_names} joint names, {len(pos)} '
                                                  f'positions, {len(vel)} velocities, {len(acc)} accelerations')
        m = self._des_map
        if names != m.names:
            m.build(names, self.layout)
        if m.error is not None:
            return self._reject_desired(*m.error)
        n = len(self.layout)
        out = []
        for field, values in (('positions', pos), ('velocities', vel), ('accelerations', acc)):
            if not len(values):
                out.append(np.zeros(n))
                continue
            a = np.asarray(values, dtype=float)[m.idx]
            if not np.isfinite(a).all():
                bad = [self.layout[k] for k in np.flatnonzero(~np.isfinite(a))]
                return self._reject_desired('nonfinite', f'non-finite {field} for {bad}')
            out.append(a)
        self.desired = tuple(out)
        self.desired_time = self.clock() if now is None else now
        self.desired_accepted += 1
        return True

    def _reject_trajectory(self, text):
        self.trajectories_rejected += 1
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
        tau = self._add_friction(res['efforts'], res['velocities'])
        lim = self._limit
        over = np.abs(tau) > lim
        if over.any():
            tau = np.clip(tau, -lim, lim)
            joints = [self.layout[k] for k in np.flatnonzero(over.any(axis=0))]
            self.events.append(('warn', 'trajectory:clamp', f'trajectory efforts clamped to limit x '
                                f"{self.settings['effort_limit_scale']} at {int(over.any(axis=1).sum())} of "
                                f'{len(tau)} points for {joints}'))
        if not np.isfinite(tau).all():
            return self._reject_trajectory('non-finite effort computed')
        names = list(names)
        efforts = np.zeros((len(tau), len(names)))
        efforts[:, [names.index(j) for j in model.joint_names]] = tau
        self.trajectories_filled += 1
        return efforts

    def _clamp(self, tau):
        if (np.abs(tau) <= self._limit_finite).all():  # fast path: finite and within the limits
            return tau
        lim = self._limit
        over = np.abs(tau) > lim
        if over.any():
            tau = np.clip(tau, -lim, lim)
            self.clamp_count += 1
            self._win_clamped += 1
            self.clamped = [self.layout[k] for k in np.flatnonzero(over)]
            self.events.append(('warn', 'clamp', f'effort clamped to limit x {self.settings["effort_limit_scale"]}'
                                                 f' for {self.clamped} (total {self.clamp_count})'))
        if not np.isfinite(tau).all():
            return None
        return tau

    # ------------------------------------------------------------------ watchdog
    def tick(self, now=None):
        """Watchdog; call periodically. Returns the stale command to publish once, or None."""
        now = self.clock() if now is None else now
        if self.stale or self.last_valid_time is None:
            return None
        timeout = self.settings['stale_timeout']
        if now - self.last_valid_time <= timeout:
            return None
        self.stale = True
        self.stale_events += 1
        action = self.settings['stale_action']
        self.events.append(('warn', None, f'no valid joint_states for {now - self.last_valid_time:.3f} s '
                                          f'(stale_timeout {timeout} s): {action}'))
        if not self.settings['enabled'] or self.model is None:
            return None
        if action == 'zero':
            return np.zeros(self.model.n)
        if self.last_q is None or len(self.last_q) != self.model.n:
            return np.zeros(self.model.n)
        tau = self._clamp(self.model.gravity(self.last_q))
        return np.zeros(self.model.n) if tau is None else tau

    # ------------------------------------------------------------------ diagnostics
    def record_compute_time(self, seconds):
        self._win_times.append(seconds)

    def diagnostics(self, now=None):
        """(level, message, [(key, value-string)]) for the window since the last call; resets it."""
        now = self.clock() if now is None else now
        dt = max(now - self._win_start, 1e-9)
        times = self._win_times
        rate = self._win_accepted / dt
        m = self.model
        s = self.settings
        msgs, level = [], OK
        report, repaired = self.inertia_report, self.inertia_repaired
        if m is None:
            level, msgs = ERROR, ['no robot model (waiting for robot_description)']
        else:
            if self.last_valid_time is None:
                level = WARN
                msgs.append('waiting for joint_states')
            elif self.stale:
                level = WARN
                msgs.append(f"joint_states stale: {s['stale_action']}")
            elif s['mode'] in NEEDS_DESIRED and not self.desired_is_fresh(now):
                level = WARN
                msgs.append(f"mode {s['mode']}: " + ('no desired state yet' if self.desired_time is None else
                                                    'desired state stale') + ': gravity fallback')
            if self.description_error:
                level = max(level, WARN)
                msgs.append('last robot description rejected, previous model kept')
            if report:
                level = max(level, WARN)
                msgs.append(f'{len(report)} link(s) with inconsistent inertia'
                            + (f' ({repaired} repaired)' if repaired else ''))
            if self._win_rejected:
                level = max(level, WARN)
                msgs.append(f'{self._win_rejected} joint_states rejected')
            if self._win_clamped:
                level = max(level, WARN)
                msgs.append(f'{self._win_clamped} commands clamped')
            if not s['enabled']:
                msgs.append('disabled')
            if self._win_desired_rejected:
                level = max(level, WARN)
                msgs.append(f'{self._win_desired_rejected} desired states rejected')
            if not msgs:
                msgs.append('compensating' if s['mode'] == 'gravity' else s['mode'])
        values = [
            ('model_loaded', str(m is not None)),
            ('model_name', m.name if m is not None else ''),
            ('model_source', self.model_info),
            ('joint_count', str(m.n if m is not None else 0)),
            ('joints', ','.join(self.layout or [])),
            ('locked_joints', ','.join(m.locked_joint_names) if m is not None else ''),
            ('enabled', str(s['enabled'])),
            ('mode', s['mode']),
            ('control_law', self.law or ''),
            ('desired_age_ms', f'{1e3 * (now - self.desired_time):.1f}' if self.desired_time is not None else 'inf'),
            ('desired_received_total', str(self.desired_received)),
            ('desired_accepted_total', str(self.desired_accepted)),
            ('desired_rejected_total', str(self.desired_rejected)),
            ('desired_fallback_events', str(self.fallback_events)),
            ('trajectories_filled_total', str(self.trajectories_filled)),
            ('trajectories_rejected_total', str(self.trajectories_rejected)),
            ('input_rate_hz', f'{rate:.1f}'),
            ('compute_time_mean_ms', f'{1e3 * sum(times) / len(times):.4f}' if times else 'nan'),
            ('compute_time_max_ms', f'{1e3 * max(times):.4f}' if times else 'nan'),
            ('received_total', str(self.received)),
            ('accepted_total', str(self.accepted)),
            ('rejected_total', str(self.rejected)),
            ('stale', str(self.stale or self.last_valid_time is None)),
            ('stale_action', s['stale_action']),
            ('stale_events', str(self.stale_events)),
            ('clamp_count', str(self.clamp_count)),
            ('velocity_unavailable_count', str(self.velocity_unavailable)),
            ('last_error', self.last_error),
            ('description_error', self.description_error),
            ('inertia_policy', s['inertia_policy']),
            ('inertia_warnings', str(len(report))),
            ('inertia_repaired', str(repaired)),
            ('inertia_report', _clip(' | '.join(r['message'] for r in report[:INERTIA_DIAG_MESSAGES]),
                                     DIAG_TEXT_MAX)),
        ]
        self._win_start = now
        self._win_accepted = self._win_rejected = self._win_clamped = self._win_desired_rejected = 0
        self._win_times = []
        return level, '; '.join(msgs), values
