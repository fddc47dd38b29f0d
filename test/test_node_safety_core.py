"""The dynamics node's safety logic without ROS: ramps, the newest state only, implausible
positions, nothing before the first state, the description-update policy, bounded texts,
the background worker and the serialized-trajectory reader."""
import math
import re
import threading
import time

import numpy as np
import pytest

from lie_dynamics import load_urdf
from lie_dynamics.ros.core.compensator import DIAG_TEXT_MAX, Compensator, Throttle
from lie_dynamics.ros.core.diagnostics import names_text, problem_key
from lie_dynamics.ros.core.params import check_value, defaults
from lie_dynamics.ros.core.ramp import Ramp
from lie_dynamics.ros.core.watchdog import Watchdog
from lie_dynamics.ros.loading.worker import Worker
from oracle import Oracle
from core_cases import Clock, big_limits, fill_trajectory, make
from robots import random_urdf

TOL = 1e-9


@pytest.fixture(scope='module')
def arm():
    """A 4-joint revolute chain with wide joint limits (random ones are narrow)."""
    xml = big_limits(random_urdf(21, 4, joint_types=('revolute',), mimic=False))
    xml = re.sub(r'lower="[^"]*" upper="[^"]*"', 'lower="-3" upper="3"', xml)
    return xml, load_urdf(xml).joint_names


def test_new_parameters_and_their_checks():
    d = defaults()
    assert d['ramp_time'] == 0.2 and d['description_update'] == 'same_robot'
    assert d['max_trajectory_points'] == 10_000 and d['max_description_bytes'] == 2_000_000
    assert d['max_description_links'] == 256 and d['position_margin'] == 0.5
    assert d['continuous_position_bound'] == 1e4
    for name, value in [('ramp_time', -0.1), ('ramp_time', 11.0), ('description_update', 'never'),
                        ('max_trajectory_points', 0), ('max_trajectory_points', 1.5), ('max_description_bytes', True),
                        ('position_margin', math.nan), ('continuous_position_bound', 0.5)]:
        with pytest.raises(ValueError):
            check_value(name, value)
    # a rejection reason quotes the value bounded
    with pytest.raises(ValueError) as info:
        check_value('mode', 'x' * 100_000)
    assert len(str(info.value)) < 300


def test_ramp_enable_disable_and_silence(arm):
    xml, ctrl = arm
    clock = Clock()
    c = make(xml, ctrl, clock=clock, ramp_time=1.0)
    q = np.full(len(ctrl), 0.3)
    g = c.model.gravity(q)
    np.testing.assert_allclose(c.on_joint_state(ctrl, q), g, atol=TOL)   # start-up: no ramp
    assert c.set_enabled(False) is None                                  # ramps down with the input
    out = []
    for _ in range(6):
        out.append(c.on_joint_state(ctrl, q))
        clock.t += 0.25
    np.testing.assert_allclose(out[0], g, atol=TOL)        # the ramp starts at the first command
    for k, level in enumerate((0.75, 0.5, 0.25), start=1):
        np.testing.assert_allclose(out[k], level * g, atol=TOL)
    np.testing.assert_array_equal(out[4], np.zeros(len(ctrl)))   # the last one: exact zeros
    assert out[5] is None and c.silent                            # then silent
    assert c.set_enabled(True) is None
    first = c.on_joint_state(ctrl, q)
    np.testing.assert_array_equal(first, np.zeros(len(ctrl)))   # enable ramps up from zero
    clock.t += 0.5
    np.testing.assert_allclose(c.on_joint_state(ctrl, q), 0.5 * g, atol=TOL)
    c.set_enabled(False)   # a disable during the enable ramp continues from where it is
    clock.t += 0.25
    np.testing.assert_allclose(c.on_joint_state(ctrl, q), 0.25 * g, atol=TOL)
    c.set_enabled(True)
    clock.t += 2.0
    np.testing.assert_allclose(c.on_joint_state(ctrl, q), g, atol=TOL)
    assert c.ramp.idle


