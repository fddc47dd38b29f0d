"""A smooth desired-state stream for the feedforward demo (ROS 2 node + the pure function), or a
trajectory CSV played to the dynamics node or to a joint_trajectory_controller.

    python -m lie_dynamics.sim.trajectory_source --ros-args -p desired_topic:=/dynamics_node/desired

For every joint_states message (stamped with the simulator's time t) it publishes one
trajectory_msgs/JointTrajectory point with the desired positions, velocities and
accelerations at t + lead (default: one simulator step ahead, the moment the command
computed from that state is applied):
    q_d(t) = q_home + a * (1 - cos(2 pi f t)) / 2
which starts at rest at q_home and stays between q_home and q_home + a (keep that inside the
joint limits).

With `file` (a trajectory CSV: time, pos.<joint>, [vel.<joint>], [acc.<joint>], as
`fill_trajectory` and `excitation_trajectory` write it; missing derivatives are derived as
lie_dynamics.trajectory does) the CSV is played instead, as `file_output` says:
  desired     the desired state of each joint_states message, as above, interpolated linearly in
              the CSV at t + lead - t_start, with t_start = the first joint_states stamp +
              start_after; before it the first point is held, after the end the last (at rest),
              for the dynamics node in mode feedforward or computed_torque;
  controller  one trajectory_msgs/JointTrajectory with every point on controller_topic (a
              joint_trajectory_controller's, the way a robot under position control plays it),
              the first point start_after s after it arrives, sent once min_subscribers (at
              least 1) readers match.
"""
import math
import sys

import numpy as np
from rclpy.node import Node
from sensor_msgs.msg import JointState
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

from ..ros.core.cdr import stamp_ns
from ..model.joint_names import broadcast_joints
from ..ros.core.settings import Values
from ..ros.run import node_parser, run
from ..trajectory import derivative, read_csv

# (name, default, meaning): declared in this order; --help lists them. Arrays: one value for
# every joint, or one per joint (in the order of joint_states).
PARAMETERS = (
    ('home', [0.0], 'q_home, rad (m): where the motion starts, at rest'),
    ('amplitude', [0.3], 'a, rad (m): the motion spans q_home .. q_home + a'),
    ('frequency', [0.25], 'f, Hz'),
    ('lead', 1e-3, 's ahead of each joint_states stamp (one simulator step)'),
    ('desired_topic', 'dynamics_node/desired',
     'trajectory_msgs/JointTrajectory output (relative: the dynamics node of this namespace)'),
    ('min_subscribers', 0, 'answer joint_states only once desired_topic has this many matched readers, >= 0'),
    ('file', '', 'trajectory CSV to play instead of the cosine motion ("": none)'),
    ('file_output', 'desired', 'how the file is played: desired (states on desired_topic, one per joint_states) '
                               'or controller (one JointTrajectory on controller_topic)'),
    ('controller_topic', 'joint_trajectory_controller/joint_trajectory',
     'trajectory_msgs/JointTrajectory input of a joint_trajectory_controller (file_output controller)'),
    ('start_after', 1.0, 's from the first joint_states (desired) or from the message (controller) to the first '
                         'point, >= 0'),
)
FILE_OUTPUTS = ('desired', 'controller')
EXAMPLE = """
python -m lie_dynamics.sim.trajectory_source --ros-args -p "home:=[0.0,-0.6,0.0,2.0,0.0,1.6,0.8]" \\
    -p "amplitude:=[0.4]" -p "frequency:=[0.3]" -p desired_topic:=/dynamics_node/desired
"""


def desired_state(t, q_home, amplitude, frequency):
    """(q, qd, qdd) of the demo trajectory at time t (arrays of the joints' shape)."""
    w = 2 * np.pi * np.asarray(frequency, dtype=float)
    a = 0.5 * np.asarray(amplitude, dtype=float)
    q = np.asarray(q_home, dtype=float) + a * (1 - np.cos(w * t))
    return q, a * w * np.sin(w * t), a * w * w * np.cos(w * t)


