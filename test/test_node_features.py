"""Per-sample features on a real node (an rclpy context in this process, joint_states as the
serialized bytes its subscription delivers): a registered feature sees each accepted state
once, in order, after its command, and no rejected one, across a model version change and a
model swap from a new robot_description; and the plain-Python pieces the node's shell uses
(core/sample.py, core/log.py, loading/parameter_change.py) without ROS."""
import os
import pickle
import re
import struct
import threading
import time

import numpy as np
import pytest

from lie_dynamics import default_urdf_path
from lie_dynamics.ros.core.compensator import Compensator
from lie_dynamics.ros.core.log import LOG_LINES_PER_CALLBACK, EventLog
from lie_dynamics.ros.core.sample import SampleResult
from lie_dynamics.ros.core.watchdog import Every, tick_period
from lie_dynamics.ros.loading.parameter_change import ParameterChanges, plan_change, reload_answer, start_source

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
JOINTS = [f'joint{i}' for i in range(1, 8)]
Q = np.array([0.1, 0.5, -0.2, 1.2, 0.3, 0.8, 0.1])


def heavier(xml, factor):
    return re.sub(r'<mass value="([^"]*)"', lambda m: f'<mass value="{factor * float(m.group(1))!r}"', xml)


# ---------------------------------------------------------------------- a real node
@pytest.fixture
def node_in_context():
    rclpy = pytest.importorskip('rclpy')
    from lie_dynamics.ros.features.base import Feature
    from lie_dynamics.ros.node import FEATURES, DynamicsNode

    order = []   # ('command' | 'feature', stamp), as they happen

    class Recording(Feature):
        name = 'recording'

        def __init__(self, node):
            super().__init__()
            self.seen, self.arrays = [], []

        def configure(self, settings, model, derived):
            self.active = model is not None

        def on_sample(self, s):
            order.append(('feature', s.stamp))
            self.seen.append((s.stamp, s.version, s.model))
            self.arrays.append((np.array(s.q), np.array(s.effort)))

    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    node = DynamicsNode('feature_test_node', context=ctx, features=(Recording,) + FEATURES, parameter_overrides=[
        rclpy.parameter.Parameter('urdf_path', value=default_urdf_path()),
        rclpy.parameter.Parameter('stale_timeout', value=60.0), rclpy.parameter.Parameter('ramp_time', value=0.0)])
    command = node.outputs.command

    def recorded_command(tau, names, stamp=None):
        order.append(('command', stamp))
        command(tau, names, stamp)
    node.outputs.command = recorded_command
    # the fused command path (ros/core/fused.py) publishes bytes it made through Outputs.publish: its
    # command is the one of the message being handled, whose stamp the header's first 8 bytes give
    publish, on_joint_state, handling = node.outputs.publish, node.on_joint_state, [None]

    def recorded_publish(command, joint_state=None):
        order.append(('command', handling[0]))
        publish(command, joint_state)

    def handle(data):
        if isinstance(data, bytes) and len(data) >= 12:
            sec, nsec = struct.unpack_from('<iI', data, 4)
            handling[0] = sec * 10**9 + nsec
        return on_joint_state(data)
    node.outputs.publish = recorded_publish
    node.on_joint_state = handle
    lines = []
    emit = node.event_log.emit
    node.event_log.emit = lambda severity, text: (lines.append(text), emit(severity, text))
    node.lines = lines
    try:
        yield node, node.features.get('recording'), order
    finally:
        node.destroy_node()
        rclpy.shutdown(context=ctx)


def serialized(q, stamp, names=JOINTS, effort=None):
    from rclpy.serialization import serialize_message
    from sensor_msgs.msg import JointState
    m = JointState(name=list(names), position=[float(v) for v in q], velocity=[0.0] * len(names),
                   effort=[float(v) for v in (np.arange(len(names)) if effort is None else effort)])
    m.header.stamp.sec, m.header.stamp.nanosec = divmod(stamp, 10**9)
    return bytes(serialize_message(m))


