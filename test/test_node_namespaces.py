"""Several robots in one DDS domain: two dynamics_node processes started with -r __ns:=/robot1 and
/robot2, for two different robots (the bundled arm and a UR5 from example-robot-data). Every
default topic resolves in the node's namespace: each node answers only its own joint_states, on
its own effort_controller/commands, and nothing reaches the global /effort_controller/commands.
Each node's trajectory process serves its namespaced ~/trajectory_in and ends with it."""
import glob
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

rclpy = pytest.importorskip('rclpy')

from diagnostic_msgs.msg import DiagnosticArray  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from sensor_msgs.msg import JointState  # noqa: E402
from std_msgs.msg import Float64MultiArray  # noqa: E402

from lie_dynamics import default_urdf_path, load_urdf  # noqa: E402

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
UR5 = next(iter(glob.glob(os.path.join(sys.prefix, 'lib', 'python3*', 'site-packages', 'cmeel.prefix', 'share',
                                       'example-robot-data', 'robots', 'ur_description', 'urdf',
                                       'ur5_robot.urdf'))), None)
ROBOTS = {'/robot1': default_urdf_path(), '/robot2': UR5}
TOL = 1e-9
QUIET = 1.0  # s to wait for a message that must not come
TRAJECTORY_PROCESS = 'lie_dynamics.ros.trajectories.trajectory_process'


def _start(ns, urdf):
    return subprocess.Popen([sys.executable, '-m', 'lie_dynamics.dynamics_node', '--ros-args', '-r', f'__ns:={ns}',
                             '-p', f'urdf_path:={urdf}', '-p', 'ramp_time:=0.0', '-p', 'stale_timeout:=60.0'],
                            cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)


def _children(pid, module):
    """Pids of the `python -m module <pid>` children of process `pid` (build_process.start_child)."""
    out = []
    for d in os.listdir('/proc'):
        try:
            with open(f'/proc/{d}/cmdline', 'rb') as fh:
                argv = fh.read().split(b'\0')[:-1]
        except OSError:
            continue
        if argv[-3:] == [b'-m', module.encode(), str(pid).encode()]:
            out.append(int(d))
    return out


def _running(pid):
    """The process exists and is not a zombie."""
    try:
        with open(f'/proc/{pid}/stat') as fh:
            return fh.read().rsplit(')', 1)[1].split()[0] != 'Z'
    except OSError:
        return False


def _stop(proc):
    proc.send_signal(signal.SIGINT)
    try:
        return proc.communicate(timeout=30)[0]
    except subprocess.TimeoutExpired:
        proc.kill()
        return proc.communicate()[0]


@pytest.mark.skipif(UR5 is None, reason='example-robot-data is a test dependency (requirements-dev.txt)')
def test_two_namespaced_nodes_for_two_robots_in_one_domain():
    import warnings
    with warnings.catch_warnings():
        warnings.simplefilter('ignore')  # the vendor inertias are warned about, not refused
        models = {ns: load_urdf(path) for ns, path in ROBOTS.items()}
    assert models['/robot1'].joint_names != models['/robot2'].joint_names
    procs = {ns: _start(ns, path) for ns, path in ROBOTS.items()}
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    node = rclpy.create_node('namespace_tester', context=ctx)
    ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(node)
    cmds = {topic: [] for topic in ('/robot1/effort_controller/commands', '/robot2/effort_controller/commands',
                                    '/effort_controller/commands')}
    for topic, got in cmds.items():
        node.create_subscription(Float64MultiArray, topic, lambda m, got=got: got.append(np.array(m.data)), 100)
    states = {ns: node.create_publisher(JointState, f'{ns}/joint_states', 10) for ns in ROBOTS}
    diagnostics = set()  # /diagnostics is global: each status names its node's namespace
    node.create_subscription(DiagnosticArray, '/diagnostics',
                             lambda m: diagnostics.update((s.name, s.hardware_id) for s in m.status), 10)

    def spin_until(cond, timeout=60.0):
        end = time.monotonic() + timeout
        while time.monotonic() < end and not cond():
            ex.spin_once(timeout_sec=0.02)
        return cond()

    try:
        assert spin_until(lambda: all(p.get_subscription_count() >= 1 for p in states.values())
                          and all(node.count_publishers(f'{ns}/effort_controller/commands') >= 1 for ns in ROBOTS)), \
            'the namespaced nodes did not come up'
        assert node.count_publishers('/effort_controller/commands') == 0
        # the trajectory process of each node serves the node's namespaced topics
        assert spin_until(lambda: all(node.count_subscribers(f'{ns}/dynamics_node/trajectory_in') == 1 and
                                      node.count_publishers(f'{ns}/dynamics_node/trajectory_out') == 1
                                      for ns in ROBOTS)), 'no trajectory process on the namespaced topics'
        assert node.count_subscribers('/dynamics_node/trajectory_in') == 0
        trajectory_children = [c for p in procs.values() for c in _children(p.pid, TRAJECTORY_PROCESS)]
        assert len(trajectory_children) == 2, trajectory_children
        rng = np.random.default_rng(20)
        for ns, model in models.items():
            other = next(o for o in ROBOTS if o != ns)
            mine, theirs = cmds[f'{ns}/effort_controller/commands'], cmds[f'{other}/effort_controller/commands']
            n_theirs = len(theirs)
            q = rng.uniform(np.maximum(model.position_lower, -np.pi), np.minimum(model.position_upper, np.pi))
            msg = JointState(name=list(model.joint_names), position=q.tolist(), velocity=[0.0] * model.n)
            # resent until answered: the model loads at start-up, and best-effort joint_states
            # can lose a message while discovery completes
            n0 = len(mine)
            end = time.monotonic() + 60.0
            while len(mine) == n0 and time.monotonic() < end:
                states[ns].publish(msg)
                spin_until(lambda mine=mine, n0=n0: len(mine) > n0, timeout=0.5)
            assert len(mine) > n0, f'no command from {ns}'
            spin_until(lambda: False, timeout=QUIET)  # let any stray message arrive
            lim = np.asarray(model.effort_limits)
            expected = np.clip(model.gravity(q), -lim, lim)
            for tau in mine[n0:]:
                np.testing.assert_allclose(tau, expected, atol=TOL, rtol=TOL)
            assert len(theirs) == n_theirs, f'{other} answered the states of {ns}'
            assert cmds['/effort_controller/commands'] == [], 'a command reached the global topic'
        expected = {('robot1/dynamics_node: gravity compensation', 'lie_arm7'),
                    ('robot2/dynamics_node: gravity compensation', models['/robot2'].name)}
        assert spin_until(lambda: expected <= diagnostics, timeout=30.0), diagnostics
    finally:
        ex.shutdown()
        node.destroy_node()
        rclpy.shutdown(context=ctx)
        logs = {ns: _stop(p) for ns, p in procs.items()}
    for ns, log in logs.items():
        assert procs[ns].returncode == 0, log
    for pid in trajectory_children:   # gone with their node
        assert not _running(pid), pid