class FileTrajectory:
    """A trajectory CSV as arrays: times from 0 (s), joint names, q, q̇, q̈ (points, joints).
    Raises ValueError naming the file and the problem."""

    def __init__(self, path):
        try:
            traj = read_csv(path)
        except OSError as exc:
            raise ValueError(f'file {path}: {exc.strerror or exc}') from None
        t = traj['time_from_start']
        if len(t) < 2:
            raise ValueError(f'{path}: a trajectory needs at least 2 points, got {len(t)}')
        for key in ('time_from_start', 'positions', 'velocities', 'accelerations'):
            if key in traj and not np.all(np.isfinite(traj[key])):
                raise ValueError(f'{path}: non-finite {key}')
        if np.any(np.diff(t) <= 0):
            k = int(np.argmax(np.diff(t) <= 0)) + 1
            raise ValueError(f'{path}: times must increase strictly (data row {k + 1}: {t[k]} after {t[k - 1]})')
        self.t = t - t[0]
        self.names = list(traj['joint_names'])
        self.q = traj['positions']
        self.qd = traj['velocities'] if 'velocities' in traj else derivative(self.q, self.t)
        self.qdd = traj['accelerations'] if 'accelerations' in traj else derivative(self.qd, self.t)

    @property
    def duration(self):
        return float(self.t[-1])

    def state(self, t):
        """(q, q̇, q̈) at t s from the start, linearly interpolated; the first point (at rest)
        before 0, the last one (at rest) after the end."""
        if t <= 0 or t >= self.t[-1]:
            k = 0 if t <= 0 else len(self.t) - 1
            return self.q[k], np.zeros(len(self.names)), np.zeros(len(self.names))
        k = int(np.searchsorted(self.t, t, side='right')) - 1
        f = (t - self.t[k]) / (self.t[k + 1] - self.t[k])
        return tuple(a[k] + f * (a[k + 1] - a[k]) for a in (self.q, self.qd, self.qdd))

    def message(self, start_after):
        """The whole trajectory as one JointTrajectory (header stamp 0: start on arrival)."""
        out = JointTrajectory(joint_names=self.names)
        points = []
        for k, tk in enumerate(self.t + start_after):
            p = JointTrajectoryPoint(positions=self.q[k].tolist(), velocities=self.qd[k].tolist(),
                                     accelerations=self.qdd[k].tolist())
            sec = int(tk)
            p.time_from_start.sec, p.time_from_start.nanosec = sec, int(round((tk - sec) * 1e9))
            points.append(p)
        out.points = points
        return out


def per_joint(values, n, name):
    """A parameter array for n joints: one value for all, or exactly n values."""
    out = broadcast_joints(values, n)
    if out is None:
        raise ValueError(f'{name} has {np.size(values)} values for {n} joints (give 1 or {n})')
    return out