def test_each_accepted_state_once_in_order_across_a_model_swap(node_in_context):
    from rclpy.parameter import Parameter
    node, rec, order = node_in_context
    core = node.core
    first = core.model
    expected, rejected = [], []
    stamp = 10**9

    def send(data, stamp, good):
        n = core.count.accepted
        node.on_joint_state(data)
        if core.count.accepted == n + 1:
            expected.append((stamp, core.model.version, core.model))
        else:
            rejected.append(stamp)
        assert (core.count.accepted == n + 1) == good, (stamp, core.last_error)

    for k in range(40):
        stamp += 1_000_000
        send(serialized(Q + 0.001 * k, stamp), stamp, True)
        if k % 5 == 1:   # a non-finite position: rejected
            send(serialized(np.full(7, np.nan), stamp + 1), stamp + 1, False)
        if k % 5 == 2:   # older than the last accepted: rejected
            send(serialized(Q, stamp - 500_000), stamp - 500_000, False)
        if k % 5 == 3:   # a controlled joint missing: rejected
            send(serialized(Q[:6], stamp + 2, JOINTS[:6]), stamp + 2, False)
        if k % 5 == 4:   # malformed bytes: rejected, no stamp read
            node.on_joint_state(b'\x00\x01\x00\x00\x07')
        if k == 10:      # the model's version changes (a payload), not the model
            assert all(r.successful for r in node.set_parameters([Parameter('payload.link', value='hand'),
                                                                  Parameter('payload.mass', value=1.5)]))
        if k == 20:      # a new description: the swap happens between two states
            with open(default_urdf_path()) as fh:
                xml = heavier(fh.read(), 2.0)
            assert node.set_parameters([Parameter('robot_description', value=xml)])[0].successful
            deadline = time.monotonic() + 60
            while core.model is first and time.monotonic() < deadline:
                stamp += 1_000_000
                send(serialized(Q, stamp), stamp, True)
                time.sleep(0.01)
            assert core.model is not first
    seen = rec.seen
    assert seen == expected
    assert not [line for line in node.lines if 'internal error' in line]
    assert any('rejected' in line for line in node.lines)
    assert not set(rejected) & {s for s, _, _ in seen}
    on_first = [m is first for _, _, m in seen]
    assert on_first == sorted(on_first, reverse=True) and on_first[0] and not on_first[-1]   # one swap
    for model in (first, core.model):
        versions = [v for _, v, m in seen if m is model]
        assert versions == sorted(versions)
    assert len({v for _, v, m in seen if m is first}) >= 2   # the payload changed the version, not the model
    stamps = [s for s, _, _ in seen]
    assert stamps == sorted(stamps) and len(set(stamps)) == len(stamps)
    # each state's command went out before any feature saw it
    assert [s for what, s in order if what == 'feature'] == stamps
    for s in stamps:
        assert order.index(('command', s)) < order.index(('feature', s))
    # what the feature got: the validated positions and the message's efforts, in model order
    np.testing.assert_array_equal(rec.arrays[0][0], Q)
    np.testing.assert_array_equal(rec.arrays[0][1], np.arange(7.0))
    # the node's diagnostics and events come from the one queue and the one chain
    level, message, values = node.features.report(*core.diagnostics())
    keys = [k for k, _ in values]
    assert keys.index('observer') < keys.index('gravity_source') < keys.index('payload_identification') \
        < keys.index('dynamics_topics')
    assert not node.events


def kernel_builders(monkeypatch):
    """The list of the threads that build a kernel's Python forms or its C library from now on
    (kernel.builds() counts every thread's: the loader thread may build meanwhile)."""
    from lie_dynamics.codegen.kernel import Kernel
    builders = []

    def spying(name):
        orig = getattr(Kernel, name)

        def spy(self):
            if not self.built(name == 'native'):
                builders.append(threading.get_ident())
            return orig(self)
        return spy
    for name in ('python', 'native'):
        monkeypatch.setattr(Kernel, name, spying(name))
    return builders


