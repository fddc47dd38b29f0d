"""~/record through the running node over real DDS (test_node.Harness): the accepted joint_states
with their efforts, written as an mcap rosbag2 folder and read back with
lie_dynamics.calibration.recordings; recording_max_s ends a recording by itself."""
import os

import numpy as np
import pytest

rclpy = pytest.importorskip('rclpy')
pytest.importorskip('rosbags')

from sensor_msgs.msg import JointState  # noqa: E402
from std_srvs.srv import SetBool  # noqa: E402

from lie_dynamics import default_urdf_path  # noqa: E402
from lie_dynamics.calibration.recordings import read_recording  # noqa: E402
from lie_dynamics.ros.core.settings import Settings  # noqa: E402
from lie_dynamics.ros.core.timebase import TimeBase  # noqa: E402
from lie_dynamics.ros.features.recording import Recorder  # noqa: E402
from test_node import wait_until  # noqa: E402

JOINTS = [f'joint{i}' for i in range(1, 8)]
SERVICE = '/dynamics_node/record'



@pytest.fixture(scope='module')
def xml():
    with open(default_urdf_path()) as fh:
        return fh.read()


def record(ros, on):
    res = ros.call(SetBool, SERVICE, SetBool.Request(data=on))
    return res.success, res.message


def send(ros, stamp_ns, q, qd, effort, names=JOINTS):
    msg = JointState(name=list(names), position=[float(x) for x in q], velocity=[float(x) for x in qd],
                     effort=[float(x) for x in effort])
    msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(int(stamp_ns), 10 ** 9)
    ros.publish_msg_processed(msg)


def states(N, seed):
    rng = np.random.default_rng(seed)
    return 0.3 * rng.normal(size=(N, 7)), rng.normal(size=(N, 7)), 10 * rng.normal(size=(N, 7))


def test_record_writes_the_accepted_samples(ros, xml, tmp_path):
    ros.start(robot_description=xml, recording_dir=str(tmp_path / 'recs'))
    assert record(ros, False) == (False, 'not recording')
    ok, text = record(ros, True)
    assert ok and str(tmp_path / 'recs') in text, text
    ok, text = record(ros, True)
    assert not ok and 'already recording' in text
    q, qd, e = states(40, 0)
    t0 = 1_000 * 10 ** 9
    stamps = t0 + 2_000_000 * np.arange(40)
    order = [3, 0, 6, 1, 2, 5, 4]   # the message's joint order differs from the model's
    n0 = len(ros.cmds)
    for k in range(40):
        if k == 10:   # without efforts: accepted and commanded, not recorded
            send(ros, stamps[k], q[k], qd[k], [])
            continue
        send(ros, stamps[k], q[k][order], qd[k][order], e[k][order], names=[JOINTS[i] for i in order])
    wait_until(lambda: len(ros.cmds) - n0 == 40, what='a command per state')
    ok, path = record(ros, False)
    assert ok and path.startswith(str(tmp_path / 'recs')) and '1 samples without efforts left out' in path, path
    folder = path.split(' (')[0]
    assert os.path.isfile(os.path.join(folder, 'metadata.yaml'))
    rec = read_recording(folder)
    keep = np.arange(40) != 10
    assert rec.joint_names == JOINTS and rec.dropped == 0 and len(rec.t) == 39
    np.testing.assert_array_equal(rec.q, q[keep])
    np.testing.assert_array_equal(rec.qd, qd[keep])
    np.testing.assert_array_equal(rec.effort, e[keep])
    assert rec.t0_ns == t0
    np.testing.assert_array_equal(np.round(rec.t * 1e9).astype(np.int64), stamps[keep] - t0)
    assert record(ros, False) == (False, 'not recording')
    assert ros.node.features.get('recording').recorder.written == 1
    # a recording without any effort: refused, nothing written
    assert record(ros, True)[0]
    for k in range(3):
        send(ros, stamps[-1] + (k + 1) * 2_000_000, q[k], qd[k], [])
    ok, text = record(ros, False)
    assert not ok and 'none of the 3 samples recorded has finite efforts' in text, text
    assert len(os.listdir(tmp_path / 'recs')) == 1


