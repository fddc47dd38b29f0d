"""External joint torques and collision detection for the dynamics node, in plain Python (no
rclpy import).

`ContactMonitor` runs the generalized-momentum observer (lie_dynamics.algorithms.observer,
r -> tau_ext as a first-order filter of time constant 1 / observer.gain) on every accepted
joint_states message that carries an effort for every controlled joint, and debounces the
collision flag: it rises once |r_j| > collision.threshold_j for some joint j has held for
collision.hold_time, and falls once every |r_j| <= threshold_j has held as long, so neither edge
is a one-sample glitch.

Measured effort conventions (`measured_effort`, `motor_torque`): `total` — the effort is the
torque the motor puts on the joint, gravity included (ros2_control's effort state interface of
most drives, the simulator); `gravity_removed` — the driver already subtracted its own gravity
model, so g(q) of this model is added back; `none` — no usable effort, the observer is off.

Time base: core/timebase.TimeBase (the header stamps, the simulated time in the demo, the
drive's clock on a robot; a message without stamp uses `clock`); a switch between the two (a
simulator's first state is stamped 0) quietly starts a new integral. A sample with the stamp of
the previous one (a re-sent state) changes nothing. The observer pauses and re-initialises
(estimate 0, flag cleared) instead of integrating garbage when an effort or a velocity is
missing or non-finite, when time goes back, after a gap longer than MAX_GAP_S, when the model,
its friction, gravity or payload change, and if an estimate ever came out non-finite. Nothing
is published for a paused sample.
"""
import math
import time
import weakref

import numpy as np

from ...algorithms.observer import MomentumObserver
from ...model.joint_names import in_joint_order
from ..core.diagnostics import OK, WARN, clip, names_text
from ..core.params import EFFORT_CONVENTIONS, PAYLOAD_KEYS, per_joint_values
from ..core.timebase import TimeBase

__all__ = ['EFFORT_CONVENTIONS', 'ContactMonitor', 'Debounce', 'check_settings', 'effort_convention', 'effort_offset',
           'motor_torque', 'observer_on', 'thresholds', 'warm_observer']
# A longer gap between two samples is not integrated (the trapezoid would spread garbage over it).
MAX_GAP_S = 0.5
# Settings whose change starts a new integral: the model's dynamics or the observer itself.
REINIT_KEYS = ('observer.enabled', 'observer.gain', 'measured_effort', 'gravity', 'gravity_scale') + PAYLOAD_KEYS + (
    'friction.viscous', 'friction.coulomb', 'friction.coulomb_velocity_epsilon', 'calibration_file')


def effort_convention(settings):
    """What a joint_states effort holds (`measured_effort`: total | gravity_removed | none), the
    one rule for the observer and the payload identification. robot_compensates_gravity does not
    change it: it says what the robot adds to the command, not what its sensors report (a drive
    that echoes the command while the robot adds gravity reports gravity_removed; a torque
    sensor, as Franka's tau_J or KUKA's measured torque, reports total)."""
    return settings.measured_effort


def observer_on(settings):
    """Whether the settings run the observer (with a model): observer.enabled and a usable effort."""
    return bool(settings.observer.enabled) and effort_convention(settings) != 'none'


def effort_offset(model):
    """(n,) effort offsets (model order) of the calibration the model carries
    (Model.with_calibration; measured effort = true effort + offset), or None: none. An offset
    the calibration does not give (NaN, or a joint it does not name) is 0."""
    c = getattr(model, 'calibration', None)
    if c is None:
        return None
    cached = _OFFSETS.get(model)
    if cached is None or cached[0] is not c:   # once per model and calibration, not per sample
        out = np.zeros(model.n)
        for name, value in zip(c.joint_names, c.offset, strict=True):
            if np.isfinite(value):
                out[list(model.joint_names).index(name)] = value
        cached = _OFFSETS[model] = (c, out if np.any(out) else None)
    return cached[1]


_OFFSETS = weakref.WeakKeyDictionary()   # model -> (its calibration, the offsets effort_offset gave)


def motor_torque(model, q, effort, convention):
    """The total torque the motors put on the joints, from a measured `effort` (model order)
    under `convention` (EFFORT_CONVENTIONS): `total` as is, `gravity_removed` + g(q), `none`
    None (no usable effort); a calibration's effort offsets (effort_offset) are subtracted first.
    Raises ValueError for an unknown convention."""
    if convention in ('total', 'gravity_removed'):
        effort = np.asarray(effort, dtype=float)
        offset = effort_offset(model)
        if offset is not None:
            effort = effort - offset
    if convention == 'total':
        return effort
    if convention == 'gravity_removed':
        return effort + model.gravity(q)
    if convention == 'none':
        return None
    raise ValueError(f'measured_effort must be one of {list(EFFORT_CONVENTIONS)}, got {clip(repr(convention), 120)}')


def thresholds(values, n):
    """collision.threshold as n per-joint values: one value for every joint, or n values.
    Raises ValueError."""
    return per_joint_values('collision.threshold', values, n)


