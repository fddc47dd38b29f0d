"""Models for the control path, in plain Python (no rclpy import): the warm-up that moves code
generation off it, and the default Jacobian link. (Which new model may replace the running one
and what changed between them: core/descriptions.py.)
"""
import numpy as np

from ...algorithms.observer import MomentumObserver


def tip_link(model):
    """The default Jacobian link: the last link (URDF order) carried by the model's last body,
    the end of the controlled chain of a serial arm."""
    last = model.nb - 1
    links = [name for name, (b, _) in model.link_frames.items() if b == last]
    return links[-1]


# What the control path calls per kernel key (Feature.kernels): run once, each generates its
# kernel's code (or loads it from the disk cache). 'jacobian' keys carry (link or None: tip_link, frame).
_WARM = {
    'gravity': lambda m, z: m.gravity(z),
    'inverse_dynamics': lambda m, z: m.inverse_dynamics(z, z, z),
    'coriolis': lambda m, z: m.coriolis_term(z, z),
    'mass_matrix': lambda m, z: m.mass_matrix(z),
    'observer': lambda m, z: MomentumObserver(m, 1.0).update(0.0, z, z, z),
    'jacobian': lambda m, z, link, frame: m.jacobian(z, link or tip_link(m), frame),
    # a recording's batch (payload identification): the regressor and inverse dynamics on rows
    'identification': lambda m, z: (m.regressor(*(np.zeros((IDENTIFY_BATCH, m.n)),) * 3),
                                    m.inverse_dynamics(*(np.zeros((IDENTIFY_BATCH, m.n)),) * 3)),
}
IDENTIFY_BATCH = 200   # states: above every size's rows threshold (codegen/thresholds.py)
# Every model's: the command's laws.
BASE_KERNELS = (('gravity',), ('inverse_dynamics',))


def warm_up(model, kernels=BASE_KERNELS):
    """Run once the kernels the control path will call (keys as Feature.kernels gives them;
    BASE_KERNELS always), so that their code is generated here (the loading thread, or the
    build process, which compiles them into the disk cache) and not at the first joint_states
    after the swap (a new structure's observer kernel was compiled there)."""
    z = np.zeros(model.n)
    for key in dict.fromkeys(BASE_KERNELS + tuple(kernels)):
        try:
            _WARM[key[0]](model, z, *key[1:])
        except Exception:  # noqa: BLE001 - the control path reports a model that cannot compute
            pass
