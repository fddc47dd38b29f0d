"""Decision logic of the dynamics node without ROS: lie_dynamics.ros.core.compensator / params."""
import math
import re
import warnings

import numpy as np
import pytest

from lie_dynamics import load_urdf
from lie_dynamics.ros.core.compensator import (DIAG_TEXT_MAX, ERROR, INERTIA_LOG_LINES, INERTIA_TEXT_MAX, OK, WARN,
    Compensator, Throttle)
from lie_dynamics.ros.core.params import PARAMS, check_value, defaults
from oracle import Oracle
from core_cases import Clock, big_limits, make
from robots import random_urdf

TOL = 1e-9


@pytest.fixture
def chain():
    """A 5-joint chain: joints[1] is left out of `joints`, so it is locked and fed by joint_states."""
    xml = big_limits(random_urdf(21, 5, joint_types=('revolute',), mimic=False))
    names = load_urdf(xml).joint_names
    ctrl = [names[0]] + names[2:]
    return xml, ctrl, names[1]


def test_gravity_with_moving_locked_joint_in_any_message_order(chain):
    xml, ctrl, locked = chain
    c = make(xml, ctrl)
    rng = np.random.default_rng(1)
    for _ in range(4):
        q = rng.uniform(-2, 2, len(ctrl))
        ql = rng.uniform(-2, 2)
        names = [locked, 'unrelated_joint'] + ctrl[::-1]
        tau = c.on_joint_state(names, [ql, 7.0] + q[::-1].tolist())
        ref = Oracle(xml, joints=ctrl, locked={locked: ql}).gravity(q)
        np.testing.assert_allclose(tau, ref, atol=TOL, rtol=0)
    assert c.count.accepted == 4 and c.count.rejected == 0


def test_gravity_scale_gravity_vector_and_payload(chain):
    xml, ctrl, locked = chain
    c = make(xml, ctrl)
    q = np.linspace(-1, 1, len(ctrl))
    names = ctrl + [locked]
    c.update({'gravity': [0.0, -9.81, 0.0], 'gravity_scale': 0.5})
    tau = c.on_joint_state(names, q.tolist() + [0.3])
    ref = Oracle(xml, joints=ctrl, locked={locked: 0.3}, gravity=(0, -4.905, 0)).gravity(q)
    np.testing.assert_allclose(tau, ref, atol=TOL, rtol=0)
    # payload == an extra fixed link in the URDF
    model = c.model
    link = [k for k, (b, _) in model.link_frames.items() if b == model.nb - 1][0]
    c.update({'gravity_scale': 1.0, 'payload.link': link})
    c.update({'payload.mass': 2.0, 'payload.com': [0.1, 0.0, 0.05], 'payload.inertia': [0.01, 0, 0, 0.02, 0, 0.03]})
    xml_p = xml.replace('</robot>', f'''<link name="pl"><inertial><origin xyz="0.1 0 0.05"/><mass value="2"/>
      <inertia ixx="0.01" ixy="0" ixz="0" iyy="0.02" iyz="0" izz="0.03"/></inertial></link>
      <joint name="pl_joint" type="fixed"><parent link="{link}"/><child link="pl"/></joint></robot>''')
    tau = c.on_joint_state(names, q.tolist() + [0.3])
    ref = Oracle(xml_p, joints=ctrl, locked={locked: 0.3}, gravity=(0, -9.81, 0)).gravity(q)
    np.testing.assert_allclose(tau, ref, atol=TOL, rtol=0)
    c.update({'payload.mass': 0.0})
    tau = c.on_joint_state(names, q.tolist() + [0.3])
    ref = Oracle(xml, joints=ctrl, locked={locked: 0.3}, gravity=(0, -9.81, 0)).gravity(q)
    np.testing.assert_allclose(tau, ref, atol=TOL, rtol=0)


