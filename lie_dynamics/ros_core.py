"""Decision logic of the dynamics node, in plain Python (no rclpy import).

`Compensator` turns joint_states messages into effort commands: it validates each message,
maps joints by name, feeds uncontrolled joints to the model's locked values, applies the
torque law, clamps, and runs the stale-input watchdog. The ROS node (dynamics_node.py) only
moves messages in and out and logs the `events` this class queues.

Torque law (command order = controlled joints):
    tau = g(q)|gravity*gravity_scale  [+ C(q, qd) qd]  + b*qd + fc*tanh(qd/eps)
then clamped to +-effort_limit*effort_limit_scale. Velocity-dependent terms use the measured
velocity; a NaN/inf (or absent) velocity of a joint counts as unavailable and is used as 0.
Locked joints are treated as stationary.
"""
import time

import numpy as np

from .ros_params import check_value, defaults

# diagnostic_msgs/DiagnosticStatus levels
OK, WARN, ERROR = 0, 1, 2


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
        self.model_info = ''          # where the current model came from
        self.events = []
        # derived from (model, settings)
        self._limit = None
        self._limit_finite = None
        self._viscous = None
        self._coulomb = None
        self._need_velocity = False
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
        return limit, viscous, coulomb

    def _adopt(self, limit, viscous, coulomb):
        self._limit, self._viscous, self._coulomb = limit, viscous, coulomb
        self._limit_finite = np.minimum(limit, np.finfo(float).max)  # so that +-inf fails `<=`
        self._need_velocity = (self.settings['include_velocity_terms'] or viscous is not None
                               or coulomb is not None)

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

    def note_description_error(self, text):
        self.description_error = text
        self.last_error = text
        kept = f" (keeping model '{self.model.name}')" if self.model is not None else ''
        self.events.append(('error', None, f'robot description rejected: {text}{kept}'))

    def update(self, changes):
        """Validate and apply parameter changes atomically. Raises ValueError with the reason."""
        new = dict(self.settings)
        for k, v in changes.items():
            new[k] = check_value(k, v)
        if new['joints'] != self.settings['joints']:
            raise ValueError('joints cannot change at run time')
        self._check_payload_pair(new)
        enable_changed = new['enabled'] != self.settings['enabled']
        if self.model is not None:
            old = self.settings
            derived = self._configure(self.model, new, old['payload.link'] if old['payload.mass'] > 0 else '')
            self.settings = new
            self._adopt(*derived)
        else:
            self.settings = new
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
        self._names = list(names)
        self._map_error = None
        index = {}
        dup = []
        for i, name in enumerate(names):
            if name in index:
                dup.append(name)
            index[name] = i
        if dup:
            self._map_error = ('duplicate', f'duplicate joint names {sorted(set(dup))}')
            return
        missing = [j for j in self.layout if j not in index]
        if missing:
            self._map_error = ('missing', f'missing controlled joints {missing}')
            return
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
        qd = None
        if self._need_velocity:
            if len(velocity):
                qd = np.asarray(velocity, dtype=float)[self._ctrl_idx]
                ok = np.isfinite(qd)
                if not ok.all():
                    qd = np.where(ok, qd, 0.0)
                    self.velocity_unavailable += 1
            else:
                qd = np.zeros(model.n)
                self.velocity_unavailable += 1
        if qd is not None and s['include_velocity_terms']:
            tau = model.inverse_dynamics(q, qd, np.zeros(model.n))
        else:
            tau = model.gravity(q)
        if self._viscous is not None:
            tau = tau + self._viscous * qd
        if self._coulomb is not None:
            tau = tau + self._coulomb * np.tanh(qd / s['friction.coulomb_velocity_epsilon'])
        tau = self._clamp(tau)
        if tau is None:
            return self._reject('nonfinite_output', f'non-finite torque computed at q={q.tolist()}')

        self.accepted += 1
        self._win_accepted += 1
        self.last_q = q
        self.last_valid_time = self.clock() if now is None else now
        if self.stale:
            self.stale = False
            self.events.append(('info', None, 'joint_states valid again: compensation resumed'))
        if not s['enabled']:
            return None
        return tau

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
        if m is None:
            level, msgs = ERROR, ['no robot model (waiting for robot_description)']
        else:
            if self.last_valid_time is None:
                level = WARN
                msgs.append('waiting for joint_states')
            elif self.stale:
                level = WARN
                msgs.append(f"joint_states stale: {s['stale_action']}")
            if self.description_error:
                level = max(level, WARN)
                msgs.append('last robot description rejected, previous model kept')
            if self._win_rejected:
                level = max(level, WARN)
                msgs.append(f'{self._win_rejected} joint_states rejected')
            if self._win_clamped:
                level = max(level, WARN)
                msgs.append(f'{self._win_clamped} commands clamped')
            if not s['enabled']:
                msgs.append('disabled')
            if not msgs:
                msgs.append('compensating')
        values = [
            ('model_loaded', str(m is not None)),
            ('model_name', m.name if m is not None else ''),
            ('model_source', self.model_info),
            ('joint_count', str(m.n if m is not None else 0)),
            ('joints', ','.join(self.layout or [])),
            ('locked_joints', ','.join(m.locked_joint_names) if m is not None else ''),
            ('enabled', str(s['enabled'])),
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
        ]
        self._win_start = now
        self._win_accepted = self._win_rejected = self._win_clamped = 0
        self._win_times = []
        return level, '; '.join(msgs), values
