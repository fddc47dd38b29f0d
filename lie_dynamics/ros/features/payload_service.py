"""Payload identification and direct payload setting for the dynamics node, in plain Python (no
rclpy import). The node's services (payload_services.py) call these; the fit is
lie_dynamics.algorithms.payload.identify_payload.

`~/identify_payload` records `identify.duration` seconds of accepted joint_states with efforts
(`Identification`: one at a time, a bounded `Recording`), turns the efforts into motor torques by
the node's effort convention (contact.effort_convention and contact.motor_torque), derives q̈
(`dynamic` mode: a Savitzky-Golay derivative of the recorded q̇; `static` mode: only the samples at rest,
q̇ = q̈ = 0, which determine mass and CoM only), fits, and refuses a fit that explains too little of
the payload's torque (`identify.max_residual_ratio`). What it returns becomes the payload.*
parameters. Time is core/timebase.TimeBase's: the joint_states stamp when there is one (simulated
time in lockstep), else the steady clock; a recording keeps to the base it started in.

`~/set_payload` takes the four payload.* values in one request (`check_payload_request`): all of
them, a full inertia about the CoM, physically consistent (Model.check_payload, the check setting
the parameters makes), on a link that moves a controlled joint; mass 0 (or link '') clears the
payload. An identified payload is set through the parameters, so the same check applies to it.
"""
import copy
import threading
import time
from typing import NamedTuple

import numpy as np

from ...algorithms.payload import identify_payload
from ...laws import friction_torque
from ..core.diagnostics import DIAG_TEXT_MAX, clip
from ..core.timebase import TimeBase
from .base import Feature
from .contact import effort_convention, motor_torque
from ..core.params import IDENTIFY_MODES, PAYLOAD_KEYS, check_value

__all__ = ['IDENTIFY_MODES', 'FitJob', 'Identification', 'PayloadRecording', 'Recording', 'check_payload_request',
           'fit', 'prepare', 'smooth_derivative', 'warm_fit']

# Samples kept: when full, every other one is dropped and the stride doubles (memory is bounded
# whatever identify.duration and the input rate; 4,000 samples of 7 joints fit in 10-70 ms).
MAX_SAMPLES = 4000
MIN_SAMPLES = 20
# Static mode: samples moving faster than this (rad/s or m/s, any joint) are not at rest.
STILL_VELOCITY = 0.02
# Half-width (s) of the local cubic fit that differentiates q̇ (a Savitzky-Golay derivative): it
# averages out sensor noise, and a cubic keeps the bias far below a linear fit's (measured on the
# excitation trajectory at 500 Hz: 5e-6 against 4e-3 rad/s² for a linear fit over +-30 ms, with
# about the same noise gain).
DERIVATIVE_HALF_WIDTH = 0.05
# Wall-clock limit of a recording: joint_states may run slower than real time (lockstep simulation)
WALL_FACTOR, WALL_EXTRA = 5.0, 10.0


class Recording:
    """Up to `capacity` samples (t, q, q̇, effort) of n joints, decimated by two whenever full."""

    def __init__(self, n, duration, capacity=MAX_SAMPLES):
        self.duration = duration
        self.t = np.empty(capacity)
        self.q, self.qd, self.effort = (np.empty((capacity, n)) for _ in range(3))
        self.size = 0
        self.stride = 1
        self._skip = 0
        self.t0 = self.last_t = None
        self.stamped = None        # time base: header stamps (True) or the steady clock
        self.seen = 0              # samples offered with an effort
        self.no_effort = 0         # accepted joint_states without (finite) efforts

    @property
    def elapsed(self):
        return 0.0 if self.t0 is None else self.last_t - self.t0

    def add(self, t, q, qd, effort, stamped=True):
        """Offer one sample; returns True once `duration` is covered."""
        if self.stamped is None:
            self.stamped = stamped
        if stamped != self.stamped or (self.last_t is not None and t <= self.last_t):
            return False   # another time base, or not newer: a derivative across it is meaningless
        if self.t0 is None:
            self.t0 = t
        self.last_t = t
        self.seen += 1
        self._skip += 1
        if self._skip >= self.stride:
            self._skip = 0
            if self.size == len(self.t):
                keep = slice(0, self.size, 2)
                for a in (self.t, self.q, self.qd, self.effort):
                    kept = a[keep].copy()
                    a[:len(kept)] = kept
                self.size = len(kept)
                self.stride *= 2
            k = self.size
            self.t[k], self.q[k], self.qd[k], self.effort[k] = t, q, qd, effort
            self.size += 1
        return self.elapsed >= self.duration

    def arrays(self):
        k = self.size
        return self.t[:k].copy(), self.q[:k].copy(), self.qd[:k].copy(), self.effort[:k].copy()