def test_ramp_blends_mode_payload_gravity_and_model_changes(arm):
    xml, ctrl = arm
    clock = Clock()
    c = make(xml, ctrl, clock=clock, ramp_time=1.0, kp=[50.0])
    o = Oracle(xml, joints=ctrl)
    q, q_d = np.full(len(ctrl), 0.3), np.full(len(ctrl), 0.5)
    g = o.gravity(q)
    np.testing.assert_allclose(c.on_joint_state(ctrl, q), g, atol=TOL)
    from trajectory_msgs.msg import JointTrajectoryPoint
    c.on_desired(ctrl, [JointTrajectoryPoint(positions=q_d.tolist())])
    c.update({'mode': 'pd', 'desired_timeout': 60.0})
    pd = 50.0 * (q_d - q)
    for w in (0.0, 0.5, 1.0, 1.5):  # at a constant state: (1 - w) old + w new
        np.testing.assert_allclose(c.on_joint_state(ctrl, q), (1 - min(w, 1)) * g + min(w, 1) * pd, atol=1e-9)
        clock.t += 0.5
    # gravity and payload changes blend too
    c.update({'mode': 'gravity'})
    clock.t += 5.0
    c.on_joint_state(ctrl, q)
    clock.t += 5.0
    np.testing.assert_allclose(c.on_joint_state(ctrl, q), g, atol=TOL)
    c.update({'gravity_scale': 0.5})
    np.testing.assert_allclose(c.on_joint_state(ctrl, q), g, atol=TOL)
    clock.t += 0.5
    np.testing.assert_allclose(c.on_joint_state(ctrl, q), 0.75 * g, atol=1e-9)
    c.update({'gravity_scale': 1.0})   # a switch during a blend starts from where the command is
    np.testing.assert_allclose(c.on_joint_state(ctrl, q), 0.75 * g, atol=1e-9)
    clock.t += 1.0
    np.testing.assert_allclose(c.on_joint_state(ctrl, q), g, atol=1e-9)
    link = c.model.body_link_names[-1]
    c.update({'payload.link': link, 'payload.mass': 3.0})
    np.testing.assert_allclose(c.on_joint_state(ctrl, q), g, atol=1e-9)
    clock.t += 1.0
    np.testing.assert_allclose(c.on_joint_state(ctrl, q), c.model.gravity(q), atol=1e-9)
    assert np.abs(c.model.gravity(q) - g).max() > 0.1
    # a new model (same robot, heavier) blends as well
    heavier = re.sub(r'<mass value="([^"]*)"', lambda m: f'<mass value="{2 * float(m.group(1))!r}"', xml)
    before = c.on_joint_state(ctrl, q)
    c.set_model(load_urdf(heavier, joints=ctrl))
    np.testing.assert_allclose(c.on_joint_state(ctrl, q), before, atol=1e-9)
    clock.t += 1.0
    np.testing.assert_allclose(c.on_joint_state(ctrl, q), c.model.gravity(q), atol=1e-9)


