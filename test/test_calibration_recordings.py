"""lie_dynamics.calibration.recordings: rosbag2 folders in both storage formats and trajectory CSVs.

The bags are written here with other tools than the reader (which is `rosbags`): the messages are
serialized by rclpy, the sqlite3 file is made with Python's sqlite3 module in rosbag2's Jazzy
schema, the mcap file with the `mcap` package's writer, and metadata.yaml by hand as rosbag2
writes it. The node's writer (write_joint_states) is read back by the `mcap` reader and rclpy."""
import sqlite3

import numpy as np
import pytest

pytest.importorskip('rclpy')
pytest.importorskip('rosbags')
mcap_writer = pytest.importorskip('mcap.writer')

from rclpy.serialization import deserialize_message, serialize_message  # noqa: E402
from sensor_msgs.msg import JointState  # noqa: E402
from std_msgs.msg import String  # noqa: E402

from lie_dynamics.calibration.recordings import (read_bag, read_csv_recording, read_recording,  # noqa: E402
                                                 write_joint_states)

JOINTS = ['j1', 'j2', 'j3']
T0 = 1_700_000_000_000_000_000   # ns
STEP = 2_000_000                 # ns: 500 Hz
JOINT_STATE_DEF = """std_msgs/Header header
string[] name
float64[] position
float64[] velocity
float64[] effort
================================================================================
MSG: std_msgs/Header
builtin_interfaces/Time stamp
string frame_id
================================================================================
MSG: builtin_interfaces/Time
int32 sec
uint32 nanosec
"""


def samples(N=200, seed=0):
    rng = np.random.default_rng(seed)
    return (T0 + STEP * np.arange(N), rng.normal(size=(N, 3)), rng.normal(size=(N, 3)), rng.normal(size=(N, 3)))


def messages(stamps, q, qd, e, quirks=True):
    """[(log time ns, serialized JointState)]: with quirks, a gripper joint besides the arm's, every
    tenth message in another joint order, message 5 unstamped, message 7 with a NaN position,
    message 9 without efforts."""
    out = []
    for k in range(len(stamps)):
        names, order = JOINTS + ['gripper'], [0, 1, 2]
        if quirks and k % 10 == 3:
            names, order = ['gripper', 'j3', 'j1', 'j2'], [2, 0, 1]
        pos, vel, eff = ([float(x) for x in a[k][order]] for a in (q, qd, e))
        if names[0] == 'gripper':
            pos, vel, eff = [0.01] + pos, [0.0] + vel, [0.5] + eff
        else:
            pos, vel, eff = pos + [0.01], vel + [0.0], eff + [0.5]
        if quirks and k == 7:
            pos[1] = float('nan')
        if quirks and k == 9:
            eff = []
        msg = JointState(name=names, position=pos, velocity=vel, effort=eff)
        stamp = 0 if quirks and k == 5 else int(stamps[k])
        msg.header.stamp.sec, msg.header.stamp.nanosec = stamp // 10 ** 9, stamp % 10 ** 9
        out.append((int(stamps[k]) + 1000, serialize_message(msg)))   # the bag took it 1 us later
    return out


def metadata(storage, file, topics):
    """metadata.yaml as rosbag2 (Jazzy, version 9) writes it; topics: [(name, type, count, t0, t1)]."""
    start = min(t[3] for t in topics)
    end = max(t[4] for t in topics)
    count = sum(t[2] for t in topics)
    entries = ''.join(f"""    - topic_metadata:
        name: {name}
        type: {typ}
        serialization_format: cdr
        offered_qos_profiles: ""
        type_description_hash: ""
      message_count: {n}
""" for name, typ, n, _, _ in topics)
    return f"""rosbag2_bagfile_information:
  version: 9
  storage_identifier: {storage}
  duration:
    nanoseconds: {end - start}
  starting_time:
    nanoseconds_since_epoch: {start}
  message_count: {count}
  topics_with_message_count:
{entries}  compression_format: ""
  compression_mode: ""
  relative_file_paths:
    - {file}
  files:
    - path: {file}
      starting_time:
        nanoseconds_since_epoch: {start}
      duration:
        nanoseconds: {end - start}
      message_count: {count}
  custom_data: ~
  ros_distro: jazzy
"""


def definition(typ):
    return JOINT_STATE_DEF if typ.endswith('JointState') else 'string data\n'


def other_topic():
    return [(T0 + 5, serialize_message(String(data='hello')))]


