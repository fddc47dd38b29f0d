"""The dynamics node's external-torque topics: the rclpy side of contact.py.

Publishes   ~/external_torques (sensor_msgs/JointState: name = the command layout, effort = the
            estimate, header.stamp = the joint_states stamp) and ~/collision (std_msgs/Bool),
            one of each per new accepted joint_states message with efforts, after its command.
Depth 100: a reader whose acknowledgements lag a little (a recorder) loses no estimate.
Both are published serialized (cdr.Template, as the dynamics topics; ~/external_torques through
one cdr.Writer per joint layout): writing the estimate into a message serialized once costs less
than rclpy's conversion of a message object.
"""
from rclpy.serialization import serialize_message
from sensor_msgs.msg import JointState
from std_msgs.msg import Bool

from .contact import ContactMonitor
from .dynamics_topics import joint_state_template

# ~/collision's two possible messages, serialized
_FLAG = {v: serialize_message(Bool(data=v)) for v in (False, True)}


class ContactTopics:
    """ContactMonitor fed from the node's hot path, its results published."""

    def __init__(self, node, pub_events):
        self.monitor = ContactMonitor()
        self._ext_pub = node.create_publisher(JointState, '~/external_torques', 100, event_callbacks=pub_events)
        self._flag_pub = node.create_publisher(Bool, '~/collision', 100, event_callbacks=pub_events)
        self._names = self._ext = None   # the layout of ~/external_torques, its cdr.Writer's message
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
        if names is not self._names:  # built when the layout changes: no position, no velocity
            template, stamp_at, slots = joint_state_template(names, (0, 0, len(names)))
            self._names, self._ext = names, template.writer(slots[2:], stamp_at).message
        self._ext_pub.publish(self._ext((out[0],), sample.stamp))
        self._flag_pub.publish(_FLAG[out[1]])