def test_velocity_terms_friction_and_nan_velocity(chain):
    xml, ctrl, locked = chain
    n = len(ctrl)
    c = make(xml, ctrl, include_velocity_terms=True, **{'friction.viscous': [0.3], 'friction.coulomb': [0.2]})
    rng = np.random.default_rng(4)
    q, qd = rng.uniform(-1, 1, n), rng.uniform(-1, 1, n)
    eps = defaults()['friction.coulomb_velocity_epsilon']
    o = Oracle(xml, joints=ctrl)
    tau = c.on_joint_state(ctrl, q.tolist(), qd.tolist())
    ref = o.rnea(q, qd, np.zeros(n)) + 0.3 * qd + 0.2 * np.tanh(qd / eps)
    np.testing.assert_allclose(tau, ref, atol=TOL, rtol=0)
    # NaN velocity (joint_state_broadcaster without a velocity interface): used as 0
    qd_nan = qd.copy()
    qd_nan[1] = math.nan
    qd0 = qd.copy()
    qd0[1] = 0.0
    tau = c.on_joint_state(ctrl, q.tolist(), qd_nan.tolist())
    ref = o.rnea(q, qd0, np.zeros(n)) + 0.3 * qd0 + 0.2 * np.tanh(qd0 / eps)
    np.testing.assert_allclose(tau, ref, atol=TOL, rtol=0)
    assert c.count.velocity_unavailable == 1
    # no velocity array at all: gravity only
    tau = c.on_joint_state(ctrl, q.tolist())
    np.testing.assert_allclose(tau, o.gravity(q), atol=TOL, rtol=0)


def test_friction_defaults_from_urdf():
    xml = random_urdf(5, 3, joint_types=('revolute',))
    xml = big_limits(re.sub(r'<dynamics[^>]*/>', '', xml))
    xml = re.sub(r'(<limit [^>]*/>)', r'\1<dynamics damping="0.7" friction="0.4"/>', xml)
    m = load_urdf(xml)
    c = Compensator(clock=Clock())
    c.set_model(load_urdf(xml))
    q, qd = np.zeros(m.n), np.full(m.n, 0.5)
    tau = c.on_joint_state(m.joint_names, q, qd)
    eps = c.settings['friction.coulomb_velocity_epsilon']
    np.testing.assert_allclose(tau, m.gravity(q) + 0.7 * qd + 0.4 * np.tanh(qd / eps), atol=TOL)
    c.update({'friction.viscous': [0.0], 'friction.coulomb': [0.0]})
    np.testing.assert_allclose(c.on_joint_state(m.joint_names, q, qd), m.gravity(q), atol=TOL)
    with pytest.raises(ValueError, match='0, 1 or 3'):
        c.update({'friction.viscous': [0.1, 0.2]})


def test_rejections_publish_nothing_and_name_the_problem(chain):
    xml, ctrl, locked = chain
    c = make(xml, ctrl)
    n = len(ctrl)
    good = list(np.linspace(0, 1, n))
    cases = [
        ('length', ctrl, good[:-1], [], []),
        ('length', ctrl, good, [0.0], []),
        ('length', ctrl, good, [], [0.0] * (n + 1)),
        ('duplicate', ctrl + [ctrl[0]], good + [0.0], [], []),
        ('nonfinite', ctrl, good[:-1] + [math.nan], [], []),
        ('nonfinite', ctrl, good[:-1] + [math.inf], [], []),
        ('nonfinite', ctrl + [locked], good + [math.nan], [], []),
        ('missing', ctrl[1:], good[1:], [], []),
    ]
    for k, (kind, names, pos, vel, eff) in enumerate(cases):
        c.events.clear()
        assert c.on_joint_state(names, pos, vel, eff) is None, kind
        assert c.count.rejected == k + 1
        assert [e[1] for e in c.events] == ['reject:' + kind]
        text = c.events[0][2]
        assert {'length': 'lengths', 'duplicate': ctrl[0], 'nonfinite': 'non-finite',
                'missing': ctrl[0]}[kind] in text
    assert c.on_joint_state(ctrl, good) is not None
    assert c.count.accepted == 1


