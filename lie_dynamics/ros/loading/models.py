"""Models for the control path, in plain Python (no rclpy import): the warm-up that moves code
generation off it, and the default Jacobian link. (Which new model may replace the running one
and what changed between them: core/descriptions.py.)
"""
import pickle

import numpy as np


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
