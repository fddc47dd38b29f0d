"""The dynamics node's external-torque topics: contact.py's ContactMonitor as a per-sample
feature (base.py), its results published.

Publishes   ~/external_torques (sensor_msgs/JointState: name = the command layout, effort = the
            estimate, header.stamp = the joint_states stamp) and ~/collision (std_msgs/Bool),
            one of each per new accepted joint_states message with efforts, after its command
            (QoS: interfaces.py).
"""
import array

from sensor_msgs.msg import JointState
from std_msgs.msg import Bool

from .. import interfaces
from ..core.cdr import stamp_parts
from .base import Feature
from .contact import ContactMonitor


class ContactTopics(Feature):
    """ContactMonitor fed each accepted sample, its estimate and flag published."""

    name = 'contact'

    def __init__(self, node):
        self.monitor = ContactMonitor()
        super().__init__()
        self._ext_pub = interfaces.publisher(node, '~/external_torques')
        self._flag_pub = interfaces.publisher(node, '~/collision')
        self._ext, self._flag = JointState(), Bool()

    @property
    def events(self):   # the monitor's queue is the feature's
        return self.monitor.events

    @events.setter
    def events(self, queue):
        self.monitor.events = queue

    def configure(self, settings, model, derived):
        m = self.monitor
        m.sync(settings, model, None if derived is None else derived.friction,
               None if model is None else model.joint_names)
        self.active = m.active

    def on_sample(self, s):
        out = self.monitor.on_state(s.columns, s.q, s.message_velocity, s.message_effort, s.stamp)
        if out is None:
            return
        ext = self._ext
        ext.header.stamp.sec, ext.header.stamp.nanosec = stamp_parts(s.stamp)
        if ext.name is not s.names:  # the setter checks every name: only when the layout changes
            ext.name = s.names
        ext.effort = array.array('d', out[0].tobytes())
        self._ext_pub.publish(ext)
        self._flag.data = out[1]
        self._flag_pub.publish(self._flag)

    def report(self, level, message):
        return self.monitor.report(level, message, [])
