"""The dynamics node's own outputs (rclpy): the command, ~/commanded_efforts, /diagnostics
(interfaces.py has their types and QoS) and the writing of its log lines (which ones and when:
core/log.py, through the node's one event queue). The command and ~/commanded_efforts are published
serialized: their bytes written by a `cdr.Writer` (the message's constant bytes, made once per
layout, joined with the stamp and the efforts), as the joint_states input is read serialized; rclpy
then neither builds a message object nor converts and serializes it (`python -m bench.node_callback`),
and they go through interfaces.SerializedPublisher (publish_raw without rclpy's per-call checks)."""
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.duration import Duration
from rclpy.impl.implementation_singleton import rclpy_implementation as rclpy_c
from rclpy.logging import LoggingSeverity

from . import interfaces
from .core.cdr import joint_state_template, multi_array_template

LEVELS = {'info': LoggingSeverity.INFO, 'warn': LoggingSeverity.WARN, 'error': LoggingSeverity.ERROR}


class Outputs:
    """The command publishers and the diagnostics publisher of `node`; command_topic: its name."""

    def __init__(self, node, command_topic):
        self.node = node
        # published at every state: serialized through the handle (close() releases it)
        self._cmd_pub = interfaces.serialized_publisher(node, '<command_topic>', command_topic)
        self._js_pub = None
        self._diag_pub = interfaces.publisher(node, '/diagnostics')
        self._cmd_writer = self._js_writer = None   # cdr.Writers, made for the first command's layout
        self._cmd_size, self._js_names = -1, None
        self._warned_publishers = set()   # robot_description publishers already named

    def joint_state(self, on):
        """~/commanded_efforts on or off."""
        if on and self._js_pub is None:
            self._js_pub = interfaces.serialized_publisher(self.node, '~/commanded_efforts')
        elif not on and self._js_pub is not None:
            self._js_pub.close()
            self.node.destroy_publisher(self._js_pub.publisher)
            self._js_pub = None

    def close(self):
        """Release the command publishers' handles (before the node is destroyed); idempotent."""
        for pub in (self._cmd_pub, self._js_pub):
            if pub is not None:
                pub.close()

    def writers(self, n, names):
        """(command Writer, ~/commanded_efforts Writer or None while it is off) of n efforts in the
        layout `names` (the same list while it holds): each made once per size or layout."""
        if n != self._cmd_size:   # the command's bytes but for the efforts: once per size
            t, slots = multi_array_template(n)
            self._cmd_writer, self._cmd_size = t.writer(slots), n
        if self._js_pub is None:
            return self._cmd_writer, None
        if names is not self._js_names:   # its names: once per layout
            t, stamp_at, slots = joint_state_template(names, (0, 0, len(names)))
            self._js_writer, self._js_names = t.writer(slots[2:], stamp_at), names
        return self._cmd_writer, self._js_writer

    def command(self, tau, names, stamp=None):
        """The command (names: the layout, the same list while it holds); stamp: the input's (ns), None: now."""
        cmd, js = self.writers(len(tau), names)
        self._cmd_pub.publish(cmd.message((tau,)))
        if js is not None:
            if stamp is None:
                stamp = self.node.get_clock().now().nanoseconds
            self._js_pub.publish(js.message((tau,), stamp))

    def publish(self, command, joint_state=None):
        """A command already serialized by the writers' parts (the fused command path,
        core/fused.py) and its ~/commanded_efforts (None: off)."""
        self._cmd_pub.publish(command)
        if joint_state is not None and self._js_pub is not None:
            self._js_pub.publish(joint_state)

    def log_line(self, severity, text):
        """One line of the node's log (core/log.py decides which and when), through rclpy's C
        logging call, the one its Python logger ends in, named as logged here: that logger first
        finds its caller by inspecting the stack and reading the caller's source, 0.2 ms per line
        on a quiet machine and up to 1.3 ms in a loaded node (`python -m bench.node_loads
        --trace`), against a few microseconds for the call itself. The level set for the node's
        logger still applies; an rclpy without that call gets the Python logger."""
        level, log = LEVELS[severity], self.node.get_logger()
        if not log.is_enabled_for(level):
            return
        try:
            rclpy_c.rclpy_logging_rcutils_log(level, log.name, text, 'log_line', __file__, _LOG_LINE)
        except (AttributeError, TypeError):   # one call site per severity: rclpy's logger wants that
            if severity == 'info':
                log.info(text)
            elif severity == 'warn':
                log.warning(text)
            else:
                log.error(text)

    def wait_for_command_acked(self, seconds):
        try:
            self._cmd_pub.publisher.wait_for_all_acked(Duration(seconds=seconds))
        except Exception:  # best effort: the process is exiting
            pass

    def diagnostics(self, level, message, values, hardware_id):
        """One status, named after the node's full name: /diagnostics is shared by every namespace."""
        st = DiagnosticStatus(level=bytes([level]), name=f"{self.node.get_fully_qualified_name().lstrip('/')}: "
                              'gravity compensation', message=message, hardware_id=hardware_id)
        st.values = [KeyValue(key=k, value=v) for k, v in values]
        arr = DiagnosticArray(status=[st])
        arr.header.stamp = self.node.get_clock().now().to_msg()
        self._diag_pub.publish(arr)

    def description_publisher_problems(self):
        """[(publisher, log line)] for each publisher of robot_description whose QoS this node
        cannot receive, once per publisher (at most 100 named); the node logs them (its one
        event queue)."""
        node, warned, out = self.node, self._warned_publishers, []
        topic = node.resolve_topic_name('robot_description')
        for info in node.get_publishers_info_by_topic(topic):
            bad = interfaces.description_qos_problems(info.qos_profile)
            who = f'{info.node_namespace.rstrip("/")}/{info.node_name}'
            if bad and who not in warned and len(warned) < 100:
                warned.add(who)
                out.append((who, f"'{topic}' publisher {who} offers {' and '.join(bad)}: this node (like "
                                 "robot_state_publisher's subscribers) needs reliable + transient local, so it will "
                                 'not receive that description'))
        return out


_LOG_LINE = Outputs.log_line.__code__.co_firstlineno   # the call site /rosout names