def smooth_derivative(t, x, half_width=DERIVATIVE_HALF_WIDTH):
    """(t_u, dx_u): x (N, n) resampled on a uniform grid at the median step and its derivative
    by a centred local cubic fit over +-half_width (Savitzky-Golay: no lag); the ends, where the
    window is incomplete, are dropped. Raises ValueError when too short."""
    dt = float(np.median(np.diff(t))) if len(t) > 1 else 0.0
    if not dt > 0:
        raise ValueError('the recorded joint_states have no time step')
    grid = np.arange(t[0], t[-1] + 0.5 * dt, dt)
    xu = _resampled(grid, t, x)
    w = max(2, int(round(half_width / dt)))
    if len(grid) < 2 * w + MIN_SAMPLES:
        raise ValueError(f'only {len(grid)} time steps recorded: too short to differentiate q̇')
    k = np.arange(-w, w + 1, dtype=float)
    weights = np.linalg.pinv(np.vander(k, 4, increasing=True))[1] / dt   # d/dt of the cubic at the centre
    d = sum(weights[i] * xu[i:len(grid) - 2 * w + i] for i in range(2 * w + 1))
    return grid[w:len(grid) - w], d


def prepare(t, q, qd, effort, mode):
    """(q, q̇, q̈, effort) for the fit from a recording's arrays. Raises ValueError."""
    if mode == 'static':
        still = np.max(np.abs(qd), axis=1) < STILL_VELOCITY
        if np.count_nonzero(still) < MIN_SAMPLES:
            raise ValueError(f'static mode: only {int(np.count_nonzero(still))} samples at rest (|q̇| < '
                             f'{STILL_VELOCITY} on every joint): hold the arm still in a few poses')
        z = np.zeros_like(qd[still])
        return q[still], z, z, effort[still]
    grid, qdd = smooth_derivative(t, qd)
    return _resampled(grid, t, q), _resampled(grid, t, qd), qdd, _resampled(grid, t, effort)


def _resampled(grid, t, x):
    return np.stack([np.interp(grid, t, x[:, j]) for j in range(x.shape[1])], axis=1)


def fit(model, link, t, q, qd, effort, mode, convention, max_ratio, friction=None):
    """(PayloadResult, changes {payload.*: value}, message) from recorded data on `model` (a copy
    taken when the recording ended; its payload, if any, is replaced by the fit). friction: the
    node's friction model (laws.Friction or None), taken out of the motor torque as the observer
    does: what the node compensates as friction is not payload. Raises ValueError with the reason:
    too little data, nothing excited, a non-positive mass, a bad fit."""
    if len(t) < MIN_SAMPLES:
        raise ValueError(f'only {len(t)} joint_states with efforts recorded (need {MIN_SAMPLES})')
    q, qd, qdd, effort = prepare(t, q, qd, effort, mode)
    tau = np.asarray(motor_torque(model, q, effort, convention), dtype=float)
    if friction is not None:
        tau = tau - friction_torque(qd, *friction)
    res = identify_payload(model, link, q, qd, qdd, tau)
    bare = model.with_body_inertias(model.J_links)
    signal = float(np.sqrt(np.mean((tau - bare.inverse_dynamics(q, qd, qdd)) ** 2)))
    resid = float(np.sqrt(np.mean(res.residual_rms ** 2)))
    ratio = resid / signal if signal > 0 else np.inf
    if not ratio <= max_ratio:
        raise ValueError(f'bad fit: residual {resid:.3g} N m is {100 * ratio:.0f}% of the payload torque '
                         f'{signal:.3g} N m (identify.max_residual_ratio {max_ratio}): {res.summary}')
    changes = {'payload.link': link, 'payload.mass': float(res.mass), 'payload.com': [float(c) for c in res.com],
               'payload.inertia': [] if res.inertia is None else [float(v) for v in res.inertia]}
    span = float(t[-1] - t[0])
    message = (f'{res.summary}; {len(q)} samples over {span:.2f} s ({mode}), residual {100 * ratio:.1f}% of '
               'the payload torque; payload.* parameters set')
    return res, changes, clip(message, DIAG_TEXT_MAX)


