"""Every topic and service of the dynamics node in one table: name, type, QoS and the module that
owns it (makes it and uses it). The node and its features make their publishers,
subscriptions and services here (`publisher`, `subscription`, `service`), so that a QoS is
decided once; docs/node.md describes each one.

A name in <angle brackets> is a parameter's value (default in params.py). Every other name is
relative or private, except /diagnostics (global by ROS convention), so that `-r __ns:=/robot1`
moves the node with all of them. No default QoS-event handlers anywhere: each one is waited on
at every executor wake-up (the hot path); the usual robot_description mistake is reported from
the timer instead (`description_qos_problems`).
"""
from typing import NamedTuple

from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import Vector3Stamped, WrenchStamped
from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor
from rcl_interfaces.srv import SetParametersAtomically
from rclpy.event_handler import PublisherEventCallbacks, SubscriptionEventCallbacks
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState
from std_msgs.msg import Bool, Float64MultiArray, String
from std_srvs.srv import SetBool, Trigger
from trajectory_msgs.msg import JointTrajectory


def _qos(depth, reliable=True, transient=False):
    return QoSProfile(depth=depth, history=HistoryPolicy.KEEP_LAST,
                      reliability=ReliabilityPolicy.RELIABLE if reliable else ReliabilityPolicy.BEST_EFFORT,
                      durability=DurabilityPolicy.TRANSIENT_LOCAL if transient else DurabilityPolicy.VOLATILE)


# As robot_state_publisher publishes it: a late subscriber must also be transient local.
DESCRIPTION_QOS = _qos(1, transient=True)
# Only the newest state matters (an old one queued behind it is never answered); best effort, like
# robot_state_publisher's subscription: compatible with any publisher, a lost sample only skips
# one command update.
JOINT_STATES_QOS = _qos(1, reliable=False)
DESIRED_QOS = _qos(1, reliable=False)
# Only the newest vector matters; best effort accepts any publisher (an IMU filter, a base estimator).
GRAVITY_QOS = _qos(1, reliable=False)
# Trajectories: reliable, one kept each way. Only the newest one matters (a newer one replaces a
# waiting fill anyway), and DDS keeps a kept sample's memory (a 100,000-point trajectory: 20 MB).
TRAJECTORY_QOS = _qos(1)
# Requests kept per service: rclpy's default (10) dropped 975 of 1,000 concurrent calls, whose
# clients then waited forever. A kept request costs its message only (a SetBool or Trigger
# request is a few bytes), and each is answered in microseconds.
SERVICE_QUEUE = 1000
SERVICE_QOS = _qos(SERVICE_QUEUE)
OUT_QOS = _qos(10)
# The observer's outputs: a reader whose acknowledgements lag a little (a recorder) loses no estimate.
ESTIMATE_QOS = _qos(100)
# No default QoS-event handlers (module docstring); also used by bench/.
NO_PUB_EVENTS = PublisherEventCallbacks(use_default_callbacks=False)
NO_SUB_EVENTS = SubscriptionEventCallbacks(use_default_callbacks=False)


class Interface(NamedTuple):
    kind: str        # 'pub', 'sub' (raw: taken serialized) or 'srv'
    type: object
    qos: QoSProfile
    owner: str       # the module that makes and uses it
    raw: bool = False


INTERFACES = {
    'robot_description': Interface('sub', String, DESCRIPTION_QOS, 'node'),
    'joint_states': Interface('sub', JointState, JOINT_STATES_QOS, 'node', raw=True),
    '<desired_topic>': Interface('sub', JointTrajectory, DESIRED_QOS, 'node', raw=True),
    '~/trajectory_in': Interface('sub', JointTrajectory, TRAJECTORY_QOS, 'trajectory_process (a child)', True),
    '<gravity_topic>': Interface('sub', Vector3Stamped, GRAVITY_QOS, 'features.gravity_topic'),
    '<command_topic>': Interface('pub', Float64MultiArray, OUT_QOS, 'node'),
    '~/commanded_efforts': Interface('pub', JointState, OUT_QOS, 'node'),
    '/diagnostics': Interface('pub', DiagnosticArray, OUT_QOS, 'node'),
    '~/trajectory_out': Interface('pub', JointTrajectory, TRAJECTORY_QOS, 'trajectory_process (a child)'),
    '~/external_torques': Interface('pub', JointState, ESTIMATE_QOS, 'features.contact_topics'),
    '~/collision': Interface('pub', Bool, ESTIMATE_QOS, 'features.contact_topics'),
    '~/contact/wrench': Interface('pub', WrenchStamped, ESTIMATE_QOS, 'features.contact_topics'),
    '~/contact/tool_wrench': Interface('pub', WrenchStamped, ESTIMATE_QOS, 'features.contact_topics'),
    '~/contact/link': Interface('pub', String, ESTIMATE_QOS, 'features.contact_topics'),
    '~/dynamics/gravity': Interface('pub', JointState, OUT_QOS, 'features.dynamics_topics'),
    '~/dynamics/coriolis': Interface('pub', JointState, OUT_QOS, 'features.dynamics_topics'),
    '~/dynamics/mass_matrix': Interface('pub', Float64MultiArray, OUT_QOS, 'features.dynamics_topics'),
    '~/dynamics/jacobian': Interface('pub', Float64MultiArray, OUT_QOS, 'features.dynamics_topics'),
    '~/set_enabled': Interface('srv', SetBool, SERVICE_QOS, 'control'),
    '~/reload_model': Interface('srv', Trigger, SERVICE_QOS, 'control'),
    '~/set_payload': Interface('srv', SetParametersAtomically, SERVICE_QOS, 'features.payload_services'),
    '~/identify_payload': Interface('srv', Trigger, SERVICE_QOS, 'features.payload_services (its helper node)'),
    '~/record': Interface('srv', SetBool, SERVICE_QOS, 'features.recording (its helper node)'),
}