def test_clamp_and_nonfinite_output(chain):
    xml, ctrl, locked = chain
    xml = big_limits(xml, '2.0')
    c = make(xml, ctrl, effort_limit_scale=0.5)
    q = np.full(len(ctrl), 0.7)
    tau = c.on_joint_state(ctrl, q)
    ref = Oracle(xml, joints=ctrl).gravity(q)
    assert np.any(np.abs(ref) > 1.0)
    np.testing.assert_allclose(tau, np.clip(ref, -1.0, 1.0), atol=TOL)
    assert c.count.clamp_count == 1 and c.clamped
    assert [e[1] for e in c.events if e[1] != 'model'] == ['clamp']
    # a model that produces NaN must never reach the output
    c.model.gravity = lambda q: np.full(len(ctrl), math.nan)
    assert c.on_joint_state(ctrl, q) is None
    assert 'non-finite torque' in c.last_error
    c.model.gravity = lambda q: np.full(len(ctrl), -math.inf)   # beyond any finite limit: clamped
    np.testing.assert_array_equal(c.on_joint_state(ctrl, q), np.full(len(ctrl), -1.0))
    # no URDF effort limit: not clamped, but an infinite value is still never published
    c2 = make(re.sub(r' effort="[^"]*"', '', xml), ctrl)
    assert not np.isfinite(c2.model.effort_limits).any()
    assert any('no URDF effort limit' in e[2] for e in c2.events)
    c2.model.gravity = lambda q: np.full(len(ctrl), math.inf)
    assert c2.on_joint_state(ctrl, q) is None


def test_stale_hold_zero_and_recovery(chain):
    xml, ctrl, locked = chain
    clock = Clock()
    c = make(xml, ctrl, clock=clock, stale_timeout=0.2, include_velocity_terms=True)
    assert c.tick() is None  # nothing received yet: nothing to hold
    q, qd = np.full(len(ctrl), 0.4), np.full(len(ctrl), 1.0)
    tau = c.on_joint_state(ctrl, q, qd)
    clock.t += 0.15
    assert c.tick() is None and not c.watchdog.stale
    clock.t += 0.1
    held = c.tick()
    assert c.watchdog.stale and c.watchdog.stale_events == 1
    np.testing.assert_allclose(held, c.model.gravity(q), atol=TOL)   # velocity terms dropped
    assert not np.allclose(held, tau)
    assert c.tick() is None  # once
    assert c.diagnostics()[0] == WARN
    assert c.on_joint_state(ctrl, q, qd) is not None and not c.watchdog.stale
    c.update({'stale_action': 'zero'})
    clock.t += 1.0
    np.testing.assert_array_equal(c.tick(), np.zeros(len(ctrl)))


def test_enable_disable(chain):
    xml, ctrl, locked = chain
    c = make(xml, ctrl)
    q = np.zeros(len(ctrl))
    assert c.set_enabled(False) is None      # nothing was published yet: nothing to release
    assert c.set_enabled(True) is None
    assert c.on_joint_state(ctrl, q) is not None
    zeros = c.set_enabled(False)
    np.testing.assert_array_equal(zeros, np.zeros(len(ctrl)))
    assert c.on_joint_state(ctrl, q) is None and c.count.accepted == 2   # still tracked, not published
    assert c.set_enabled(False) is None                            # no change, nothing to send
    assert c.set_enabled(True) is None
    assert c.on_joint_state(ctrl, q) is not None


def test_model_swap_keeps_layout_and_locked_values(chain):
    xml, ctrl, locked = chain
    c = make(xml, ctrl)
    q = np.full(len(ctrl), 0.2)
    c.on_joint_state(ctrl + [locked], list(q) + [0.9])
    heavier = re.sub(r'<mass value="([^"]*)"', lambda m: f'<mass value="{2 * float(m.group(1))!r}"', xml)
    c.set_model(load_urdf(heavier, joints=ctrl))
    assert c.model.locked_values[locked] == 0.9
    ref = Oracle(heavier, joints=ctrl, locked={locked: 0.9}).gravity(q)
    np.testing.assert_allclose(c.on_joint_state(ctrl, q), ref, atol=TOL)
    with pytest.raises(ValueError, match='layout'):
        c.set_model(load_urdf(xml, joints=ctrl[::-1]))


