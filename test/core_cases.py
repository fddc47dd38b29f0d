"""Shared pieces of the tests of the node's decision logic without ROS (lie_dynamics.ros.core.compensator)."""
import re

from lie_dynamics import load_urdf
from lie_dynamics.ros.core.compensator import Compensator
from lie_dynamics.ros.core.messages import Rejected
from lie_dynamics.ros.trajectories.fill import TrajectoryInput
from lie_dynamics.ros.trajectories.trajectory_msgs import trajectory_arrays


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


def fill_trajectory(core, names, points):
    """A planner's trajectory (JointTrajectory joint_names and points) filled the node's way,
    without ROS or its trajectory process: TrajectoryInput.job (a refusal is counted), the
    process's fill of the message (trajectory_arrays, TrajectoryFill.fill), TrajectoryInput.done.
    Efforts (N, len(names)) in the message's joint order, or None (rejected)."""
    side = TrajectoryInput(core)
    job = side.job(len(points))
    if isinstance(job, Rejected):
        return side.done(job.text, kind=job.kind)
    try:
        efforts, note = job.fill(names, trajectory_arrays(names, points))
    except ValueError as exc:
        return side.done(str(exc))
    side.done(None, note)
    return efforts
