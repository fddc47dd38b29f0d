"""contact.py without ROS: effort conventions, hold-time debouncing, the monitor's pauses and
re-initialisations, against Pinocchio-made efforts with a known external torque."""
import glob
import math
import os
import sys
import warnings
import zlib

import numpy as np
import pytest

from lie_dynamics import default_urdf_path, load_urdf
from lie_dynamics.algorithms.observer import MomentumObserver
from lie_dynamics.laws import friction_torque, make_friction
from lie_dynamics.ros.features.contact import (MAX_GAP_S, ContactMonitor, Debounce, check_settings, motor_torque,
                                      thresholds)
from lie_dynamics.ros.core.diagnostics import OK, WARN
from lie_dynamics.ros.core.params import check_value
from lie_dynamics.ros.core.settings import Settings
from lie_dynamics.ros.core.sample import SampleResult
from oracle import Oracle

XML = open(default_urdf_path()).read()
JOINTS = [f'joint{i}' for i in range(1, 8)]
DT = 1e-3
MS = 1_000_000  # ns


@pytest.fixture(scope='module')
def oracle():
    return Oracle(XML, joints=JOINTS)


@pytest.fixture
def model():
    return load_urdf(XML)


def settings(**changes):
    return Settings({k.replace('__', '.'): v for k, v in changes.items()})


def motion(t):
    """A smooth motion with exact derivatives."""
    a, w = np.linspace(0.2, 0.5, 7), np.linspace(1.0, 2.0, 7)
    return (np.array([0.0, -0.6, 0.0, 2.0, 0.0, 1.6, 0.8]) + a * np.sin(w * t), a * w * np.cos(w * t),
            -a * w * w * np.sin(w * t))


def monitor(model, **changes):
    m = ContactMonitor(clock=lambda: 0.0)
    m.adopt(settings(**changes), model, None, JOINTS)
    return m


def feed(mon, oracle, k, ext=None, effort=None, velocity=None, stamp=None):
    """Sample k (time k ms): efforts = Pinocchio's inverse dynamics minus ext (the motors supply
    what the contact does not)."""
    q, qd, qdd = motion(k * DT)
    if effort is None:
        effort = oracle.rnea(q, qd, qdd) - (0.0 if ext is None else ext)
    return mon.on_sample(accepted(mon, q, qd if velocity is None else velocity, effort,
                                  k * MS + 5 * 10 ** 18 if stamp is None else stamp))


def accepted(mon, q, velocity, effort, stamp, columns=None):
    """The core's SampleResult of a joint_states message with these arrays (message order:
    `columns` maps them to model order; default the same order), as ContactTopics hands it on."""
    q = np.array(q, dtype=float)
    columns = np.arange(len(q)) if columns is None else columns
    return SampleResult.accept(stamp, q, mon.model, mon.layout, columns, np.asarray(velocity, dtype=float),
                               np.asarray(effort, dtype=float))


def test_motor_torque_conventions(model, oracle):
    q = np.linspace(-1.0, 1.0, 7)
    e = np.arange(7.0)
    np.testing.assert_array_equal(motor_torque(model, q, e, 'total'), e)
    np.testing.assert_allclose(motor_torque(model, q, e, 'gravity_removed'), e + oracle.gravity(q), atol=1e-9, rtol=0)
    assert motor_torque(model, q, e, 'none') is None
    with pytest.raises(ValueError, match='measured_effort must be one of'):
        motor_torque(model, q, e, 'motor')


def test_thresholds_and_settings_checks():
    np.testing.assert_array_equal(thresholds([2.0], 3), [2.0, 2.0, 2.0])
    np.testing.assert_array_equal(thresholds([1.0, 2.0, 3.0], 3), [1.0, 2.0, 3.0])
    for bad, msg in (([1.0, 2.0], '1 or 3 values'), ([0.0], '> 0'), ([math.nan], '> 0')):
        with pytest.raises(ValueError, match=msg):
            thresholds(bad, 3)
    check_settings(settings(collision__threshold=[1.0, 2.0]), None)  # joint count not known yet: later
    with pytest.raises(ValueError, match='collision.threshold'):
        check_settings(settings(collision__threshold=[1.0, 2.0]), 7)
    for name, value in (('collision.threshold', [-1.0]), ('collision.threshold', []), ('measured_effort', 'raw'),
                        ('observer.gain', 0.0), ('collision.hold_time', -0.1)):
        with pytest.raises(ValueError, match=name):
            check_value(name, value)


