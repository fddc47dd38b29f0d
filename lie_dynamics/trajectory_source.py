"""A smooth desired-state stream for the feedforward demo (ROS 2 node + the pure function).

    python -m lie_dynamics.trajectory_source --ros-args -p desired_topic:=/dynamics_node/desired

For every joint_states message (stamped with the simulator's time t) it publishes one
trajectory_msgs/JointTrajectory point with the desired positions, velocities and
accelerations at t + lead (default: one simulator step ahead, the moment the command
computed from that state is applied):
    q_d(t) = q_home + a * (1 - cos(2 pi f t)) / 2
which starts at rest at q_home and stays within q_home +- a (kept inside the joint limits).
"""
import sys

import numpy as np
from rclpy.node import Node
from sensor_msgs.msg import JointState
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

from .ros_run import run


def desired_state(t, q_home, amplitude, frequency):
    """(q, qd, qdd) of the demo trajectory at time t (arrays of the joints' shape)."""
    w = 2 * np.pi * np.asarray(frequency, dtype=float)
    a = 0.5 * np.asarray(amplitude, dtype=float)
    q = np.asarray(q_home, dtype=float) + a * (1 - np.cos(w * t))
    return q, a * w * np.sin(w * t), a * w * w * np.cos(w * t)


def per_joint(values, n, name):
    """A parameter array for n joints: one value for all, or exactly n values."""
    values = np.asarray(values, dtype=float)
    if values.shape == (1,):
        return np.full(n, values[0])
    if values.shape != (n,):
        raise ValueError(f'{name} has {values.size} values for {n} joints (give 1 or {n})')
    return values


class TrajectorySource(Node):
    def __init__(self, **kwargs):
        super().__init__('trajectory_source', **kwargs)
        p = self.declare_parameter
        self.home = np.array(p('home', [0.0]).value, dtype=float)
        self.amplitude = np.array(p('amplitude', [0.3]).value, dtype=float)
        self.frequency = np.array(p('frequency', [0.25]).value, dtype=float)
        self.lead = float(p('lead', 1e-3).value)
        topic = p('desired_topic', '/dynamics_node/desired').value
        self.pub = self.create_publisher(JointTrajectory, topic, 10)
        self.create_subscription(JointState, 'joint_states', self._on_state, 10)

    def _on_state(self, msg):
        n = len(msg.name)
        if n == 0:
            return
        t = msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9 + self.lead
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


def main(args=None):
    return run(TrajectorySource, 'trajectory_source', args)


if __name__ == '__main__':
    sys.exit(main())
