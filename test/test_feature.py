"""The per-sample feature interface (ros/features/base.py) with a real Compensator, and the rate gate of
the dynamics topics and their serialized message templates, without DDS."""
import numpy as np
import pytest

from lie_dynamics import default_urdf_path
from lie_dynamics.ros.core.cdr import JointStateSample
from lie_dynamics.ros.core.compensator import Compensator
from lie_dynamics.ros.features.base import Feature, Features

JOINTS = [f'joint{i}' for i in range(1, 8)]


class Recorder(Feature):
    name = 'recorder'

    def __init__(self):
        super().__init__()
        self.samples, self.configured = [], 0

    def check(self, settings, model):
        if settings['dynamics.link'] == 'refused':
            raise ValueError('refused link')

    def configure(self, settings, model, derived):
        self.configured += 1
        self.active = model is not None and settings['dynamics.rate'] > 0

    def on_sample(self, s):
        self.samples.append((s.q.copy(), s.qd.copy(), s.effort.copy(), s.stamp, s.version, s.velocity.copy()))
        self.events.append(('info', 'recorder', f'sample {s.stamp}'))

    def report(self, level, message):
        return max(level, 1), message + '; recorded', [('recorder_samples', str(len(self.samples)))]


def sample(q, qd=(), effort=(), stamp=0, names=JOINTS):
    return JointStateSample(stamp, tuple(names), np.asarray(q, float), np.asarray(qd, float),
                            np.asarray(effort, float))


def test_features_get_each_accepted_sample_once_in_model_order():
    core = Compensator({'stale_timeout': 60.0, 'ramp_time': 0.0})
    rec = Recorder()
    feats = Features([rec], events=core.events)
    core.on_sample(sample(np.zeros(7)))
    feats.feed(core)                                       # no model: nothing accepted, nothing fed
    assert core.result.reason == 'no_model' and not rec.samples
    core.load(default_urdf_path())
    q = np.linspace(-0.5, 0.5, 7)
    order = JOINTS[::-1]
    s = sample(q[::-1], [np.nan] + list(np.arange(6.0))[::-1], np.arange(7.0)[::-1], stamp=5, names=order)
    assert core.on_sample(s) is not None
    feats.feed(core)
    assert rec.configured == 2 and len(rec.samples) == 1
    fq, fqd, fe, stamp, version, fv = rec.samples[0]
    assert np.isnan(fv[-1]) and np.array_equal(fv[:-1], fqd[:-1])   # as sent, in model order
    assert np.array_equal(fq, q) and stamp == 5 and version == core.model.version
    assert np.array_equal(fqd, [0.0, 1.0, 2.0, 3.0, 4.0, 5.0, 0.0])   # reversed back; NaN as 0
    assert np.array_equal(fe, np.arange(7.0))
    feats.feed(core)                                       # the same result again: not fed again
    bad = sample(np.full(7, np.nan), stamp=6)
    core.on_sample(bad)
    feats.feed(core)                                       # rejected: not fed
    assert len(rec.samples) == 1 and core.result.reason == 'nonfinite' and not core.result.accepted
    events = feats.drain()   # one queue: the core's rejection and the feature's line, in order
    assert ('info', 'recorder', 'sample 5') in events and events[-1][1] == 'reject:nonfinite'
    assert not feats.events and core.events is feats.events
    assert feats.report(0, 'ok', [('core', 'x')]) == (1, 'ok; recorded', [('core', 'x'), ('recorder_samples', '1')])
    # switched off by a setting: no call at all, and a rejection while off is not fed afterwards
    core.update({'dynamics.rate': 0.0})
    core.on_sample(sample(q, stamp=7))
    feats.feed(core)
    core.on_sample(sample(np.full(7, np.nan), stamp=8))
    feats.feed(core)
    assert rec.active is False and len(rec.samples) == 1
    core.update({'dynamics.rate': 10.0})
    feats.feed(core)
    assert len(rec.samples) == 1
    with pytest.raises(ValueError, match='refused link'):
        feats.check(core.settings.replace({'dynamics.link': 'refused'}), core.model)


def test_rate_gate_keeps_the_average_rate_and_restarts_on_a_new_stream():
    pytest.importorskip('rclpy')
    from lie_dynamics.ros.features.dynamics_topics import RateGate
    ms = 1_000_000
    gate = RateGate(100.0)
    passed = [k for k in range(100) if gate.passes(k * ms)]
    assert passed == list(range(0, 100, 10))
    jitter = RateGate(100.0)   # stamps 1 ms apart with +-0.3 ms jitter: still every tenth on average
    rng = np.random.default_rng(0)
    t = np.arange(1000) * ms + rng.integers(-300_000, 300_000, 1000)
    assert 99 <= sum(jitter.passes(int(x)) for x in t) <= 101
    assert gate.passes(5 * ms)                     # back in time: a new stream starts at once
    assert not gate.passes(6 * ms) and gate.passes(15 * ms)
    assert gate.passes(10_000 * ms) and not gate.passes(10_001 * ms)   # after a gap: from there
    every = RateGate(0.0)
    assert all(every.passes(0) for _ in range(5))


@pytest.mark.parametrize('names', [['joint1', 'j2é', 'a_longer_joint_name_3'], ['x'], []])
def test_serialized_templates_read_back_as_the_messages(names):
    pytest.importorskip('rclpy')
    from rclpy.serialization import deserialize_message
    from sensor_msgs.msg import JointState
    from std_msgs.msg import Float64MultiArray
    from lie_dynamics.ros.core.cdr import joint_state_template
    from lie_dynamics.ros.features.dynamics_topics import matrix_template
    n = len(names)
    rng = np.random.default_rng(1)
    q, qd, e = rng.normal(size=(3, n))
    t, stamp_at, slots = joint_state_template(names)
    ns = 1_700_000_000 * 10 ** 9 + 123_456_789
    msg = deserialize_message(t.fill(slots, (q, qd, e), stamp_at, ns), JointState)
    assert (msg.header.stamp.sec, msg.header.stamp.nanosec, msg.header.frame_id) == (1_700_000_000, 123_456_789, '')
    assert list(msg.name) == names
    assert np.array_equal(msg.position, q) and np.array_equal(msg.velocity, qd) and np.array_equal(msg.effort, e)
    A = rng.normal(size=(6, n))
    t, slots = matrix_template('rows: vx,vy,vz,wx,wy,wz; frame: local; link: tool0', 'cols: ' + ','.join(names), 6, n)
    msg = deserialize_message(t.fill(slots, (A,)), Float64MultiArray)
    rows, cols = msg.layout.dim
    assert (rows.label, rows.size, rows.stride) == ('rows: vx,vy,vz,wx,wy,wz; frame: local; link: tool0', 6, 6 * n)
    assert (cols.label, cols.size, cols.stride, msg.layout.data_offset) == ('cols: ' + ','.join(names), n, n, 0)
    assert np.array_equal(np.asarray(msg.data).reshape(6, n), A)
