"""ROS 2 node: a simulated arm standing in for a ros2_control robot with an effort controller.

    ros2 run lie_dynamics sim_node
    python -m lie_dynamics.sim_node --ros-args -p rate:=1000.0

Publishes   robot_description (std_msgs/String, reliable, transient local, depth 1),
            joint_states (sensor_msgs/JointState: position, velocity, effort = applied torque;
            header.stamp = simulated time)
Subscribes  <command_topic> (std_msgs/Float64MultiArray, ordered as `joints`), held until the
            next one like JointGroupEffortController; a message of the wrong length or with a
            non-finite value is dropped with a log line (recent controllers drop them too).

Parameters  urdf_path (default: the bundled arm), joints (default: all), rate (Hz, 1000),
            initial_positions, damping (URDF joint damping on/off), command_topic,
            lockstep (hold the initial state until the first command arrives, then wait for
            the command answering each published state, re-sending the state every
            `resend_period` s and stepping anyway after `lockstep_timeout` s: results then do
            not depend on machine load), min_subscribers (do not start before this many
            joint_states readers are matched, so no reader misses the start),
            max_steps (0 = run until shut down).
"""
import sys

import numpy as np
from rclpy.duration import Duration
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from rclpy.time import Time
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray, String

from . import default_urdf_path
from .ros_run import run
from .sim import ArmSim
from .urdf import load_urdf

DESCRIPTION_QOS = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL)


class SimNode(Node):
    def __init__(self, **kwargs):
        super().__init__('sim_node', **kwargs)
        p = self.declare_parameter
        urdf_path = p('urdf_path', default_urdf_path()).value or default_urdf_path()
        joints = list(p('joints', ['']).value)
        rate = float(p('rate', 1000.0).value)
        q0 = list(p('initial_positions', [0.0]).value)
        damping = bool(p('damping', True).value)
        self.command_topic = p('command_topic', '/effort_controller/commands').value
        self.lockstep = bool(p('lockstep', False).value)
        self.lockstep_timeout = float(p('lockstep_timeout', 0.05).value)
        self.resend_period = float(p('resend_period', 0.01).value)
        self.max_steps = int(p('max_steps', 0).value)
        self.min_subscribers = int(p('min_subscribers', 0).value)
        with open(urdf_path, encoding='utf-8') as fh:
            self.xml = fh.read()
        model = load_urdf(self.xml, joints=[j for j in joints if j] or None)
        if len(q0) == 1 and model.n != 1:
            q0 = q0 * model.n
        if len(q0) != model.n:
            raise ValueError(f'initial_positions needs {model.n} values, got {len(q0)}')
        if rate <= 0:
            raise ValueError(f'rate must be positive, got {rate}')
        self.sim = ArmSim(model, dt=1.0 / rate, q0=q0, damping=damping)
        self.names = model.joint_names
        self.desc_pub = self.create_publisher(String, 'robot_description', DESCRIPTION_QOS)
        self.desc_pub.publish(String(data=self.xml))
        # Deep history: a reliable reader whose acknowledgements lag (a busy recorder) must not lose
        # states while the lockstep loop with a fast controller runs ahead of it.
        self.state_pub = self.create_publisher(JointState, 'joint_states', 1000)
        self.create_subscription(Float64MultiArray, self.command_topic, self._on_command, 10)
        self.fresh_command = False
        self.started = not self.lockstep
        self.wait_ticks = 0
        self.timeout_ticks = max(1, int(round(self.lockstep_timeout * rate)))
        self.resend_ticks = max(1, int(round(self.resend_period * rate)))
        self.steps = 0
        self.bad_commands = 0
        self.timer = self.create_timer(1.0 / rate, self._tick)
        self._publish_state()
        self.get_logger().info(f'simulating {model.name} ({model.n} joints) at {rate:g} Hz'
                               f"{', lockstep' if self.lockstep else ''}; commands on {self.command_topic}")

    def _on_command(self, msg):
        data = np.asarray(msg.data, dtype=float)
        if data.shape != (len(self.names),) or not np.all(np.isfinite(data)):
            self.bad_commands += 1
            self.get_logger().warn(f'dropping command: need {len(self.names)} finite values, got {list(msg.data)}',
                                   throttle_duration_sec=2.0)
            return
        self.sim.set_command(data)
        self.fresh_command = True

    def _tick(self):
        if self.max_steps and self.steps >= self.max_steps:
            return
        if not self.steps and not self._readers_ready():
            return  # discovery still under way
        if self.lockstep and not self.fresh_command:
            if not self.steps:  # _readers_ready counts the ticks and re-sends before the first step
                return
            # The answer to the last state has not come (yet): wait, re-sending the state in
            # case a best-effort reader lost it; before the first command, wait indefinitely.
            self.wait_ticks += 1
            if not self.started or self.wait_ticks < self.timeout_ticks:
                if self.wait_ticks % self.resend_ticks == 0:
                    self._publish_state()
                return
            self.get_logger().warn(f'no command within {self.lockstep_timeout} s: stepping with the held one',
                                   throttle_duration_sec=2.0)
        self.started = True
        self.wait_ticks = 0
        self.fresh_command = False
        self.sim.step()
        self.steps += 1
        self._publish_state()

    def _readers_ready(self):
        """Before the first step: enough joint_states readers matched, and every reliable one
        has acknowledged the initial state (so it has matched us too: none misses the start)."""
        self.wait_ticks += 1
        if self.wait_ticks % self.resend_ticks == 0:
            self._publish_state()
        if self.state_pub.get_subscription_count() < self.min_subscribers:
            return False
        return self.state_pub.wait_for_all_acked(Duration(seconds=0))

    def _publish_state(self):
        msg = JointState()
        msg.header.stamp = Time(nanoseconds=int(round(self.sim.t * 1e9))).to_msg()
        msg.name = self.names
        msg.position = self.sim.q.tolist()
        msg.velocity = self.sim.qd.tolist()
        msg.effort = self.sim.applied.tolist()
        self.state_pub.publish(msg)


def main(args=None):
    return run(SimNode, 'sim_node', args, done=lambda n: bool(n.max_steps) and n.steps >= n.max_steps)


if __name__ == '__main__':
    sys.exit(main())