def _row(key, kind):
    row = INTERFACES[key]
    if row.kind != kind:
        raise ValueError(f"'{key}' is a {row.kind}, not a {kind}")
    return row


def publisher(node, key, name=None):
    """node's publisher of table entry `key` (name: the resolved parameter value of a <...> entry)."""
    row = _row(key, 'pub')
    return node.create_publisher(row.type, name or key, row.qos, event_callbacks=NO_PUB_EVENTS)


class SerializedPublisher:
    """publish(bytes) of a serialized message on an rclpy publisher, for a topic published at every
    sample: its handle's publish_raw called directly. rclpy's `publish` holds the handle in use for
    each call and checks the message's type (about half its time); here the handle is held in use
    once, from here to close() (a feature's stop(), before the node is destroyed), so the rcl
    publisher cannot go while the node may publish (once it is gone after close(), publishing
    raises RCLError)."""

    def __init__(self, publisher):
        self.publisher = publisher
        self._handle = publisher.handle
        self._handle.__enter__()
        self.publish = self._handle.publish_raw   # an attribute, not a method: no Python frame per call

    def close(self):
        """Release the handle (rclpy then destroys the publisher when its node goes); idempotent."""
        if self._handle is not None:
            self._handle.__exit__(None, None, None)
            self._handle = None


def serialized_publisher(node, key, name=None):
    """A SerializedPublisher of node's publisher of table entry `key` (publisher)."""
    return SerializedPublisher(publisher(node, key, name))


def subscription(node, key, callback, name=None):
    row = _row(key, 'sub')
    return node.create_subscription(row.type, name or key, callback, row.qos, raw=row.raw,
                                    event_callbacks=NO_SUB_EVENTS)


def service(node, key, callback, name=None, **kwargs):
    row = _row(key, 'srv')
    return node.create_service(row.type, name or key, callback, qos_profile=row.qos, **kwargs)


def description_qos_problems(qos):
    """What a robot_description publisher's offered QoS lacks for DESCRIPTION_QOS ([] if nothing)."""
    return [p for p, ok in (('volatile durability', qos.durability == DurabilityPolicy.TRANSIENT_LOCAL),
                            ('best-effort reliability', qos.reliability == ReliabilityPolicy.RELIABLE)) if not ok]


PARAMETER_TYPES = {'bool': Parameter.Type.BOOL, 'integer': Parameter.Type.INTEGER, 'double': Parameter.Type.DOUBLE,
                   'string': Parameter.Type.STRING, 'double_array': Parameter.Type.DOUBLE_ARRAY,
                   'string_array': Parameter.Type.STRING_ARRAY}


def parameter_descriptor(spec):
    """The rclpy descriptor of a params.PARAMS entry (read-only unless live; its range)."""
    desc = ParameterDescriptor(description=spec.description, read_only=not spec.live,
                               additional_constraints=spec.constraints)
    if spec.range is not None and spec.kind == 'double':
        desc.floating_point_range = [FloatingPointRange(from_value=spec.range[0], to_value=spec.range[1], step=0.0)]
    elif spec.range is not None:
        desc.integer_range = [IntegerRange(from_value=int(spec.range[0]), to_value=int(spec.range[1]), step=0)]
    return desc


def declare_parameters(node, specs):
    """Declare each params.PARAMS entry on the node (its type when it has no default); their values."""
    return {spec.name: node.declare_parameter(
        spec.name, PARAMETER_TYPES[spec.kind] if spec.default is None else spec.default,
        parameter_descriptor(spec)).value for spec in specs}
