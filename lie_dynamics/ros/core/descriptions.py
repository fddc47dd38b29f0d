"""Robot descriptions into models, in plain Python (no rclpy import): the one description-update
rule (`update_refusal`: which new model may replace the running one, description_update), what
changed between two models (`model_changes`, logged on the swap), and the build of a model from a
description in this process (`read_description` within the caps, `build`). The node runs `build`
in a child process (loading/build_process.py) and hands the core that builder
(Compensator.build_model's `builder`); the core's default is `build` here.
"""
import warnings

import numpy as np

from ... import InertiaWarning, load_urdf
from .diagnostics import clip, names_text


def update_refusal(policy, running, new=None):
    """The one description-update policy: why model `new` may not replace `running` under
    description_update `policy`, or None. new=None asks before a description is read (a reload,
    a description to parse): only 'none' refuses then. (That a new model controls the same joints
    is checked with the command layout, Compensator.plan.)"""
    if running is None:
        return None
    if policy == 'none':
        return "description_update is 'none': the running model stays"
    if policy == 'same_robot' and new is not None and new.name != running.name:
        return (f"robot '{clip(new.name, 80)}' is not the running robot '{running.name}' (description_update "
                "'same_robot'; 'any' accepts another robot with the controlled joints)")
    return None


def _per_joint(label, unit, names, old, new):
    """[(severity, text)] for the joints whose value differs; a raised effort limit warns."""
    old, new = np.asarray(old, dtype=float), np.asarray(new, dtype=float)
    same = (old == new) | (np.isnan(old) & np.isnan(new))
    idx = np.flatnonzero(~same)
    if not len(idx):
        return []
    items = [f'{names[k]} {old[k]:.6g} -> {new[k]:.6g}' for k in idx]
    raised = label == 'effort limits' and bool(np.any(new[idx] > old[idx]))
    return [('warn' if raised else 'info', f'{label} changed ({unit}): {names_text(items, 6)}')]


def model_changes(old, new):
    """[(severity, text)]: what differs between the running model `old` and its replacement
    `new` (robot name, masses, effort / position / velocity limits, joint frames and axes,
    locked joints), each line bounded."""
    out = []
    if old.name != new.name:
        out.append(('warn', f"robot name changed: '{old.name}' -> '{clip(new.name, 80)}'"))
    joints = list(new.joint_names)
    out += _per_joint('effort limits', 'N m or N', joints, old.effort_limits, new.effort_limits)
    out += _per_joint('lower position limits', 'rad or m', joints, old.position_lower, new.position_lower)
    out += _per_joint('upper position limits', 'rad or m', joints, old.position_upper, new.position_upper)
    out += _per_joint('velocity limits', 'rad/s or m/s', joints, old.velocity_limits, new.velocity_limits)
    if list(old.body_link_names) != list(new.body_link_names):
        out.append(('warn', f'kinematic tree changed: moving links {names_text(old.body_link_names)} -> '
                            f'{names_text(new.body_link_names)}'))
    else:
        mass_old = np.asarray(old.inertial_parameters()).reshape(-1, 10)[:, 0]
        mass_new = np.asarray(new.inertial_parameters()).reshape(-1, 10)[:, 0]
        out += _per_joint('masses', 'kg, per moving body', list(new.body_link_names), mass_old, mass_new)
        if old.M.shape == new.M.shape and not (np.array_equal(old.M, new.M) and np.array_equal(old.S, new.S)):
            out.append(('warn', 'joint frames or axes changed'))
    if list(old.locked_joint_names) != list(new.locked_joint_names):
        out.append(('info', f'locked joints changed: {names_text(old.locked_joint_names)} -> '
                            f'{names_text(new.locked_joint_names)}'))
    return out


def read_description(source, caps=None):
    """The URDF text of `source` within caps = (is_file, max_bytes, max_links): a file is read
    up to max_bytes + 1 characters; more than max_links `<link` tags (an upper bound: comments
    count too) raises ValueError before parsing. Without caps: source unchanged."""
    if caps is None:
        return source
    is_file, max_bytes, max_links = caps
    if is_file:
        with open(source, encoding='utf-8') as fh:
            source = fh.read(max_bytes + 1)
    links = source.count('<link')
    if links > max_links:
        raise ValueError(f'{links} <link> elements, more than max_description_links ({max_links})')
    return source


def build(source, caps=None, *, joints=None, gravity=(0.0, 0.0, -9.81), inertia='warn', running=None):
    """(model, other warnings) of a description: read_description, then load_urdf with its
    InertiaWarnings recorded (the model's physical_consistency() report carries them; the
    caller logs that once) and any other warning returned as (message, category, filename,
    lineno) for the caller to re-issue. running: None, or (description_update, the running
    robot's name): a model that policy refuses is refused here (update_refusal), so a
    child never sends back a model (thousands of bodies, perhaps) only to have it refused.
    Raises ValueError."""
    text = read_description(source, caps)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter('always', InertiaWarning)
        model = load_urdf(text, joints=joints, gravity=gravity, inertia=inertia)
    if running is not None:
        refusal = update_refusal(running[0], _Running(running[1]), model)
        if refusal:
            raise ValueError(refusal)
    other = [(str(w.message), w.category, w.filename, w.lineno) for w in caught
             if not issubclass(w.category, InertiaWarning)]
    return model, other


class _Running:
    """What update_refusal reads of the running model."""
    __slots__ = ('name',)

    def __init__(self, name):
        self.name = name