def test_clamp_and_stale_action_apply_during_ramps(arm):
    xml, ctrl = arm
    clock = Clock()
    lim = 0.01
    c = make(big_limits(xml, str(lim)), ctrl, clock=clock, ramp_time=1.0, stale_timeout=0.1)
    q = np.full(len(ctrl), 0.3)
    g = c.model.gravity(q)
    assert np.abs(g).max() > 2 * lim
    np.testing.assert_allclose(c.on_joint_state(ctrl, q), np.clip(g, -lim, lim), atol=TOL)
    c.update({'mode': 'pd', 'kp': [100.0]})   # the blend is clamped too
    clamps = c.count.clamp_count
    out = c.on_joint_state(ctrl, q)
    assert np.all(np.abs(out) <= lim) and c.count.clamp_count > clamps
    # enable ramp: input stops, the stale action goes out in full; returning input blends from it
    c.update({'mode': 'gravity'})
    c.set_enabled(False)
    for _ in range(5):
        c.on_joint_state(ctrl, q)
        clock.t += 0.3
    assert c.silent
    c.set_enabled(True)
    c.on_joint_state(ctrl, q)
    clock.t += 0.3
    np.testing.assert_allclose(c.on_joint_state(ctrl, q), np.clip(0.3 * g, -lim, lim), atol=TOL)
    clock.t += 0.2
    held = c.tick()
    np.testing.assert_allclose(held, np.clip(g, -lim, lim), atol=TOL)
    clock.t += 0.01
    np.testing.assert_allclose(c.on_joint_state(ctrl, q), held, atol=TOL)   # blends from the held command


def test_disable_without_input_ramps_the_held_command_down_on_the_timer(arm):
    xml, ctrl = arm
    clock = Clock()
    c = make(xml, ctrl, clock=clock, ramp_time=1.0, stale_timeout=0.1)
    q = np.full(len(ctrl), 0.3)
    g = c.on_joint_state(ctrl, q)
    clock.t += 0.2
    held = c.tick()                          # stale: the stale action, in full
    np.testing.assert_allclose(held, g, atol=TOL)
    assert c.set_enabled(False) is None      # no input: the timer ramps the held command down
    out = []
    for _ in range(5):
        clock.t += 0.3
        out.append(c.tick())
    np.testing.assert_allclose(out[0], 0.7 * g, atol=1e-9)
    np.testing.assert_allclose(out[2], 0.1 * g, atol=1e-9)
    np.testing.assert_array_equal(out[3], np.zeros(len(ctrl)))
    assert out[4] is None and c.silent
    # stale during a disable ramp with input: the stale action is ramped down with the rest
    c.set_enabled(True)
    clock.t += 5.0
    c.on_joint_state(ctrl, q)
    clock.t += 5.0
    c.on_joint_state(ctrl, q)
    c.set_enabled(False)
    c.on_joint_state(ctrl, q)
    clock.t += 0.5
    np.testing.assert_allclose(c.on_joint_state(ctrl, q), 0.5 * g, atol=1e-9)
    clock.t += 0.2
    np.testing.assert_allclose(c.tick(), 0.3 * c.model.gravity(q), atol=1e-9)
    clock.t += 0.3
    np.testing.assert_array_equal(c.tick(), np.zeros(len(ctrl)))
    assert c.silent and c.tick() is None and c.final_command() is None
    # shutdown during a disable ramp: the stale action at the ramp's level, once
    c.set_enabled(True)
    c.on_joint_state(ctrl, q)
    clock.t += 2.0
    np.testing.assert_allclose(c.on_joint_state(ctrl, q), c.model.gravity(q), atol=1e-9)
    c.set_enabled(False)
    c.on_joint_state(ctrl, q)
    clock.t += 0.05
    c.on_joint_state(ctrl, q)
    clock.t += 0.05
    np.testing.assert_allclose(c.final_command(), 0.9 * c.model.gravity(q), atol=1e-9)


def test_nothing_is_published_before_the_first_valid_state(arm):
    xml, ctrl = arm
    for ramp in (0.0, 0.5):
        c = make(xml, ctrl, ramp_time=ramp)
        assert c.set_enabled(False) is None and c.silent
        assert c.on_joint_state(ctrl, [1e308] * len(ctrl)) is None
        assert c.set_enabled(True) is None
        assert c.tick(1e9) is None and c.final_command() is None
        assert c.on_joint_state(ctrl, np.zeros(len(ctrl))) is not None
    c = make(xml, ctrl, enabled=False)
    assert c.silent and c.on_joint_state(ctrl, np.zeros(len(ctrl))) is None
    assert c.set_enabled(True) is None