# States of the warm-up batch: above every size's rows threshold (codegen/thresholds.py), so that
# the fit's row kernels are the ones generated.
IDENTIFY_BATCH = 200


def warm_fit(model):
    """The fit's batch kernels (regressor, inverse dynamics on rows), generated by one batch at
    rest (a Feature.kernels warm-up call)."""
    z = np.zeros((IDENTIFY_BATCH, model.n))
    model.regressor(z, z, z)
    model.inverse_dynamics(z, z, z)


def identify_link(settings):
    return settings.identify.link or settings.payload.link


def _payload_link(model, link, name):
    """A link that may carry a payload of `model`, by the one rule (Model.check_payload: a link
    that moves a controlled joint). Raises ValueError naming the parameter."""
    try:
        model.check_payload(link, 0.0, (0.0, 0.0, 0.0))
    except ValueError as exc:
        raise ValueError(f'{name}: {exc}') from None


def check_identify_link(settings, model):
    """identify.link must name a link that may carry a payload of `model` (when set and a model
    is loaded): what it identifies becomes payload.link. Raises ValueError."""
    if settings.identify.link and model is not None:
        _payload_link(model, settings.identify.link, 'identify.link')


class FitJob(NamedTuple):
    """What a finished recording is fitted with (Identification.take; `run` outside the lock)."""
    recording: Recording
    model: object          # a copy of the model the recording was made with
    link: str
    mode: str              # identify.mode
    convention: str        # contact.effort_convention
    max_ratio: float       # identify.max_residual_ratio
    friction: object       # laws.Friction or None

    def run(self):
        """fit(...) of this job: (PayloadResult, changes, message). Raises ValueError."""
        return fit(self.model, self.link, *self.recording.arrays(), self.mode, self.convention, self.max_ratio,
                   self.friction)


class Identification:
    """One identification at a time. begin() and add() run under the node's lock (add on the
    control path, after each accepted joint_states); wait() and the fit run in the service's own
    thread."""

    def __init__(self, clock=time.monotonic):
        self.clock = clock
        self.recording = None      # the Recording being filled (None: not recording)
        self.busy = False
        self.done = threading.Event()
        self.state = 'idle'
        self.last = ''             # the last outcome, for the diagnostics
        self.succeeded = self.refused = 0
        self._rec = self._model = self.time = None
        self._abort = ''
        self.started = None

    def begin(self, core, now=None):
        """Start recording for core's model and settings. Raises ValueError (refused at once)."""
        if self.busy:
            raise ValueError('an identification is already running')
        if core.model is None:
            raise ValueError('no robot model loaded')
        s = core.settings
        link = identify_link(s)
        if not link:
            raise ValueError('no link to identify on: set identify.link (or payload.link)')
        _payload_link(core.model, link, 'identify.link')
        if effort_convention(s) == 'none':
            raise ValueError("measured_effort is 'none': joint_states efforts are not motor torques")
        self.busy, self._abort = True, ''
        self.done.clear()
        self._rec = self.recording = Recording(core.model.n, s.identify.duration)
        self._model, self.time = core.model, TimeBase(self.clock)
        self.started = self.clock() if now is None else now
        self.state = f"recording {s.identify.duration:g} s"
        return link

    def add(self, sample, now=None):
        """One accepted joint_states (core.sample.SampleResult), after its command (control path)."""
        rec = self.recording
        if rec is None:
            return
        if sample.model is not self._model:
            return self.stop('the robot model changed while recording')
        e = sample.effort
        if np.count_nonzero(np.isfinite(e)) != e.size:
            rec.no_effort += 1
            return
        t = self.time.seconds(sample.stamp, now)
        if rec.add(t, sample.q, sample.qd, e, stamped=self.time.stamped):
            self.stop()

    def stop(self, why=''):
        """End the recording (why: the reason it is abandoned)."""
        self.recording = None
        self._abort = self._abort or why
        self.done.set()

    def wait(self):
        """(service thread) Block until the recording ends or its wall-clock limit passes."""
        rec = self._rec
        if not self.done.wait(WALL_FACTOR * rec.duration + WALL_EXTRA):
            self.stop(f'joint_states with efforts covered only {rec.elapsed:.2f} of {rec.duration:g} s in '
                      f'{WALL_FACTOR * rec.duration + WALL_EXTRA:g} s')

    def take(self, core):
        """The FitJob of the recording once stopped (under the node's lock). Raises ValueError for
        an abandoned recording."""
        rec = self._rec
        if self._abort:
            raise ValueError(self._abort)
        if rec.size < MIN_SAMPLES:
            raise ValueError(f'only {rec.size} joint_states with efforts recorded ({rec.no_effort} without efforts)')
        if core.model is not self._model:
            raise ValueError('the robot model changed while recording')
        s = core.settings
        self.state = 'fitting'
        return FitJob(rec, copy.deepcopy(core.model), identify_link(s), s.identify.mode, effort_convention(s),
                      s.identify.max_residual_ratio, core.friction)

    def finish(self, ok, message):
        self.busy = False
        self.recording = self._rec = self._model = None
        self.state = 'idle'
        self.last = ('identified: ' if ok else 'refused: ') + message   # bounded by Features.report
        if ok:
            self.succeeded += 1
        else:
            self.refused += 1

    def report(self):
        return [('payload_identification', self.state), ('payload_identification_last', self.last),
                ('payload_identifications_total', str(self.succeeded)),
                ('payload_identifications_refused', str(self.refused))]


