"""ROS 2 node: gravity compensation / torque feedforward from joint_states to ros2_control effort
commands, and feedforward efforts for joint_trajectory_controller trajectories.

    ros2 run lie_dynamics dynamics_node --ros-args --params-file config/arm7_gravity.yaml
    python -m lie_dynamics.dynamics_node --ros-args -p urdf_path:=config/arm7.urdf

A thin shell around `compensator.Compensator` (all decisions live there and in its pieces,
messages.py, watchdog.py, ramp.py, models.py, diagnostics.py and lie_dynamics.laws: testable
without ROS); heavy work runs off the control path (background.py). The behaviour, parameter
by parameter, is described in docs/node.md.

Subscribes  robot_description (std_msgs/String, reliable, transient local, depth 1)
            joint_states      (sensor_msgs/JointState, best effort, depth 1: only the newest
                              state matters, an old one queued behind it is never answered;
                              taken serialized, read by cdr.py: a malformed one is one log line)
            <desired_topic>   (trajectory_msgs/JointTrajectory, one point; best effort, depth 1),
                              default ~/desired; taken serialized, like joint_states
            ~/trajectory_in   (trajectory_msgs/JointTrajectory from a planner; reliable, depth 1:
                              only the newest matters; taken, filled and published by a process
                              of its own, trajectories/process.py)
Publishes   <command_topic>   (std_msgs/Float64MultiArray, `joints` order), one per valid joint_states;
                              default effort_controller/commands (relative)
            ~/trajectory_out  (~/trajectory_in with `effort` filled, reliable, depth 1; remap it to
                              the controller)
            ~/commanded_efforts (sensor_msgs/JointState, if publish_joint_state; input stamp)
            ~/external_torques, ~/collision: the momentum observer on the efforts (contact_topics.py)
            ~/dynamics/{gravity,coriolis,mass_matrix,jacobian}: the terms listed in dynamics.publish
                              (dynamics_topics.py, a per-sample feature: feature.py)
            /diagnostics      (diagnostic_msgs/DiagnosticArray, every diagnostics_period; global by
                              ROS convention, statuses named after the node's full name)
Names: every other topic and service is relative or private, so `-r __ns:=/robot1` moves the
node with all of them under /robot1 (several robots in one DDS domain).
Services    ~/set_enabled (std_srvs/SetBool), ~/reload_model (std_srvs/Trigger); reliable,
            keep-last SERVICE_QUEUE requests each (beyond that the oldest unanswered ones are
            dropped and their clients wait: call with a timeout)
            ~/set_payload, ~/identify_payload and <gravity_topic>: gravity_payload.py

Timing: the watchdog and diagnostics timer runs on the steady clock (with use_sim_time a
stopped /clock must not stop the safety timer); stamps of published messages are ROS time.
Logging: at most one line per problem class every LOG_THROTTLE_S seconds; what is held back is
counted in the class's next line, or by the timer once the period is over (or at shutdown);
every line at most LOG_TEXT_MAX characters.
"""
import array
import sys
import threading
import time

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rcl_interfaces.msg import (FloatingPointRange, IntegerRange, ParameterDescriptor,
                                SetParametersResult)
from rclpy.clock import Clock, ClockType
from rclpy.duration import Duration
from rclpy.event_handler import PublisherEventCallbacks, SubscriptionEventCallbacks
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray, String
from std_srvs.srv import SetBool, Trigger
from trajectory_msgs.msg import JointTrajectory

from .loading.background import Background
from .core.cdr import JointStateDecoder, read_desired, sample_of, stamp_parts
from .core.compensator import Compensator, Throttle
from .features.contact import check_settings
from .features.contact_topics import ContactTopics
from .features.dynamics_topics import DynamicsTopics
from .features.base import Features
from .features.gravity_payload import GravityPayload
from .core.diagnostics import DIAG_TEXT_MAX, LOG_TEXT_MAX, clip, held_text
from .core.params import HELP_DESCRIPTION, HELP_EXAMPLE, PARAMS, SPECS, check_value, help_rows
from .run import node_parser, run
from .loading.sources import Sources, source_label