def three_kinds():
    """A revolute, a continuous and a prismatic joint (limits [-1, 2] where they have them)."""
    parts = ['<robot name="three"><link name="base"/>']
    for i, kind in enumerate(('revolute', 'continuous', 'prismatic')):
        limit = '' if kind == 'continuous' else ' lower="-1" upper="2"'
        parts.append(f'<link name="l{i}"><inertial><origin xyz="0.1 0 0.1"/><mass value="1"/><inertia ixx="0.01" '
                     f'ixy="0" ixz="0" iyy="0.01" iyz="0" izz="0.01"/></inertial></link>'
                     f'<joint name="{kind}_j" type="{kind}"><parent link="{"base" if i == 0 else f"l{i - 1}"}"/>'
                     f'<child link="l{i}"/><origin xyz="0 0 0.2"/><axis xyz="0 1 0"/>'
                     f'<limit effort="100" velocity="1"{limit}/></joint>')
    return ''.join(parts) + '</robot>'


def test_implausible_positions_are_rejected_like_nonfinite_ones():
    m = load_urdf(three_kinds())
    names = m.joint_names
    c = Compensator({'friction.viscous': [0.0], 'friction.coulomb': [0.0]}, clock=Clock())
    c.set_model(m)
    kinds = m.joint_types
    assert 'continuous' in kinds
    ok = np.array([1.9 if t != 'continuous' else 500.0 for t in kinds])
    assert c.on_joint_state(names, ok) is not None
    for k, t in enumerate(kinds):
        for bad in ([1e308, -1e308] + ([2.6, -1.6] if t != 'continuous' else [2e4, -2e4])):
            q = ok.copy()
            q[k] = bad
            c.events.clear()
            assert c.on_joint_state(names, q) is None, (t, bad)
            [(_, key, text)] = [e for e in c.events if e[1].startswith('reject')]
            assert key == 'reject:implausible' and names[k] in text
    for bad in (math.nan, math.inf):
        c.events.clear()
        assert c.on_joint_state(names, [bad] + ok[1:].tolist()) is None
        assert [e[1] for e in c.events] == ['reject:nonfinite']
    c.update({'position_margin': 1.0, 'continuous_position_bound': 1e5})   # live
    q = ok.copy()
    q[[k for k, t in enumerate(kinds) if t != 'continuous'][0]] = 2.6
    q[[k for k, t in enumerate(kinds) if t == 'continuous'][0]] = 2e4
    assert c.on_joint_state(names, q) is not None


def test_locked_joints_have_the_sanity_bound():
    xml = big_limits(random_urdf(21, 5, joint_types=('revolute',), mimic=False))
    names = load_urdf(xml).joint_names
    ctrl = [names[0]] + names[2:]
    c = make(xml, ctrl, position_margin=0.5)
    lo = load_urdf(xml, joints=ctrl).position_lower
    q = lo + 0.1
    assert c.on_joint_state(ctrl + [names[1]], q.tolist() + [9e3]) is not None
    assert c.on_joint_state(ctrl + [names[1]], q.tolist() + [2e4]) is None
    assert 'implausible' in c.last_error and names[1] in c.last_error


def test_only_the_newest_state_is_answered(arm):
    xml, ctrl = arm
    clock = Clock()
    c = make(xml, ctrl, clock=clock, stale_timeout=0.1)
    q = np.zeros(len(ctrl))
    assert c.on_joint_state(ctrl, q, stamp=2_000_000_000) is not None
    assert c.on_joint_state(ctrl, q, stamp=2_000_000_000) is not None   # the same stamp again: a re-send
    assert c.on_joint_state(ctrl, q, stamp=1_999_999_999) is None       # older: refused
    assert [e[1] for e in c.events if e[1].startswith('reject')] == ['reject:old']
    assert c.on_joint_state(ctrl, q, stamp=0) is not None               # unstamped: not compared
    assert c.on_joint_state(ctrl, q, stamp=3_000_000_000) is not None
    clock.t += 1.0
    assert c.tick() is not None                                         # stale
    # after a stale period any stamp starts a new stream (a restarted simulator)
    assert c.on_joint_state(ctrl, q, stamp=5) is not None
    assert c.on_joint_state(ctrl, q, stamp=4) is None