def test_debounce_ignores_glitches_shorter_than_the_hold_time():
    d = Debounce(0.01)
    assert not d.update(True, 0.0) and not d.update(True, 0.009) and not d.update(False, 0.0095)
    assert d.state is False
    assert not d.update(True, 0.02) and d.update(True, 0.03) and d.state is True   # held 10 ms
    assert not d.update(False, 0.031) and not d.update(True, 0.035)                 # a short dip
    assert not d.update(False, 0.04) and d.update(False, 0.05) and d.state is False
    d0 = Debounce(0.0)
    assert d0.update(True, 1.0) and d0.state and d0.update(False, 1.0) and not d0.state


def test_step_converges_and_flags_within_the_hold_time(model, oracle):
    gain, hold, thr = 50.0, 0.01, 3.0
    mon = monitor(model, observer__gain=gain, collision__hold_time=hold, collision__threshold=[thr])
    step = np.array([0.0, 6.0, 0.0, -4.0, 0.0, 1.0, 0.0])
    on, n = 300, 700
    flags, est = [], []
    for k in range(n):
        r, flag = feed(mon, oracle, k, ext=step if k >= on else None)
        flags.append(flag)
        est.append(r)
    est = np.array(est)
    assert np.abs(est[:on]).max() < 1e-6          # free motion: integration error only
    assert not any(flags[:on])                     # no false alarm
    np.testing.assert_allclose(est[-1], step, atol=1e-3 * np.abs(step).max())
    # first sample beyond the threshold (joint 2), then the flag exactly hold_time later
    cross = on + int(np.argmax(np.abs(est[on:, 1]) > thr))
    first = flags.index(True)
    assert first == cross + round(hold / DT), (cross, first)
    assert mon.collision_events == 1 and any('collision' in e[2] and 'joint2' in e[2] for e in mon.events)
    level, message, values = mon.report(OK, 'compensating', [])
    v = dict(values)
    assert level == WARN and 'collision' in message
    assert v['collision'] == 'True' and v['external_torque_max_joint'] == 'joint2'
    assert abs(float(v['external_torque_max']) - 6.0) < 0.05
    # the contact ends: the flag falls after the hold time below the thresholds
    for k in range(n, n + 300):
        r, flag = feed(mon, oracle, k)
    assert not flag and np.abs(r).max() < 1e-3


def test_gravity_removed_efforts_give_the_same_estimate(model, oracle):
    step = np.linspace(-2.0, 2.0, 7)
    a, b = monitor(model), monitor(model, measured_effort='gravity_removed')
    for k in range(200):
        q, qd, qdd = motion(k * DT)
        tau = oracle.rnea(q, qd, qdd) - (step if k > 50 else 0.0)
        ra = feed(a, oracle, k, effort=tau)[0]
        rb = feed(b, oracle, k, effort=tau - oracle.gravity(q))[0]
        np.testing.assert_allclose(ra, rb, atol=1e-9, rtol=0)
    assert np.abs(ra - step).max() < 0.01 * np.abs(step).max()


def test_bad_efforts_pause_and_reinitialise(model, oracle):
    mon = monitor(model)
    step = np.full(7, 2.0)
    assert feed(mon, oracle, 0, effort=[]) is None                  # no efforts yet: waiting, no fault
    assert mon.state == 'waiting for efforts' and mon.resets == 0
    for k in range(1, 200):
        r, _ = feed(mon, oracle, k, ext=step)
    assert np.abs(r - step).max() < 0.01
    effort = np.full(7, 1.0)
    effort[3] = math.nan
    assert feed(mon, oracle, 200, effort=effort) is None
    assert mon.effort_unavailable == 2 and mon.resets == 1 and mon.state.startswith('paused')
    assert any("non-finite effort for ['joint4']" in e[2] for e in mon.events)
    r, _ = feed(mon, oracle, 201, ext=step)                          # a new integral: starts at 0
    assert np.all(r == 0) and mon.state == 'running'
    assert feed(mon, oracle, 202, effort=[]) is None                 # efforts stopped: a fault now
    assert mon.resets == 2 and mon.effort_unavailable == 3
    qd = motion(203 * DT)[1]
    qd[0] = math.nan
    assert feed(mon, oracle, 203, velocity=qd, ext=step) is None     # p needs the velocities
    assert mon.resets == 3
    assert np.all(feed(mon, oracle, 204, ext=step)[0] == 0)
    assert feed(mon, oracle, 204, ext=step) is None                  # the same state again: nothing new
    for bad in ([1e308] * 7, [math.inf] * 7):                        # never a non-finite estimate out
        out = feed(mon, oracle, 205, effort=bad)
        assert out is None or np.all(np.isfinite(out[0]))
    level, message, values = mon.report(OK, '', [])
    assert dict(values)['effort_unavailable_count'] == '4' and level == WARN


