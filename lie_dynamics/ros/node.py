"""ROS 2 node: gravity compensation / torque feedforward from joint_states to ros2_control effort
commands, and feedforward efforts for joint_trajectory_controller trajectories.

    ros2 run lie_dynamics dynamics_node --ros-args --params-file config/arm7_gravity.yaml
    python -m lie_dynamics.dynamics_node --ros-args -p urdf_path:=config/arm7.urdf

A thin shell around `compensator.Compensator` (all decisions live there and in its pieces,
messages.py, watchdog.py, diagnostics.py and lie_dynamics.laws: testable without ROS).

Subscribes  robot_description (std_msgs/String, reliable, transient local, depth 1)
            joint_states      (sensor_msgs/JointState, best effort, depth 10 - as robot_state_publisher)
            <desired_topic>   (trajectory_msgs/JointTrajectory, one point; best effort, depth 1: only the
                              latest set-point matters; compatible with reliable publishers), default ~/desired
            ~/trajectory_in   (trajectory_msgs/JointTrajectory from a planner; reliable, depth 10)
Publishes   <command_topic>   (std_msgs/Float64MultiArray, `joints` order), one per valid joint_states
            ~/trajectory_out  (trajectory_msgs/JointTrajectory: ~/trajectory_in with `effort` filled;
                              remap it to the controller, e.g.
                              -r ~/trajectory_out:=/joint_trajectory_controller/joint_trajectory)
            ~/commanded_efforts (sensor_msgs/JointState, if publish_joint_state; input stamp)
            /diagnostics      (diagnostic_msgs/DiagnosticArray, every diagnostics_period)
Services    ~/set_enabled (std_srvs/SetBool), ~/reload_model (std_srvs/Trigger)

Behaviour (the effort controller holds the last command forever and does not clamp):
* Model source: at start-up the robot_description parameter, else urdf_path (`package://` URIs
  resolve through the ament index); every message on the robot_description topic then replaces
  the model, as does setting either parameter. A description that fails to load (or does not
  contain the controlled joints) is rejected: the previous model keeps running. The command
  layout (`joints`, or the first model's joints when empty) never changes at run time.
  ~/reload_model re-reads the current source (last topic message, parameter, or the file;
  before any model loaded: the last topic message, else the start-up parameters).
* Inertia: `inertia_policy` (warn, strict, repair; live) is load_urdf's policy for physically
  inconsistent link inertias. warn/repair: one log line per offending link and load (at most
  20, then a count), and a WARN in the diagnostics; strict: the description is rejected like
  any bad one. Setting it reloads the current source; if that fails while a model runs, the
  change is rejected and model and policy stay as they were.
* No model yet: nothing is published (said once in the log). No valid joint_states yet:
  nothing is published.
* Invalid joint_states (array lengths, duplicate names, non-finite positions of used joints,
  missing controlled joints): nothing published for it, one throttled log line per problem.
  NaN/inf or absent velocities are used as 0 in the velocity-dependent terms.
* Stale input (no valid joint_states for stale_timeout): stale_action is published once -
  gravity at the last valid state without velocity terms, or zeros; recovery is automatic.
* Disabling (parameter or ~/set_enabled) publishes one all-zero command, then nothing, so
  another publisher may take over the controller; enabling resumes with the next message.
* Shutdown (SIGINT/SIGTERM) publishes the stale_action command once.
* Torque law: parameter `mode` (gravity, feedforward, computed_torque, pd; live), see lie_dynamics.laws.
  The modes other than gravity use the last valid desired state; without one younger than
  desired_timeout they fall back to the gravity law at the measured state (one log line,
  diagnostics), and resume with the next valid desired state. Commands are still computed
  and published per joint_states message; a desired message only updates the set-point.
* Desired messages: exactly one point (a whole trajectory belongs on ~/trajectory_in);
  positions for every name; velocities / accelerations one per name or empty (= zeros);
  point effort and time_from_start, and the header, are ignored. Names are mapped; names
  that are not controlled joints (including locked ones) are ignored; every controlled joint
  must be present with finite values. A rejected message (one throttled log line per
  problem) leaves the last valid desired state in place, including its age.
* Trajectories: the message is republished unchanged except that every point's `effort` is
  set (one value per joint name, in the message's order): inverse dynamics at the point plus
  friction compensation at its velocity, clamped to the effort limits; 0 for names that are
  not controlled joints. Missing velocities / accelerations are derived from positions /
  velocities and time_from_start (trajectory.py). Malformed trajectories (no points, ragged
  arrays, times not strictly increasing, duplicate names, missing controlled joints,
  non-finite values) are rejected with one log line and nothing is published; so are
  trajectories arriving without a model or while disabled.
* Invalid parameters at start-up: the process exits with status 2 and says why; invalid
  live updates are rejected with the reason.
"""
import array
import sys
import threading
import time

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rcl_interfaces.msg import FloatingPointRange, ParameterDescriptor, SetParametersResult
from rclpy.duration import Duration
from rclpy.event_handler import PublisherEventCallbacks, SubscriptionEventCallbacks
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray, String
from std_srvs.srv import SetBool, Trigger
from trajectory_msgs.msg import JointTrajectory

