"""Trajectory effort fill of the dynamics node, in plain Python (no rclpy import).

`TrajectoryInput` is the node's trajectory side, composed with the Compensator: checks,
counters and log lines.

`TrajectoryFill` is a snapshot of what a fill needs (model, friction, effort limits), taken on
the control path; its `fill` may then run in another thread. Effort of a controlled joint:
inverse dynamics at the point (missing velocities / accelerations derived, see
lie_dynamics.trajectory) + friction compensation at the point's velocity, clamped like
commands (laws.clamp); joints that are not controlled get 0. With robot_compensates_gravity
the gravity torque at the point is left out, as in every command.
"""
from typing import NamedTuple, Optional

import numpy as np

from ...laws import add_friction, clamp
from ...model.joint_names import joint_columns
from ...trajectory import fill_trajectory_efforts
from ..core.diagnostics import names_text, problem_key
from ..core.messages import Rejected, columns_refusal


class TrajectoryFill(NamedTuple):
    model: object
    friction: Optional[object]     # laws.Friction or None
    limits: object                 # laws.EffortLimits
    scale: float                   # effort_limit_scale (for the clamp note)
    gravity_free: bool = False     # robot_compensates_gravity: efforts without g(q)

    def fill(self, names, arrays):
        """(efforts (N, len(names)) in the message's joint order, clamp note or None) for a
        trajectory given as trajectory_msgs.trajectory_arrays. Raises ValueError (bounded text)."""
        names = list(names)
        model = self.model
        mapped = joint_columns(names, model.joint_names)
        refusal = columns_refusal(mapped, names, model.joint_names)   # the joint_states wording
        if refusal is not None:
            raise refusal
        res = fill_trajectory_efforts(model, arrays, with_gravity=not self.gravity_free)
        tau, over = clamp(add_friction(res['efforts'], res['velocities'], self.friction), self.limits)
        note = None
        if over is not None:
            joints = [model.joint_names[k] for k in np.flatnonzero(over.any(axis=0))]
            note = (f'trajectory efforts clamped to limit x {self.scale} at {int(over.any(axis=1).sum())} of '
                    f'{len(over)} points for {names_text(joints)}')
        if tau is None:
            raise ValueError('non-finite effort computed')
        efforts = np.zeros((len(tau), len(names)))
        efforts[:, mapped.columns] = tau
        return efforts, note


class TrajectoryInput:
    """The node's trajectory side, composed with the Compensator `core`: what a fill may use
    (`job`) and what became of one (`done`), read from the core's public state and told through
    its public methods (`note_problem`; its counters)."""

    def __init__(self, core):
        self.core = core

    def job(self, points):
        """A TrajectoryFill of the current model and settings for a trajectory of `points`
        points (its fill may run in another thread), or why it is refused (messages.Rejected).
        Not while disabled, not above max_trajectory_points."""
        core = self.core
        if core.model is None:
            return Rejected('model', 'no robot model yet')
        s = core.settings
        if not s.enabled:
            return Rejected('disabled', 'node disabled')
        cap = s.max_trajectory_points
        if points > cap:
            return Rejected('points', f'{points} points, more than max_trajectory_points ({cap})')
        return TrajectoryFill(core.model, core.friction, core.limits, s.effort_limit_scale,
                              s.robot_compensates_gravity)

    def done(self, error=None, note=None, kind='malformed'):
        """Count a trajectory fill and queue its log lines: error is why it was rejected
        (nothing published; kind the problem class), note the clamp note of a filled one. Kind
        'process': the trajectory process was lost during the fill, perhaps after publishing it."""
        core = self.core
        if note:
            core.event('warn', 'trajectory:clamp', note)
        if error is None:
            core.count.trajectories_filled += 1
            return
        core.count.trajectories_rejected += 1
        key = 'trajectory:' + (problem_key(error) if kind == 'malformed' else kind)
        said = ' (the lost process may have published it first)' if kind == 'process' else ' (nothing published)'
        core.note_problem(key, f'trajectory rejected: {error}', said)
