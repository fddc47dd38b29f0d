"""The dynamics node's gravity topic and payload services: the rclpy side of gravity_source.py
and payload_service.py, which hold the logic.

    <gravity_topic>      geometry_msgs/Vector3Stamped (best effort, depth 1), if set
    ~/set_payload        rcl_interfaces/SetParametersAtomically: payload.link, payload.mass,
                         payload.com, payload.inertia in one request, checked for consistency
    ~/identify_payload   std_srvs/Trigger: record identify.duration s, fit, set payload.*; the
                         answer says what was identified or why it was refused

~/identify_payload answers only after its recording and fit (seconds), and rclpy's executors
cannot answer a request later from another callback (the EventsExecutor calls service callbacks
synchronously). So it is served by a hidden helper node in the same context, spun by its own
two-thread executor: one thread may wait for the recording while the other refuses concurrent
calls at once, and the node's own executor never waits. The recording itself happens on the
node's control path (Identification.add after each joint_states).
"""
import threading

from geometry_msgs.msg import Vector3Stamped
from rcl_interfaces.msg import SetParametersResult
from rcl_interfaces.srv import SetParametersAtomically
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.executors import MultiThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from std_srvs.srv import Trigger

from ..core.diagnostics import DIAG_TEXT_MAX, clip
from .gravity_source import GravitySource
from .payload_service import Identification, check_identify_link, check_payload_request, fit

# Only the newest vector matters; best effort accepts any publisher (an IMU filter, a base estimator).
GRAVITY_QOS = QoSProfile(depth=1, history=HistoryPolicy.KEEP_LAST, reliability=ReliabilityPolicy.BEST_EFFORT,
                         durability=DurabilityPolicy.VOLATILE)


def _parameter(name, value):
    if isinstance(value, list):  # an empty list has no type of its own
        return Parameter(name, Parameter.Type.DOUBLE_ARRAY, [float(v) for v in value])
    return Parameter(name, value=value)


class GravityPayload:
    """Attached to a DynamicsNode `node` (uses its public core, lock and log_event); `values`: its start-up
    parameters; service_qos: the QoS of its services."""

    def __init__(self, node, values, service_qos, sub_events=None):
        self.node = node
        self.gravity = GravitySource()
        self.ident = Identification()
        if values['gravity_topic']:
            sub = node.create_subscription(Vector3Stamped, values['gravity_topic'], self._on_gravity, GRAVITY_QOS,
                                           event_callbacks=sub_events)
            self.gravity.topic = sub.topic_name
        node.create_service(SetParametersAtomically, '~/set_payload', self._srv_set_payload, qos_profile=service_qos)
        self._helper = Node(f'_{node.get_name()}_payload', namespace=node.get_namespace(), context=node.context,
                            start_parameter_services=False, enable_rosout=False,
                            use_global_arguments=False)  # a `-r __node:=...` names the node, not its helper
        self._helper.create_service(Trigger, f'{node.get_fully_qualified_name()}/identify_payload',
                                    self._srv_identify, qos_profile=service_qos,
                                    callback_group=ReentrantCallbackGroup())
        self._executor = MultiThreadedExecutor(num_threads=2, context=node.context)
        self._executor.add_node(self._helper)
        self._thread = threading.Thread(target=self._spin, name='lie_dynamics_payload', daemon=True)
        self._thread.start()

    def _spin(self):
        try:
            self._executor.spin()
        except Exception:  # noqa: BLE001 - the context shut down under it: nothing left to serve
            pass

    def stop(self):
        self.ident.stop('the node is shutting down')
        self._executor.shutdown(timeout_sec=2.0)
        self._thread.join(timeout=2.0)
        self._helper.destroy_node()

    # ------------------------------------------------------------------ control path (node's lock held)
    def before_command(self, core):
        """The gravity in force for the next command (topic or parameter)."""
        if self.gravity.topic:
            self.gravity.sync(core)
            if self.gravity.events:
                self._drain()

    def _drain(self):
        events, self.gravity.events = self.gravity.events, []
        for severity, key, text in events:
            self.node.log_event(severity, key, text)

    def report(self, level, message, values):
        level, message, extra = self.gravity.report(level, message)
        extra = [(k, clip(v, DIAG_TEXT_MAX)) for k, v in extra + self.ident.report()]
        return level, clip(message, DIAG_TEXT_MAX), values + extra

    def check(self, settings):
        """Validation of a parameter change that needs the model (on-set; raises ValueError)."""
        check_identify_link(settings, self.node.core.model)

    def _on_gravity(self, msg):
        node = self.node
        try:
            with node.lock:
                v = msg.vector
                self.gravity.offer((v.x, v.y, v.z), msg.header.frame_id, node.core.model)
                self.gravity.sync(node.core)
                if self.gravity.events:
                    self._drain()
        except Exception as exc:  # noqa: BLE001 - the node never dies on input
            node.log_event('error', 'internal:gravity',
                           clip(f'gravity message: {type(exc).__name__}: {exc}', DIAG_TEXT_MAX))

    # ------------------------------------------------------------------ services
    def _srv_set_payload(self, request, response):
        node = self.node
        try:
            values = {p.name: Parameter.from_parameter_msg(p).value for p in request.parameters}
            with node.lock:
                changes = check_payload_request(values, node.core.model)
            response.result = node.set_parameters_atomically([_parameter(k, v) for k, v in changes.items()])
        except Exception as exc:  # noqa: BLE001 - refused with the reason, never raised into the executor
            text = str(exc) if isinstance(exc, ValueError) else f'{type(exc).__name__}: {exc}'
            response.result = SetParametersResult(successful=False, reason=clip(text, DIAG_TEXT_MAX))
        return response

    def _srv_identify(self, request, response):
        """(helper thread) Record, fit, set payload.*; refused at once when busy or impossible."""
        node, ident = self.node, self.ident
        try:
            with node.lock:
                ident.begin(node.core)
        except ValueError as exc:
            response.success, response.message = False, clip(f'refused: {exc}', DIAG_TEXT_MAX)
            return response
        ok, text = False, 'interrupted'
        try:
            ident.wait()
            with node.lock:
                rec, model, link, mode, convention, max_ratio, friction = ident.take(node.core)
            _, changes, text = fit(model, link, *rec.arrays(), mode, convention, max_ratio, friction)
            result = node.set_parameters_atomically([_parameter(k, v) for k, v in changes.items()])
            if not result.successful:
                raise ValueError(f'the identified payload was refused: {result.reason}')
            ok = True
        except ValueError as exc:
            text = f'refused, payload unchanged: {exc}'
        except Exception as exc:  # noqa: BLE001 - reported to the caller, the node carries on
            text = f'refused, payload unchanged: {type(exc).__name__}: {exc}'
        finally:
            ident.finish(ok, text)
        with node.lock:
            node.log_event('info' if ok else 'warn', 'identify', f'~/identify_payload: {text}')
        response.success, response.message = ok, clip(text, DIAG_TEXT_MAX)
        return response
