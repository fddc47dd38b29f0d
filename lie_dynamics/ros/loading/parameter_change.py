"""What a parameter change of the dynamics node does, decided in plain Python (no rclpy import):
the new settings (Compensator.plan) and which description, if any, to load once it is set.

rclpy calls the node's on-set callback with the whole change; only when it accepts are the
values set, and then the post-set callback applies the plan. Validation checks the settings
and what can be said of a new description without reading it (background.precheck:
description_update, size, a missing file; inertia_policy 'strict' against the running model's
inertia report); a change that fails there is rejected as a whole. After the set the plan
becomes current, and a new description or policy starts loading in the background: a model
that then fails to load is reported in the log and diagnostics, and the previous one keeps
running.
"""
from ..core.diagnostics import DIAG_TEXT_MAX, clip
from ..core.descriptions import update_refusal
from ..core.params import check_value
from .sources import source_label

# The description parameters, in the order start-up tries them, and the source kind of each.
SOURCES = (('robot_description', 'parameter'), ('urdf_path', 'file'))


def plan_change(core, changes, check, precheck, current_source):
    """(plan, load) for a parameter change {name: value}; load: (kind, text) to load afterwards,
    or None. check(settings): the node's checks that need the model (ValueError);
    precheck(kind, text, settings): background.precheck; current_source(): (kind, text) of the
    running model (Sources.reload_source). Raises ValueError with the reason."""
    rest = {k: v for k, v in changes.items() if k not in dict(SOURCES)}
    plan = core.plan(rest)
    check(plan.settings)
    s = plan.settings
    load = None
    for key, kind in SOURCES:
        text = check_value(key, changes[key]) if key in changes else ''
        if text:
            err = precheck(kind, text, s)
            if err:
                raise ValueError(f'{source_label(kind, text)}: {err}')
            load = (kind, text)
    if load is None and 'inertia_policy' in changes and s.inertia_policy != core.settings.inertia_policy:
        kind, text = current_source()
        if kind is not None and core.model is not None:
            if refusal := update_refusal(s.description_update, core.model):
                raise ValueError(f'{refusal} (an inertia_policy change reloads the description)')
            if s.inertia_policy == 'strict' and core.inertia_report:
                raise ValueError("inertia_policy 'strict' would refuse the running description: " +
                                 '; '.join(r['message'] for r in core.inertia_report))
        if kind is not None:
            load = (kind, text)
    return plan, load


class ParameterChanges:
    """The node's on-set / post-set pair around plan_change (arguments as there): `validate`
    plans a change and keeps the plan, `apply` makes it current (planned again if the change
    is not the one validated last, or the state moved in between)."""

    def __init__(self, core, check, precheck, current_source):
        self.core, self._args = core, (check, precheck, current_source)
        self.pending = None   # (changes, plan, load) of the change validated last

    def validate(self, changes):
        """None if `changes` can be set, else the reason (bounded)."""
        self.pending = None
        if not changes:
            return None
        try:
            self.pending = (changes,) + plan_change(self.core, changes, *self._args)
        except ValueError as exc:
            return clip(str(exc), DIAG_TEXT_MAX)
        return None

    def apply(self, changes):
        """(command to publish once or None, (kind, text) to load or None). Raises ValueError."""
        pending, self.pending = self.pending, None
        if pending is None or pending[0] != changes:
            pending = (changes,) + plan_change(self.core, changes, *self._args)
        _, plan, load = pending
        return self.core.apply(plan), load


def start_source(values):
    """(kind, text) of the description to load at start-up: the first source parameter set, or None."""
    for name, kind in SOURCES:
        if values[name]:
            return kind, values[name]
    return None


def reload_answer(kind, text, err):
    """(success, message) of ~/reload_model for source (kind, text) (None: none to reload) and the
    load request's refusal err (None: started)."""
    if kind is None:
        return False, 'no robot description to reload'
    if err is not None:
        return False, err
    return True, (f'loading {source_label(kind, text)} in the background; the running model answers until it is '
                  'ready (result: log, diagnostics model_state / description_error)')
