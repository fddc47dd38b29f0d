"""Model builds in the build process (lie_dynamics.ros.loading.build_process) and trajectories in
the trajectory process (lie_dynamics.ros.trajectories.process): models pickle whole, a child
that dies or hangs is reported once while the running model keeps answering and a new one
takes over, nothing outlives the node, and replies keep flowing during heavy loads (the node
as its own process, measured from another one)."""
import os
import pickle
import signal
import time

import numpy as np
import pytest

rclpy = pytest.importorskip('rclpy')

from std_msgs.msg import String  # noqa: E402
from std_srvs.srv import Trigger  # noqa: E402
from trajectory_msgs.msg import JointTrajectory  # noqa: E402

from bench.node_loads import folded_description  # noqa: E402
from lie_dynamics import load_urdf  # noqa: E402
from lie_dynamics.ros.loading.build_process import BuildLost, BuildProcess  # noqa: E402
from lie_dynamics.ros.trajectories.process import (SILENT_S, STOP_S, TrajectoryProcess, dds_segments,  # noqa: E402
                                                   remove_dead_segments)
from lie_dynamics.ros.trajectories.trajectory_process import child_config  # noqa: E402
from lie_dynamics.ros.core.params import SPECS  # noqa: E402
from lie_dynamics.ros.node import LOG_THROTTLE_S  # noqa: E402
from test_node import MODEL_TIMEOUT, wait_until  # noqa: E402

from test_node_robustness import ARM, JOINTS, Q, ROOT, heavier, serialized  # noqa: E402

BIG = {'max_description_links': 5000, 'max_description_bytes': 20_000_000}



def _alive(pid):
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    return True


SHM = '/dev/shm'


def _shm_files():
    return set(os.listdir(SHM)) if os.path.isdir(SHM) else set()


def _shm_in_use():
    """Names of the /dev/shm files some live process maps or holds open."""
    used = set()
    for pid in filter(str.isdigit, os.listdir('/proc')):
        try:
            with open(f'/proc/{pid}/maps') as fh:
                used.update(line.split(SHM + '/', 1)[1].split()[0] for line in fh if SHM + '/' in line)
            for fd in os.listdir(f'/proc/{pid}/fd'):
                target = os.readlink(f'/proc/{pid}/fd/{fd}')
                if target.startswith(SHM + '/'):
                    used.add(target[len(SHM) + 1:].split()[0])
        except OSError:   # a process that ended meanwhile, or one we may not read
            continue
    return used


def _remove_files_of_killed_processes(before):
    """A process killed with -9 leaves its Fast DDS shared-memory files behind (no participant
    cleanup runs): remove those this test made that no live process maps or holds, with their
    `_el` and `sem.<name>_mutex` companions (only when the file they belong to goes too)."""
    new = _shm_files() - before
    dead = {n for n in new - _shm_in_use() if 'fastrtps' in n}
    owners = {n for n in dead if not n.endswith('_el') and not n.startswith('sem.')}
    for name in dead:
        base = name[len('sem.'):-len('_mutex')] if name.startswith('sem.') else name.removesuffix('_el')
        if base in owners or base not in new:
            try:
                os.remove(os.path.join(SHM, name))
            except OSError:
                pass


def test_a_built_model_pickles_whole():
    model = load_urdf(folded_description(300), joints=JOINTS)
    copy = pickle.loads(pickle.dumps(model))
    assert copy.link_frames.keys() == model.link_frames.keys() and len(copy.link_frames) == 300
    for link, (b, T) in model.link_frames.items():
        assert copy.link_frames[link][0] == b and np.array_equal(copy.link_frames[link][1], T)
    for k, v in vars(model).items():   # the model's arrays stay read-only
        if isinstance(v, np.ndarray):
            assert getattr(copy, k).flags.writeable == v.flags.writeable, k
    assert not copy.M.flags.writeable and not copy.link_frames['link1'][1].flags.writeable
    np.testing.assert_array_equal(copy.gravity(Q), model.gravity(Q))
    np.testing.assert_array_equal(copy.inverse_dynamics(Q, Q, Q), model.inverse_dynamics(Q, Q, Q))