def test_no_model_publishes_nothing():
    c = Compensator(clock=Clock())
    assert c.on_joint_state(['a'], [0.0]) is None
    assert c.tick(1e9) is None
    assert c.set_enabled(False) is None
    assert c.diagnostics()[0] == ERROR


def test_parameter_checks():
    assert set(defaults()) == {p.name for p in PARAMS}
    bad = [('gravity_scale', 1.5), ('gravity', [0.0, 9.81]), ('gravity', [0.0, 0.0, math.nan]),
           ('gravity', [0.0, 0.0, -981.0]), ('stale_action', 'freeze'), ('payload.inertia', [1.0, 2.0]),
           ('friction.viscous', [-1.0]), ('joints', ['a', 'a']), ('enabled', 1), ('stale_timeout', 0.0),
           ('inertia_policy', 'lenient'), ('inertia_policy', 'Warn')]
    for name, value in bad:
        with pytest.raises(ValueError):
            check_value(name, value)
    with pytest.raises(ValueError, match='payload.link'):
        Compensator({'payload.mass': 1.0})


def test_diagnostics_window(chain):
    xml, ctrl, locked = chain
    clock = Clock()
    c = make(xml, ctrl, clock=clock)
    c.diagnostics()
    for _ in range(10):
        c.on_joint_state(ctrl, np.zeros(len(ctrl)))
        c.record_compute_time(1e-4)
    clock.t += 2.0
    level, msg, values = c.diagnostics()
    v = dict(values)
    assert level == OK and msg == 'compensating'
    assert float(v['input_rate_hz']) == pytest.approx(5.0)
    assert float(v['compute_time_mean_ms']) == pytest.approx(0.1)
    assert v['joint_count'] == str(len(ctrl)) and v['model_loaded'] == 'True'


def test_throttle():
    clock = Clock()
    t = Throttle(2.0, clock)
    assert t.ready('a') and not t.ready('a') and t.ready('b')
    clock.t += 2.0
    assert t.ready('a')


def inertia_chain(k, bad=()):
    """k revolute joints j1..jk moving links link_1..link_k (0.05 kg); the links numbered in `bad`
    break the triangle inequality (0.001 + 0.001 < 0.01 kg m^2)."""
    parts = ['<robot name="inertia_chain"><link name="base_link"/>']
    for i in range(1, k + 1):
        izz = '0.01' if i in bad else '0.001'
        parts.append(
            f'<link name="link_{i}"><inertial><origin xyz="0 0 0.05"/><mass value="0.05"/>'
            f'<inertia ixx="0.001" ixy="0" ixz="0" iyy="0.001" iyz="0" izz="{izz}"/></inertial></link>'
            f'<joint name="j{i}" type="revolute"><parent link="{"base_link" if i == 1 else f"link_{i - 1}"}"/>'
            f'<child link="link_{i}"/><origin xyz="0 0 0.1"/><axis xyz="0 1 0"/>'
            '<limit effort="1e6" velocity="1" lower="-3" upper="3"/></joint>')
    return ''.join(parts) + '</robot>'


def _inertia_events(c):
    return [e for e in c.events if e[2].startswith('inertia')]


