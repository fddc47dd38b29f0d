"""Rules the node applies in several places, each implemented once: the parameter table's checks
(as data of the specs), the per-joint expansion, the payload rule, the description-update
policy, the joint-name mapping and its refusals, the freshness of inputs, a sample's time, the
bounds of diagnostics and log lines, and the kernel warm-up. Each test checks the rule and that
its users follow it (no ROS)."""
import math

import numpy as np
import pytest

from lie_dynamics import default_urdf_path, load_urdf
from lie_dynamics.model.joint_names import broadcast_joints, joint_columns
from lie_dynamics.ros.core import settings as settings_module
from lie_dynamics.ros.core.compensator import Compensator
from lie_dynamics.ros.core.diagnostics import DIAG_TEXT_MAX
from lie_dynamics.ros.core.log import EventLog
from lie_dynamics.ros.core.messages import NameMap, Rejected, read_desired
from lie_dynamics.ros.core.params import PARAMS, PAYLOAD_KEYS, SPECS, ParamSpec, check_value, per_joint_values
from lie_dynamics.ros.core.settings import Settings
from lie_dynamics.ros.core.timebase import TimeBase
from lie_dynamics.ros.core.watchdog import Freshness, Watchdog, fresh
from lie_dynamics.ros.features import contact, payload_service
from lie_dynamics.ros.features.base import Feature, Features
from lie_dynamics.ros.features.gravity_source import GravitySource
from lie_dynamics.ros.core.descriptions import update_refusal
from lie_dynamics.ros.loading.models import at_rest, portable, warm_up
from lie_dynamics.ros.trajectories.fill import TrajectoryFill
from lie_dynamics.laws import effort_limits
from lie_dynamics.sim.trajectory_source import per_joint as sim_per_joint
from lie_dynamics.trajectory import fill_trajectory_efforts

COM, INERTIA = [0.01, -0.02, 0.05], [3e-3, 1e-4, 0.0, 4e-3, -2e-4, 2e-3]


@pytest.fixture(scope='module')
def arm():
    return load_urdf(default_urdf_path())


# ---------------------------------------------------------------- parameter specs as data
@pytest.mark.parametrize('name, value, message', [
    ('gravity', [0.0, 9.81], 'gravity must have 3 values, got 2'),
    ('gravity', [0.0, 0.0, -981.0], r'gravity norm must be <= 100 m/s\^2 \(units\?\)'),
    ('payload.com', [0.0], 'payload.com must have 3 values, got 1'),
    ('payload.inertia', [1.0, 2.0], 'payload.inertia must be empty or have 6 values, got 2'),
    ('kp', [1.0, -1.0], 'kp must be >= 0, got'),
    ('friction.coulomb', [-0.1], 'friction.coulomb must be >= 0, got'),
    ('collision.threshold', [0.0], 'collision.threshold must be one or more values > 0, got'),
    ('collision.threshold', [], 'collision.threshold must be one or more values > 0, got'),
    ('command_topic', '  ', 'command_topic must not be empty'),
    ('mode', 'torque', r"mode must be one of \['gravity'"),
])
def test_check_value_reads_the_spec(name, value, message):
    with pytest.raises(ValueError, match=message):
        check_value(name, value)


def test_specs_carry_their_rules():
    assert SPECS['gravity'].lengths == (3,) and SPECS['gravity'].norm_max == 100.0
    assert SPECS['payload.inertia'].lengths == (0, 6)
    assert {p.name: p.per_joint for p in PARAMS if p.per_joint} == {
        'kp': 'zero', 'kd': 'zero', 'friction.viscous': 'urdf', 'friction.coulomb': 'urdf',
        'collision.threshold': 'required'}
    # an accepted value of each: the boundaries themselves
    assert check_value('gravity', [0.0, 0.0, -100.0]) == [0.0, 0.0, -100.0]
    assert check_value('kp', [0.0]) == [0.0] and check_value('payload.inertia', []) == []
    with pytest.raises(ValueError, match='per_joint must be one of'):
        ParamSpec('x', 'double_array', None, '', True, per_joint='each')


# ---------------------------------------------------------------- one value or one per joint
def test_broadcast_joints():
    np.testing.assert_array_equal(broadcast_joints([2.0], 3), [2.0, 2.0, 2.0])
    given = np.array([1.0, 2.0, 3.0])
    out = broadcast_joints(given, 3)
    np.testing.assert_array_equal(out, given)
    assert out is not given   # a new array: the caller's is never aliased
    assert broadcast_joints([1.0, 2.0], 3) is None and broadcast_joints([], 3) is None
    assert broadcast_joints([[1.0, 2.0, 3.0]], 3) is None
    assert broadcast_joints([], 0).shape == (0,)