def test_build_process_answers_refuses_and_is_replaced():
    proc = BuildProcess()
    try:
        model, other = proc.build(ARM, (False, 10**6, 100), joints=JOINTS)
        np.testing.assert_array_equal(model.gravity(Q), load_urdf(ARM).gravity(Q))
        assert other == []
        with pytest.raises(ValueError, match='max_description_links'):
            proc.build(ARM, (False, 10**6, 3), joints=JOINTS)
        with pytest.raises(ValueError, match='not-a-joint'):
            proc.build(ARM, None, joints=['not-a-joint'])
        # description_update applied where the model is built: another robot is refused there
        # (no model travels back only to be refused), the same robot is answered
        name = load_urdf(ARM).name
        with pytest.raises(ValueError, match="is not the running robot 'other'.*same_robot"):
            proc.build(ARM, None, joints=JOINTS, running=('same_robot', 'other'))
        assert proc.build(ARM, None, joints=JOINTS, running=('same_robot', name))[0].name == name
        assert proc.build(ARM, None, joints=JOINTS, running=('any', 'other'))[0].name == name
        first = proc.pid
        os.kill(first, signal.SIGKILL)
        with pytest.raises(BuildLost, match='signal 9'):
            proc.build(ARM, None, joints=JOINTS)
        proc.timeout = 0.05   # far less than any build takes
        with pytest.raises(BuildLost, match='did not answer'):
            proc.build(folded_description(2000), None, joints=JOINTS)
        proc.timeout = 60.0
        assert proc.build(ARM, None, joints=JOINTS)[0].n == 7 and proc.started == 3
        assert not _alive(first)
    finally:
        pid = proc.pid
        proc.stop()
    assert pid is not None and not _alive(pid) and proc.pid is None
    with pytest.raises(BuildLost, match='stopped'):   # no child starts after stop
        proc.build(ARM, None, joints=JOINTS)
    assert proc.started == 3 and proc.pid is None


def _loading(node):
    return node.background.process.pid is not None and node.core.loading != ''


def test_the_build_process_answers_a_repeated_request_without_building_again(tmp_path):
    """(in-process: the build process's Builder) 20 reloads of an unchanged file cost one build;
    a changed file, other options or a description that fails are built (and the failure is not
    kept)."""
    from lie_dynamics.ros.loading.build_process import Builder
    path = tmp_path / 'arm.urdf'
    path.write_text(ARM)
    caps = (True, 10**7, 1000)

    def request(gravity=(0.0, 0.0, -9.81)):
        return str(path), caps, JOINTS, gravity, 'warn', None, ()
    builder = Builder()
    answers = [builder.answer(request()) for _ in range(20)]
    assert all(ok for ok, _ in answers) and builder.builds == 1
    np.testing.assert_allclose(answers[-1][1][0].gravity(Q), load_urdf(ARM).gravity(Q), atol=1e-12)
    path.write_text(heavier(ARM, 2.0))   # the file changed: read again, built again
    ok, (model, _) = builder.answer(request())
    assert ok and builder.builds == 2
    np.testing.assert_allclose(model.gravity(Q), load_urdf(heavier(ARM, 2.0)).gravity(Q), atol=1e-12)
    assert builder.answer(request((0.0, -9.81, 0.0)))[0] and builder.builds == 3   # other options
    path.write_text('<robot name="broken">')
    assert builder.answer(request())[0] is False and builder.answer(request())[0] is False
    assert builder.builds == 5   # a failure is built again
    path.write_text(heavier(ARM, 2.0))
    assert builder.answer(request((0.0, -9.81, 0.0)))[0] and builder.builds == 5   # the last model built


def test_a_node_without_a_model_starts_its_build_process_at_once(ros):
    """Waiting for its first description, the node starts the build process at start-up (an
    interpreter's start-up took ~10 s on a loaded machine), and that process builds it."""
    node = ros.start(wait_model=False)
    proc = node.background.process
    assert node.core.model is None and proc.started == 1
    pid = proc.pid
    assert pid is not None
    ros.desc_pub.publish(String(data=ARM))
    wait_until(lambda: node.core.model is not None, timeout=MODEL_TIMEOUT, what='model from the topic')
    assert proc.started == 1 and proc.pid == pid


