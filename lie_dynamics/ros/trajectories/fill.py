"""Trajectory effort fill of the dynamics node, in plain Python (no rclpy import).

`TrajectoryInput` is the Compensator's trajectory side: checks, counters and log lines.

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
from ..core.diagnostics import DIAG_TEXT_MAX, clip, names_text, problem_key
from ..core.messages import Rejected, columns_refusal
from .trajectory_msgs import trajectory_arrays


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
    """The trajectory side of the Compensator (a base class: it uses the core's model,
    settings, friction, limits, counters, events and last_error)."""

    def trajectory_fill(self, points):
        """A TrajectoryFill of the current model and settings for a trajectory of `points`
        points (its fill may run in another thread), or why it is refused (messages.Rejected)."""
        if self.model is None:
            return Rejected('model', 'no robot model yet')
        if not self.settings['enabled']:
            return Rejected('disabled', 'node disabled')
        cap = self.settings['max_trajectory_points']
        if points > cap:
            return Rejected('points', f'{points} points, more than max_trajectory_points ({cap})')
        return TrajectoryFill(self.model, self.friction, self.limits, self.settings['effort_limit_scale'],
                              self.settings['robot_compensates_gravity'])

    def trajectory_done(self, error=None, note=None, kind='malformed'):
        """Count a trajectory fill and queue its log lines: error is why it was rejected
        (nothing published; kind the problem class), note the clamp note of a filled one. Kind
        'process': the trajectory process was lost during the fill, perhaps after publishing it."""
        if note:
            self.events.append(('warn', 'trajectory:clamp', note))
        if error is None:
            self.count.trajectories_filled += 1
            return None
        self.count.trajectories_rejected += 1
        self.last_error = clip(f'trajectory rejected: {error}', DIAG_TEXT_MAX)
        key = 'trajectory:' + (problem_key(error) if kind == 'malformed' else kind)
        said = ' (the lost process may have published it first)' if kind == 'process' else ' (nothing published)'
        self.events.append(('warn', key, self.last_error + said))
        return None

    def on_trajectory(self, names, points):
        """A planner's trajectory (JointTrajectory joint_names and points) -> efforts (N, k) in the
        message's joint order, or None (rejected: publish nothing). Not while disabled, not
        above max_trajectory_points."""
        job = self.trajectory_fill(len(points))
        if isinstance(job, Rejected):
            return self.trajectory_done(job.text, kind=job.kind)
        try:
            efforts, note = job.fill(names, trajectory_arrays(names, points))
        except ValueError as exc:
            return self.trajectory_done(str(exc))
        self.trajectory_done(None, note)
        return efforts