def test_inertia_warn_logs_each_bad_link_once_and_diagnoses():
    c = Compensator(clock=Clock())
    with warnings.catch_warnings():
        warnings.simplefilter('error')  # no InertiaWarning may escape raw (stderr)
        c.load(inertia_chain(2, bad={2}), 'test')
    [(severity, key, text)] = _inertia_events(c)
    assert severity == 'warn' and key == 'inertia:0'   # one throttle key per line of a load
    assert 'link_2' in text and 'triangle inequality' in text and 'link_1' not in text
    assert [(r['link'], r['rule'], r['repaired']) for r in c.inertia_report] == [('link_2', 'triangle inequality',
                                                                                  False)]
    c.events.clear()
    for q in (0.0, 0.5, 1.0):  # per load, not per message
        assert c.on_joint_state(['j1', 'j2'], [q, q]) is not None
    assert not _inertia_events(c)
    level, msg, values = c.diagnostics()
    v = dict(values)
    assert level == WARN and '1 link(s) with inconsistent inertia' in msg
    assert v['inertia_policy'] == 'warn' and v['inertia_warnings'] == '1' and v['inertia_repaired'] == '0'
    assert 'link_2' in v['inertia_report']
    c.load(inertia_chain(2), 'test')  # a consistent model clears the report
    assert not _inertia_events(c) and c.inertia_report == []
    c.on_joint_state(['j1', 'j2'], [0.0, 0.0])
    level, msg, values = c.diagnostics()
    assert level == OK and dict(values)['inertia_warnings'] == '0' and dict(values)['inertia_report'] == ''


def test_inertia_strict_refuses_and_keeps_previous_model():
    c = Compensator({'inertia_policy': 'strict'}, clock=Clock())
    good = c.load(inertia_chain(2), 'good')
    with pytest.raises(ValueError, match='link_2') as info:
        c.load(inertia_chain(2, bad={2}), 'bad')
    assert 'triangle inequality' in str(info.value)
    assert c.model is good and c.inertia_report == []
    c.note_description_error(f'bad: {info.value}')  # as the node does with any refused description
    c.on_joint_state(['j1', 'j2'], [0.0, 0.0])
    level, msg, values = c.diagnostics()
    assert level == WARN and 'previous model kept' in msg and 'link_2' in dict(values)['description_error']
    # `inertia` overrides the setting for one load (the node's reload on a policy change)
    c.load(inertia_chain(2, bad={2}), 'bad', inertia='warn')
    assert c.model is not good and len(c.inertia_report) == 1


def test_the_builder_is_handed_to_the_core():
    """The core builds models with the builder it is given (the node's: its build process), per
    call or at construction; by default descriptions.build in this process."""
    from lie_dynamics.ros.core.descriptions import build
    calls = []

    def builder(source, **options):
        calls.append((source, options))
        return build(source, **options)

    c = Compensator({'joints': ['j1', 'j2'], 'gravity': [0.0, 0.0, -3.0]}, clock=Clock(), builder=builder)
    c.load(inertia_chain(2), 'a')
    assert calls == [(inertia_chain(2), dict(joints=['j1', 'j2'], gravity=[0.0, 0.0, -3.0], inertia='warn',
                                              running=None))]
    other = []
    c.build_model(inertia_chain(2), builder=lambda source, **o: other.append(o) or build(source, **o))
    assert len(calls) == 1 and other == [dict(joints=['j1', 'j2'], gravity=[0.0, 0.0, -3.0], inertia='warn',
                                              running=('same_robot', c.model.name))]
    assert Compensator(clock=Clock()).builder is build


def test_inertia_repair_reports_repaired():
    c = Compensator({'inertia_policy': 'repair'}, clock=Clock())
    with warnings.catch_warnings():
        warnings.simplefilter('error')
        c.load(inertia_chain(2, bad={2}), 'test')
    assert [(r['link'], r['repaired']) for r in c.inertia_report] == [('link_2', True)]
    [(severity, _, text)] = _inertia_events(c)
    assert severity == 'warn' and 'link_2' in text
    c.on_joint_state(['j1', 'j2'], [0.0, 0.0])
    level, msg, values = c.diagnostics()
    assert level == WARN and '(1 repaired)' in msg and dict(values)['inertia_repaired'] == '1'