def test_a_build_process_that_dies_or_hangs_is_reported_once(ros):
    node = ros.start(robot_description=ARM, **BIG)
    g_arm = load_urdf(ARM).gravity(Q)
    big = folded_description(5000)   # seconds to build: time to kill its process mid-load
    ros.desc_pub.publish(String(data=big))
    wait_until(lambda: _loading(node), timeout=30, what='load running in the build process')
    pid = node.background.process.pid
    time.sleep(0.2)
    os.kill(pid, signal.SIGKILL)
    wait_until(lambda: node.core.loading == '', timeout=30, what='load over')
    assert 'build process ended (signal 9)' in node.core.description_error
    np.testing.assert_allclose(ros.send(JOINTS, Q), g_arm, atol=1e-9)   # the old model serves
    wait_until(lambda: any('build process' in m for m in ros.logs), what='log line')
    time.sleep(LOG_THROTTLE_S)   # the next failure is logged, not held back as one more like this
    # a hung build: timed out, killed, reported; the old model serves
    node.background.process.timeout = 0.3
    ros.desc_pub.publish(String(data=big + '<!-- again -->'))
    wait_until(lambda: _loading(node), timeout=30, what='second load running')
    pid2 = node.background.process.pid
    wait_until(lambda: node.core.loading == '', timeout=30, what='second load over')
    assert 'did not answer within 0.3 s' in node.core.description_error and not _alive(pid2)
    np.testing.assert_allclose(ros.send(JOINTS, Q), g_arm, atol=1e-9)
    time.sleep(0.5)
    assert sum('build process' in m for m in ros.logs) == 2, ros.logs   # once each
    # the next load starts a new process and works
    node.background.process.timeout = 60.0
    ros.desc_pub.publish(String(data=heavier(ARM, 2.0)))
    wait_until(lambda: node.background.process.started == 3 and node.core.loading == '', timeout=60, what='third load')
    np.testing.assert_allclose(ros.send(JOINTS, Q), load_urdf(heavier(ARM, 2.0)).gravity(Q), atol=1e-9)
    assert node.core.description_error == ''
    last = node.background.process.pid
    node.destroy_node()   # no build process outlives the node
    ros.ex.remove_node(node)
    ros.node = None
    assert last is not None and not _alive(last)


def test_reload_service_during_loads_answers_with_the_old_model(ros):
    node = ros.start(robot_description=ARM, **BIG)
    ros.desc_pub.publish(String(data=folded_description(5000)))
    wait_until(lambda: _loading(node), timeout=30, what='load running')
    for _ in range(20):
        res = ros.call(Trigger, '/dynamics_node/reload_model', Trigger.Request())
        assert res.success, res.message
        np.testing.assert_allclose(ros.send(JOINTS, Q), load_urdf(ARM).gravity(Q), atol=1e-9)
    wait_until(lambda: node.core.loading == '', timeout=120, what='loads done')
    # the topic's model swapped in, then the last reload (of the parameter: the running source then)
    assert node.core.description_error == '' and node.background.worker.replaced['model'] == 19
    assert len(node.core.model.link_frames) == 11 and node.core.model_info == 'parameter robot_description'


def test_a_description_repeated_on_the_topic_keeps_the_running_model(ros):
    """robot_state_publisher repeating the file the node started from: the model object stays (a
    rebuild would only replace it, which ends a payload recording); it becomes the source; a
    different description on the topic still loads."""
    node = ros.start(urdf_path=os.path.join(ROOT, 'config', 'arm7.urdf'))
    model = node.core.model
    ros.desc_pub.publish(String(data=ARM))
    wait_until(lambda: node.sources.current == ('topic', ARM), what='the topic as the source')
    assert node.core.model is model and node.core.loading == ''
    np.testing.assert_allclose(ros.send(JOINTS, Q), model.gravity(Q), atol=1e-12)
    ros.desc_pub.publish(String(data=heavier(ARM, 2.0)))
    wait_until(lambda: node.core.model is not model, timeout=60, what='the heavier model')
    np.testing.assert_allclose(ros.send(JOINTS, Q), 2.0 * model.gravity(Q), rtol=1e-9, atol=1e-9)


def _fill_one(ros, pub, out, timeout=60.0):
    """Publish a small trajectory until one comes back filled (a new trajectory process
    subscribes a while after it starts; a killed one's endpoint may still look matched), then
    wait until the process is idle: the copy of the last one sent is back and the node has its
    'done' (the process publishes a copy before it reports it: a kill in between would be a kill
    mid-fill). Each one sent has its own length; the process takes them in order, so the last
    one comes back last. None is sent once the process has taken one (a third one arriving while
    the first fills would replace the second: a rejection)."""
    node = ros.node
    tp, count = node.background.trajectories, node.core.count
    n0, outcomes = len(out), count.trajectories_filled + count.trajectories_rejected

    def taken():
        return tp.busy or len(out) > n0 or count.trajectories_filled + count.trajectories_rejected > outcomes
    sent = []
    end = time.monotonic() + timeout
    while not taken():
        assert time.monotonic() < end, 'no filled trajectory'
        sent.append(serialized(10 + len(sent)))
        pub.publish(sent[-1])
        wait_for = time.monotonic() + 1.0
        while not taken() and time.monotonic() < wait_for:
            time.sleep(0.01)
    last = len(sent[-1])
    wait_until(lambda: any(len(m) == last for m in out[n0:]) and not tp.busy, timeout=max(1.0, end - time.monotonic()),
               what='the last trajectory sent filled and reported')
    assert next(m for m in out[n0:] if len(m) == last) != sent[-1]   # filled: the efforts written