def test_a_new_structure_swaps_in_without_generating_kernels_on_the_control_path(node_in_context, tmp_path,
                                                                                   monkeypatch):
    """Every kernel the command and the features call for a new kinematic structure (the laws,
    the observer, each ~/dynamics term) is generated where the model is built, not in the
    joint_states callback that swaps it in (the observer's kernel was compiled there)."""
    from rclpy.parameter import Parameter

    monkeypatch.setenv('LIE_DYNAMICS_CACHE_DIR', str(tmp_path))   # nothing cached: the build process compiles
    builders = kernel_builders(monkeypatch)
    node, rec, order = node_in_context
    core = node.core
    assert all(r.successful for r in node.set_parameters([
        Parameter('dynamics.publish', value=['gravity', 'coriolis', 'mass_matrix', 'jacobian']),
        Parameter('dynamics.rate', value=0.0)]))
    stamp = 10**9
    for _ in range(5):
        stamp += 1_000_000
        node.on_joint_state(serialized(Q, stamp))
    assert node.contact_monitor.active
    first = core.model
    with open(default_urdf_path()) as fh:
        xml = fh.read()
    old = '<origin xyz="0 0 0.34" rpy="0 0 0"/>'
    assert old in xml
    # joint1 moved by 3.217 micrometres: a structure no other test uses
    xml = xml.replace(old, '<origin xyz="0 0 0.340003217" rpy="0 0 0"/>', 1)
    assert node.set_parameters([Parameter('robot_description', value=xml)])[0].successful
    deadline = time.monotonic() + 120
    while node.background.worker.busy('model') is not None and time.monotonic() < deadline:
        time.sleep(0.01)
    published = dict(node.features.get('dynamics').published)
    n0, deferred = len(node.lines), node.background.builds_deferred
    builders.clear()
    for k in range(5):   # the swap, then the first samples on the new model
        stamp += 1_000_000
        n = len(node.lines)
        node.on_joint_state(serialized(Q + 0.01 * k, stamp))
        assert threading.get_ident() not in builders, k
        assert node.background.builds_deferred == deferred, k   # warmed with the model: none lacking
        assert len(node.lines) - n <= LOG_LINES_PER_CALLBACK, node.lines[n:]   # the swap's lines are paced
    assert core.model is not first and rec.seen[-1][2] is core.model
    node.event_log.close()   # ('model' lines are throttled: start-up said one within 2 s; and the waiting ones)
    swap_lines = node.lines[n0:]
    assert any('loaded' in t for t in swap_lines), swap_lines
    assert any('joint frames or axes changed' in t for t in swap_lines), swap_lines
    assert node.contact_monitor.active and node.contact_monitor.samples > 0
    after = node.features.get('dynamics').published
    assert all(after[t] > published[t] for t in published), (published, after)


def test_a_feature_turned_on_at_run_time_gets_its_kernels_built_off_the_control_path(node_in_context, tmp_path,
                                                                                   monkeypatch):
    """A kernel the control path lacks (here: ~/dynamics terms turned on after their model was
    loaded, on a structure no cache holds) is not built in a joint_states callback: the reference
    answers there, the loader thread builds it, and later samples use it."""
    from rclpy.parameter import Parameter

    monkeypatch.setenv('LIE_DYNAMICS_CACHE_DIR', str(tmp_path))
    builders = kernel_builders(monkeypatch)
    node, rec, order = node_in_context
    core = node.core
    with open(default_urdf_path()) as fh:
        xml = fh.read()
    # joint1 moved by 5.113 micrometres: a structure no other test uses, loaded with no ~/dynamics term
    xml = xml.replace('<origin xyz="0 0 0.34" rpy="0 0 0"/>', '<origin xyz="0 0 0.340005113" rpy="0 0 0"/>', 1)
    first = core.model
    assert node.set_parameters([Parameter('robot_description', value=xml)])[0].successful
    deadline = time.monotonic() + 120
    while node.background.worker.busy('model') is not None and time.monotonic() < deadline:
        time.sleep(0.01)
    stamp = 10**9
    node.on_joint_state(serialized(Q, stamp))
    assert core.model is not first
    assert all(r.successful for r in node.set_parameters([
        Parameter('dynamics.publish', value=['mass_matrix', 'jacobian']), Parameter('dynamics.rate', value=0.0)]))
    deferred = node.background.builds_deferred
    builders.clear()
    for k in range(5):
        stamp += 1_000_000
        node.on_joint_state(serialized(Q + 0.01 * k, stamp))
    me = threading.get_ident()
    assert me not in builders   # the callbacks built nothing ...
    assert node.background.builds_deferred > deferred   # ... they asked the loader thread
    published = dict(node.features.get('dynamics').published)
    assert published['mass_matrix'] >= 5 and published['jacobian'] >= 5   # answered by the reference
    while node.background.worker.busy('kernels') is not None and time.monotonic() < deadline:
        time.sleep(0.01)
    assert builders and me not in builders   # built there
    deferred = node.background.builds_deferred
    for _ in range(3):
        stamp += 1_000_000
        node.on_joint_state(serialized(Q, stamp))
    assert node.background.builds_deferred == deferred and me not in builders   # now the kernels serve


