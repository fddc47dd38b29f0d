"""Robot description updates, in plain Python (no rclpy import): which new model may replace
the running one (description_update), what changed between them (logged on the swap), and the
warm-up that moves code generation off the control path.
"""
import pickle

import numpy as np

from ..core.diagnostics import clip, names_text


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


def tip_link(model):
    """The default Jacobian link: the last link (URDF order) carried by the model's last body,
    the end of the controlled chain of a serial arm."""
    last = model.nb - 1
    links = [name for name, (b, _) in model.link_frames.items() if b == last]
    return links[-1]


def at_rest(model, method, states=1):
    """model.<method> at `states` zero states (q; q, q̇; q, q̇, q̈): a warm-up call (Feature.kernels)
    that generates the kernel of a Model method the control path calls."""
    z = np.zeros(model.n)
    getattr(model, method)(*(z,) * states)


def jacobian_at_rest(model, link, frame):
    """model.jacobian at rest of `link` ('': tip_link) in `frame`: a warm-up call."""
    model.jacobian(np.zeros(model.n), link or tip_link(model), frame)


# Every model's: the command's laws.
BASE_KERNELS = ((at_rest, 'gravity'), (at_rest, 'inverse_dynamics', 3))


def warm_up(model, kernels=BASE_KERNELS):
    """Run once the kernels the control path will call: the warm-up calls (function, *args) of
    the features (Feature.kernels), run as function(model, *args), and BASE_KERNELS always, so
    that their code is generated here (the loading thread, or the build process, which compiles
    them into the disk cache) and not at the first joint_states after the swap (a new
    structure's observer kernel was compiled there). A call may come pickled (`portable`)."""
    for call in dict.fromkeys(BASE_KERNELS + tuple(kernels)):
        try:
            if isinstance(call, bytes):   # (the build process) one whose module it cannot import is skipped
                call = pickle.loads(call)
            call[0](model, *call[1:])
        except Exception:  # noqa: BLE001 - the control path reports a model that cannot compute
            pass


def portable(kernels):
    """Warm-up calls as the build process takes them: each pickled on its own, so that one it
    cannot import (a feature's module outside its path) or one that does not pickle (a lambda)
    leaves the others; the loading thread runs them all again (warm_up) in any case."""
    out = []
    for call in kernels:
        try:
            out.append(pickle.dumps(call))
        except Exception:  # noqa: BLE001 - not picklable: warmed in the loading thread only
            pass
    return tuple(out)