from .compensator import Compensator, Throttle
from .params import PARAMS, SPECS, check_value
from .run import run
from .sources import Sources, open_source, source_label
from .trajectory_msgs import set_point_efforts

# As robot_state_publisher publishes it: a late subscriber must also be transient local.
DESCRIPTION_QOS = QoSProfile(depth=1, history=HistoryPolicy.KEEP_LAST, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL)
JOINT_STATES_QOS = QoSProfile(depth=10, history=HistoryPolicy.KEEP_LAST,
                              reliability=ReliabilityPolicy.BEST_EFFORT, durability=DurabilityPolicy.VOLATILE)
DESIRED_QOS = QoSProfile(depth=1, history=HistoryPolicy.KEEP_LAST,
                         reliability=ReliabilityPolicy.BEST_EFFORT, durability=DurabilityPolicy.VOLATILE)
# No default QoS-event handlers (see the hot-path note in DynamicsNode.__init__); also used by bench/.
NO_PUB_EVENTS = PublisherEventCallbacks(use_default_callbacks=False)
NO_SUB_EVENTS = SubscriptionEventCallbacks(use_default_callbacks=False)
_TYPES = {'bool': Parameter.Type.BOOL, 'double': Parameter.Type.DOUBLE, 'string': Parameter.Type.STRING,
          'double_array': Parameter.Type.DOUBLE_ARRAY, 'string_array': Parameter.Type.STRING_ARRAY}
LOG_THROTTLE_S = 2.0


def _guarded(callback):
    """The node never dies on input: an unexpected exception in a callback is logged, not raised."""
    def wrapper(self, *args):
        try:
            return callback(self, *args)
        except Exception as exc:  # noqa: BLE001 - last line of defence
            self.core.last_error = f'{callback.__name__}: {type(exc).__name__}: {exc}'
            self.get_logger().error(f'internal error in {callback.__name__}: {type(exc).__name__}: {exc}',
                                    throttle_duration_sec=LOG_THROTTLE_S)
            return args[-1] if callback.__name__.startswith('_srv') else None
    wrapper.__name__ = callback.__name__
    return wrapper


def _tick_period(stale_timeout, diagnostics_period):
    """One timer serves the watchdog and diagnostics: stale input is detected between
    stale_timeout and 1.5 x stale_timeout. (Each rclpy wake-up costs CPU on the hot path.)"""
    return max(min(stale_timeout / 2.0, diagnostics_period), 0.002)