def test_description_update_policy_and_change_log(arm):
    xml, ctrl = arm
    c = make(xml, ctrl)
    other = xml.replace(f'<robot name="{c.model.name}"', '<robot name="another_robot"')
    other = big_limits(other, '1000')
    with pytest.raises(ValueError, match="another_robot.*same_robot"):
        c.plan(None, load_urdf(other, joints=ctrl))
    # same robot, changed masses and limits: accepted, what changed is logged
    changed = re.sub(r'<mass value="([^"]*)"', lambda m: f'<mass value="{2 * float(m.group(1))!r}"', xml)
    changed = big_limits(changed, '2e6')
    c.events.clear()
    c.set_model(load_urdf(changed, joints=ctrl))
    lines = {key: (sev, text) for sev, key, text in c.events}
    changes = [t for k, (s, t) in lines.items() if k.startswith('model:change')]
    assert any('effort limits changed' in t and '1e+06 -> 2e+06' in t for t in changes)
    assert any('masses changed' in t for t in changes)
    assert [s for k, (s, t) in lines.items() if 'effort limits' in t] == ['warn']   # raised limits warn
    c.update({'description_update': 'any'})
    c.set_model(load_urdf(other, joints=ctrl))
    assert c.model.name == 'another_robot'
    assert any("robot name changed" in e[2] for e in c.events)
    c.update({'description_update': 'none'})
    with pytest.raises(ValueError, match="'none'"):
        c.plan(None, load_urdf(xml, joints=ctrl))
    assert c.model.name == 'another_robot'


def test_texts_quoting_input_are_bounded(arm):
    xml, ctrl = arm
    c = make(xml, ctrl)
    many = [f'j{i}' for i in range(10_000)]
    long = ['n' * 100_000]
    for names in (many, long, many + many[:5]):
        c.events.clear()
        assert c.on_joint_state(names, [0.0] * len(names)) is None
        assert all(len(e[2]) <= DIAG_TEXT_MAX for e in c.events) and len(c.last_error) <= DIAG_TEXT_MAX
    assert '(+9992 more)' in names_text(many)
    assert all(len(v) <= DIAG_TEXT_MAX for _, v in c.diagnostics()[2])
    c.on_desired(many, [type('P', (), dict(positions=[0.0] * 10_000, velocities=[], accelerations=[]))()])
    assert len(c.last_error) <= DIAG_TEXT_MAX
    from trajectory_msgs.msg import JointTrajectoryPoint
    pts = [JointTrajectoryPoint(positions=[0.0] * 10_000)]
    assert fill_trajectory(c, many + many[:3], pts * 2) is None and len(c.last_error) <= DIAG_TEXT_MAX
    assert c.note_description_error('x' * 1_000_000) and len(c.description_error) <= DIAG_TEXT_MAX


def test_problem_keys_and_throttle_counts_held_lines():
    assert problem_key('trajectory point 3 has 6 positions for 7 joints') == \
        problem_key('trajectory point 41 has 2 positions for 9 joints')
    assert problem_key("lacks controlled joints ['a', 'b']") == problem_key("lacks controlled joints ['z']")
    assert problem_key('x' * 10_000) == 'x' * 80
    clock = Clock()
    t = Throttle(2.0, clock)
    assert t.check('a') == 0 and t.check('a') is None and t.check('a') is None
    clock.t += 2.0
    assert t.check('a') == 2 and t.check('a') is None
    for k in range(5000):   # however many keys: bounded
        t.check(f'k{k}')
        clock.t += 0.01
    assert len(t._last) <= 1001