class PayloadRecording(Feature):
    """The recording of ~/identify_payload as a per-sample feature (base.py): active while an
    Identification records, fed each accepted sample; identify.link checked on every change."""

    name = 'payload'

    def __init__(self, clock=time.monotonic):
        super().__init__()
        self.ident = Identification(clock)

    @property
    def active(self):
        return self.ident.recording is not None

    def check(self, settings, model):
        check_identify_link(settings, model)

    def kernels(self, settings):
        # the fit's batch kernels, generated before the first ~/identify_payload waits for them
        return ((warm_fit,),) if settings.identify.link or settings.payload.link else ()

    def on_sample(self, sample):
        self.ident.add(sample)

    def report(self, level, message):
        return level, message, self.ident.report()


def check_payload_request(values, model):
    """{payload.*: value} to set from a ~/set_payload request {name: value}; raises ValueError with
    the reason. A payload needs all four values (a full inertia about the CoM in link axes: ixx,
    ixy, ixz, iyy, iyz, izz); each is checked as the parameter table checks it (check_value), the
    payload as a whole by the one payload rule (Model.check_payload), the check that setting the
    parameters applies too. Mass 0 or link '' clears it."""
    unknown = sorted(set(values) - set(PAYLOAD_KEYS))
    if unknown:
        raise ValueError(f'unknown names {clip(repr(unknown), 200)}: expected {list(PAYLOAD_KEYS)}')
    if 'payload.link' not in values:
        raise ValueError('payload.link (a string) is required')
    link = check_value('payload.link', values['payload.link'])
    mass = check_value('payload.mass', values.get('payload.mass', 0.0 if not link else None))
    if not link or mass == 0:
        return {'payload.link': '', 'payload.mass': 0.0, 'payload.com': [0.0, 0.0, 0.0], 'payload.inertia': []}
    com, inertia = (check_value(k, values[k]) if k in values else [] for k in ('payload.com', 'payload.inertia'))
    missing = [k for k, v in (('payload.com', com), ('payload.inertia', inertia)) if not v]
    if missing:
        raise ValueError(f'{" and ".join(missing)} required (a full payload: mass, CoM and inertia)')
    if model is None:
        raise ValueError('no robot model loaded')
    model.check_payload(link, mass, com, inertia)   # the one payload rule, as setting the parameters applies it
    return {'payload.link': link, 'payload.mass': mass, 'payload.com': com, 'payload.inertia': inertia}