def test_inertia_log_and_diagnostics_are_bounded():
    k = INERTIA_LOG_LINES + 10
    c = Compensator(clock=Clock())
    c.load(inertia_chain(k, bad=set(range(1, k + 1))), 'test')
    events = _inertia_events(c)
    assert len(events) == INERTIA_LOG_LINES + 1
    assert events[-1][2].endswith('... and 10 more links with inconsistent inertia')
    assert all(len(e[2]) <= INERTIA_TEXT_MAX for e in events)
    v = dict(c.diagnostics()[2])
    assert v['inertia_warnings'] == str(k) and 0 < len(v['inertia_report']) <= DIAG_TEXT_MAX


def test_plan_changes_nothing_until_applied(chain):
    """Compensator.plan validates (a payload on a scratch copy, a new model privately);
    apply makes the plan current. The node validates in on_set and applies in post_set."""
    xml, ctrl, locked = chain
    c = make(xml, ctrl)
    model = c.model
    q = np.linspace(-1, 1, len(ctrl))
    names = ctrl + [locked]
    before = c.on_joint_state(names, q.tolist() + [0.3])
    link = [k for k, (b, _) in model.link_frames.items() if b == model.nb - 1][0]
    inertia = [0.01, 0, 0, 0.02, 0, 0.03]
    plan = c.plan({'payload.link': link, 'payload.mass': 2.0, 'payload.com': [0.1, 0.0, 0.05],
                   'payload.inertia': inertia, 'gravity_scale': 0.5})
    assert c.settings['payload.mass'] == 0.0 and c.settings['gravity_scale'] == 1.0 and c.model is model
    np.testing.assert_array_equal(c.on_joint_state(names, q.tolist() + [0.3]), before)
    assert c.apply(plan) is None and c.model is model
    xml_p = xml.replace('</robot>', f'''<link name="pl"><inertial><origin xyz="0.1 0 0.05"/><mass value="2"/>
      <inertia ixx="0.01" ixy="0" ixz="0" iyy="0.02" iyz="0" izz="0.03"/></inertial></link>
      <joint name="pl_joint" type="fixed"><parent link="{link}"/><child link="pl"/></joint></robot>''')
    ref = Oracle(xml_p, joints=ctrl, locked={locked: 0.3}, gravity=(0, 0, -4.905)).gravity(q)
    np.testing.assert_allclose(c.on_joint_state(names, q.tolist() + [0.3]), ref, atol=TOL, rtol=0)
    # refused: a payload inertia breaking the triangle inequality; a new model with bad settings
    with pytest.raises(ValueError, match='triangle'):
        c.plan({'payload.inertia': [0.001, 0, 0, 0.001, 0, 0.01]})
    heavier = re.sub(r'<mass value="([^"]*)"', lambda m: f'<mass value="{2 * float(m.group(1))!r}"', xml)
    with pytest.raises(ValueError, match='kp'):
        c.plan({'kp': [1.0, 2.0]}, load_urdf(heavier, joints=ctrl))
    assert c.model is model and c.settings['payload.inertia'] == inertia
    np.testing.assert_allclose(c.on_joint_state(names, q.tolist() + [0.3]), ref, atol=TOL, rtol=0)
    # a new model and settings together; the payload moves onto the new model
    c.apply(c.plan({'gravity_scale': 1.0}, load_urdf(heavier, joints=ctrl), 'heavier'))
    assert c.model is not model and c.model_info == 'heavier'
    ref = Oracle(heavier.replace('</robot>', xml_p[xml_p.index('<link name="pl">'):]), joints=ctrl,
                 locked={locked: 0.3}).gravity(q)
    np.testing.assert_allclose(c.on_joint_state(names, q.tolist() + [0.3]), ref, atol=TOL, rtol=0)
    # disabling returns the one zero command; a plan made before another change is checked again
    np.testing.assert_array_equal(c.apply(c.plan({'enabled': False})), np.zeros(len(ctrl)))
    stale_plan = c.plan({'kp': [1.0]})
    c.update({'enabled': True})
    assert c.apply(stale_plan) is None and c.settings['enabled'] and c.settings['kp'] == [1.0]
