"""calibration_file set over real DDS on the running node (rclpy's parameter client, as `ros2
param set` uses the node's parameter services): the published gravity command follows the
calibrated model, and a bad file is refused with the old values kept."""
import numpy as np
import pytest

rclpy = pytest.importorskip('rclpy')

from rclpy.parameter import Parameter  # noqa: E402

from lie_dynamics import default_urdf_path, load_urdf  # noqa: E402
from test_node import TIMEOUT, wait_until  # noqa: E402
from test_node_calibration import calibration_of  # noqa: E402

JOINTS = [f'joint{i}' for i in range(1, 8)]



def test_calibration_file_over_dds(ros, tmp_path):
    from rclpy.parameter_client import AsyncParameterClient
    with open(default_urdf_path()) as fh:
        xml = fh.read()
    arm = load_urdf(xml)
    path = str(calibration_of(arm, seed=2).save(tmp_path / 'calibration.yaml'))
    node = ros.start(robot_description=xml)
    params = AsyncParameterClient(ros.t, '/dynamics_node')
    assert params.wait_for_services(timeout_sec=TIMEOUT)

    def set_file(value):
        fut = params.set_parameters([Parameter('calibration_file', value=value)])
        wait_until(fut.done, what='set_parameters')
        return fut.result().results[0]

    q, zero = np.array([0.4, -0.3, 0.1, 1.2, 0.5, 0.3, -0.6]), np.zeros(7)
    np.testing.assert_allclose(ros.send(JOINTS, q, zero), arm.gravity(q), atol=1e-9, rtol=0)
    assert set_file(path).successful
    want = arm.with_calibration(path).gravity(q)
    assert np.max(np.abs(want - arm.gravity(q))) > 0.1
    np.testing.assert_allclose(ros.send(JOINTS, q, zero), want, atol=1e-9, rtol=0)
    # a bad file: refused with the reason, the calibration kept
    (tmp_path / 'bad.yaml').write_text('a: 1\n')
    answer = set_file(str(tmp_path / 'bad.yaml'))
    assert not answer.successful and 'not a calibration file' in answer.reason, answer.reason
    assert node.get_parameter('calibration_file').value == path
    np.testing.assert_allclose(ros.send(JOINTS, q, zero), want, atol=1e-9, rtol=0)
