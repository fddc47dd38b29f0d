"""ROS 2 node: a simulated arm standing in for a ros2_control robot with an effort controller.

    ros2 run lie_dynamics sim_node
    python -m lie_dynamics.sim.sim_node --ros-args -p rate:=1000.0

Publishes   robot_description (std_msgs/String, reliable, transient local, depth 1),
            joint_states (sensor_msgs/JointState: position, velocity, effort = the motor torque
            acting at that state, i.e. the clipped held command, as a drive reports it, plus the
            sensor's offset and noise if set; header.stamp = simulated time),
            ~/external_torques_true (sensor_msgs/JointState, effort = J^T F of the external wrench,
            while external.duration > 0: the ground truth of external-torque estimates)
Subscribes  <command_topic> (std_msgs/Float64MultiArray, ordered as `joints`), held until the
            next one like JointGroupEffortController; a message of the wrong length or with a
            non-finite value is dropped with a log line (recent controllers drop them too).

payload.*: a load the simulated arm carries that its robot_description does not show (what
~/identify_payload of the dynamics node has to find). calibration_file: the simulated arm is the
robot that file describes (its link inertias, armature, friction and effort offsets), not the
URDF it publishes (what a calibration of the dynamics node has to find).

The effort reported with a state is the torque acting at that state's instant: a step from a
state applies the torque reported with it, and a command that arrives answering a state acts
from the next state on (where it is reported), as on a drive that holds its command until the
next one. Only the first command, releasing the held initial state, acts at once.

Parameters: see PARAMETERS below, or `python -m lie_dynamics.sim.sim_node --help`. By default
(hold_until_command) the simulator holds the initial state until the first command arrives, so
a controller started after it (or still loading its model) finds the arm where it started, not
fallen. Free-running (lockstep false, the default) it then steps at `rate`. With lockstep it
steps as soon as the command answering each published state has arrived (not on a timer: as
fast as the round trip allows), re-sending the state every `resend_period` s and stepping
anyway after `lockstep_timeout` s: results then do not depend on machine load. With
`lockstep_stamped_topic` it also waits for the message on that topic stamped with the state's
time (the demo's desired state for the next step), so the controller has it before the next
state: the loop is then as deterministic as the timer-paced one, only faster.
"""
import math
import sys
import time

import numpy as np
from rclpy.duration import Duration
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray, String
from trajectory_msgs.msg import JointTrajectory

from .. import default_urdf_path
from ..ros.run import node_parser, run
from ..ros.core.cdr import stamp_parts
from ..ros.core.settings import Values
from ..calibration import load_calibration, with_calibration
from ..laws import COULOMB_VELOCITY_EPSILON
from .arm import ArmSim, EffortSensor
from ..model.joint_names import broadcast_joints
from ..model.urdf import load_urdf

DESCRIPTION_QOS = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL)