def test_time_going_back_or_a_gap_restarts_the_integral(model, oracle):
    mon = monitor(model)
    step = np.full(7, 2.0)
    for k in range(100):
        r, _ = feed(mon, oracle, k, ext=step)
    assert np.abs(r).max() > 1.0
    r, _ = feed(mon, oracle, 50, ext=step)                           # time went back (a restarted driver)
    assert np.all(r == 0) and mon.resets == 1
    gap = 51 + int(MAX_GAP_S / DT) + 10
    r, _ = feed(mon, oracle, gap, ext=step)
    assert np.all(r == 0) and mon.resets == 2
    assert any('gap of' in e[2] for e in mon.events) and any('time went back' in e[2] for e in mon.events)


def test_stamps_absent_use_the_clock(model, oracle):
    now = [0.0]
    mon = ContactMonitor(clock=lambda: now[0])
    mon.adopt(settings(), model, None, JOINTS)
    step = np.full(7, 1.5)
    for k in range(300):
        now[0] = 100.0 + k * DT
        r, _ = feed(mon, oracle, k, ext=step, stamp=0)
    np.testing.assert_allclose(r, step, atol=1e-3)


def test_settings_changes_and_model_swaps(model, oracle):
    mon = monitor(model)
    s = mon.settings
    for k in range(50):
        feed(mon, oracle, k, ext=np.ones(7))
    obs = mon.observer
    mon.adopt(s.replace({'collision.threshold': [1.0], 'collision.hold_time': 0.5}), model, None, JOINTS)
    assert mon.observer is obs and mon.last_stamp is not None          # no restart for thresholds
    assert mon.debounce.hold == 0.5 and np.all(mon.threshold == 1.0)
    mon.adopt(mon.settings.replace({'observer.gain': 10.0}), model, None, JOINTS)
    assert mon.observer is not obs and mon.last_stamp is None and mon.observer.gain[0] == 10.0
    mon.adopt(mon.settings.replace({'observer.enabled': False}), model, None, JOINTS)
    assert not mon.active and mon.state == 'off' and feed(mon, oracle, 60) is None
    mon.adopt(mon.settings.replace({'observer.enabled': True, 'measured_effort': 'none'}), model, None, JOINTS)
    assert not mon.active
    mon.adopt(mon.settings.replace({'measured_effort': 'total'}), model, None, JOINTS)
    assert mon.active
    other = load_urdf(XML)
    feed(mon, oracle, 61)
    mon.adopt(mon.settings, other, None, JOINTS)                       # a new model: a new integral
    assert mon.observer.model is other and mon.last_stamp is None
    few = load_urdf(XML, joints=JOINTS[:3])                           # thresholds that do not fit: off, said
    mon.adopt(mon.settings.replace({'collision.threshold': [1.0] * 7}), few, None, JOINTS[:3])
    assert not mon.active and 'collision.threshold' in mon.error
    assert any(e[0] == 'error' for e in mon.events)


def test_a_stream_that_starts_at_stamp_zero_switches_time_base_quietly(model, oracle):
    now = [50.0]
    mon = ContactMonitor(clock=lambda: now[0])
    mon.adopt(settings(), model, None, JOINTS)
    step = np.full(7, 1.5)
    for _ in range(3):                                   # a simulator re-sending its first state, stamp 0
        now[0] += 0.003
        assert feed(mon, oracle, 0, ext=step, stamp=0) is not None
    for k in range(1, 300):                              # then simulated time: a new integral, no fault
        r, _ = feed(mon, oracle, k, ext=step, stamp=k * MS)
        if k == 1:
            assert np.all(r == 0)
    np.testing.assert_allclose(r, step, atol=1e-3)
    assert mon.resets == 0 and mon.effort_unavailable == 0 and not mon.events


def test_motor_torque_keeps_its_documented_path():
    """lie_dynamics.ros.contact.motor_torque, the path docs/node.md named first, still imports: the same
    function as the observer's."""
    from lie_dynamics.ros.contact import motor_torque as public
    assert public is motor_torque