def test_per_joint_values_by_shape():
    urdf = [0.1, 0.2, 0.3]
    np.testing.assert_array_equal(per_joint_values('friction.viscous', [], 3, urdf), urdf)
    np.testing.assert_array_equal(per_joint_values('kp', [], 3), np.zeros(3))
    np.testing.assert_array_equal(per_joint_values('collision.threshold', [5.0], 3), [5.0] * 3)
    for name, values, message in (
            ('friction.viscous', [1.0, 2.0], r'friction.viscous must have 0, 1 or 3 values \(one per controlled '
                                             r'joint\), got 2'),
            ('kd', [1.0, 2.0], 'kd must have 1 or 3 values'),
            ('collision.threshold', [], 'collision.threshold must have 1 or 3 values'),
            ('kp', [-1.0], 'kp must be finite and >= 0'),
            ('collision.threshold', [0.0], r'collision.threshold must be finite and > 0 \(N m\)'),
            ('friction.coulomb', [], 'friction.coulomb must be finite and >= 0')):   # a NaN in the URDF
        with pytest.raises(ValueError, match=message):
            per_joint_values(name, values, 3, [0.0, math.nan, 0.0])


def test_every_per_joint_user_follows_the_rule(arm):
    n = arm.n
    assert settings_module.gains([], n, 'kp') is None       # all zero: off
    np.testing.assert_array_equal(settings_module.gains([2.0], n, 'kp'), per_joint_values('kp', [2.0], n))
    np.testing.assert_array_equal(settings_module.per_joint([0.5], arm.damping, n, 'friction.viscous'),
                                  np.full(n, 0.5))
    np.testing.assert_array_equal(contact.thresholds([3.0], n), np.full(n, 3.0))
    np.testing.assert_array_equal(sim_per_joint([0.5], 3, 'home'), [0.5] * 3)
    for call in (lambda: settings_module.gains([1.0, 2.0], n, 'kp'), lambda: contact.thresholds([1.0, 2.0], n),
                 lambda: settings_module.per_joint([1.0, 2.0], arm.damping, n, 'friction.viscous')):
        with pytest.raises(ValueError, match=f'1 or {n} values'):
            call()


# ---------------------------------------------------------------- payload
def test_model_check_payload_is_set_payload_check(arm):
    version = arm.version
    m, c, inertia = arm.check_payload('hand', 2.0, COM, INERTIA)
    assert arm.version == version   # checks only
    assert m == 2.0 and np.array_equal(c, COM) and np.array_equal(inertia, inertia.T)
    bad = [0.001, 0.0, 0.0, 0.001, 0.0, 0.01]   # 1e-3 + 1e-3 < 1e-2: triangle inequality
    for call in (lambda: arm.check_payload('hand', 2.0, COM, bad), lambda: arm.set_payload('hand', 2.0, COM, bad)):
        with pytest.raises(ValueError, match='payload inertia is not physically valid: triangle inequality'):
            call()
    assert arm.version == version


def test_set_payload_service_uses_the_model_check(arm, monkeypatch):
    calls = []
    real = type(arm).check_payload

    def spy(self, *args):
        calls.append(args)
        return real(self, *args)

    monkeypatch.setattr(type(arm), 'check_payload', spy)
    request = {'payload.link': 'hand', 'payload.mass': 2.0, 'payload.com': COM, 'payload.inertia': INERTIA}
    assert payload_service.check_payload_request(request, arm)['payload.mass'] == 2.0
    assert calls == [('hand', 2.0, COM, INERTIA)]
    # and so does setting the parameters (Compensator.plan -> place_payload -> Model.set_payload)
    core = Compensator()
    core.set_model(load_urdf(default_urdf_path()))
    calls.clear()
    core.update(request)
    assert calls and calls[-1][0] == 'hand'