def write_sqlite3(folder, msgs, extra=()):
    """A rosbag2 sqlite3 folder in the Jazzy schema (version 4), with Python's sqlite3."""
    folder.mkdir()
    db = sqlite3.connect(folder / 'bag_0.db3')
    db.executescript("""
        CREATE TABLE schema(schema_version INTEGER PRIMARY KEY, ros_distro TEXT NOT NULL);
        CREATE TABLE metadata(id INTEGER PRIMARY KEY, metadata_version INTEGER NOT NULL, metadata TEXT NOT NULL);
        CREATE TABLE topics(id INTEGER PRIMARY KEY, name TEXT NOT NULL, type TEXT NOT NULL,
                            serialization_format TEXT NOT NULL, offered_qos_profiles TEXT NOT NULL,
                            type_description_hash TEXT NOT NULL);
        CREATE TABLE message_definitions(id INTEGER PRIMARY KEY, topic_type TEXT NOT NULL, encoding TEXT NOT NULL,
                                         encoded_message_definition TEXT NOT NULL,
                                         type_description_hash TEXT NOT NULL);
        CREATE TABLE messages(id INTEGER PRIMARY KEY, topic_id INTEGER NOT NULL, timestamp INTEGER NOT NULL,
                              data BLOB NOT NULL);
        INSERT INTO schema VALUES (4, 'jazzy');""")
    topics = [('/joint_states', 'sensor_msgs/msg/JointState', msgs)] + list(extra)
    info = []
    for tid, (name, typ, rows) in enumerate(topics, start=1):
        db.execute('INSERT INTO topics VALUES (?, ?, ?, ?, ?, ?)', (tid, name, typ, 'cdr', '', ''))
        db.execute('INSERT INTO message_definitions VALUES (?, ?, ?, ?, ?)', (tid, typ, 'ros2msg', definition(typ), ''))
        db.executemany('INSERT INTO messages(topic_id, timestamp, data) VALUES (?, ?, ?)',
                       [(tid, ts, data) for ts, data in rows])
        info.append((name, typ, len(rows), rows[0][0], rows[-1][0]))
    db.commit()
    db.close()
    (folder / 'metadata.yaml').write_text(metadata('sqlite3', 'bag_0.db3', info))
    return folder


def write_mcap(folder, msgs, extra=()):
    """A rosbag2 mcap folder with the `mcap` package's writer (zstd chunks, as rosbag2's default)."""
    folder.mkdir()
    topics = [('/joint_states', 'sensor_msgs/msg/JointState', msgs)] + list(extra)
    info = []
    with open(folder / 'bag_0.mcap', 'wb') as fh:
        w = mcap_writer.Writer(fh)
        w.start(profile='ros2', library='test')
        for name, typ, rows in topics:
            schema = w.register_schema(name=typ, encoding='ros2msg', data=definition(typ).encode())
            channel = w.register_channel(topic=name, message_encoding='cdr', schema_id=schema)
            for seq, (ts, data) in enumerate(rows):
                w.add_message(channel, log_time=ts, data=data, publish_time=ts, sequence=seq)
            info.append((name, typ, len(rows), rows[0][0], rows[-1][0]))
        w.finish()
    (folder / 'metadata.yaml').write_text(metadata('mcap', 'bag_0.mcap', info))
    return folder


WRITERS = {'sqlite3': write_sqlite3, 'mcap': write_mcap}


@pytest.mark.parametrize('storage', sorted(WRITERS))
def test_bag_read_back(tmp_path, storage):
    stamps, q, qd, e = samples()
    bag = WRITERS[storage](tmp_path / 'bag', messages(stamps, q, qd, e), [('/other', 'std_msgs/msg/String',
                                                                             other_topic())])
    rec = read_recording(bag, joints=JOINTS)
    keep = np.setdiff1d(np.arange(len(stamps)), [7, 9])   # a NaN position, no efforts
    assert rec.dropped == 2 and rec.messages == len(stamps) and rec.joint_names == JOINTS
    np.testing.assert_array_equal(rec.q, q[keep])
    np.testing.assert_array_equal(rec.qd, qd[keep])
    np.testing.assert_array_equal(rec.effort, e[keep])
    expect = stamps[keep].copy()
    expect[keep == 5] += 1000   # unstamped: the time the bag took it
    assert rec.t0_ns == T0
    np.testing.assert_allclose(rec.t, (expect - T0) * 1e-9, rtol=0, atol=1e-12)
    # every joint the messages name, in the order they first appear
    everything = read_bag(bag)
    assert everything.joint_names == JOINTS + ['gripper'] and np.all(everything.q[:, 3] == 0.01)


