"""The configuration half of the node's decision core, in plain Python (no rclpy import): settings
and models change in two steps. `plan` validates (a parameter change, a new model, or both)
without changing anything, `apply` makes a plan current; `update` and `set_model` do both.
`build_model` builds a model from a description with the builder it is given (descriptions.build
in this process by default; the node passes its build process), `load` builds and sets it,
applying `inertia_policy`; the model's physical_consistency() report is logged once per load (at
most INERTIA_LOG_LINES lines) and kept for the diagnostics. A new model must pass
`description_update` (descriptions.update_refusal); what changed is logged.

`Configuration` is the base of `compensator.Compensator`, which adds the command path and
reacts to an applied plan in `_applied`.
"""
import copy
import os
import time
import warnings

import numpy as np

from ...calibration.result import load_calibration, with_calibration
from ...laws import LAWS, uses_velocity
from .descriptions import build, model_changes, update_refusal
from .diagnostics import DIAG_TEXT_MAX, INERTIA_LOG_LINES, INERTIA_TEXT_MAX, Counters, clip, names_text
from .messages import JointStateReader
from .params import check_value
from .settings import PAYLOAD_KEYS, Plan, Settings, check_payload_pair, derive, gains, payload_link, place_payload


class Configuration:
    """Settings and model of the core: plan/apply, build/load. Events (severity, throttle_key,
    text) queue in `events` for the caller to drain and log; totals are in `count`."""

    def __init__(self, settings=None, clock=time.monotonic, builder=None):
        self.clock = clock
        self.builder = builder or build   # description -> (model, other warnings), as descriptions.build
        s = Settings(settings)   # ValueError on a bad value
        check_payload_pair(s)
        self.settings = s
        self.layout = list(s.joints) or None  # command joint order, fixed once known
        if self.layout is not None:
            gains(s.kp, len(self.layout), 'kp')
            gains(s.kd, len(self.layout), 'kd')
        self.model = None
        self.model_info = ''          # where the current model came from
        self.loading = ''             # what is being loaded in the background (note_context)
        self.inertia_report = []      # physical_consistency() of the current model
        self.inertia_repaired = 0     # entries of it with repaired=True
        self.events = []
        self.count = Counters()
        self.reader = None            # JointStateReader of the current model
        self.known_locked = {}        # last measured value of each locked joint, kept across models
        self.derived = None           # settings.Derived of (model, settings)
        self.limits = None            # laws.EffortLimits
        self.friction = None          # laws.Friction or None (off)
        self.kp = self.kd = None      # per-joint gains or None (0)
        self.needs_velocity = {}      # mode -> does its law read the measured velocity
        self.last_error = ''
        self.description_error = ''
        self.calibration = None       # CalibrationResult of calibration_file on the current model, or None
        self.uncalibrated = None      # with a calibration: the model it was applied to (no payload)

    def event(self, severity, key, text):
        """Queue a log line (severity 'info'/'warn'/'error', throttle key = its problem class)."""
        self.events.append((severity, key, text))

    def note_error(self, text):
        """Keep `text` as the last error (diagnostics); returns it as kept (bounded)."""
        self.last_error = clip(text, DIAG_TEXT_MAX)
        return self.last_error

    def note_problem(self, key, text, said=''):
        """A refused input: `text` becomes the last error (bounded) and a warn line (with `said`
        after it)."""
        self.events.append(('warn', key, self.note_error(text) + said))
        return self.last_error

    # ------------------------------------------------------------------ plan and apply
    def plan(self, changes=None, model=None, info=''):
        """Validate parameter `changes` and/or a new `model` (its joint_names must equal the
        fixed layout, and description_update must let it replace the running one) without
        making them current. Returns a Plan for `apply`; raises ValueError with the reason.
        Only a new model is touched (configured with the settings); a payload on the current
        model is tried on a scratch copy of it."""
        changes = dict(changes or {})
        new = self.settings.replace(changes)
        if new.joints != self.settings.joints:
            raise ValueError('joints cannot change at run time')
        check_payload_pair(new)
        derived = None
        calibration = None
        if model is not None or new.calibration_file != self.settings.calibration_file:
            model, calibration = self._calibrate(new, model)
        if calibration is not None and model is None:
            pass   # no model yet: the file is checked, a model gets it when it comes
        elif model is not None:
            if self.layout is not None and list(model.joint_names) != self.layout:
                raise ValueError(f'the model controls {names_text(model.joint_names)}, but the command layout is '
                                 f'{names_text(self.layout)}')
            refusal = update_refusal(new.description_update, self.model, model)
            if refusal:
                raise ValueError(refusal)
            derived = derive(model, new)
            # a calibrated model is a fresh copy without payload; another new model carries at most
            # a payload an earlier plan put there (current settings)
            place_payload(model, new, '' if calibration is not None else payload_link(self.settings))
        elif self.model is not None:
            derived = derive(self.model, new)
            if payload_link(new) and new.differs(self.settings, PAYLOAD_KEYS):
                place_payload(copy.deepcopy(self.model), new, payload_link(self.settings))
        elif self.layout is not None:  # gains are checked against the layout early
            gains(new.kp, len(self.layout), 'kp')
            gains(new.kd, len(self.layout), 'kd')
        report = None
        if model is not None:
            report = (model_changes(self.model, model) if self.model is not None else [], model.physical_consistency())
        return Plan(new, changes, model, info, derived, (self.model, self.settings), report, calibration)

    def _calibrate(self, new, model):
        """(model, (uncalibrated, CalibrationResult or None, the description model given or None))
        for settings `new` and a new description model (None: the running one), or (model, None)
        when no calibration is
        involved. The calibration goes on a payload-free copy; a file is read only when
        calibration_file changes. ValueError (load_calibration / with_calibration) with the file's
        name: missing, malformed, another robot, physically invalid values."""
        path, given = new.calibration_file, model
        if model is not None:
            if not path:
                return model, None
            base = model
            base.clear_payload()
        elif self.model is None:
            base = None
        elif self.uncalibrated is not None:
            base = self.uncalibrated
        else:
            base = copy.deepcopy(self.model)
            base.clear_payload()
        if not path:
            return (None if base is None else copy.deepcopy(base)), (base, None, given)
        c = self.calibration
        if c is None or path != self.settings.calibration_file:
            try:
                # read in the parameter callback (a refusal keeps the old value): bounded as a description
                size = os.path.getsize(path)
                if size > new.max_description_bytes:
                    raise ValueError(f'calibration_file {path}: {size} bytes, more than max_description_bytes '
                                     f'({new.max_description_bytes})')
                c = load_calibration(path)
            except OSError as exc:
                raise ValueError(f'calibration_file {path}: {exc.strerror or exc}') from None
        if base is None:
            return None, (None, c, given)
        try:
            return with_calibration(base, c), (base, c, given)
        except ValueError as exc:
            raise ValueError(f'calibration_file {path}: {exc}') from None

    def apply(self, plan, now=None):
        """Make `plan` current. Returns the command to publish once (the zero command when it
        disables without a ramp), or None. A plan made before another change is checked again
        (ValueError)."""
        if plan.base[0] is not self.model or plan.base[1] is not self.settings:
            given = plan.calibration[2] if plan.calibration is not None else plan.model
            plan = self.plan(plan.changes, given, plan.info)
        now = self.clock() if now is None else now
        old = self.settings
        if plan.model is None and self.model is not None:
            place_payload(self.model, plan.settings, payload_link(old))
        self.settings = plan.settings
        if plan.calibration is not None:
            base, c, _ = plan.calibration
            self.uncalibrated, self.calibration = (base, c) if c is not None else (None, None)
            if c is not None:
                self.event('info', 'calibration', f'calibration {self.settings.calibration_file} applied '
                                                  f"(robot '{c.robot}')")
                eps = self.settings.friction.coulomb_velocity_epsilon
                if c.eps != eps:   # its Coulomb values were identified with its own eps
                    self.event('warn', 'calibration:eps', f'the calibration was identified with Coulomb '
                                                          f'velocity epsilon {c.eps}, '
                                                          f'friction.coulomb_velocity_epsilon is {eps}')
        if plan.model is not None:
            self._install(plan.model, plan.info, plan.report)
        if plan.derived is not None:
            self._adopt(plan.derived)
        return self._applied(plan, old, now)

    def _applied(self, plan, old, now):
        """What the command path does once `plan` is current (old: the settings before it);
        returns the command to publish once, or None."""
        return None

    def _adopt(self, derived):
        self.derived = derived
        self.limits, self.friction, self.kp, self.kd = derived.limits, derived.friction, derived.kp, derived.kd
        if self.reader is not None:
            self.reader.bounds = derived.bounds
        vt = self.settings.include_velocity_terms
        self.needs_velocity = {mode: uses_velocity(mode, self.kd, self.friction, vt) for mode in LAWS}

    def _install(self, model, info, report):
        """report: the plan's (model_changes against the running model, physical_consistency)."""
        self.model = model
        self.layout = list(model.joint_names)
        self.model_info = info
        self.reader = JointStateReader(model, self.known_locked)
        self.description_error = ''
        self.event('info', 'model', f"model '{model.name}' loaded{' from ' + info if info else ''}: "
                                    f'{model.n} controlled joints {names_text(model.joint_names)}, '
                                    f'locked {names_text(model.locked_joint_names)}')
        for k, (severity, text) in enumerate(report[0]):
            self.event(severity, f'model:change:{k}', f'model update: {text}')
        lim = np.asarray(model.effort_limits)
        unlimited = [j for j, e in zip(model.joint_names, lim, strict=True) if not np.isfinite(e)]
        if unlimited:
            self.event('warn', 'model:unlimited', f'no URDF effort limit for {names_text(unlimited)}: not clamped')
        self._note_inertia(report[1])

    def update(self, changes):
        """Validate and apply parameter changes atomically (plan + apply). Raises ValueError with
        the reason; returns the command to publish once, or None."""
        return self.apply(self.plan(changes))

    def set_model(self, model, info=''):
        """Make `model` current (its joint_names must equal the fixed layout). Raises ValueError
        and keeps the previous model if the new one does not fit the settings."""
        self.apply(self.plan(None, model, info))

    # ------------------------------------------------------------------ descriptions
    def build_model(self, source, inertia=None, builder=None):
        """load_urdf(source) for the command layout with the configured gravity and inertia
        policy (`inertia` overrides `inertia_policy`); not made current. Raises ValueError (also
        for a strict refusal). builder: a callable with descriptions.build's signature (the
        node's build process: BuildProcess.build); None: the one this core was given."""
        policy = check_value('inertia_policy', self.settings.inertia_policy if inertia is None else inertia)
        # InertiaWarnings are recorded: set_model reports the model's own report once per link;
        # a model description_update refuses is refused where it is built (plan checks it again)
        running = None if self.model is None else (self.settings.description_update, self.model.name)
        model, other = (builder or self.builder)(source, joints=self.layout, gravity=self.settings.gravity,
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
            self.event('warn', f'inertia:{k}', clip(f"inertia: {item['message']}", INERTIA_TEXT_MAX))
        more = len(self.inertia_report) - INERTIA_LOG_LINES
        if more > 0:
            self.event('warn', 'inertia:more', f'inertia: ... and {more} more links with inconsistent inertia')

    def note_description_error(self, text):
        """Record a refused description; returns the text as kept (bounded)."""
        text = clip(text, DIAG_TEXT_MAX)  # e.g. a strict refusal listing thousands of links
        self.description_error = text
        self.last_error = text
        kept = f" (keeping model '{self.model.name}')" if self.model is not None else ''
        self.event('error', 'description', f'robot description rejected: {text}{kept}')
        return text