# As robot_state_publisher publishes it: a late subscriber must also be transient local.
DESCRIPTION_QOS = QoSProfile(depth=1, history=HistoryPolicy.KEEP_LAST, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL)
JOINT_STATES_QOS = QoSProfile(depth=1, history=HistoryPolicy.KEEP_LAST,
                              reliability=ReliabilityPolicy.BEST_EFFORT, durability=DurabilityPolicy.VOLATILE)
DESIRED_QOS = QoSProfile(depth=1, history=HistoryPolicy.KEEP_LAST,
                         reliability=ReliabilityPolicy.BEST_EFFORT, durability=DurabilityPolicy.VOLATILE)
# Trajectories: reliable, one kept each way. Only the newest one matters (a newer one replaces a
# waiting fill anyway), and DDS keeps a kept sample's memory (a 100,000-point trajectory: 20 MB).
TRAJECTORY_QOS = QoSProfile(depth=1, history=HistoryPolicy.KEEP_LAST, reliability=ReliabilityPolicy.RELIABLE,
                            durability=DurabilityPolicy.VOLATILE)
# Requests kept per service: rclpy's default (10) dropped 975 of 1,000 concurrent calls, whose
# clients then waited forever. A kept request costs its message only (a SetBool or Trigger
# request is a few bytes), and each is answered in microseconds.
SERVICE_QUEUE = 1000
SERVICE_QOS = QoSProfile(depth=SERVICE_QUEUE, history=HistoryPolicy.KEEP_LAST,
                         reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.VOLATILE)
# No default QoS-event handlers (see the hot-path note in DynamicsNode.__init__); also used by bench/.
NO_PUB_EVENTS = PublisherEventCallbacks(use_default_callbacks=False)
NO_SUB_EVENTS = SubscriptionEventCallbacks(use_default_callbacks=False)
_TYPES = {'bool': Parameter.Type.BOOL, 'integer': Parameter.Type.INTEGER, 'double': Parameter.Type.DOUBLE,
          'string': Parameter.Type.STRING, 'double_array': Parameter.Type.DOUBLE_ARRAY,
          'string_array': Parameter.Type.STRING_ARRAY}
LOG_THROTTLE_S = 2.0
SOURCES = (('robot_description', 'parameter'), ('urdf_path', 'file'))


def _guarded(callback):
    """The node never dies on input: an unexpected exception in a callback is logged, not raised."""
    def wrapper(self, *args):
        try:
            return callback(self, *args)
        except Exception as exc:  # noqa: BLE001 - last line of defence
            text = clip(f'{callback.__name__}: {type(exc).__name__}: {exc}', DIAG_TEXT_MAX)
            self.core.last_error = text
            self.log_event('error', 'internal:' + callback.__name__, f'internal error in {text}')
            return args[-1] if callback.__name__.startswith('_srv') else None
    wrapper.__name__ = callback.__name__
    return wrapper


def _tick_period(stale_timeout, diagnostics_period):
    """One timer serves the watchdog, ramps without input and diagnostics: stale input is
    detected between stale_timeout and 1.5 x stale_timeout. (Each wake-up costs CPU.)"""
    return max(min(stale_timeout / 2.0, diagnostics_period), 0.002)


def _descriptor(spec):
    desc = ParameterDescriptor(description=spec.description, read_only=not spec.live,
                               additional_constraints=spec.constraints)
    if spec.range is not None and spec.kind == 'double':
        desc.floating_point_range = [FloatingPointRange(from_value=spec.range[0], to_value=spec.range[1], step=0.0)]
    elif spec.range is not None:
        desc.integer_range = [IntegerRange(from_value=int(spec.range[0]), to_value=int(spec.range[1]), step=0)]
    return desc