# (name, default, meaning): declared in this order; --help lists them.
PARAMETERS = (
    ('urdf_path', '', 'URDF file (empty: the bundled 7-DoF arm)'),
    ('joints', [''], "simulated joints, the order of commands (['']: every movable joint)"),
    ('rate', 1000.0, 'simulation rate, Hz, > 0'),
    ('initial_positions', [0.0], 'start pose, rad (m): one value for every joint, or one per joint'),
    ('damping', True, 'apply the URDF joint damping'),
    ('command_topic', 'effort_controller/commands',
     'std_msgs/Float64MultiArray effort commands (relative: in the node\'s namespace)'),
    ('lockstep', False, 'step only once the command answering the last state has arrived'),
    ('hold_until_command', True,
     'hold the initial state (re-sent every resend_period s) until the first command arrives, like a robot '
     'on its brakes; false: free-running starts at once and an arm nobody commands falls'),
    ('lockstep_timeout', 0.05, 'lockstep: step with the held command after this many s, > 0'),
    ('resend_period', 0.01, 'lockstep, or holding: re-send an unanswered state every this many s, > 0'),
    ('min_subscribers', 0, 'do not start before this many joint_states readers match, >= 0'),
    ('max_steps', 0, 'exit after this many steps, >= 0 (0: run until shut down)'),
    ('external.link', '', 'link an external wrench acts on (empty: none)'),
    ('external.wrench', [0.0, 0.0, 0.0, 0.0, 0.0, 0.0], 'external wrench (m, f) in the link frame, N m and N'),
    ('external.start', 0.0, 'simulated time the external wrench starts, s'),
    ('external.duration', 0.0, 'how long it acts, s (0: never)'),
    ('lockstep_stamped_topic', '',
     'lockstep: also wait for a trajectory_msgs/JointTrajectory stamped with the last state (empty: none)'),
    # a load the simulated arm carries but its published robot_description does not show
    ('payload.link', '', 'link carrying a payload unknown to the controller (empty: none)'),
    ('payload.mass', 0.0, 'its mass, kg, >= 0'),
    ('payload.com', [0.0, 0.0, 0.0], 'its centre of mass in the link frame, m'),
    ('payload.inertia', [0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
     'its inertia about the CoM in link axes: ixx ixy ixz iyy iyz izz (zeros: a point mass)'),
    # a plant that differs from the published description (calibration, docs/node.md)
    ('calibration_file', '',
     "calibration.yaml (load_calibration's format) the simulated arm follows: link inertias, armature, "
     "viscous and Coulomb friction, effort offsets (empty: the URDF's arm)"),
    ('coulomb_friction', False,
     "simulate the model's Coulomb friction fc tanh(qd / eps) (the URDF's <dynamics friction>, or the "
     "calibration's, with its eps)"),
    ('effort_offset', [0.0], 'added to the reported effort, N m (N): one value or one per joint '
                             "(on top of the calibration's offsets)"),
    ('effort_noise', [0.0], 'std of Gaussian noise on the reported effort, N m (N), >= 0: one value or one per joint'),
    ('noise_seed', 0, 'seed of the effort noise (fixed: runs repeat)'),
)
EXAMPLE = """
ros2 run lie_dynamics sim_node --ros-args -p rate:=500.0 -p "initial_positions:=[0.0,-0.6,0.0,2.0,0.0,1.6,0.8]"
python -m lie_dynamics.sim.sim_node --ros-args -p lockstep:=true -p max_steps:=5000
"""


def plant_offsets(model, cal):
    """(n,) effort offsets of calibration `cal` on the model's joints (0 where it has none)."""
    out = np.zeros(model.n)
    for j, name in enumerate(cal.joint_names):
        if np.isfinite(cal.offset[j]):
            out[model.joint_names.index(name)] = cal.offset[j]
    return out


class SimNode(Node):
    def __init__(self, **kwargs):
        super().__init__('sim_node', **kwargs)
        v = Values({name: self.declare_parameter(name, default).value for name, default, _ in PARAMETERS})
        urdf_path = v.urdf_path or default_urdf_path()
        joints = list(v.joints or [])  # an empty override ([]) comes as None
        rate = float(v.rate)
        q0 = list(v.initial_positions or [])
        damping = bool(v.damping)
        self.command_topic = v.command_topic
        self.lockstep = bool(v.lockstep)
        self.hold = bool(v.hold_until_command)
        self.lockstep_timeout = float(v.lockstep_timeout)
        self.resend_period = float(v.resend_period)
        self.max_steps = int(v.max_steps)
        self.min_subscribers = int(v.min_subscribers)
        # refuse at start-up what would only fail (or misbehave silently) once running
        if not (math.isfinite(rate) and rate > 0):
            raise ValueError(f'rate must be positive, got {rate}')
        for name in ('lockstep_timeout', 'resend_period'):
            if not (math.isfinite(v[name]) and v[name] > 0):
                raise ValueError(f'{name} must be positive, got {v[name]}')
        for name in ('max_steps', 'min_subscribers'):
            if v[name] < 0:
                raise ValueError(f'{name} must be >= 0, got {v[name]}')
        if not self.command_topic.strip():
            raise ValueError('command_topic must not be empty')
        if not all(math.isfinite(x) for x in q0):
            raise ValueError(f'initial_positions must be finite, got {q0}')
        try:
            with open(urdf_path, encoding='utf-8') as fh:
                self.xml = fh.read()
        except OSError as exc:
            raise ValueError(f'urdf_path {urdf_path!r}: {exc.strerror or exc}') from None
        model = load_urdf(self.xml, joints=[j for j in joints if j] or None)
        q = broadcast_joints(q0, model.n)
        if q is None:
            raise ValueError(f'initial_positions needs {model.n} values, got {len(q0)} (or one for every joint)')
        q0 = q
        offset, eps = np.zeros(model.n), COULOMB_VELOCITY_EPSILON
        if v.calibration_file:  # simulated, never published
            try:
                cal = load_calibration(v.calibration_file)
                model = with_calibration(model, cal)
            except (OSError, ValueError) as exc:
                raise ValueError(f'calibration_file {v.calibration_file!r}: {getattr(exc, "strerror", None) or exc}') \
                    from None
            offset = plant_offsets(model, cal)
            eps = cal.eps
        if v.payload.link or v.payload.mass:  # simulated, never published: the controller must find it
            model.set_payload(v.payload.link, v.payload.mass, list(v.payload.com), list(v.payload.inertia))
        sensor = [broadcast_joints(list(v[k] or []), model.n) for k in ('effort_offset', 'effort_noise')]
        if any(x is None for x in sensor):
            raise ValueError(f'effort_offset and effort_noise need one value or {model.n}')
        self.sensor = EffortSensor(model.n, offset + sensor[0], sensor[1], v.noise_seed)
        self.sim = ArmSim(model, dt=1.0 / rate, q0=q0, damping=damping,
                          coulomb=model.friction if v.coulomb_friction else None, eps=eps)
        self.pending = None   # a command that acts from the next state on
        self.effort = self.sensor.read(self.sim.held_torque)  # reported with the current state
        self.names = model.joint_names
        self.truth_pub = None
        if v.external.link and v.external.duration > 0:
            self.sim.set_external(v.external.link, list(v.external.wrench), v.external.start,
                                  v.external.duration)
            self.truth_pub = self.create_publisher(JointState, '~/external_torques_true', 1000)
        self.desc_pub = self.create_publisher(String, 'robot_description', DESCRIPTION_QOS)
        self.desc_pub.publish(String(data=self.xml))
        # Deep history: a reliable reader whose acknowledgements lag (a busy recorder) must not lose
        # states while the lockstep loop with a fast controller runs ahead of it.
        self.state_pub = self.create_publisher(JointState, 'joint_states', 1000)
        self.command_topic = self.create_subscription(Float64MultiArray, self.command_topic, self._on_command,
                                                      10).topic_name  # resolved: /<ns>/...
        self.stamped_topic = v.lockstep_stamped_topic.strip()
        self.stamped = not (self.lockstep and self.stamped_topic)  # the stamped message of this state came
        if not self.stamped:
            self.create_subscription(JointTrajectory, self.stamped_topic, self._on_stamped, 10)
        self.fresh_command = False
        self.readers_ok = False  # every joint_states reader matched and acknowledged the first state
        self.started = not (self.lockstep or self.hold)  # the first step was taken (or may be)
        self.wait_ticks = 0
        # Free-running, the timer steps the simulation at `rate`. In lockstep the answers step it
        # (_ready_to_step) and the timer only re-sends and times out, so it ticks more slowly.
        tick = min(self.resend_period, self.lockstep_timeout) / 2.0 if self.lockstep else 1.0 / rate
        self.timeout_ticks = max(1, int(round(self.lockstep_timeout / tick)))
        self.resend_ticks = max(1, int(round(self.resend_period / tick)))
        self.steps = 0
        self.bad_commands = 0
        self.timer = self.create_timer(tick, self._tick)
        self._publish_state()
        self.get_logger().info(f'simulating {model.name} ({model.n} joints) at {rate:g} Hz'
                               f"{', lockstep' if self.lockstep else ''}; commands on {self.command_topic}"
                               + ('' if self.started else '; holding the initial state until the first command'))

    def _on_command(self, msg):
        data = np.asarray(msg.data, dtype=float)
        if data.shape != (len(self.names),) or not np.all(np.isfinite(data)):
            self.bad_commands += 1
            self.get_logger().warn(f'dropping command: need {len(self.names)} finite values, got {list(msg.data)}',
                                   throttle_duration_sec=2.0)
            return
        if self.steps:
            self.pending = data
        else:  # releasing the held initial state (or the first step): it acts at once
            self.sim.set_command(data)
        self.fresh_command = True
        if not self.lockstep:
            self.started = True  # hold_until_command: released; the timer steps from now on
        self._ready_to_step()

    def _on_stamped(self, msg):
        if (msg.header.stamp.sec, msg.header.stamp.nanosec) == self._stamp():
            self.stamped = True
            self._ready_to_step()

    def _ready_to_step(self):
        """Lockstep: step at once when the answers to the last state are all in."""
        if (self.lockstep and self.fresh_command and self.stamped and self.readers_ok
                and not (self.max_steps and self.steps >= self.max_steps)):
            self._advance()

    def _advance(self):
        self.started = True
        self.wait_ticks = 0
        self.fresh_command = False
        self.stamped = not (self.lockstep and self.stamped_topic)
        self.sim.step()   # with the torque reported with the state it leaves
        if self.pending is not None:
            self.sim.set_command(self.pending)
            self.pending = None
        self.effort = self.sensor.read(self.sim.held_torque)
        self.steps += 1
        self._publish_state()

    def _tick(self):
        if self.max_steps and self.steps >= self.max_steps:
            return
        if not self.readers_ok:
            self.readers_ok = self._readers_ready()
            self._ready_to_step()
            return  # discovery still under way
        if not self.lockstep:
            if self.started:
                self._advance()
            else:  # hold_until_command: no command yet, keep the state visible to late readers
                self.wait_ticks += 1
                if self.wait_ticks % self.resend_ticks == 0:
                    self._publish_state()
            return
        if not (self.fresh_command and self.stamped):
            # The answers to the last state have not all come (yet): wait, re-sending the state
            # in case a best-effort reader lost it; before the first step, wait indefinitely.
            self.wait_ticks += 1
            if not self.started or self.wait_ticks < self.timeout_ticks:
                if self.wait_ticks % self.resend_ticks == 0:
                    self._publish_state()
                return
            self.get_logger().warn(f'no answer within {self.lockstep_timeout} s: stepping with the held command',
                                   throttle_duration_sec=2.0)
        self._advance()

    def _readers_ready(self):
        """Before the first step: enough joint_states readers matched, and every reliable one
        has acknowledged the initial state (so it has matched us too: none misses the start).
        Checked before re-sending: a state sent just now cannot have been acknowledged yet."""
        if (self.state_pub.get_subscription_count() >= self.min_subscribers
                and self.state_pub.wait_for_all_acked(Duration(seconds=0))):
            return True
        self.wait_ticks += 1
        if self.wait_ticks % self.resend_ticks == 0:
            self._publish_state()
        return False

    def _stamp(self):
        return stamp_parts(int(round(self.sim.t * 1e9)))

    def _publish_state(self):
        msg = JointState()
        msg.header.stamp.sec, msg.header.stamp.nanosec = self._stamp()
        msg.name = self.names
        msg.position = self.sim.q.tolist()
        msg.velocity = self.sim.qd.tolist()
        msg.effort = self.effort.tolist()
        self.state_pub.publish(msg)
        if self.truth_pub is not None:
            truth = JointState()
            truth.header.stamp = msg.header.stamp
            truth.name = self.names
            truth.effort = self.sim.external_torque.tolist()
            self.truth_pub.publish(truth)


# How long a run that ended by itself (max_steps) waits, at most, for its last states to be acknowledged
DELIVER_TIMEOUT_S = 5.0


def _deliver(node, timeout_s=DELIVER_TIMEOUT_S):
    """Before the process ends: its last states reach their readers. A reliable sample not yet
    acknowledged goes with the writer (a busy reader may lag by hundreds of states). Only when the
    run ended by itself (max_steps): a signal stops at once. timeout_s bounds the whole wait."""
    if not (node.max_steps and node.steps >= node.max_steps):
        return
    end = time.monotonic() + timeout_s
    for pub in (node.state_pub, node.truth_pub):
        if pub is not None:
            try:
                pub.wait_for_all_acked(Duration(seconds=max(0.0, end - time.monotonic())))
            except Exception:  # best effort: the process is exiting
                pass


def main(args=None):
    """Run the simulator until shut down (or max_steps); 2 on bad arguments or parameters."""
    parser = node_parser('sim_node', __doc__.split('\nParameters:')[0], PARAMETERS, EXAMPLE)
    return run(SimNode, 'sim_node', args, done=lambda n: bool(n.max_steps) and n.steps >= n.max_steps,
               on_stop=_deliver, parser=parser)


if __name__ == '__main__':
    sys.exit(main())
