"""The dynamics node's external-torque topics: contact.py's ContactMonitor as a per-sample
feature (base.py), its results published.

Publishes   ~/external_torques (sensor_msgs/JointState: name = the command layout, effort = the
            estimate, header.stamp = the joint_states stamp) and ~/collision (std_msgs/Bool),
            one of each per new accepted joint_states message with efforts, after its command
            (QoS: interfaces.py). Both are published serialized (cdr.Template, as the dynamics
topics; ~/external_torques through one cdr.Writer per joint layout): writing the estimate into
a message serialized once costs less than rclpy's conversion of a message object.
"""
from rclpy.serialization import serialize_message
from std_msgs.msg import Bool

from .. import interfaces
from ..core.cdr import joint_state_template
from .base import Feature
from .contact import ContactMonitor, check_settings, observer_on, warm_observer

# ~/collision's two possible messages, serialized
_FLAG = {v: serialize_message(Bool(data=v)) for v in (False, True)}


class ContactTopics(Feature):
    """ContactMonitor fed each accepted sample, its estimate and flag published. Attached to a
    DynamicsNode `node` (its public core: the command layout before a model is loaded)."""

    name = 'contact'

    def __init__(self, node):
        super().__init__()
        self.monitor = ContactMonitor()
        self._core = node.core
        self._ext_pub = interfaces.publisher(node, '~/external_torques')
        self._flag_pub = interfaces.publisher(node, '~/collision')
        self._names = self._ext = None   # the layout of ~/external_torques, its cdr.Writer's message

    def use_events(self, queue):
        super().use_events(queue)
        self.monitor.events = queue   # the monitor's lines go to the one queue too

    def check(self, settings, model):
        layout = self._core.layout   # known before the model when `joints` is set
        check_settings(settings, model.n if model is not None else len(layout) if layout else None)

    def kernels(self, settings):
        return ((warm_observer,),) if observer_on(settings) else ()

    def configure(self, settings, model, derived):
        m = self.monitor
        m.sync(settings, model, None if derived is None else derived.friction,
               None if model is None else model.joint_names)
        self.active = m.active

    def on_sample(self, s):
        out = self.monitor.on_sample(s)
        if out is None:
            return
        names = s.names
        if names is not self._names:  # built when the layout changes: no position, no velocity
            template, stamp_at, slots = joint_state_template(names, (0, 0, len(names)))
            self._names, self._ext = names, template.writer(slots[2:], stamp_at).message
        self._ext_pub.publish(self._ext((out[0],), s.stamp))
        self._flag_pub.publish(_FLAG[out[1]])

    def report(self, level, message):
        return self.monitor.report(level, message, [])