class DynamicsNode(Node):
    """Dynamics node. Extra keyword arguments go to rclpy's Node (context, overrides)."""

    def __init__(self, node_name='dynamics_node', **kwargs):
        super().__init__(node_name, **kwargs)
        self._bg = self._gp = None
        self._features = Features()
        try:
            self._construct()
        except BaseException:
            # refused at start-up: no worker thread may outlive the node, and the rcl node goes
            # too (a half-made node keeps its /rosout publisher, which rcl shares by logger name
            # with the next node of the same name in this process: that node's log would be lost)
            self.destroy_node()
            raise

    def _construct(self):
        values = {}
        for spec in PARAMS:
            default = _TYPES[spec.kind] if spec.default is None else spec.default
            values[spec.name] = self.declare_parameter(spec.name, default, _descriptor(spec)).value
        self.core = Compensator(values)  # ValueError on an invalid configuration
        self._throttle = Throttle(LOG_THROTTLE_S)
        self.lock = threading.RLock()  # services/parameters vs. callbacks when spun by several threads
        self._sources = Sources()      # the running model's source, the last topic message
        self._pending = None           # (changes, plan, load): validated by on_set, applied by post_set
        self._out_names = []
        # reused for every command (measured: -5 us per message, -12 us with publish_joint_state)
        self._cmd_msg = Float64MultiArray()
        self._js_msg = JointState()
        self._decoder = JointStateDecoder()   # keeps the last name list: decoded once per stream

        # Hot path: no default QoS-event handlers (each one is waited on at every executor
        # wake-up). joint_states is best effort, like robot_state_publisher's subscription:
        # compatible with any publisher; a lost sample only skips one command update.
        self._cmd_pub = self.create_publisher(Float64MultiArray, values['command_topic'], 10,
                                              event_callbacks=NO_PUB_EVENTS)
        self._js_pub = None
        self._diag_pub = self.create_publisher(DiagnosticArray, '/diagnostics', 10, event_callbacks=NO_PUB_EVENTS)
        # ~/trajectory_in and ~/trajectory_out: served by a process of their own (trajectories/process.py)
        self._bg = Background(self.core, self._sources, trajectories=dict(
            domain_id=self.context.get_domain_id(), name=f'{self.get_name()}_trajectories',
            namespace=self.get_namespace(), topic_in=self.resolve_topic_name('~/trajectory_in'),
            topic_out=self.resolve_topic_name('~/trajectory_out'),
            qos=dict(depth=TRAJECTORY_QOS.depth, history=TRAJECTORY_QOS.history,
                     reliability=TRAJECTORY_QOS.reliability, durability=TRAJECTORY_QOS.durability)))
        self._start(values)

    def _start(self, values):
        """The rest of the start-up, once worker threads exist (__init__ stops them if this raises)."""
        # No QoS-event handlers here either; _check_description_publishers() reports the usual
        # mistake (a volatile or best-effort robot_description publisher) from the timer instead.
        self.create_subscription(String, 'robot_description', self._on_description, DESCRIPTION_QOS,
                                 event_callbacks=NO_SUB_EVENTS)
        self._warned_publishers = set()
        # Raw: read by cdr.py; rclpy's deserializer would log every malformed message unthrottled.
        self.create_subscription(JointState, 'joint_states', self.on_joint_state, JOINT_STATES_QOS, raw=True,
                                 event_callbacks=NO_SUB_EVENTS)
        desired = self.create_subscription(JointTrajectory, values['desired_topic'], self._on_desired,
                                           DESIRED_QOS, raw=True, event_callbacks=NO_SUB_EVENTS)
        self.core.desired_topic = desired.topic_name
        self.create_service(SetBool, '~/set_enabled', self._srv_set_enabled, qos_profile=SERVICE_QOS)
        self.create_service(Trigger, '~/reload_model', self._srv_reload, qos_profile=SERVICE_QOS)
        self._gp = GravityPayload(self, values, SERVICE_QOS, NO_SUB_EVENTS)  # gravity topic, payload services
        self._diag_period = values['diagnostics_period']
        self._next_diag = time.monotonic() + self._diag_period
        self._timer = self.create_timer(_tick_period(values['stale_timeout'], self._diag_period), self._on_timer,
                                        clock=Clock(clock_type=ClockType.STEADY_TIME))
        self._set_js_publisher(values['publish_joint_state'])
        self._contact = ContactTopics(self, NO_PUB_EVENTS)  # external torques, collisions
        # per-sample features (feature.py): the node feeds each accepted sample to the active ones
        self._features = Features([DynamicsTopics(
            lambda msg_type, topic, depth: self.create_publisher(msg_type, topic, depth,
                                                                 event_callbacks=NO_PUB_EVENTS))])
        self.add_on_set_parameters_callback(self._validate_parameters)
        self.add_post_set_parameters_callback(self._apply_parameters)

        for name, kind in SOURCES:  # at start-up in this thread: nothing to keep answering yet
            if values[name]:
                # a start-up description that cannot load (a typo in a launch file) refuses to start (exit 2)
                err = self._bg.load_now(kind, values[name])
                if err is not None:
                    raise ValueError(err)
                break
        self._adopt_layout()
        check_settings(self.core.settings, len(self.core.layout) if self.core.layout else None)  # exit 2
        self._features.check(self.core.settings, self.core.model)  # exit 2
        self._features.sync(self.core)
        self._drain_events()
        if self.core.model is None:
            topic = self.resolve_topic_name('robot_description')
            self.log_event('info', None, f"no robot model yet: waiting for '{topic}' "
                           '(publishing nothing until a model is loaded)')

    def note_executor(self, kind):
        """The executor that spins the node (run.py), shown in the diagnostics."""
        self.core.executor = kind

    def _stop_workers(self):
        if self._bg is not None:
            self._bg.stop()  # before the publishers go: a fill in progress may still publish
        if self._gp is not None:
            self._gp.stop()

    def destroy_node(self):
        self._stop_workers()
        if self._bg is not None:   # lines still held back are said before the node goes
            self._log_held(float('inf'))
        return super().destroy_node()

    # ------------------------------------------------------------------ model
    def _adopt_layout(self):
        if self.core.layout is not None and self._out_names != self.core.layout:
            self._out_names = list(self.core.layout)

    def _collect(self):
        """Finished background work: a new model swaps in here, between two commands."""
        self._bg.collect()
        self._adopt_layout()

    @_guarded
    def _on_description(self, msg):
        with self.lock:
            self._sources.topic_xml = msg.data
            self._bg.request('topic', msg.data, skip_identical=True)
            self._drain_events()

    # ------------------------------------------------------------------ hot path
    @_guarded
    def on_joint_state(self, msg):
        """The joint_states callback: the serialized message (bytes, as the subscription delivers
        it) or a sensor_msgs/JointState (benchmarks drive it in-process with either)."""
        t0 = time.perf_counter()
        with self.lock:
            core = self.core
            try:
                sample = self._decoder.read(msg) if isinstance(msg, bytes) else sample_of(msg)
            except ValueError as exc:
                core.refuse_malformed('joint_states', str(exc))
                self._drain_events()
                return
            if self._bg.worker.has_outcomes:
                self._collect()
            self._gp.before_command(core)
            tau = core.on_sample(sample)
            if tau is not None:
                self._publish(tau, sample.stamp)
            self._contact.observe(core, sample, self._out_names)  # after the command: never delays it
            if self._gp.ident.recording is not None:  # ~/identify_payload records (after the command)
                self._gp.ident.add(core, sample.velocity, sample.effort, sample.stamp)
            features = self._features
            features.feed(core, sample, self._out_names)
            if core.events or self._contact.monitor.events or features.has_events:
                self._drain_events()
            core.record_compute_time(time.perf_counter() - t0)

    @_guarded
    def _on_desired(self, data):
        with self.lock:
            try:
                names, points = read_desired(data, one=True)
            except ValueError as exc:
                self.core.refuse_malformed('desired', str(exc))
            else:
                self.core.on_desired(names, points)
            if self.core.events:
                self._drain_events()

    def _publish(self, tau, stamp=None):  # stamp: the input's (ns); None: now
        data = array.array('d', tau.tobytes())
        out = self._cmd_msg
        out.data = data
        self._cmd_pub.publish(out)
        if self._js_pub is not None:
            js = self._js_msg
            if stamp is None:
                js.header.stamp = self.get_clock().now().to_msg()
            else:
                js.header.stamp.sec, js.header.stamp.nanosec = stamp_parts(stamp)
            if js.name is not self._out_names:  # the setter checks every name: only when the layout changes
                js.name = self._out_names
            js.effort = data
            self._js_pub.publish(js)

    def _publish_optional(self, cmd):
        if cmd is not None:
            self._publish(cmd)

    @property
    def contact_monitor(self):
        """The external-torque observer and collision flag (contact.ContactMonitor)."""
        return self._contact.monitor

    def log_event(self, severity, key, text):
        """One log line, at most one per `key` (the problem class) every LOG_THROTTLE_S s."""
        if key is not None:
            held = self._throttle.check(key, payload=(severity, text))
            if held is None:
                return
            text = held_text(text, held, LOG_THROTTLE_S)
        self._emit(severity, text)

    def _log_held(self, now=None):
        """Classes whose period ended with lines held back: their newest line, with how many more."""
        for (severity, text), more in self._throttle.due(now):
            self._emit(severity, held_text(text, more, LOG_THROTTLE_S))

    def _emit(self, severity, text):
        text = clip(text, LOG_TEXT_MAX)
        log = self.get_logger()
        # one call site per severity: rclpy's logger refuses to change it per call site
        if severity == 'info':
            log.info(text)
        elif severity == 'warn':
            log.warning(text)
        else:
            log.error(text)

    def _drain_events(self):
        events, self.core.events = self.core.events + self._contact.monitor.events, []
        self._contact.monitor.events = []
        if self._features.has_events:
            events += self._features.drain()
        for severity, key, text in events:
            self.log_event(severity, key, text)

    # ------------------------------------------------------------------ timers
    @_guarded
    def _on_timer(self):
        with self.lock:
            self._collect()
            self._gp.before_command(self.core)
            self._publish_optional(self.core.tick())
            if self.core.events:
                self._drain_events()
        self._log_held()
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
            if bad and who not in self._warned_publishers and len(self._warned_publishers) < 100:
                self._warned_publishers.add(who)
                self.get_logger().warning(
                    f"'{topic}' publisher {who} offers {' and '.join(bad)}: this node (like robot_state_publisher's "
                    'subscribers) needs reliable + transient local, so it will not receive that description')

    def _publish_diagnostics(self):
        with self.lock:
            level, message, values = self._gp.report(*self._contact.monitor.report(*self.core.diagnostics()))
            values = values + self._features.report()
            m = self.core.model
        # /diagnostics is shared by every namespace: the status names the node's namespace too
        st = DiagnosticStatus(level=bytes([level]), name=f"{self.get_fully_qualified_name().lstrip('/')}: "
                              'gravity compensation',
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
    # Validation checks the settings (Compensator.plan) and what can be said of a new
    # description without reading it (background.precheck: description_update, size, a missing
    # file; inertia_policy 'strict' against the running model's inertia report); a change that
    # fails there is rejected as a whole. After the set (post_set): the plan becomes current
    # (the one zero command on disable, the timer period, ~/commanded_efforts), and a new
    # description or policy starts loading in the background: a model that then fails to load
    # is reported in the log and diagnostics, and the previous one keeps running.
    def _validate_parameters(self, params):
        changes = {p.name: p.value for p in params if p.name in SPECS}
        with self.lock:
            self._pending = None
            if not changes:
                return SetParametersResult(successful=True)
            try:
                self._pending = (changes,) + self._plan_parameters(changes)
            except ValueError as exc:
                self._drain_events()
                return SetParametersResult(successful=False, reason=clip(str(exc), DIAG_TEXT_MAX))
        return SetParametersResult(successful=True)

    def _plan_parameters(self, changes):
        """(plan, load) for a parameter change; load: (kind, text) to load afterwards, or None.
        Raises ValueError with the reason."""
        rest = {k: v for k, v in changes.items() if k not in dict(SOURCES)}
        plan = self.core.plan(rest)
        check_settings(plan.settings, len(self.core.layout) if self.core.layout else None)
        self._gp.check(plan.settings)
        self._features.check(plan.settings, self.core.model)
        s, core = plan.settings, self.core
        load = None
        for key, kind in SOURCES:
            text = check_value(key, changes[key]) if key in changes else ''
            if text:
                err = self._bg.precheck(kind, text, s)
                if err:
                    raise ValueError(f'{source_label(kind, text)}: {err}')
                load = (kind, text)
        if load is None and 'inertia_policy' in changes and s['inertia_policy'] != core.settings['inertia_policy']:
            kind, text = self._current_source()
            if kind is not None and core.model is not None:
                if s['description_update'] == 'none':
                    raise ValueError("description_update is 'none': the running model cannot be reloaded under "
                                     'another inertia_policy')
                if s['inertia_policy'] == 'strict' and core.inertia_report:
                    raise ValueError("inertia_policy 'strict' would refuse the running description: " +
                                     '; '.join(r['message'] for r in core.inertia_report))
            if kind is not None:
                load = (kind, text)
        return plan, load

    def _apply_parameters(self, params):
        changes = {p.name: p.value for p in params if p.name in SPECS}
        if not changes:
            return
        with self.lock:
            pending, self._pending = self._pending, None
            try:
                if pending is None or pending[0] != changes:  # not the change validated last: check again
                    pending = (changes,) + self._plan_parameters(changes)
                _, plan, load = pending
                cmd = self.core.apply(plan)
            except ValueError as exc:  # only if the state moved between validation and now
                self.log_event('error', 'parameters', f'parameter change {sorted(changes)} not applied: {exc}')
                self._drain_events()
                return
            self._publish_optional(cmd)
            if load is not None:
                self._bg.request(*load)
            if 'stale_timeout' in changes:
                period = _tick_period(self.core.settings['stale_timeout'], self._diag_period)
                self._timer.timer_period_ns = int(period * 1e9)
            if 'publish_joint_state' in changes:
                self._set_js_publisher(self.core.settings['publish_joint_state'])
            self._features.sync(self.core)  # publishers made here, not on the control path
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
        """Starts the reload (answered at once): the running model answers until the new one is
        ready; the result is in the log and the diagnostics (model_state, description_error)."""
        with self.lock:
            kind, text = self._current_source()
            if kind is None:
                response.success, response.message = False, 'no robot description to reload'
                return response
            err = self._bg.request(kind, text)
            self._drain_events()
        response.success = err is None
        response.message = err if err is not None else (
            f'loading {source_label(kind, text)} in the background; the running model answers until it is ready '
            '(result: log, diagnostics model_state / description_error)')
        return response

    def shutdown_command(self):
        """Publish the stale_action command once (the effort controller holds the last command)."""
        with self.lock:
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
    """Entry point of `ros2 run lie_dynamics dynamics_node`: --help prints usage, arguments outside
    --ros-args and a start-up configuration that cannot work exit with status 2 (run.run)."""
    parser = node_parser('dynamics_node', HELP_DESCRIPTION, help_rows(), HELP_EXAMPLE)
    return run(DynamicsNode, 'dynamics_node', args, on_stop=_last_command, parser=parser)


if __name__ == '__main__':
    sys.exit(main())