@pytest.fixture
def killed_dds_process():
    """For a test that kills a DDS process with -9: its shared-memory files are removed once the
    test's own participants are gone too (this fixture is set up first, so torn down last)."""
    before = _shm_files()
    yield
    _remove_files_of_killed_processes(before)


def _trajectory_ends(ros):
    """([filled trajectories as they arrive], the publisher of ~/trajectory_in) on the tester node."""
    out = []
    ros.t.create_subscription(JointTrajectory, '/dynamics_node/trajectory_out', out.append, 10, raw=True)
    return out, ros.t.create_publisher(JointTrajectory, '/dynamics_node/trajectory_in', 10)


def test_a_trajectory_process_that_dies_or_hangs_is_reported_once(killed_dds_process, ros):
    node = ros.start(robot_description=ARM, max_trajectory_points=200_000)
    g_arm = load_urdf(ARM).gravity(Q)
    out, pub = _trajectory_ends(ros)
    tp = node.background.trajectories
    first = tp.pid
    assert first is not None
    _fill_one(ros, pub, out)
    # killed (kill -9) while idle: reported once, a new one starts and fills; the model serves
    os.kill(first, signal.SIGKILL)
    wait_until(lambda: any('trajectory process ended (signal 9)' in m for m in ros.logs), timeout=30,
               what='log line')
    np.testing.assert_allclose(ros.send(JOINTS, Q), g_arm, atol=1e-9)
    wait_until(lambda: tp.started == 2 and tp.pid is not None, timeout=30, what='a new trajectory process')
    _fill_one(ros, pub, out)
    assert not _alive(first) and node.core.count.trajectories_rejected == 0
    time.sleep(LOG_THROTTLE_S)   # the next failure is logged, not held back as one more like this
    # hung (stopped in the middle of a fill): killed after its timeout, the trajectory rejected,
    # reported once
    second = tp.pid
    tp.timeout = 0.5
    pub.publish(serialized(100_000))   # a fill long enough to be caught in
    wait_until(lambda: tp.busy, timeout=60, what='fill under way')
    os.kill(second, signal.SIGSTOP)
    wait_until(lambda: node.core.count.trajectories_rejected == 1, timeout=60, what='hung fill rejected')
    assert 'did not finish a fill within 0.5 s' in node.core.last_error and not _alive(second)
    np.testing.assert_allclose(ros.send(JOINTS, Q), g_arm, atol=1e-9)
    tp.timeout = 120.0
    wait_until(lambda: tp.started == 3 and tp.pid is not None, timeout=30, what='a third trajectory process')
    _fill_one(ros, pub, out)
    time.sleep(0.5)
    assert sum('trajectory process' in m for m in ros.logs) == 2, ros.logs   # once each
    last = tp.pid
    node.destroy_node()   # no trajectory process outlives the node
    ros.ex.remove_node(node)
    ros.node = None
    assert last is not None and not _alive(last)


def test_a_silent_trajectory_process_is_taken_for_hung_unless_it_waited_for_a_cpu(killed_dds_process, ros):
    """The silence bound on an injected clock and CPU-wait counter: the child (a real one, told
    to send one message once subscribed and then nothing for an hour) is killed once silent for
    more than SILENT_S s of its own, the time it waited for a CPU not counted; reported once."""
    now, waited = [0.0], [0.0]
    tp = TrajectoryProcess(child_config(ros.t), lambda *a: None, clock=lambda: now[0], cpu_wait=lambda pid: waited[0])
    tp.heartbeat = 3600.0
    assert tp.start()
    pid = tp.pid
    try:
        wait_until(lambda: tp.last_heard is not None, timeout=120, what='its first message')
        assert tp.last_heard == 0.0
        now[0] = SILENT_S   # at the bound: not yet
        assert tp.collect() == [] and tp.pid == pid
        waited[0] = 2.0   # then it waited 2 s for a CPU
        now[0] = SILENT_S + 1.9
        assert tp.collect() == [] and tp.pid == pid
        now[0] = SILENT_S + 2.1
        assert tp.collect() == [('lost', f'the trajectory process was silent for {SILENT_S:g} s and was killed',
                                 False)]
        assert not tp.running and not _alive(pid)
        now[0] += 100.0
        assert tp.collect() == []   # once
    finally:
        tp.stop()