@pytest.mark.parametrize('name', ['arm', 'ur_description/urdf/ur5_robot.urdf'])
def test_monitor_equals_the_reference_observer_step_by_step(name, monkeypatch):
    """ContactMonitor.on_state (its one-kernel steady state) against the numpy reference
    (MomentumObserver.momentum_terms + advance) on random states with friction, restarted where
    the monitor pauses: a NaN effort and a gap beyond MAX_GAP_S. The flag follows |r_j| > threshold_j
    with the hold time, the window maximum is the largest |r|; between restarts, one step each."""
    if name == 'arm':
        xml, joints = XML, JOINTS
    else:
        root = next(iter(glob.glob(os.path.join(sys.prefix, 'lib', 'python3*', 'site-packages', 'cmeel.prefix',
                                                'share', 'example-robot-data', 'robots'))), None)
        if root is None:
            pytest.skip('example-robot-data is not installed')
        with open(os.path.join(root, name), encoding='utf-8') as fh:
            xml = fh.read()
        joints = None
    with warnings.catch_warnings():
        warnings.simplefilter('ignore')   # vendor inertias are warned about
        model = load_urdf(xml)
    joints = joints or model.joint_names
    n = model.n
    rng = np.random.default_rng(zlib.crc32(f'monitor {name}'.encode()))
    friction = make_friction(rng.uniform(0.0, 1.0, n), rng.uniform(0.0, 0.5, n), 0.05)
    thr = np.linspace(2.0, 8.0, n)                # per joint: the largest |r| is not always the one over
    s = settings(observer__gain=40.0, collision__threshold=thr.tolist(), collision__hold_time=0.003)
    mon = ContactMonitor(clock=lambda: 0.0)
    mon.adopt(s, model, friction, joints)
    ref = MomentumObserver(model, 40.0, friction)
    calls = {'update': 0}
    update = MomentumObserver.update

    def counted(self, *a):
        calls['update'] += 1
        return update(self, *a)
    monkeypatch.setattr(MomentumObserver, 'update', counted)
    idx = rng.permutation(n)                     # message columns in another order than the model's
    amp, w, phase = rng.uniform(0.2, 1.0, n), rng.uniform(0.5, 3.0, n), rng.uniform(0, 6, n)   # the motion
    stamp, top, flagged, flags = 7 * 10 ** 18, 0.0, 0, Debounce(0.003)   # flags: the reference flag
    for k in range(300):
        stamp += (int(MAX_GAP_S * 1e9) + 10 * MS) if k == 200 else int(rng.integers(MS // 2, 3 * MS // 2))
        t = (stamp - 7 * 10 ** 18) * 1e-9
        arg = w * t + phase
        q, qd, qdd = amp * np.sin(arg), amp * w * np.cos(arg), -amp * w * w * np.sin(arg)
        if k % 30 == 0:                          # a new external torque every 30 samples, around thr
            ext = rng.uniform(-1.5, 1.5, n) * thr
        tau = model.inverse_dynamics(q, qd, qdd) + friction_torque(qd, *friction) - ext
        effort, velocity = np.empty(n), np.empty(n)
        effort[idx], velocity[idx] = tau, qd     # message order: column idx[j] holds joint j
        if k == 120:
            effort[idx[2]] = math.nan
            assert mon.on_sample(accepted(mon, q, velocity, effort, stamp, idx)) is None
            assert mon.state == f"paused: non-finite effort for ['{joints[2]}']"
            ref.reset()
            flags.reset()
            continue
        if k == 200:
            ref.reset()                          # the gap: the monitor restarts with this sample
        r, flag = mon.on_sample(accepted(mon, q, velocity, effort, stamp, idx))
        expect = ref.advance(t, *ref.momentum_terms(q, qd, tau))
        scale = max(1.0, np.abs(expect).max())
        assert np.abs(r - expect).max() <= 1e-9 * scale, k
        if k == 200:
            flags.reset()
        flags.update(bool(np.any(np.abs(expect) > thr)), t)
        top = max(top, np.abs(expect).max())
        assert flag == flags.state, k
        flagged += flag
    assert calls['update'] == 3                  # the full path only where the integral (re)starts
    assert mon.resets == 2 and any('gap of' in e[2] for e in mon.events)
    v = dict(mon.report(OK, '', [])[2])
    assert float(v['external_torque_max']) == float(f'{top:.4g}') and 10 < flagged < 270   # both states, often