def test_the_payload_rule_is_the_same_for_every_way_in(arm):
    """A link no controlled joint moves, a mass out of the parameter's range: each way a payload
    comes in (Model.set_payload, the payload.* parameters, ~/set_payload's check, identify.link)
    answers by the one rule, in its words."""
    fixed = 'base_link'   # the root: fixed to the world
    assert arm.link_frames[fixed][0] < 0 and arm.link_frames['hand'][0] >= 0
    why = f"payload link '{fixed}' is not a link that moves a controlled joint"
    version = arm.version
    for call in (lambda: arm.check_payload(fixed, 2.0, COM, INERTIA),
                 lambda: arm.set_payload(fixed, 2.0, COM, INERTIA)):
        with pytest.raises(ValueError, match=why):
            call()
    assert arm.version == version
    request = {'payload.link': fixed, 'payload.mass': 2.0, 'payload.com': COM, 'payload.inertia': INERTIA}
    core = Compensator()
    core.set_model(load_urdf(default_urdf_path()))
    for call in (lambda: payload_service.check_payload_request(request, arm), lambda: core.update(request),
                 lambda: payload_service.check_identify_link(Settings({'identify.link': fixed}), arm)):
        with pytest.raises(ValueError, match=why):
            call()
    assert core.settings['payload.link'] == ''   # refused: nothing changed
    heavy = dict(request, **{'payload.link': 'hand', 'payload.mass': 2000.0})
    for call in (lambda: payload_service.check_payload_request(heavy, arm), lambda: core.update(heavy)):
        with pytest.raises(ValueError, match=r'payload.mass must be in \[0.0, 1000.0\], got 2000.0'):
            call()


def test_payload_keys_are_one_list():
    assert PAYLOAD_KEYS == ('payload.link', 'payload.mass', 'payload.com', 'payload.inertia')
    assert settings_module.PAYLOAD_KEYS is PAYLOAD_KEYS
    assert set(PAYLOAD_KEYS) <= set(contact.REINIT_KEYS) and set(PAYLOAD_KEYS) <= set(settings_module.BLEND_KEYS)


# ---------------------------------------------------------------- description updates
def test_update_refusal_is_the_policy(arm):
    other = load_urdf(default_urdf_path())
    assert update_refusal('none', None) is None and update_refusal('none', None, arm) is None   # nothing runs yet
    assert "description_update is 'none'" in update_refusal('none', arm)          # before reading
    assert "description_update is 'none'" in update_refusal('none', arm, other)
    assert update_refusal('same_robot', arm) is None and update_refusal('any', arm) is None
    assert update_refusal('same_robot', arm, other) is None                          # same name
    other.name = 'another'
    assert "'same_robot'" in update_refusal('same_robot', arm, other)
    assert update_refusal('any', arm, other) is None


# ---------------------------------------------------------------- joint names
def test_joint_columns():
    m = joint_columns(['c', 'x', 'a', 'b'], ['a', 'b', 'c'])
    assert m.columns.tolist() == [2, 3, 0] and not m.duplicates and not m.missing
    m = joint_columns(['a', 'b', 'a', 'c', 'b'], ['a', 'b', 'c'])
    assert m.columns is None and m.duplicates == ['a', 'b'] and m.index['a'] == 0
    m = joint_columns(['b'], ['a', 'b', 'c'])
    assert m.columns is None and m.missing == ['a', 'c']


def test_every_name_mapping_follows_it(arm):
    joints = list(arm.joint_names)
    names = ['finger'] + joints[::-1]
    cols = joint_columns(names, joints).columns
    nm = NameMap()
    nm.build(names, joints)
    assert nm.error is None and nm.idx.tolist() == cols.tolist()
    q = np.linspace(0.1, 0.7, len(joints))
    msg_q = np.concatenate([[9.0], q[::-1]])

    class Point:
        positions, velocities, accelerations = msg_q, [], []

    np.testing.assert_array_equal(read_desired(names, [Point], joints, NameMap())[0], q)
    traj = {'joint_names': names, 'positions': np.stack([msg_q, msg_q]), 'time_from_start': [0.0, 0.1]}
    ref = fill_trajectory_efforts(arm, traj)['efforts']
    fill = TrajectoryFill(arm, None, effort_limits(np.full(arm.n, np.inf)), 1.0)
    efforts, _ = fill.fill(names, traj)
    np.testing.assert_allclose(efforts[:, cols], ref, rtol=0, atol=1e-12)
    assert np.all(efforts[:, 0] == 0)   # not a controlled joint
    # the same refusals in the same words (messages.columns_refusal) for messages and trajectories;
    # the library's own trajectory check (fill_trajectory_efforts) words its ValueError itself
    dup = names + [joints[0]]
    nm.build(dup, joints)
    assert isinstance(nm.error, Rejected) and nm.error.kind == 'duplicate' and joints[0] in nm.error.text
    with pytest.raises(ValueError) as refused:
        fill.fill(dup, dict(traj, joint_names=dup, positions=np.zeros((2, len(dup)))))
    assert str(refused.value) == nm.error.text == f"duplicate joint names ['{joints[0]}']"
    short = names[:-1]
    nm.build(short, joints)
    with pytest.raises(ValueError) as refused:
        fill.fill(short, dict(traj, joint_names=short, positions=msg_q[None, :-1].repeat(2, axis=0)))
    assert str(refused.value) == nm.error.text and nm.error.kind == 'missing'
    assert nm.error.text.startswith(f"missing controlled joints ['{joints[0]}'] (it names ['finger']")
    with pytest.raises(ValueError, match=f"lacks controlled joints \\['{joints[0]}'\\]"):
        fill_trajectory_efforts(arm, dict(traj, joint_names=names[:-1], positions=msg_q[None, :-1]))


