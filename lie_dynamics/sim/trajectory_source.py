"""A smooth desired-state stream for the feedforward demo (ROS 2 node + the pure function).

    python -m lie_dynamics.sim.trajectory_source --ros-args -p desired_topic:=/dynamics_node/desired

For every joint_states message (stamped with the simulator's time t) it publishes one
trajectory_msgs/JointTrajectory point with the desired positions, velocities and
accelerations at t + lead (default: one simulator step ahead, the moment the command
computed from that state is applied):
    q_d(t) = q_home + a * (1 - cos(2 pi f t)) / 2
which starts at rest at q_home and stays between q_home and q_home + a (keep that inside the
joint limits).
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
)
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

    def _on_state(self, msg):
        n = len(msg.name)
        if n == 0:
            return
        t = stamp_ns(msg.header.stamp.sec, msg.header.stamp.nanosec) * 1e-9 + self.lead
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
    """Publish desired states until shut down; 2 on bad arguments or parameters."""
    parser = node_parser('trajectory_source', __doc__, PARAMETERS, EXAMPLE)
    return run(TrajectorySource, 'trajectory_source', args, parser=parser)


if __name__ == '__main__':
    sys.exit(main())