def test_throttle_reports_what_it_held_once_the_period_is_over():
    clock = Clock()
    t = Throttle(2.0, clock)
    assert t.check('a', payload='a0') == 0 and t.check('b', payload='b0') == 0
    for k in range(1, 4):   # a burst shorter than the period, and nothing of class 'a' after it
        clock.t += 0.1
        assert t.check('a', payload=f'a{k}') is None
    assert t.due() == []   # the period is not over yet
    clock.t += 1.8
    assert t.due() == [('a3', 2)] and t.due() == []   # the newest held line stands for the 2 others
    assert t.check('a', payload='a4') is None   # the reported line opened a new period
    clock.t += 2.0
    assert t.check('a') == 1 and t.due() == []
    assert t.check('b') == 0 and t.check('b', payload='b1') is None
    assert t.due(float('inf')) == [('b1', 0)]   # at shutdown: whatever its period
    for k in range(5000):   # many keys expire while one has lines held back: its count is kept
        t.check(f'k{k}')
        if k == 0:
            assert t.check('k0', payload='k0 again') is None
        clock.t += 0.01
    assert len(t._last) <= 1002 and ('k0 again', 0) in t.due()


def test_ramp_offsets_never_carry_nonfinite_values():
    r = Ramp(1.0)
    r.last = np.array([1.0, 2.0])
    r.switch()
    out = r.shape(np.array([np.nan, 0.0]), 0.0)
    assert r.offset is None and np.isnan(out[0])
    r.set_duration(0.0)
    r.set_target(0.0, 1.0)
    assert r.level == 0.0 and r.down


def test_ramp_and_watchdog_change_state_through_their_methods():
    """What the compensator asks of them: a ramp that stops (silent), starts on the timer, notes
    an unshaped command; a watchdog expired at shutdown."""
    r = Ramp(1.0)
    r.note(np.array([1.0, 2.0]))
    r.switch()
    np.testing.assert_allclose(r.shape(np.zeros(2), 0.0), [1.0, 2.0])   # the blend starts from the noted one
    r.set_target(0.0, 0.0)
    r.stop()
    assert r.down and r.offset is None and not r.idle
    r.set_target(1.0, 1.0)
    r.start(1.0)   # the level moves from now, not from the next command
    assert r.advance(1.5) == pytest.approx(0.5)
    w = Watchdog(0.1)
    assert w.expire(0.0) is None   # nothing yet: nothing to expire
    w.feed(1.0)
    assert w.expire(1.05) == pytest.approx(0.05) and w.stale and w.stale_events == 1
    assert w.expire(2.0) is None and w.expired(2.0) is None and w.feed(2.0)


def test_worker_replaces_waiting_jobs_and_delivers_running_ones():
    w = Worker('test_worker')
    gate = threading.Event()
    ran = []

    def job(tag, wait=False):
        def run():
            if wait:
                gate.wait(5.0)
            ran.append(tag)
            return tag
        return run
    assert w.submit('model', 'a', job('a', wait=True)) is None
    end = time.monotonic() + 5.0
    while w.running is None and time.monotonic() < end:
        time.sleep(0.001)
    assert w.busy('model') == 'a'
    assert w.submit('model', 'b', job('b')) is None
    assert w.submit('model', 'c', job('c')) == 'b'   # b never runs: c replaces it
    assert w.submit('trajectory', 't', lambda: 1 / 0) is None
    gate.set()
    while len(w._done) < 3 and time.monotonic() < end:
        time.sleep(0.001)
    outs = w.outcomes()
    assert ran == ['a', 'c'] and [o.tag for o in outs] == ['a', 'c', 't']
    assert isinstance(outs[2].error, ZeroDivisionError) and not w.has_outcomes
    assert w.replaced == {'model': 1, 'trajectory': 0}
    w.stop()
    with pytest.raises(RuntimeError):
        w.submit('model', 'd', job('d'))