def test_features_name_the_kernels_they_call(node_in_context):
    """Feature.kernels: what loading/models.warm_up runs for every new model, per the settings."""
    from lie_dynamics.ros.features.contact import warm_observer
    from lie_dynamics.ros.features.payload_service import warm_fit
    from lie_dynamics.ros.loading.models import at_rest, jacobian_at_rest
    node = node_in_context[0]
    s = node.core.settings
    assert node.features.kernels(s) == ((warm_observer,),)   # the defaults: the observer only
    s = s.replace({'observer.enabled': False, 'dynamics.publish': ['mass_matrix', 'jacobian'],
                   'identify.link': 'tool0'})
    calls = node.features.kernels(s)
    assert set(calls) == {(at_rest, 'mass_matrix'), (jacobian_at_rest, '', s['dynamics.jacobian_frame']), (warm_fit,)}
    assert pickle.loads(pickle.dumps(calls)) == calls   # as they travel to the build process
    s = s.replace({'identify.link': '', 'measured_effort': 'none', 'observer.enabled': True, 'dynamics.publish': []})
    assert node.features.kernels(s) == ()


WARMED = []   # models the test feature's own warm-up call ran on (in the node's process)


def _count_warm(model):
    """A feature's own warm-up call. This test module is not on the build process's path: there
    the call is skipped (models.portable), and the build goes on."""
    WARMED.append(model)