class DynamicsNode(Node):
    """Dynamics node. Extra keyword arguments go to rclpy's Node (context, overrides)."""

    def __init__(self, node_name='dynamics_node', **kwargs):
        super().__init__(node_name, **kwargs)
        values = {}
        for spec in PARAMS:
            desc = ParameterDescriptor(description=spec.description, read_only=not spec.live,
                                       additional_constraints=spec.constraints)
            if spec.range is not None:
                desc.floating_point_range = [FloatingPointRange(from_value=spec.range[0], to_value=spec.range[1],
                                                                step=0.0)]
            default = _TYPES[spec.kind] if spec.default is None else spec.default
            values[spec.name] = self.declare_parameter(spec.name, default, desc).value
        self.core = Compensator(values)  # ValueError on an invalid configuration
        self._throttle = Throttle(LOG_THROTTLE_S)
        self._lock = threading.RLock()  # services/parameters vs. callbacks when spun by several threads
        self._sources = Sources()      # the running model's source, the last topic message
        self._pending = None           # (changes, plan, source): validated by on_set, applied by post_set
        self._out_names = []

        # Hot path: no default QoS-event handlers (each one is waited on at every executor
        # wake-up). joint_states is best effort, like robot_state_publisher's subscription:
        # compatible with any publisher; a lost sample only skips one command update.
        self._cmd_pub = self.create_publisher(Float64MultiArray, values['command_topic'], 10,
                                              event_callbacks=NO_PUB_EVENTS)
        self._js_pub = None
        self._diag_pub = self.create_publisher(DiagnosticArray, '/diagnostics', 10, event_callbacks=NO_PUB_EVENTS)
        # No QoS-event handlers here either; _check_description_publishers() reports the usual
        # mistake (a volatile or best-effort robot_description publisher) from the timer instead.
        self.create_subscription(String, 'robot_description', self._on_description, DESCRIPTION_QOS,
                                 event_callbacks=NO_SUB_EVENTS)
        self._warned_publishers = set()
        self.create_subscription(JointState, 'joint_states', self._on_joint_state, JOINT_STATES_QOS,
                                 event_callbacks=NO_SUB_EVENTS)
        desired = self.create_subscription(JointTrajectory, values['desired_topic'], self._on_desired,
                                           DESIRED_QOS, event_callbacks=NO_SUB_EVENTS)
        self.core.desired_topic = desired.topic_name
        self.create_subscription(JointTrajectory, '~/trajectory_in', self._on_trajectory, 10,
                                 event_callbacks=NO_SUB_EVENTS)
        self._traj_pub = self.create_publisher(JointTrajectory, '~/trajectory_out', 10,
                                               event_callbacks=NO_PUB_EVENTS)
        self.create_service(SetBool, '~/set_enabled', self._srv_set_enabled)
        self.create_service(Trigger, '~/reload_model', self._srv_reload)
        self._diag_period = values['diagnostics_period']
        self._next_diag = time.monotonic() + self._diag_period
        self._timer = self.create_timer(_tick_period(values['stale_timeout'], self._diag_period), self._on_timer)
        self._set_js_publisher(values['publish_joint_state'])
        self.add_on_set_parameters_callback(self._validate_parameters)
        self.add_post_set_parameters_callback(self._apply_parameters)

        for kind, name in (('parameter', 'robot_description'), ('file', 'urdf_path')):
            text = values[name]
            if text and self._load(kind, text) is None:
                break
        self._drain_events()
        if self.core.model is None:
            self.get_logger().info(
                f"no robot model yet: waiting for '{self.resolve_topic_name('robot_description')}' "
                '(publishing nothing until a model is loaded)')

    # ------------------------------------------------------------------ model
    def _candidate(self, kind, text, inertia=None):
        """A description's model, checked against the layout and the current settings but not
        made current (`inertia`: policy other than the current inertia_policy) -> (model, label).
        Raises ValueError with the reason, which is also logged and kept for the diagnostics."""
        label = source_label(kind, text)
        try:
            source, label = open_source(kind, text)
            model = self.core.build_model(source, inertia)
            self.core.plan(None, model, label)
        except Exception as exc:  # any bad input: log, keep the previous model, never die
            raise ValueError(self.core.note_description_error(f'{label}: {exc}')) from None
        return model, label

    def _load(self, kind, text, inertia=None):
        """Load a description now (start-up, topic, ~/reload_model); on failure keep the current
        model. Returns None or the error text."""
        try:
            model, label = self._candidate(kind, text, inertia)
        except ValueError as exc:
            return str(exc)
        self.core.set_model(model, label)  # fits: checked by _candidate
        self._sources.current = (kind, text)
        self._out_names = list(self.core.layout)
        return None

    @_guarded
    def _on_description(self, msg):
        with self._lock:
            self._sources.topic_xml = msg.data
            self._load('topic', msg.data)
            self._drain_events()

    # ------------------------------------------------------------------ hot path
    @_guarded
    def _on_joint_state(self, msg):
        t0 = time.perf_counter()
        with self._lock:
            core = self.core
            tau = core.on_joint_state(msg.name, msg.position, msg.velocity, msg.effort)
            if tau is not None:
                self._publish(tau, msg.header.stamp)
            if core.events:
                self._drain_events()
            core.record_compute_time(time.perf_counter() - t0)

    @_guarded
    def _on_desired(self, msg):
        with self._lock:
            self.core.on_desired(msg.joint_names, msg.points)
            if self.core.events:
                self._drain_events()

    @_guarded
    def _on_trajectory(self, msg):
        with self._lock:
            efforts = self.core.on_trajectory(msg.joint_names, msg.points)
            self._drain_events()
        if efforts is not None:
            set_point_efforts(msg.points, efforts)
            self._traj_pub.publish(msg)

    def _publish(self, tau, stamp=None):
        data = array.array('d', tau.tobytes())
        out = Float64MultiArray()
        out.data = data
        self._cmd_pub.publish(out)
        if self._js_pub is not None:
            js = JointState()
            if stamp is not None:
                js.header.stamp = stamp
            else:
                js.header.stamp = self.get_clock().now().to_msg()
            js.name = self._out_names
            js.effort = data
            self._js_pub.publish(js)

    def _publish_optional(self, cmd):
        if cmd is not None:
            self._publish(cmd)

    def _drain_events(self):
        events, self.core.events = self.core.events, []
        log = self.get_logger()
        for severity, key, text in events:
            if key is not None and not self._throttle.ready(key):
                continue
            # one call site per severity: rclpy's logger refuses to change it per call site
            if severity == 'info':
                log.info(text)
            elif severity == 'warn':
                log.warning(text)
            else:
                log.error(text)

    # ------------------------------------------------------------------ timers
    @_guarded
    def _on_timer(self):
        with self._lock:
            self._publish_optional(self.core.tick())
            if self.core.events:
                self._drain_events()
        now = time.monotonic()
        if now >= self._next_diag:
            self._next_diag = max(self._next_diag + self._diag_period, now)
            self._publish_diagnostics()
            if self._sources.topic_xml is None:
                self._check_description_publishers()

    def _check_description_publishers(self):
        topic = self.resolve_topic_name('robot_description')
        for info in self.get_publishers_info_by_topic(topic):
            qos = info.qos_profile
            bad = [p for p, ok in (('volatile durability', qos.durability == DurabilityPolicy.TRANSIENT_LOCAL),
                                   ('best-effort reliability', qos.reliability == ReliabilityPolicy.RELIABLE))
                   if not ok]
            who = f'{info.node_namespace.rstrip("/")}/{info.node_name}'
            if bad and who not in self._warned_publishers:
                self._warned_publishers.add(who)
                self.get_logger().warning(
                    f"'{topic}' publisher {who} offers {' and '.join(bad)}: this node (like robot_state_publisher's "
                    'subscribers) needs reliable + transient local, so it will not receive that description')

    def _publish_diagnostics(self):
        with self._lock:
            level, message, values = self.core.diagnostics()
            m = self.core.model
        st = DiagnosticStatus(level=bytes([level]), name=f'{self.get_name()}: gravity compensation',
                              message=message, hardware_id=m.name if m is not None else '')
        st.values = [KeyValue(key=k, value=v) for k, v in values]
        arr = DiagnosticArray(status=[st])
        arr.header.stamp = self.get_clock().now().to_msg()
        self._diag_pub.publish(arr)

    # ------------------------------------------------------------------ parameters and services
    def _set_js_publisher(self, on):
        if on and self._js_pub is None:
            self._js_pub = self.create_publisher(JointState, '~/commanded_efforts', 10,
                                                 event_callbacks=NO_PUB_EVENTS)
        elif not on and self._js_pub is not None:
            self.destroy_publisher(self._js_pub)
            self._js_pub = None

    # rclpy calls the on_set callback (_validate_parameters) with the whole change; only when it
    # accepts are the values set, and then the post_set callback (_apply_parameters) runs.
    # What stays in validation, and why: building the model of a new description (parsing the
    # URDF under the inertia policy, checking the layout) and trying a payload, because only
    # trying them tells whether they are valid; a change that fails there is rejected as a whole.
    # Nothing becomes current there: the new model stays private to the plan and the payload is
    # tried on a scratch copy of the running model (Compensator.plan); only a refused description
    # is reported (log line, description_error), as the rejection's reason.
    # What happens after the set (post_set): making the plan current (model, settings), the one
    # zero command on disable, the timer period, and creating/destroying ~/commanded_efforts.
    def _validate_parameters(self, params):
        changes = {p.name: p.value for p in params if p.name in SPECS}
        with self._lock:
            self._pending = None
            if not changes:
                return SetParametersResult(successful=True)
            try:
                self._pending = (changes,) + self._plan_parameters(changes)
            except ValueError as exc:
                self._drain_events()
                return SetParametersResult(successful=False, reason=str(exc))
        return SetParametersResult(successful=True)

    def _plan_parameters(self, changes):
        """(plan, source) for a parameter change; source (kind, text) of a new model or None.
        Raises ValueError with the reason."""
        rest = dict(changes)
        # a description set together with the policy is loaded under the new one
        policy = rest.get('inertia_policy')
        if policy is not None:
            policy = check_value('inertia_policy', policy)
        model = label = source = None
        for key, kind in (('robot_description', 'parameter'), ('urdf_path', 'file')):
            text = rest.pop(key, None)
            if text:
                model, label = self._candidate(kind, text, policy)
                source = (kind, text)
        if policy not in (None, self.core.settings['inertia_policy']) and source is None:
            kind, text = self._current_source()
            if kind is not None:
                try:
                    model, label = self._candidate(kind, text, policy)
                    source = (kind, text)
                except ValueError:
                    # without a running model there is nothing to keep consistent: the failure
                    # is reported (log, diagnostics) and the policy applies to what comes next
                    if self.core.model is not None:
                        raise
        return self.core.plan(rest, model, label or ''), source

    def _apply_parameters(self, params):
        changes = {p.name: p.value for p in params if p.name in SPECS}
        if not changes:
            return
        with self._lock:
            pending, self._pending = self._pending, None
            try:
                if pending is None or pending[0] != changes:  # not the change validated last: check again
                    pending = (changes,) + self._plan_parameters(changes)
                _, plan, source = pending
                cmd = self.core.apply(plan)
            except ValueError as exc:  # only if the state moved between validation and now
                self.get_logger().error(f'parameter change {sorted(changes)} not applied: {exc}')
                self._drain_events()
                return
            if source is not None:
                self._sources.current = source
                self._out_names = list(self.core.layout)
            self._publish_optional(cmd)
            if 'stale_timeout' in changes:
                period = _tick_period(self.core.settings['stale_timeout'], self._diag_period)
                self._timer.timer_period_ns = int(period * 1e9)
            if 'publish_joint_state' in changes:
                self._set_js_publisher(self.core.settings['publish_joint_state'])
            self._drain_events()

    @_guarded
    def _srv_set_enabled(self, request, response):
        result = self.set_parameters([Parameter('enabled', Parameter.Type.BOOL, bool(request.data))])[0]
        response.success = result.successful
        response.message = ('enabled' if request.data else 'disabled') if result.successful else result.reason
        return response

    def _current_source(self):
        """(kind, text) to reload (Sources.reload_source), or (None, None)."""
        return self._sources.reload_source(self.get_parameter('robot_description').value,
                                           self.get_parameter('urdf_path').value)

    @_guarded
    def _srv_reload(self, request, response):
        with self._lock:
            kind, text = self._current_source()
            if kind is None:
                response.success, response.message = False, 'no robot description to reload'
                return response
            err = self._load(kind, text)
            self._drain_events()
        response.success = err is None
        m = self.core.model
        response.message = err if err is not None else f"reloaded '{m.name}' ({m.n} joints) from {self.core.model_info}"
        return response

    def shutdown_command(self):
        """Publish the stale_action command once (the effort controller holds the last command)."""
        with self._lock:
            cmd = self.core.final_command()
            self.core.events.clear()
            if cmd is None:
                return False
            self._publish(cmd)
        try:
            self._cmd_pub.wait_for_all_acked(Duration(seconds=0.5))
        except Exception:  # best effort: the process is exiting
            pass
        return True


def _last_command(node):
    if node.shutdown_command():
        node.get_logger().info('shutting down: published the stale_action command once')


def main(args=None):
    """Entry point of `ros2 run lie_dynamics dynamics_node`."""
    return run(DynamicsNode, 'dynamics_node', args, on_stop=_last_command)


if __name__ == '__main__':
    sys.exit(main())