# ---------------------------------------------------------------- freshness
def test_fresh_and_its_users():
    assert fresh(10.0, 0.5, 10.5) and not fresh(10.0, 0.5, 10.5 + 1e-9) and not fresh(None, 1e9, 0.0)
    w = Watchdog(0.5)
    w.feed(10.0)
    assert w.expired(10.5) is None and w.expired(10.6) == pytest.approx(0.6)
    g = GravitySource('gravity')
    g.offer((0.0, 0.0, -9.81), '', None, now=10.0)
    assert g.fresh(0.5, 10.5) and not g.fresh(0.5, 10.6)
    core = Compensator({'desired_timeout': 0.5}, clock=lambda: 0.0)
    core.desired_time = 10.0
    assert core.desired_is_fresh(10.5) and not core.desired_is_fresh(10.6)


def test_stale_and_fresh_again_are_said_by_one_object(arm):
    """The desired state (gravity fallback) and the gravity topic (parameter fallback) change
    between fresh and stale through one Freshness each: one flag, one counter, the same lines."""
    f = Freshness('thing', 'thing_timeout', 'thing')
    assert f.check(None, 0.5, 0.0, '/t') == (False, ('warn', 'thing:none', 'no thing received yet on /t'))
    assert f.check(None, 0.5, 1.0, '/t') == (False, None) and f.events == 1 and f.fallen   # said once
    assert f.check(1.0, 0.5, 1.2, '/t') == (True, ('info', 'thing:resumed', 'thing on /t fresh again'))
    assert f.check(1.0, 0.5, 1.5, '/t') == (True, None)
    assert f.check(1.0, 0.5, 1.75, '/t') == (False, ('warn', 'thing:stale',
                                                     'no valid thing on /t for 0.750 s (thing_timeout 0.5 s)'))
    assert f.check(1.0, 0.5, 9.0, '/t') == (False, None) and f.events == 2
    never = Freshness('thing', 'thing_timeout', 'thing')   # never=False: nothing followed, nothing fell back
    assert never.check(None, 0.5, 5.0, '/t', never=False) == (False, None) and not never.fallen
    # the users: each holds one, and its lines are the object's with the user's fallback after them
    t = [0.0]
    core = Compensator({'mode': 'feedforward', 'desired_timeout': 0.5, 'friction.viscous': [0.0],
                        'friction.coulomb': [0.0]}, clock=lambda: t[0])
    core.set_model(arm)
    core.desired_topic = '/d'
    core.on_desired(arm.joint_names, [type('P', (), dict(positions=[0.0] * arm.n, velocities=[],
                                                         accelerations=[]))()], now=0.0)
    core.events.clear()
    core.on_joint_state(arm.joint_names, [0.0] * arm.n, now=0.75)
    assert isinstance(core.desired_state, Freshness) and core.desired_fallback
    assert core.events[-1] == ('warn', 'desired:stale', 'mode feedforward: no valid desired state on /d for 0.750 s '
                                                        '(desired_timeout 0.5 s): gravity compensation at the measured '
                                                        'state')
    assert core.count.fallback_events == 1
    src = GravitySource('/g', clock=lambda: t[0])
    src.offer((0.0, 0.0, -9.81), '', arm, now=0.0)
    src.apply(core, now=0.1)
    src.apply(core, now=0.75)
    assert isinstance(src.freshness, Freshness) and src.freshness.fallen
    assert src.events[-1] == ('warn', 'gravity:stale', 'no valid gravity on /g for 0.750 s (gravity_timeout 0.5 s): '
                                                       'using the gravity parameter [0.0, 0.0, -9.81]')
    src.offer((0.0, 0.0, -9.81), '', arm, now=1.0)
    src.apply(core, now=1.0)
    assert src.events[-1] == ('info', 'gravity:resumed', 'gravity on /g fresh again: following it')


