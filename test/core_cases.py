"""Shared pieces of the tests of the node's decision logic without ROS (lie_dynamics.ros.core.compensator)."""
import re

from lie_dynamics import load_urdf
from lie_dynamics.ros.core.compensator import Compensator


class Clock:
    """A settable clock for Compensator (seconds)."""

    def __init__(self):
        self.t = 100.0

    def __call__(self):
        return self.t


def big_limits(xml, effort='1e6'):
    """The URDF with every effort limit set to `effort` (by default out of the way: no clamping)."""
    return re.sub(r'effort="[^"]*"', f'effort="{effort}"', xml)


def make(xml, ctrl, clock=None, **settings):
    """A Compensator on the model of `xml` controlling `ctrl`; friction, ramps and the position
    plausibility check (random URDF limits are narrow) out of the way unless given."""
    settings.setdefault('friction.viscous', [0.0])
    settings.setdefault('friction.coulomb', [0.0])
    settings.setdefault('ramp_time', 0.0)
    settings.setdefault('position_margin', 1000.0)
    c = Compensator(dict(joints=ctrl, **settings), clock=clock or Clock())
    c.set_model(load_urdf(xml, joints=ctrl))
    return c