@pytest.mark.parametrize('storage', sorted(WRITERS))
def test_bag_bad_input(tmp_path, storage):
    stamps, q, qd, e = samples(50)
    bag = WRITERS[storage](tmp_path / 'bag', messages(stamps, q, qd, e), [('/other', 'std_msgs/msg/String',
                                                                             other_topic())])
    with pytest.raises(ValueError, match=r"no topic '/arm/joint_states'; the bag has /joint_states "
                                         r"\(sensor_msgs/msg/JointState\), /other \(std_msgs/msg/String\)"):
        read_recording(bag, topic='/arm/joint_states')
    with pytest.raises(ValueError, match="topic '/other' holds std_msgs/msg/String, not sensor_msgs/msg/JointState"):
        read_recording(bag, topic='/other')
    no_effort = [(ts, serialize_message(JointState(name=JOINTS, position=[0.0] * 3))) for ts, _ in
                 messages(stamps, q, qd, e)]
    bare = WRITERS[storage](tmp_path / 'bare', no_effort)
    with pytest.raises(ValueError, match='efforts are required'):
        read_recording(bare)
    # without velocities in one message, none are returned (they are derived from the positions)
    msgs = messages(stamps, q, qd, e, quirks=False)
    msgs[3] = (msgs[3][0], serialize_message(JointState(name=JOINTS, position=[1.0] * 3, effort=[2.0] * 3)))
    rec = read_recording(WRITERS[storage](tmp_path / 'novel', msgs), joints=JOINTS)
    assert rec.qd is None and rec.dropped == 0 and rec.q[3].tolist() == [1.0] * 3


def test_not_a_bag(tmp_path):
    (tmp_path / 'empty').mkdir()
    with pytest.raises(ValueError, match='no metadata.yaml, not a rosbag2 folder'):
        read_recording(tmp_path / 'empty')
    with pytest.raises(ValueError, match='no such file or folder'):
        read_recording(tmp_path / 'missing.csv')
    (tmp_path / 'x.mcap').write_bytes(b'')
    with pytest.raises(ValueError, match='give the rosbag2 folder'):
        read_recording(tmp_path / 'x.mcap')


def test_csv_recording(tmp_path):
    path = tmp_path / 'rec.csv'
    path.write_text('time,pos.a,pos.b,vel.a,vel.b,eff.a,eff.b\n'
                    '0.0,0.1,0.2,1,2,5,6\n0.01,0.11,0.21,1,2,5.5,6.5\n0.02,nan,0.22,1,2,5,6\n0.03,0.13,0.23,1,2,5,6\n')
    rec = read_recording(path)
    assert rec.joint_names == ['a', 'b'] and rec.dropped == 1 and rec.messages == 4
    np.testing.assert_allclose(rec.t, [0.0, 0.01, 0.03])
    np.testing.assert_allclose(rec.effort, [[5, 6], [5.5, 6.5], [5, 6]])
    np.testing.assert_allclose(rec.qd, [[1, 2]] * 3)
    assert read_csv_recording(path, joints=['b']).q[:, 0].tolist() == [0.2, 0.21, 0.22, 0.23]   # a's NaN: kept
    bad = tmp_path / 'noeff.csv'
    bad.write_text('time,pos.a,pos.b,eff.a\n0,0,0,1\n1,0,0,1\n')
    with pytest.raises(ValueError, match=r"efforts are required: the CSV needs an eff.<joint> column .* \['a', 'b'\]"):
        read_recording(bad)


def test_written_bag_read_by_other_tools(tmp_path):
    """The node's writer: an mcap rosbag2 folder that the mcap reader and rclpy read as written,
    and read_recording reads back."""
    from mcap.reader import make_reader

    stamps, q, qd, e = samples(30)
    qd = qd.copy()
    qd[4] = np.nan   # written without velocities
    folder = tmp_path / 'rec'
    assert write_joint_states(folder, JOINTS, stamps, q, qd, e, log_ns=stamps + 7) == 30
    files = sorted(p.name for p in folder.iterdir())
    assert 'metadata.yaml' in files and any(f.endswith('.mcap') for f in files)
    with open(folder / next(f for f in files if f.endswith('.mcap')), 'rb') as fh:
        got = [(ch.topic, schema.name, m.log_time, deserialize_message(m.data, JointState))
               for schema, ch, m in make_reader(fh).iter_messages()]
    assert len(got) == 30 and {g[:2] for g in got} == {('/joint_states', 'sensor_msgs/msg/JointState')}
    for k, (_, _, log, msg) in enumerate(got):
        assert log == stamps[k] + 7 and list(msg.name) == JOINTS
        assert msg.header.stamp.sec * 10 ** 9 + msg.header.stamp.nanosec == stamps[k]
        assert list(msg.position) == q[k].tolist() and list(msg.effort) == e[k].tolist()
        assert list(msg.velocity) == ([] if k == 4 else qd[k].tolist())
    rec = read_recording(folder)
    assert rec.qd is None and rec.dropped == 0
    np.testing.assert_array_equal(rec.q, q)
    with pytest.raises(ValueError, match='exists already'):
        write_joint_states(folder, JOINTS, stamps, q, qd, e)