def test_recording_max_s_stops_it(ros, xml, tmp_path):
    ros.start(robot_description=xml, recording_dir=str(tmp_path), recording_max_s=0.5)
    ok, _ = record(ros, True)
    assert ok
    q, qd, e = states(12, 1)
    t0 = 5_000 * 10 ** 9
    for k in range(12):   # 0.1 s apart: the sample at 0.5 s ends it, the rest are not recorded
        send(ros, t0 + k * 100_000_000, q[k], qd[k], e[k])
    wait_until(lambda: any('stopped by itself (recording_max_s (0.5 s) reached)' in line for line in ros.logs),
               what='the log line')
    assert not ros.node.features.get('recording').active
    ok, path = record(ros, False)   # the one that stopped by itself: its path, once
    assert ok and path.startswith(str(tmp_path)), path
    rec = read_recording(path)
    assert len(rec.t) == 6
    np.testing.assert_allclose(rec.t, 0.1 * np.arange(6), atol=1e-9)
    np.testing.assert_array_equal(rec.effort, e[:6])
    assert record(ros, False) == (False, 'not recording')


def test_recorder_refuses_without_a_model():
    r = Recorder()
    with pytest.raises(ValueError, match='no robot model loaded'):
        r.begin(None, Settings({'recording_dir': '', 'recording_max_s': 1.0}))
    assert r.stop() is None


def _sample(stamp, names, q=None, effort=(1.0, 2.0)):
    from lie_dynamics.ros.core.sample import SampleResult
    q = np.array([0.1, 0.2]) if q is None else q
    return SampleResult.accept(stamp, q.copy(), _Model(), names, np.array([1, 0]), np.array([3.0, 4.0]),
                               np.asarray(effort, dtype=float))


class _Model:
    version = 0


def test_sample_log_and_recorder_without_ros():
    """The plain part: the message's columns mapped, recording_max_s in stamp time (the steady clock
    for unstamped states), a change of the controlled joints ends a recording."""
    names = ['a', 'b']
    r = Recorder()
    r.begin(names, Settings({'recording_dir': '/nonexistent', 'recording_max_s': 1.0}))
    assert r.add(_sample(5 * 10 ** 9, names)) is None
    assert r.add(_sample(5 * 10 ** 9 + 999_999_999, names, effort=())) is None   # no effort: kept as NaN
    assert r.add(_sample(6 * 10 ** 9, names)) == 'recording_max_s (1 s) reached'
    log = r.stop()
    stamps, _, q, qd, e = (np.concatenate(c) for c in zip(*log.chunks()))
    assert stamps.tolist() == [5 * 10 ** 9, 5 * 10 ** 9 + 999_999_999, 6 * 10 ** 9] and log.size == 3
    assert q[0].tolist() == [0.1, 0.2] and qd[0].tolist() == [4.0, 3.0] and e[0].tolist() == [2.0, 1.0]
    assert np.isnan(e[1]).all()
    r.begin(names, Settings({'recording_dir': '', 'recording_max_s': 0.5}))
    assert r.add(_sample(7 * 10 ** 9, ['a', 'b'])) is None   # an equal list: the same joints
    assert r.add(_sample(7 * 10 ** 9 + 1, ['b', 'a'])) == 'the controlled joints changed'
    now = [0]
    from lie_dynamics.ros.features.recording import SampleLog
    log = SampleLog(names, 0.5, clock=lambda: now[0])
    assert isinstance(log.time, TimeBase)   # the one rule for a sample's time
    for k in range(5000):   # unstamped: the steady clock, 0.1 ms apart; more than one block
        now[0] = 100.0 + k * 1e-4
        if log.add(_sample(0, names)):
            break
    assert k == 5000 - 1 and log.size == 5000 and not log.time.stamped
    now[0] = 100.5
    assert log.add(_sample(0, names))
    assert sum(len(c[0]) for c in log.chunks()) == 5001
