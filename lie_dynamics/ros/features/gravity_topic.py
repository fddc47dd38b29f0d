"""The dynamics node's gravity topic: the rclpy side of gravity_source.py (which holds the logic),
as a per-sample feature (base.py) that steers the command.

    <gravity_topic>      geometry_msgs/Vector3Stamped (best effort, depth 1), if set: the gravity
                         in force before each command (GravitySource: checked, followed while
                         fresh, else the `gravity` parameter)
"""
from .. import interfaces
from .base import Feature
from .gravity_source import GravitySource


class GravityTopic(Feature):
    """The gravity vector from <gravity_topic> (if set) in force before every command. Attached to
    a DynamicsNode `node` (its public core, lock and drain_events)."""

    name = 'gravity'

    def __init__(self, node):
        super().__init__()
        self.node = node
        self.source = GravitySource()
        topic = node.get_parameter('gravity_topic').value
        if topic:
            self.source.topic = interfaces.subscription(node, '<gravity_topic>', self._on_gravity, topic).topic_name

    def use_events(self, queue):
        super().use_events(queue)
        self.source.events = queue   # the source's lines go to the one queue too

    def before_command(self, core):
        """The gravity in force for the next command (topic or parameter)."""
        if self.source.topic:
            self.source.apply(core)

    def report(self, level, message):
        return self.source.report(level, message)

    def _on_gravity(self, msg):
        node = self.node
        with node.lock:
            try:
                v = msg.vector
                self.source.offer((v.x, v.y, v.z), msg.header.frame_id, node.core.model)
                self.source.apply(node.core)
            except Exception as exc:  # noqa: BLE001 - the node never dies on input
                self.events.append(('error', 'internal:gravity', f'gravity message: {type(exc).__name__}: {exc}'))
            node.drain_events()