def check_settings(settings, n):
    """Validation that needs the number of controlled joints (None: not known yet)."""
    if n is not None:
        thresholds(settings.collision.threshold, n)


def warm_observer(model):
    """The observer's step kernel, generated by one step at rest (a Feature.kernels warm-up call)."""
    z = np.zeros(model.n)
    MomentumObserver(model, 1.0).update(0.0, z, z, z)


class Debounce:
    """A boolean that follows `raw` only after raw has held its new value for `hold` seconds."""

    def __init__(self, hold):
        self.hold = hold
        self.reset()

    def reset(self):
        self.state = False
        self.since = None  # when raw last started to differ from state

    def update(self, raw, t):
        """Feed raw at time t; True when `state` changed."""
        if raw == self.state:
            self.since = None
            return False
        if self.since is None:
            self.since = t
        if t - self.since >= self.hold - 1e-9:  # 1 ns: float stamps, 0.03 - 0.02 < 0.01
            self.state, self.since = raw, None
            return True
        return False


class ContactMonitor:
    """Observer + collision flag of the node (module docstring). Plain values in, plain values out.

    `adopt(settings, model, friction, layout)` follows the compensator's current configuration
    (cheap when nothing changed); `on_sample(result)` returns (estimate, collision) to publish, or
    None. `events` holds (severity, throttle_key, text) for the node's log; `report(...)` adds the
    diagnostics of the window since the last call.
    """

    def __init__(self, clock=time.monotonic):
        self.clock = clock
        self.events = []
        self.settings = self.model = self.friction = None
        self.layout = []
        self.observer = None
        self.convention = 'none'
        self.threshold = None
        self._threshold_list, self._threshold_min = [], math.inf   # the thresholds as floats (per sample)
        self.debounce = Debounce(0.0)
        self.error = ''               # why the observer is off although enabled
        self.efforts_seen = False     # an effort array came once: from then on a missing one is a fault
        self.state = 'no joint_states yet'
        self.time = TimeBase(clock)   # sample times: header stamps, else the clock
        self.last_stamp = None        # time (s, TimeBase) of the last estimate
        self.estimate = None
        self.collision = False
        self.collision_events = 0
        self.effort_unavailable = 0
        self.resets = 0
        self.samples = 0
        self._window_max = 0.0
        self._window_joint = ''
        self._window_collisions = 0

    # ------------------------------------------------------------------ configuration
    def adopt(self, settings, model, friction, layout):
        """Adopt the compensator's settings, model and friction (identity checks: per message)."""
        if settings is self.settings and model is self.model:
            return
        old = self.settings  # friction follows from the settings and the model: compared through them
        reinit = model is not self.model or old is None or settings.differs(old, REINIT_KEYS)
        self.settings, self.model, self.friction, self.layout = settings, model, friction, list(layout or [])
        self.debounce.hold = settings.collision.hold_time
        if not reinit and self.observer is not None:
            self._set_threshold(thresholds(settings.collision.threshold, model.n))
            return
        self.observer, self.error = None, ''
        self.convention = effort_convention(settings)
        if model is None or not observer_on(settings):
            self._restart('off')
            return
        try:
            self._set_threshold(thresholds(settings.collision.threshold, model.n))
            self.observer = MomentumObserver(model, settings.observer.gain, friction)
        except ValueError as exc:  # validated on set; a model with another joint count lands here
            self.error = str(exc)   # bounded where it is shown (the log, Features.report)
            self._event('error', 'observer:config', f'external torque observer off: {self.error}')
            self._restart('off')
            return
        self._restart('waiting for efforts' if not self.efforts_seen else 'running')

    def _set_threshold(self, values):
        self.threshold = values
        self._threshold_list, self._threshold_min = values.tolist(), float(values.min())

    def _restart(self, state):
        """Forget the integral and the flag (the next sample starts anew)."""
        if self.observer is not None:
            self.observer.reset()
        if self.collision:
            self._event('info', 'collision:clear', 'collision flag cleared: the observer restarts')
        self.debounce.reset()
        self.collision = False
        self.time.reset()
        self.last_stamp = None
        self.estimate = None
        self.state = state

    def _pause(self, why, key):
        self.resets += 1
        self._event('warn', 'observer:' + key, f'external torque observer paused and re-initialised: {why}')
        self._restart(f'paused: {why}')
        return None

    def _event(self, severity, key, text):
        self.events.append((severity, key, text))

    @property
    def active(self):
        return self.observer is not None

    # ------------------------------------------------------------------ per message
    def on_sample(self, s, now=None):
        """One accepted joint_states message as the core made it (core.sample.SampleResult):
        on_state with its arrays in model order. Returns (estimate (n,), collision) or None."""
        v, e = s.message_velocity, s.message_effort
        if len(v) and len(e):   # mapped here: cheaper than the memo of s.velocity and s.effort
            cols = s.columns
            return self.on_state(s.q, in_joint_order(v, cols), in_joint_order(e, cols), s.stamp, now)
        return self.on_state(s.q, s.velocity, s.effort if len(e) else None, s.stamp, now)

    def on_state(self, q, velocity, effort, stamp=0, now=None):
        """One accepted joint_states message, in model order as a core.sample.SampleResult gives
        it: q, velocity and effort (NaN where the message had none); effort None: the message
        carried no efforts. stamp in ns (0: none; then `now` or the clock). Returns (estimate
        (n,), collision) to publish, or None."""
        obs = self.observer
        if obs is None:
            return None
        if effort is None:
            self.effort_unavailable += 1
            return self._pause('joint_states without efforts', 'effort') if self.efforts_seen else None
        self.efforts_seen = True
        if not stamp and now is None:
            now = self.clock()   # read once: a restart below counts from the same time
        t = self.time.seconds(stamp, now)
        last = self.last_stamp
        if last is not None and not self.time.switched and 0.0 < t - last <= MAX_GAP_S:
            # the steady state: one kernel call; anything it declines takes the full path below
            e = motor_torque(self.model, q, effort, self.convention)
            r = obs.step(t, q, velocity, e)
            if r is not None:
                return self._accept(r, t)
        n = len(q)
        if np.count_nonzero(np.isfinite(effort)) != n:
            self.effort_unavailable += 1
            bad = [self.layout[k] for k in np.flatnonzero(~np.isfinite(effort))] if self.layout else []
            return self._pause(f'non-finite effort for {names_text(bad)}', 'effort')
        if len(velocity) != n or np.count_nonzero(np.isfinite(velocity)) != n:
            return self._pause('velocities missing or non-finite', 'velocity')
        if self.time.switched and last is not None:
            # a stream that starts (a simulator at t = 0) or stops stamping: a new integral in the
            # other time base; not a fault
            self._restart(self.state)
            t = self.time.seconds(stamp, now)
        if self.last_stamp is not None:
            dt = t - self.last_stamp
            if dt == 0:
                return None  # the same state again: nothing new
            if dt < 0 or dt > MAX_GAP_S:
                self._pause(f'time went back by {-dt:.3g} s' if dt < 0 else f'gap of {dt:.3g} s between samples',
                            'time')
                return self.on_state(q, velocity, effort, stamp, now)
        try:
            r = obs.update(t, q, velocity, motor_torque(self.model, q, effort, self.convention))
        except (ValueError, FloatingPointError) as exc:
            return self._pause(clip(str(exc), 200), 'compute')
        if np.count_nonzero(np.isfinite(r)) != n:
            return self._pause('non-finite estimate (implausible efforts?)', 'nonfinite')
        return self._accept(r, t)

    def _accept(self, r, t):
        """A finite estimate r at time t: kept, its window maximum and the debounced flag
        (on Python floats: a handful of joints costs less than numpy calls)."""
        self.last_stamp = t
        self.estimate = r
        self.samples += 1
        self.state = 'running'
        rl = r.tolist()
        top = max(map(abs, rl))
        if top > self._window_max:
            k = [abs(x) for x in rl].index(top)
            self._window_max, self._window_joint = top, self.layout[k] if self.layout else str(k)
        over = top > self._threshold_min and any(abs(x) > y for x, y in zip(rl, self._threshold_list, strict=True))
        d = self.debounce
        if (over != d.state or d.since is not None) and d.update(over, t):   # else update changes nothing
            self.collision = d.state
            if self.collision:
                self.collision_events += 1
                self._window_collisions += 1
                big = np.flatnonzero(np.abs(r) > self.threshold)
                over = [f'{self.layout[j]}: {r[j]:.3g} N m' for j in big]
                self._event('warn', 'collision', f'collision: external torque beyond collision.threshold for '
                                                 f"{self.settings.collision.hold_time:g} s at {names_text(over, 4)}"
                                                 f' (total {self.collision_events})')
            else:
                self._event('info', 'collision:clear', 'collision flag cleared: external torques below the thresholds')
        return r, self.collision

    # ------------------------------------------------------------------ diagnostics
    def report(self, level, message, values, where=''):
        """The compensator's diagnostics (level, message, values) with the observer's added;
        the window maximum restarts. where: said after 'collision' (the contact link)."""
        extra = []
        if self.collision:
            level = max(level, WARN)
            extra.append('collision' + where)
        elif self._window_collisions:
            extra.append(f'{self._window_collisions} collision(s)')
        if self.observer is not None and self.state.startswith('paused'):
            level = max(level, WARN)
            extra.append('external torque observer paused')
        if self.error:
            level = max(level, WARN)
            extra.append('external torque observer off (configuration)')
        if extra:
            message = '; '.join([message] + extra) if message else '; '.join(extra)
        top = self._window_max if self._window_joint else math.nan
        values = list(values) + [
            ('observer', self.state), ('observer_error', self.error), ('measured_effort', self.convention),
            ('external_torque_max', f'{top:.4g}'), ('external_torque_max_joint', self._window_joint),
            ('collision', str(self.collision)), ('collision_events', str(self.collision_events)),
            ('effort_unavailable_count', str(self.effort_unavailable)),
            ('observer_resets', str(self.resets)),
        ]
        self._window_max, self._window_joint, self._window_collisions = 0.0, '', 0
        return max(level, OK), message, values