# ---------------------------------------------------------------- typed settings
def test_every_parameter_is_an_attribute_with_its_table_default():
    """Settings is generated from the table: each PARAMS entry an attribute (a dotted name a
    group: payload.link is settings.payload.link) holding the table's default, checked."""
    s = Settings()
    assert len(s) == len(PARAMS)
    for p in PARAMS:
        head, _, member = p.name.partition('.')
        value = getattr(getattr(s, head), member) if member else getattr(s, head)
        assert value == check_value(p.name, p.default) == s.value(p.name) == s[p.name], p.name
    assert s.measured_effort == 'total' and s.collision.threshold == [10.0] and s.payload.link == ''
    assert s.friction.coulomb_velocity_epsilon == SPECS['friction.coulomb_velocity_epsilon'].default
    # read-only: a change is a new object, checked like every value
    with pytest.raises(AttributeError, match='read-only'):
        s.mode = 'pd'
    with pytest.raises(AttributeError, match='read-only'):
        s.payload.mass = 1.0
    t = s.replace({'payload.mass': 2.0, 'mode': 'pd'})
    assert (t.payload.mass, t.mode, s.payload.mass, s.mode) == (2.0, 'pd', 0.0, 'gravity')
    assert t.differs(s, ('mode',)) and not t.differs(s, ('gravity', 'kp'))
    with pytest.raises(ValueError, match='mode must be one of'):
        s.replace({'mode': 'torque'})
    with pytest.raises(ValueError, match='unknown parameter'):
        Settings({'collision.treshold': [1.0]})
    assert Compensator({'mode': 'pd'}).settings.mode == 'pd'


def _string_key_reads(path):
    """(function, line, text) of every read of a parameter by a string key in the file:
    x['payload.link'], x.get('measured_effort', ...); function: the innermost def around it."""
    import ast
    with open(path) as fh:
        tree = ast.parse(fh.read())
    out = []

    def visit(node, function):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            function = node.name
        key = None
        if isinstance(node, ast.Subscript) and isinstance(node.slice, ast.Constant):
            key = node.slice.value
        elif (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.func.attr == 'get'
              and node.args and isinstance(node.args[0], ast.Constant)):
            key = node.args[0].value
        if isinstance(key, str) and key in SPECS:
            out.append((function, node.lineno, ast.unparse(node)))
        for child in ast.iter_child_nodes(node):
            visit(child, function)

    visit(tree, None)
    return out


# Functions that handle a request by parameter name (not the settings): file -> {function: why}.
BY_NAME = {'ros/features/payload_service.py': {'check_payload_request': 'a ~/set_payload request {name: value}'}}


def test_parameters_are_read_as_attributes():
    """No code reads a parameter by its string key (the default would be written again, a typo
    found only when the line runs): settings.measured_effort, not settings.get('measured_effort', ...)."""
    import os
    root = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), 'lie_dynamics')
    found = {}
    for folder, dirs, files in os.walk(root):
        dirs[:] = [d for d in dirs if d != '__pycache__']
        for f in sorted(files):
            if f.endswith('.py'):
                rel = os.path.relpath(os.path.join(folder, f), root).replace(os.sep, '/')
                reads = [r for r in _string_key_reads(os.path.join(folder, f)) if r[0] not in BY_NAME.get(rel, {})]
                if reads:
                    found[rel] = reads
    assert not found, found
    assert _string_key_reads(__file__)   # the check sees such reads (this file has some)
    for rel, functions in BY_NAME.items():   # each exemption still names a function that reads by name
        reads = {r[0] for r in _string_key_reads(os.path.join(root, *rel.split('/')))}
        assert set(functions) <= reads, (rel, functions, reads)


def test_a_name_without_an_attribute_form_is_refused():
    from lie_dynamics.ros.core.settings import _layout
    for bad in ('a.b.c', 'get', 'replace', 'kp.x', 'x-y'):
        with pytest.raises(ValueError, match='attribute form|also a group'):
            _layout(('kp', bad))


