"""The dynamics node's external-torque topics: the rclpy side of contact.py.

Publishes   ~/external_torques (sensor_msgs/JointState: name = the command layout, effort = the
            estimate, header.stamp = the joint_states stamp) and ~/collision (std_msgs/Bool),
            one of each per new accepted joint_states message with efforts, after its command.
Depth 100: a reader whose acknowledgements lag a little (a recorder) loses no estimate.
"""
import array

from sensor_msgs.msg import JointState
from std_msgs.msg import Bool

from ..core.cdr import stamp_parts
from .contact import ContactMonitor


class ContactTopics:
    """ContactMonitor fed from the node's hot path, its results published."""

    def __init__(self, node, pub_events):
        self.monitor = ContactMonitor()
        self._ext_pub = node.create_publisher(JointState, '~/external_torques', 100, event_callbacks=pub_events)
        self._flag_pub = node.create_publisher(Bool, '~/collision', 100, event_callbacks=pub_events)
        self._ext, self._flag = JointState(), Bool()
        self._accepted = 0  # core.count.accepted at the last message observed

    def observe(self, core, sample, names):
        """After the command for a joint_states `sample` (cdr.JointStateSample): the observer, if
        the compensator accepted it.
        names: the command layout as the node keeps it (the same list object while it holds)."""
        if core.count.accepted == self._accepted:
            return
        self._accepted = core.count.accepted
        c = self.monitor
        c.sync(core.settings, core.model, core.friction, core.layout)
        if not c.active:
            return
        out = c.on_state(core.reader.map.idx, core.last_q, sample.velocity, sample.effort, sample.stamp)
        if out is None:
            return
        ext = self._ext
        ext.header.stamp.sec, ext.header.stamp.nanosec = stamp_parts(sample.stamp)
        if ext.name is not names:  # the setter checks every name: only when the layout changes
            ext.name = names
        ext.effort = array.array('d', out[0].tobytes())
        self._ext_pub.publish(ext)
        self._flag.data = out[1]
        self._flag_pub.publish(self._flag)
