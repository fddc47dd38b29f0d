"""DynamicsNode.settle, which run.py calls before the node serves (node.py: TRAJECTORIES_JOIN_S):
over real DDS it returns True once the node has discovered its trajectory process's
subscription; it does not wait without a trajectory process, and gives up (False) on its
timeout, on a stop signal or when the process is gone."""
import os

import pytest

rclpy = pytest.importorskip('rclpy')

from lie_dynamics import default_urdf_path  # noqa: E402
from test_node import MODEL_TIMEOUT, Harness  # noqa: E402


@pytest.fixture
def node():
    h = Harness()
    n = h.start(urdf_path=default_urdf_path())
    yield n
    h.close()


class _Child:
    """Stands in for the node's TrajectoryProcess: its topic has no subscriber."""

    def __init__(self, pid):
        self.config = {'topic_in': '/nobody_subscribes_to_this'}
        self.pid = pid


def test_settle_waits_for_the_trajectory_process(node):
    assert node.settle(timeout=MODEL_TIMEOUT) is True
    assert node.count_subscribers(node.background.trajectories.config['topic_in']) >= 1


def test_settle_without_a_trajectory_process_or_on_timeout(node):
    real = node.background.trajectories
    try:
        node.background.trajectories = None
        assert node.settle(timeout=0.0) is True
        node.background.trajectories = _Child(pid=None)   # gone: no wait
        assert node.settle(timeout=MODEL_TIMEOUT) is False
        node.background.trajectories = _Child(pid=os.getpid())   # alive, never discovered: the timeout
        assert node.settle(timeout=0.05) is False
        assert node.settle(timeout=MODEL_TIMEOUT, cancel=lambda: True) is False   # a stop signal
    finally:
        node.background.trajectories = real
