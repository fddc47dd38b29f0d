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
from .contact import ContactMonitor, observer_on

# ~/collision's two possible messages, serialized
_FLAG = {v: serialize_message(Bool(data=v)) for v in (False, True)}


class ContactTopics(Feature):
    """ContactMonitor fed each accepted sample, its estimate and flag published."""

    name = 'contact'

    def __init__(self, node):
        self.monitor = ContactMonitor()
        super().__init__()
        self._ext_pub = interfaces.publisher(node, '~/external_torques')
        self._flag_pub = interfaces.publisher(node, '~/collision')
        self._names = self._ext = None   # the layout of ~/external_torques, its cdr.Writer's message

    @property
    def events(self):   # the monitor's queue is the feature's
        return self.monitor.events

    @events.setter
    def events(self, queue):
        self.monitor.events = queue

    def kernels(self, settings):
        return (('observer',),) if observer_on(settings) else ()

    def configure(self, settings, model, derived):
        m = self.monitor
        m.sync(settings, model, None if derived is None else derived.friction,
               None if model is None else model.joint_names)
        self.active = m.active

    def on_sample(self, s):
        out = self.monitor.on_state(s.columns, s.q, s.message_velocity, s.message_effort, s.stamp)
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
