"""trajectory_source's `file` parameter: a trajectory CSV played as desired states (one per
joint_states) or as one JointTrajectory for a joint_trajectory_controller, over real DDS."""
import threading

import numpy as np
import pytest

rclpy = pytest.importorskip('rclpy')

from rclpy.context import Context  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from sensor_msgs.msg import JointState  # noqa: E402
from trajectory_msgs.msg import JointTrajectory  # noqa: E402

from lie_dynamics.sim.trajectory_source import FileTrajectory, TrajectorySource  # noqa: E402
from lie_dynamics.trajectory import write_csv  # noqa: E402
from test_node import wait_until  # noqa: E402

NAMES = ['a', 'b']


def analytic(t):
    w = np.array([1.0, 2.0])
    return (np.sin(np.outer(t, w)), np.cos(np.outer(t, w)) * w, -np.sin(np.outer(t, w)) * w ** 2)


@pytest.fixture
def csv_file(tmp_path):
    t = np.linspace(0.0, 2.0, 201)
    q, qd, qdd = analytic(t)
    path = tmp_path / 'traj.csv'
    write_csv(path, {'time_from_start': t + 3.0}, {'positions': q, 'velocities': qd, 'accelerations': qdd,
                                                   'efforts': np.zeros_like(q)}, NAMES)
    return path


def test_file_trajectory_interpolates_and_derives(tmp_path, csv_file):
    f = FileTrajectory(csv_file)
    assert f.names == NAMES and f.duration == pytest.approx(2.0)   # times from the first point
    q, qd, qdd = f.state(0.5)   # a CSV point: its row exactly
    np.testing.assert_allclose(np.concatenate([q, qd, qdd]), np.concatenate([a[0] for a in analytic([0.5])]),
                               atol=1e-12)
    q, _, _ = f.state(0.505)   # between two points: linear
    np.testing.assert_allclose(q, 0.5 * (analytic([0.5])[0][0] + analytic([0.51])[0][0]), atol=1e-12)
    for t, k in ((-1.0, 0), (5.0, -1)):   # held at rest before and after
        q, qd, qdd = f.state(t)
        assert np.array_equal(q, f.q[k]) and not qd.any() and not qdd.any()
    only_pos = tmp_path / 'pos.csv'
    only_pos.write_text('time,pos.a\n' + ''.join(f'{t},{t * t}\n' for t in np.linspace(0, 1, 11)))
    g = FileTrajectory(only_pos)
    np.testing.assert_allclose(g.qd[:, 0], 2 * g.t, atol=1e-12)   # the derivative rule of trajectory.py
    bad = tmp_path / 'bad.csv'
    bad.write_text('time,pos.a\n0,0\n1,0\n0.5,0\n')
    with pytest.raises(ValueError, match='times must increase strictly'):
        FileTrajectory(bad)


class Ros:
    def __init__(self):
        self.ctx = Context()
        rclpy.init(context=self.ctx)
        self.ex = SingleThreadedExecutor(context=self.ctx)
        self.t = rclpy.create_node('file_tester', context=self.ctx)
        self.ex.add_node(self.t)
        self.got = []
        self.thread = threading.Thread(target=self._spin, daemon=True)
        self.thread.start()

    def _spin(self):
        try:
            self.ex.spin()
        except Exception:  # noqa: BLE001 - shut down in close()
            pass

    def source(self, **params):
        node = TrajectorySource(context=self.ctx, parameter_overrides=[Parameter(k, value=v)
                                                                         for k, v in params.items()])
        self.ex.add_node(node)
        return node

    def close(self):
        self.ex.shutdown(timeout_sec=2.0)
        rclpy.shutdown(context=self.ctx)
        self.thread.join(timeout=5.0)


@pytest.fixture
def ros():
    r = Ros()
    yield r
    r.close()


def test_file_as_desired_states(ros, csv_file):
    got = []
    ros.t.create_subscription(JointTrajectory, '/test/desired', got.append, 10)
    js = ros.t.create_publisher(JointState, 'joint_states', 10)
    ros.source(file=str(csv_file), desired_topic='/test/desired', lead=0.001, start_after=0.25, min_subscribers=1)
    f = FileTrajectory(csv_file)
    wait_until(lambda: js.get_subscription_count() >= 1, what='discovery')
    for k, t in enumerate((100.0, 100.2, 100.5, 100.999, 104.0)):   # the first stamp starts the clock
        msg = JointState(name=['x'])
        msg.header.stamp.sec, msg.header.stamp.nanosec = int(t), int(round((t - int(t)) * 1e9))
        js.publish(msg)
        wait_until(lambda k=k: len(got) > k, what='a desired state')
    for msg, t in zip(got, (100.0, 100.2, 100.5, 100.999, 104.0)):
        assert list(msg.joint_names) == NAMES and len(msg.points) == 1
        p = msg.points[0]
        want = f.state(t + 0.001 - 100.25)
        for have, w in zip((p.positions, p.velocities, p.accelerations), want):
            np.testing.assert_allclose(have, w, atol=1e-12)
    np.testing.assert_allclose(got[3].points[0].positions, analytic([0.75])[0][0], atol=1e-12)
    np.testing.assert_allclose(got[4].points[0].positions, f.q[-1], atol=0)   # after the end: the last point


def test_file_to_a_joint_trajectory_controller(ros, csv_file):
    got = []
    ros.t.create_subscription(JointTrajectory, '/arm/joint_trajectory_controller/joint_trajectory', got.append, 10)
    ros.source(file=str(csv_file), file_output='controller',
               controller_topic='/arm/joint_trajectory_controller/joint_trajectory', start_after=0.5)
    wait_until(lambda: got, what='the trajectory')
    msg = got[0]
    f = FileTrajectory(csv_file)
    assert list(msg.joint_names) == NAMES and len(msg.points) == len(f.t)
    times = np.array([p.time_from_start.sec + 1e-9 * p.time_from_start.nanosec for p in msg.points])
    np.testing.assert_allclose(times, f.t + 0.5, atol=1e-9)
    np.testing.assert_array_equal(np.array([p.positions for p in msg.points]), f.q)
    np.testing.assert_array_equal(np.array([p.accelerations for p in msg.points]), f.qdd)
    assert msg.header.stamp.sec == 0 and msg.header.stamp.nanosec == 0   # start on arrival


def test_bad_file_parameters(ros, tmp_path, csv_file):
    with pytest.raises(ValueError, match='file_output must be one of'):
        ros.source(file=str(csv_file), file_output='jtc')
    with pytest.raises(ValueError, match='start_after must be finite and >= 0'):
        ros.source(file=str(csv_file), start_after=-1.0)
    with pytest.raises(ValueError, match='no_such.csv'):
        ros.source(file=str(tmp_path / 'no_such.csv'))