class TrajectorySource(Node):
    def __init__(self, **kwargs):
        super().__init__('trajectory_source', **kwargs)
        v = Values({name: self.declare_parameter(name, default).value for name, default, _ in PARAMETERS})
        self.home, self.amplitude, self.frequency = (np.array(v[k], dtype=float)
                                                     for k in ('home', 'amplitude', 'frequency'))
        self.lead = float(v.lead)
        topic = v.desired_topic
        # The joint count is only known from joint_states: refuse now what no count can fix.
        sizes = {}
        for k in ('home', 'amplitude', 'frequency'):
            a = getattr(self, k)
            if a.size == 0 or not np.all(np.isfinite(a)):
                raise ValueError(f'{k} must be 1 or one-per-joint finite values, got {list(v[k] or [])}')
            if a.size > 1:
                sizes[k] = a.size
        if len(set(sizes.values())) > 1:
            raise ValueError(f'home, amplitude and frequency give different joint counts: {sizes}')
        if not math.isfinite(self.lead):
            raise ValueError(f'lead must be finite, got {self.lead}')
        if not topic.strip():
            raise ValueError('desired_topic must not be empty')
        self.min_subscribers = int(v.min_subscribers)
        if self.min_subscribers < 0:
            raise ValueError(f'min_subscribers must be >= 0, got {self.min_subscribers}')
        self.start_after = float(v.start_after)
        if not (math.isfinite(self.start_after) and self.start_after >= 0):
            raise ValueError(f'start_after must be finite and >= 0, got {self.start_after}')
        if v.file_output not in FILE_OUTPUTS:
            raise ValueError(f"file_output must be one of {list(FILE_OUTPUTS)}, got {v.file_output!r}")
        self.file = FileTrajectory(v.file) if v.file else None
        self._t_start = None
        if self.file is not None and v.file_output == 'controller':
            self.pub = self.create_publisher(JointTrajectory, v.controller_topic, 10)
            self.min_subscribers = max(1, self.min_subscribers)   # sent once: to a reader that is there
            self._wait = self.create_timer(0.01, self._send_when_matched)
            return
        self.pub = self.create_publisher(JointTrajectory, topic, 10)
        # A desired state sent before the dynamics node's reader has matched is lost, and in a
        # lockstep run the states it answered are then computed without it: joint_states is only
        # read once the readers are there (a lockstep simulator waits for this node meanwhile).
        self._wait = self.create_timer(0.01, self._subscribe_when_matched)
        self._subscribe_when_matched()

    def _subscribe_when_matched(self):
        if self._wait is None or self.pub.get_subscription_count() < self.min_subscribers:
            return
        self.destroy_timer(self._wait)
        self._wait = None
        self.create_subscription(JointState, 'joint_states', self._on_state, 10)

    def _send_when_matched(self):
        if self._wait is None or self.pub.get_subscription_count() < self.min_subscribers:
            return
        self.destroy_timer(self._wait)
        self._wait = None
        self.pub.publish(self.file.message(self.start_after))
        self.get_logger().info(f'sent {len(self.file.t)} points ({self.file.duration:g} s) on '
                               f'{self.pub.topic_name}')

    def _on_state(self, msg):
        n = len(msg.name)
        if n == 0:
            return
        t = stamp_ns(msg.header.stamp.sec, msg.header.stamp.nanosec) * 1e-9 + self.lead
        if self.file is not None:
            self._play(msg, t)
            return
        try:
            home, amp, freq = (per_joint(x, n, k) for x, k in ((self.home, 'home'), (self.amplitude, 'amplitude'),
                                                               (self.frequency, 'frequency')))
        except ValueError as exc:
            self.get_logger().warn(f'no desired state published: {exc}', throttle_duration_sec=2.0)
            return
        q, qd, qdd = desired_state(t, home, amp, freq)
        out = JointTrajectory()
        out.header.stamp = msg.header.stamp
        out.joint_names = list(msg.name)
        out.points = [JointTrajectoryPoint(positions=q.tolist(), velocities=qd.tolist(), accelerations=qdd.tolist())]
        self.pub.publish(out)

    def _play(self, msg, t):
        """The file's desired state at t (s of the joint_states clock, lead included)."""
        if self._t_start is None:
            self._t_start = t - self.lead + self.start_after
        q, qd, qdd = self.file.state(t - self._t_start)
        out = JointTrajectory(joint_names=self.file.names)
        out.header.stamp = msg.header.stamp
        out.points = [JointTrajectoryPoint(positions=q.tolist(), velocities=qd.tolist(), accelerations=qdd.tolist())]
        self.pub.publish(out)


def main(args=None):
    """Publish desired states until shut down; 2 on bad arguments or parameters."""
    parser = node_parser('trajectory_source', __doc__, PARAMETERS, EXAMPLE)
    return run(TrajectorySource, 'trajectory_source', args, parser=parser)


if __name__ == '__main__':
    sys.exit(main())