def test_a_new_feature_is_one_class_and_one_registration_line():
    """A per-sample feature written here, registered with one line (the node's `features`: its
    FEATURES and this class), runs on a real node over DDS: refuses a setting on set, warms its
    kernels with each new model (also one built in the build process), gets each accepted state
    in model order, says a line through the one queue and adds its part to the diagnostics.
    Nothing else in the node changes."""
    pytest.importorskip('rclpy')
    from lie_dynamics import load_urdf
    from lie_dynamics.ros.features.base import Feature
    from lie_dynamics.ros.loading.models import at_rest
    from lie_dynamics.ros.node import FEATURES
    from std_msgs.msg import String
    from test_node import MODEL_TIMEOUT, Harness, wait_until

    class PeakEffort(Feature):
        """The largest |effort| measured so far, with its joint."""
        name = 'peak_effort'

        def __init__(self, node):
            super().__init__()
            self.peak, self.joint, self.samples = 0.0, '', 0

        def check(self, settings, model):
            if settings['dynamics.link'] == 'link3':   # a link the node itself takes
                raise ValueError('peak_effort refuses this link')

        def kernels(self, settings):
            return ((at_rest, 'mass_matrix'), (_count_warm,))

        def configure(self, settings, model, derived):
            self.active = model is not None

        def on_sample(self, s):
            e = np.abs(s.effort)
            k = int(np.argmax(e))
            if e[k] > self.peak:
                self.peak, self.joint = float(e[k]), s.names[k]
                self.events.append(('info', 'peak_effort', f'new peak effort {self.peak:g} N m at {self.joint}'))
            self.samples += 1   # last: the test's thread waits for it, then reads the peak

        def report(self, level, message):
            return level, message, [('peak_effort', f'{self.peak:g}'), ('peak_effort_joint', self.joint)]

    ros = Harness()
    try:
        WARMED.clear()
        with open(default_urdf_path()) as fh:
            xml = fh.read()
        node = ros.start(robot_description=xml, diagnostics_period=0.2,
                         features=FEATURES + (PeakEffort,))   # the one registration line
        feature = node.features.get('peak_effort')
        assert WARMED and WARMED[-1] is node.core.model      # warmed with the model it was built for
        result = ros.set_params(**{'dynamics.link': 'link3'})[0]
        assert not result.successful and 'peak_effort refuses this link' in result.reason
        efforts = np.array([0.5, -3.0, 1.0, 2.5, 0.0, -0.1, 0.2])
        order = JOINTS[::-1]   # message order: the feature sees model order
        ros.publish_processed(order, Q[::-1], np.zeros(7), efforts[::-1])
        wait_until(lambda: feature.samples >= 1, what='a sample')
        assert feature.peak == 3.0 and feature.joint == 'joint2'
        wait_until(lambda: any('new peak effort 3 N m at joint2' in line for line in ros.logs), what='its log line')
        wait_until(lambda: ros.diag_values().get('peak_effort') == '3', what='its diagnostics')
        assert ros.diag_values()['peak_effort_joint'] == 'joint2'
        # a new description, built in the build process (which cannot import this module)
        first, warmed = node.core.model, len(WARMED)
        ros.desc_pub.publish(String(data=heavier(xml, 2.0)))
        wait_until(lambda: node.core.model is not first, timeout=MODEL_TIMEOUT, what='the new model')
        assert len(WARMED) > warmed and WARMED[-1] is node.core.model
        assert np.allclose(node.core.model.mass_matrix(Q), load_urdf(heavier(xml, 2.0)).mass_matrix(Q))
    finally:
        ros.close()


# ---------------------------------------------------------------------- the core pieces, without ROS
def test_sample_result_is_immutable_and_maps_to_model_order():
    core = Compensator({'stale_timeout': 60.0, 'ramp_time': 0.0})
    core.on_joint_state(JOINTS, Q, stamp=3)
    r = core.result
    assert not r.accepted and r.reason == 'no_model' and r.stamp == 3
    core.load(default_urdf_path())
    order = JOINTS[::-1]
    core.on_joint_state(order, Q[::-1], [np.inf] + list(range(6))[::-1], list(range(7))[::-1], stamp=5)
    r = core.result
    assert r.accepted and r.reason == '' and r.version == core.model.version and r.model is core.model
    assert r.names is core.layout and r.q is core.last_q
    np.testing.assert_array_equal(r.q, Q)
    np.testing.assert_array_equal(r.effort, np.arange(7.0))
    assert np.isinf(r.velocity[-1]) and np.array_equal(r.qd, [0, 1, 2, 3, 4, 5, 0])
    assert r.qd is r.qd   # made once
    with pytest.raises(AttributeError):
        r.stamp = 6
    for a in (r.q, r.velocity, r.qd, r.effort):
        with pytest.raises(ValueError):
            a[0] = 1.0
    core.on_joint_state(JOINTS, Q, stamp=4)   # older: refused, and said why
    r = core.result
    assert not r.accepted and r.reason == 'old' and 'older than the last accepted' in r.why and r.q is None
    core.refuse_malformed('joint_states', 'truncated')
    assert core.result.reason == 'malformed' and not core.result.accepted
    # without efforts: NaN in model order
    core.on_joint_state(JOINTS, Q, stamp=7)
    assert core.result.accepted and np.isnan(core.result.effort).all() and not core.result.qd.any()
    assert isinstance(core.result, SampleResult)