# ---------------------------------------------------------------- a sample's time
def test_time_base_and_its_users(arm):
    clock = [100.0]
    tb = TimeBase(lambda: clock[0])
    assert tb.seconds(5 * 10**9) == 0.0 and tb.switched and tb.stamped
    assert tb.seconds(5 * 10**9 + 2_500_000) == pytest.approx(0.0025, abs=1e-15) and not tb.switched
    assert tb.seconds(0) == 0.0 and tb.switched and not tb.stamped   # the clock, from its first reading
    clock[0] = 100.5
    assert tb.seconds(0) == 0.5 and not tb.switched
    assert tb.seconds(5 * 10**9 + 10**9) == 1.0 and tb.switched        # each base keeps its origin
    tb.reset()
    assert tb.seconds(7 * 10**9) == 0.0 and tb.switched
    # its users: the observer, the payload recording (and the dynamics topics' rate gate)
    assert isinstance(contact.ContactMonitor().time, TimeBase)
    core = Compensator({'identify.link': 'hand', 'stale_timeout': 60.0})
    core.set_model(load_urdf(default_urdf_path()))
    ident = payload_service.Identification()
    ident.begin(core)
    names = list(core.model.joint_names)
    for stamp in (10**10, 10**10 + 5_000_000):
        core.on_joint_state(names, np.zeros(7), np.zeros(7), np.ones(7), stamp=stamp)
        ident.add(core.result)
    assert isinstance(ident.time, TimeBase)
    np.testing.assert_array_equal(ident.recording.arrays()[0], [0.0, 0.005])
    ident.stop('test')
    from lie_dynamics.ros.features.recording import SampleLog   # ~/record's recording_max_s
    log = SampleLog(names, 0.005)
    assert isinstance(log.time, TimeBase) and not log.add(core.result) and log.span == 0.0


# ---------------------------------------------------------------- diagnostics and log bounds
def test_features_report_bounds_every_text_once():
    class Loud(Feature):
        def report(self, level, message):
            return level, message + 'm' * 5000, [('loud', 'v' * 5000)]

    level, message, values = Features([Loud()]).report(0, 'core', [('core_value', 'c' * 3000)])
    assert len(message) == DIAG_TEXT_MAX and message.startswith('core') and message.endswith('...')
    assert [len(v) for _, v in values] == [DIAG_TEXT_MAX] * 2
    mon = contact.ContactMonitor()   # a feature's own report is not cut: Features.report does it
    mon.error = 'e' * 3000
    assert dict(mon.report(0, '', [])[2])['observer_error'] == 'e' * 3000


def test_one_paced_log_at_most_its_rate_a_second():
    t, lines = [0.0], []
    log = EventLog(lambda severity, text: lines.append(text), clock=lambda: t[0], pace=1, rate=5)
    log.events([('warn', f'class{k}', f'line {k}') for k in range(12)])   # twelve problem classes at once
    for _ in range(10):
        log.flush(1)
    assert lines == [f'line {k}' for k in range(5)] and log.waiting == 7
    t[0] = 0.999
    log.flush()
    assert len(lines) == 5
    t[0] = 1.0
    log.flush()
    assert len(lines) == 10
    log.close()   # shutdown: everything, the rate aside
    assert lines == [f'line {k}' for k in range(12)]


# ---------------------------------------------------------------- kernel warm-up
WARMED = []


def _warmed(model):
    WARMED.append(model.n)


def test_warm_up_runs_the_features_calls(arm):
    WARMED.clear()
    calls = ((_warmed,), (at_rest, 'mass_matrix'))   # hashable: each runs once however often named
    warm_up(arm, calls + calls)
    assert WARMED == [arm.n]
    sent = portable(calls + ((lambda m: None,),))   # a lambda does not pickle: left to the loading thread
    assert len(sent) == 2 and all(isinstance(c, bytes) for c in sent)
    warm_up(arm, sent + (b'not a pickle',))   # one the build process cannot read is skipped
    assert WARMED == [arm.n] * 2


def test_the_observer_gain_follows_the_per_joint_rule():
    """The math core's observer expands its gain by the same rule as the node's parameters."""
    from lie_dynamics import default_urdf_path, load_urdf
    from lie_dynamics.algorithms.observer import MomentumObserver
    from lie_dynamics.ros.core import params
    assert params.broadcast_joints is broadcast_joints   # the rule per_joint_values expands by
    model = load_urdf(default_urdf_path())
    n = model.n
    for gain in (5.0, [5.0], np.full(n, 5.0)):
        np.testing.assert_array_equal(MomentumObserver(model, gain).gain, np.full(n, 5.0))
    for bad in ([1.0, 2.0], [0.0], [np.nan], np.ones((1, n))):
        with pytest.raises(ValueError, match='observer gain must be one positive number'):
            MomentumObserver(model, bad)
