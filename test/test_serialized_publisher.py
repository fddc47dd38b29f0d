"""interfaces.SerializedPublisher (the observer's topics: publish_raw through the handle held in
use): a subscriber receives exactly the bytes given, the same message as rclpy's own publish of
the message object; the rcl publisher outlives destroy_publisher until close(), and publishing
after both raises instead of touching a freed publisher."""
import time

import pytest

pytest.importorskip('rclpy')
import rclpy  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.serialization import deserialize_message, serialize_message  # noqa: E402
from sensor_msgs.msg import JointState  # noqa: E402

from lie_dynamics.ros import interfaces  # noqa: E402


def _spin_until(executor, pred, timeout=10.0):
    end = time.monotonic() + timeout
    while time.monotonic() < end and not pred():
        executor.spin_once(timeout_sec=0.01)
    assert pred(), 'timed out'


def test_serialized_publisher_sends_the_bytes_given_and_holds_the_publisher_until_closed():
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    node = rclpy.create_node('serialized_publisher_test', context=ctx)
    ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(node)
    try:
        got = []
        pub = interfaces.serialized_publisher(node, '~/external_torques')
        node.create_subscription(JointState, '~/external_torques', got.append,
                                 pub.publisher.qos_profile, raw=True)
        _spin_until(ex, lambda: pub.publisher.get_subscription_count() >= 1)
        msg = JointState(name=['a', 'joint_b'], effort=[1.5, -2.25e-300])
        msg.header.stamp.sec, msg.header.stamp.nanosec = 17, 999_999_999
        data = bytes(serialize_message(msg))
        pub.publish(data)
        pub.publisher.publish(msg)   # rclpy's own path, for the same message
        _spin_until(ex, lambda: len(got) == 2)
        assert got[0] == data
        for raw in got:
            back = deserialize_message(raw, JointState)
            assert back.name == msg.name and list(back.effort) == list(msg.effort)
            assert (back.header.stamp.sec, back.header.stamp.nanosec) == (17, 999_999_999)
        # destroyed while held: still published; after close() the publisher goes and publishing raises
        node.destroy_publisher(pub.publisher)
        pub.publish(data)
        pub.close()
        pub.close()   # idempotent
        with pytest.raises(Exception, match='publisher'):
            pub.publish(data)
    finally:
        ex.shutdown()
        node.destroy_node()
        rclpy.shutdown(context=ctx)