def test_use_gravity_blends_only_a_source_switch_after_a_command():
    t = [0.0]
    core = Compensator({'ramp_time': 1.0, 'stale_timeout': 60.0}, clock=lambda: t[0])
    core.load(default_urdf_path())
    version = core.model.version
    core.use_gravity(np.array([0.0, 0.0, -9.81]), blend=True)   # the same vector, nothing sent yet
    assert core.model.version == version and core.ramp.idle
    g0 = core.on_joint_state(JOINTS, Q)
    core.use_gravity(np.array([0.0, -9.81, 0.0]))
    assert core.model.version > version and np.allclose(core.model.gravity_vector, [0, -9.81, 0])
    assert core.ramp.idle
    core.use_gravity(np.array([0.0, -9.81, 0.0]), blend=True)
    assert not core.ramp.idle   # the next commands blend from the last one
    assert np.allclose(core.on_joint_state(JOINTS, Q), g0)   # at the switch: still the old command


def test_event_log_throttles_per_class_and_says_what_it_held_back():
    t = [0.0]
    lines = []
    log = EventLog(lambda severity, text: lines.append((severity, text)), period=2.0, clock=lambda: t[0])
    log.events([('warn', 'a', 'first'), ('warn', 'a', 'second'), ('warn', 'a', 'third'), ('info', 'b', 'other'),
                ('error', None, 'x' * 5000)])
    assert lines[:2] == [('warn', 'first'), ('info', 'other')] and lines[2][0] == 'error'
    assert len(lines[2][1]) < 5000   # bounded
    log.held()
    assert len(lines) == 3   # the period is not over
    t[0] = 2.5
    log.held()
    assert lines[3] == ('warn', 'third (1 more like this in the last 2 s)')
    t[0] = 3.0
    log.event('warn', 'a', 'fourth')   # within the period the held line opened
    t[0] = 10.0
    log.event('warn', 'a', 'fifth')
    assert lines[4:] == [('warn', 'fifth (1 more like this in the last 2 s)')]


def test_a_paced_event_log_writes_its_lines_in_order_a_few_per_flush():
    lines = []
    log = EventLog(lambda severity, text: lines.append((severity, text)), period=2.0, clock=lambda: 0.0, pace=1,
                   queue_max=3)
    log.events([('info', None, 'first'), ('warn', 'a', 'second'), ('warn', 'a', 'held back'), ('info', None, 'third')])
    assert lines == [] and log.waiting == 3   # decided (the throttle held one back), not written yet
    log.flush(1)
    assert lines == [('info', 'first')] and log.waiting == 2
    log.events([('error', None, 'fourth'), ('error', None, 'fifth')])   # the queue holds 3: one is counted
    log.flush()
    assert [t for _, t in lines] == ['first', 'second', 'third', 'fourth',
                                     'log lines not written: 1 (more than 3 were waiting)']
    assert log.waiting == 0 and log.dropped == 0
    # the timer: one line while messages come (their callbacks write the others), all when none came
    log.events([('info', None, 'a'), ('info', None, 'b'), ('info', None, 'c')])
    log.tick(7)
    assert lines[-1] == ('info', 'a') and log.waiting == 2
    log.tick(8)
    assert lines[-1] == ('info', 'b') and log.waiting == 1
    log.events([('info', None, 'd')])
    log.tick(8)   # no message since the last tick
    assert [t for _, t in lines[-2:]] == ['c', 'd'] and log.waiting == 0


