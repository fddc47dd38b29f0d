"""The dynamics node's external-torque topics: contact.py's ContactMonitor as a per-sample
feature (base.py), its results published.

Publishes   ~/external_torques (sensor_msgs/JointState: name = the command layout, effort = the
            estimate, header.stamp = the joint_states stamp) and ~/collision (std_msgs/Bool),
            one of each per new accepted joint_states message with efforts, after its command
            (QoS: interfaces.py). Both are published serialized (cdr.Template, as the dynamics
topics; ~/external_torques through one cdr.Writer per joint layout): writing the estimate into
a message serialized once costs less than rclpy's conversion of a message object; and both
through interfaces.SerializedPublisher (rclpy's publish_raw without its per-call checks).

With them, contact_link.py's ContactIsolation: ~/contact/wrench and ~/contact/tool_wrench
(geometry_msgs/WrenchStamped, the joint_states stamp; serialized here, published as above) and
~/contact/link (std_msgs/String, a message object: it is published only when the link changes).
"""
import struct

import numpy as np

from rclpy.serialization import serialize_message
from std_msgs.msg import Bool, String

from .. import interfaces
from ..core.cdr import joint_state_template, stamp_parts
from .base import Feature
from ..loading.models import jacobian_at_rest
from .contact import ContactMonitor, check_settings, observer_on, warm_observer
from .contact_link import ContactIsolation, check_wrench_frame

# ~/collision's two possible messages, serialized
_FLAG = {v: serialize_message(Bool(data=v)) for v in (False, True)}


class ContactTopics(Feature):
    """ContactMonitor fed each accepted sample, its estimate and flag published. Attached to a
    DynamicsNode `node` (its public core: the command layout before a model is loaded)."""

    name = 'contact'
    later = True   # its work only publishes the estimates: after the next state's command if one is waiting

    def __init__(self, node):
        super().__init__()
        self.monitor = ContactMonitor()
        self.isolation = ContactIsolation()
        self._core = node.core
        # published at every sample: serialized straight through the handle (stop() releases it)
        self._ext_pub = interfaces.serialized_publisher(node, '~/external_torques')
        self._flag_pub = interfaces.serialized_publisher(node, '~/collision')
        self._wrench_pub = interfaces.serialized_publisher(node, '~/contact/wrench')
        self._tool_pub = interfaces.serialized_publisher(node, '~/contact/tool_wrench')
        self._link_pub = interfaces.publisher(node, '~/contact/link')
        self._names = self._ext = None   # the layout of ~/external_torques, its cdr.Writer's message

    def use_events(self, queue):
        super().use_events(queue)
        self.isolation.events = queue   # its lines go to the one queue too, and the monitor's through it
        self.monitor.events = self.isolation.inbox

    def check(self, settings, model):
        layout = self._core.layout   # known before the model when `joints` is set
        check_settings(settings, model.n if model is not None else len(layout) if layout else None)
        check_wrench_frame(settings, model)

    def kernels(self, settings):
        if not observer_on(settings):
            return ()
        frame = settings.contact.wrench_frame
        return ((warm_observer,),) + (((jacobian_at_rest, frame, 'local'),) if frame else ())

    def configure(self, settings, model, derived):
        m = self.monitor
        m.adopt(settings, model, None if derived is None else derived.friction,
               None if model is None else model.joint_names)
        self.isolation.adopt(settings, model)
        self.active = m.active

    def on_sample(self, s):
        m = self.monitor
        out = m.on_sample(s)
        if self.isolation.inbox:
            self.isolation.flush()   # the monitor's lines; the collision line waits for the link
        if out is None:
            if m.estimate is None:   # paused: isolation starts anew with the observer
                self.isolation.reset()
                self.isolation.flush()
            return
        names = s.names
        if names is not self._names:  # built when the layout changes: no position, no velocity
            template, stamp_at, slots = joint_state_template(names, (0, 0, len(names)))
            self._names, self._ext = names, template.writer(slots[2:], stamp_at).message
        self._ext_pub.publish(self._ext((out[0],), s.stamp))
        self._flag_pub.publish(_FLAG[out[1]])
        pub = self.isolation.update(m.last_stamp, s.q, out[0], out[1], m.threshold)
        if pub.wrench is not None:
            self._wrench_pub.publish(_wrench(pub.wrench[0], pub.wrench[1], s.stamp))
        if pub.tool is not None:
            self._tool_pub.publish(_wrench(self.isolation.frame, pub.tool, s.stamp))
        if pub.link is not None:
            self._link_pub.publish(String(data=pub.link))

    def stop(self):
        for pub in (self._ext_pub, self._flag_pub, self._wrench_pub, self._tool_pub):
            pub.close()

    def report(self, level, message):
        level, message, values = self.monitor.report(level, message, [], self.isolation.where())
        level, values = self.isolation.report(level, values)
        return level, message, values


_WRENCH_HEADS = {}


def _wrench(frame, w, stamp):
    """A geometry_msgs/WrenchStamped, serialized (plain CDR, little-endian): the header's layout
    per frame_id once, then the stamp and the six doubles (cheaper than a message object)."""
    head = _WRENCH_HEADS.get(frame)
    if head is None:
        raw = frame.encode('utf-8') + b'\0'
        body = struct.pack('<I', len(raw)) + raw
        body += b'\0' * (-(8 + len(body)) % 8)   # the doubles start 8-aligned after the encapsulation
        head = _WRENCH_HEADS[frame] = body
    sec, nsec = stamp_parts(stamp)
    return b'\x00\x01\x00\x00' + struct.pack('<iI', sec, nsec) + head + np.asarray(w, dtype='<f8').tobytes()