def test_an_idle_trajectory_process_that_stops_is_replaced(killed_dds_process, ros):
    """A child stopped (SIGSTOP) while idle sends no heartbeat: killed after SILENT_S s,
    reported once, replaced by one that fills; an idle child that heartbeats stays."""
    node = ros.start(robot_description=ARM)
    out, pub = _trajectory_ends(ros)
    tp = node.background.trajectories
    first = tp.pid
    assert first is not None
    _fill_one(ros, pub, out, timeout=120)
    time.sleep(2 * SILENT_S)   # idle for twice the bound: its heartbeats keep it
    assert tp.pid == first and tp.started == 1, ros.logs
    segments = dds_segments(first)   # its own Fast DDS segment and those it read from
    assert segments
    rejected = node.core.count.trajectories_rejected   # (a copy _fill_one sent again may have been replaced)
    os.kill(first, signal.SIGSTOP)
    wait_until(lambda: any('trajectory process was silent' in m for m in ros.logs), timeout=120, what='log line')
    assert not _alive(first)   # killed (stopped processes die of SIGKILL) and reaped
    assert node.core.count.trajectories_rejected == rejected   # idle: no trajectory went with it
    # the node removed its segment: none of them is left with its participant dead
    assert remove_dead_segments(segments) == [] and any(not os.path.exists(os.path.join(SHM, n)) for n in segments)
    wait_until(lambda: tp.started == 2 and tp.pid is not None, timeout=60, what='a new trajectory process')
    assert tp.pid != first
    _fill_one(ros, pub, out, timeout=120)
    time.sleep(0.5)
    assert sum('trajectory process' in m for m in ros.logs) == 1, ros.logs   # once
    assert tp.started == 2


def test_a_trajectory_process_leaves_the_graph_by_itself_when_the_node_stops(killed_dds_process, ros):
    """Told at the start of destroy_node, the child leaves the ROS graph and exits (status 0)
    while the node's teardown runs, also one that the loader thread started (a replacement: it
    would get SIGKILL from the kernel if that thread ended first)."""
    node = ros.start(robot_description=ARM)
    out, pub = _trajectory_ends(ros)
    tp = node.background.trajectories
    first = tp.pid
    os.kill(first, signal.SIGKILL)
    wait_until(lambda: tp.started == 2 and tp.pid is not None, timeout=60, what='a new trajectory process')
    _fill_one(ros, pub, out, timeout=120)
    second = tp.pid
    t0 = time.monotonic()
    node.destroy_node()
    took = time.monotonic() - t0
    ros.ex.remove_node(node)
    ros.node = None
    assert tp.exit_code == 0 and not _alive(second), tp.exit_code
    assert took < STOP_S, took   # it did not wait for the kill


@pytest.mark.parametrize('raised', [False, True])
def test_replies_keep_flowing_during_heavy_loads(raised):
    """Measured from another process streaming joint_states at 500 Hz (bench.node_loads): replies
    keep coming during each load (at least half the share the quiet stretch after it got: a loaded
    machine drops states whatever the node does); a description at the caps (folded into the arm,
    and a chain built in full), a new kinematic structure (kernels generated), 20 reloads and a
    100,000-point trajectory (refused by the caps from its header, or filled and published: in
    the trajectory process either way) open no gap between replies as long as stale_timeout that
    the equally long quiet stretch after them did not have too (this machine's own scheduling).
    Not a speed benchmark: a functional bound (before the trajectory process, rclpy held the
    node's interpreter lock 30-50 ms for the trajectory; a new structure's observer kernel compiled
    in the callback that swapped it in stalled it for the compile). An event that fails is run once more
    and must pass then: beside busy loops the scheduler alone opened single gaps of 100-500 ms."""
    from bench.node_loads import run
    stale_ms = 1e3 * SPECS['stale_timeout'].default   # the node runs with its defaults

    def problem(r):
        quiet_share = r['quiet_replies'] / max(1, r['quiet_sent'])   # (1 on a quiet machine)
        if not r['replies'] > 0.5 * quiet_share * r['sent']:   # half the share the quiet stretch got
            return 'replies'
        if not r['event_gap_ms'] < max(stale_ms, 2 * r['quiet_gap_ms']):
            return 'gap'
        return None
    rows = run(raised=raised)
    assert [r['event'] for r in rows][2:] == ['new structure (kernels generated)', '20 reloads',
                                              '100,000-point trajectory']
    failed = {r['event']: (problem(r), r) for r in rows if problem(r)}
    if failed:   # once more: a stall of the node comes back, a loaded machine's scheduling hiccup does not
        again = {r['event']: r for r in run(raised=raised)}
        for event, (why, first) in failed.items():
            assert problem(again[event]) is None, (why, first, again[event])
