"""The dynamics node's payload services: the rclpy side of payload_service.py (which holds the
logic), as a per-sample feature (base.py: PayloadRecording).

    ~/set_payload        rcl_interfaces/SetParametersAtomically: payload.link, payload.mass,
                         payload.com, payload.inertia in one request, checked by the one payload
                         rule (check_payload_request: Model.check_payload) and set as parameters
    ~/identify_payload   std_srvs/Trigger: record identify.duration s, fit, set payload.*; the
                         answer says what was identified or why it was refused

~/identify_payload answers only after its recording and fit (seconds), and rclpy's executors
cannot answer a request later from another callback (the EventsExecutor calls service callbacks
synchronously). So it is served by a hidden helper node in the same context, spun by its own
two-thread executor: one thread may wait for the recording while the other refuses concurrent
calls at once, and the node's own executor never waits. The recording itself happens on the
node's control path: PayloadServices is active while it records (Identification.add with each
accepted sample).
"""
import threading

from rcl_interfaces.msg import SetParametersResult
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.executors import MultiThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter

from .. import interfaces
from ..core.diagnostics import DIAG_TEXT_MAX, clip
from .payload_service import PayloadRecording, check_payload_request


def _parameter(name, value):
    if isinstance(value, list):  # an empty list has no type of its own
        return Parameter(name, Parameter.Type.DOUBLE_ARRAY, [float(v) for v in value])
    return Parameter(name, value=value)


class PayloadServices(PayloadRecording):
    """~/set_payload and ~/identify_payload of a DynamicsNode `node` (its public core, lock,
    drain_events and parameters); records while an identification runs (PayloadRecording)."""

    def __init__(self, node):
        super().__init__()
        self.node = node
        interfaces.service(node, '~/set_payload', self._srv_set_payload)
        self._helper = Node(f'_{node.get_name()}_payload', namespace=node.get_namespace(), context=node.context,
                            start_parameter_services=False, enable_rosout=False,
                            use_global_arguments=False)  # a `-r __node:=...` names the node, not its helper
        interfaces.service(self._helper, '~/identify_payload', self._srv_identify,
                           f'{node.get_fully_qualified_name()}/identify_payload',
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
                job = ident.take(node.core)
            _, changes, text = job.run()
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
            self.events.append(('info' if ok else 'warn', 'identify', f'~/identify_payload: {text}'))
            node.drain_events()
        response.success, response.message = ok, clip(text, DIAG_TEXT_MAX)
        return response