def test_parameter_change_plans_checks_and_loads():
    core = Compensator({'stale_timeout': 60.0})
    core.load(default_urdf_path())
    checked, prechecked = [], []

    def check(settings):
        checked.append(settings['mode'])
        if settings['dynamics.link'] == 'nowhere':
            raise ValueError('no such link')

    def precheck(kind, text, settings):
        prechecked.append((kind, text))
        return 'too big' if text == 'big.urdf' else None

    source = [('file', default_urdf_path())]
    changes = ParameterChanges(core, check, precheck, lambda: source[0])
    assert changes.validate({'mode': 'feedforward'}) is None and checked == ['feedforward']
    cmd, load = changes.apply({'mode': 'feedforward'})
    assert cmd is None and load is None and core.settings['mode'] == 'feedforward'
    assert 'no such link' in changes.validate({'dynamics.link': 'nowhere'}) and changes.pending is None
    assert core.settings['dynamics.link'] == ''
    assert changes.validate({'urdf_path': 'big.urdf'}).endswith('too big')
    plan, load = plan_change(core, {'urdf_path': 'other.urdf', 'mode': 'gravity'}, check, precheck, lambda: source[0])
    assert load == ('file', 'other.urdf') and plan.settings['mode'] == 'gravity'
    # another inertia policy reloads the running description, unless description_update forbids it
    _, load = plan_change(core, {'inertia_policy': 'repair'}, check, precheck, lambda: source[0])
    assert load == source[0]
    with pytest.raises(ValueError, match="description_update is 'none'"):
        plan_change(core, {'inertia_policy': 'repair', 'description_update': 'none'}, check, precheck,
                    lambda: source[0])
    # a change applied without its validation (or after another) is planned again
    assert changes.validate({'mode': 'pd'}) is None
    cmd, _ = changes.apply({'enabled': False})   # nothing was published: no zero command to send
    assert core.settings['mode'] == 'feedforward' and not core.settings['enabled'] and cmd is None


def test_tick_period_serves_the_watchdog_and_the_diagnostics():
    assert tick_period(0.5, 1.0) == 0.25 and tick_period(10.0, 1.0) == 1.0 and tick_period(0.001, 1.0) == 0.002


def test_every_is_due_once_per_period_and_a_late_check_keeps_no_debt():
    now = [0.0]
    every = Every(1.0, clock=lambda: now[0])
    seen = []
    for t in (0.5, 1.0, 1.2, 2.0, 2.9, 3.0, 6.5, 6.6, 7.4, 7.5):
        now[0] = t
        seen.append(every.due())
    assert seen == [False, True, False, True, False, True, True, False, False, True]


def test_start_source_and_reload_answer():
    assert start_source({'robot_description': '', 'urdf_path': ''}) is None
    assert start_source({'robot_description': '<robot/>', 'urdf_path': 'a.urdf'}) == ('parameter', '<robot/>')
    assert start_source({'robot_description': '', 'urdf_path': 'a.urdf'}) == ('file', 'a.urdf')
    assert reload_answer(None, None, None) == (False, 'no robot description to reload')
    assert reload_answer('file', 'a.urdf', 'refused: too big') == (False, 'refused: too big')
    ok, text = reload_answer('file', 'a.urdf', None)
    assert ok and 'a.urdf' in text and 'the running model answers until it is ready' in text


def test_a_kernel_build_that_fails_is_reported_once_and_not_asked_for_again(monkeypatch):
    from lie_dynamics import load_urdf
    from lie_dynamics.codegen import runtime
    from lie_dynamics.ros.loading.background import Background
    from lie_dynamics.ros.loading.sources import Sources
    from robots import random_urdf
    core = Compensator({'stale_timeout': 60.0})
    core.load(default_urdf_path())
    background = Background(core, Sources())
    tried = []

    def failing(model, spec):
        tried.append(spec.name)
        raise RuntimeError('no compiler today')
    monkeypatch.setattr(runtime, 'build', failing)
    model = load_urdf(random_urdf(90818, 5))   # a structure no other test uses: nothing built
    q = np.linspace(-1.0, 1.0, model.n)
    try:
        for _ in range(3):
            with background.deferred():
                g = model.gravity(q)   # the reference answers meanwhile
            deadline = time.monotonic() + 30
            while background.worker.busy('kernels') is not None and time.monotonic() < deadline:
                time.sleep(0.01)
            background.collect()
        assert np.allclose(g, model.gravity(q))
        assert tried == ['gravity'] and background.builds_deferred == 1
        said = [e for e in core.events if e[1] == 'kernels']
        assert len(said) == 1 and 'no compiler today' in said[0][2]
    finally:
        background.stop()
