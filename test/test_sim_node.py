"""sim_node and trajectory_source: bad configuration is refused with a clear message; sim_node
holds its arm until a controller commands it."""
import glob
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

rclpy = pytest.importorskip('rclpy')

from lie_dynamics.sim.trajectory_source import desired_state, per_joint  # noqa: E402

ROOT = os.path.join(os.path.dirname(__file__), '..')


@pytest.mark.parametrize('params, msg', [
    (['-p', 'initial_positions:=[0.0, 1.0]'], 'initial_positions needs 7 values, got 2'),
    (['-p', 'rate:=-5.0'], 'rate must be positive'),
    (['-p', 'joints:=[nope]'], "unknown joint 'nope'"),
    (['-p', 'external.link:=nope', '-p', 'external.duration:=0.1'], "unknown link 'nope' for the external wrench"),
    (['-p', 'external.link:=hand', '-p', 'external.duration:=0.1', '-p', 'external.wrench:=[1.0]'],
     'external wrench must be 6 finite numbers'),
    (['-p', 'payload.link:=nope', '-p', 'payload.mass:=1.0'], "unknown link 'nope' for payload"),
    (['-p', 'payload.mass:=2.0'], "unknown link '' for payload"),
    (['-p', 'payload.link:=tool0', '-p', 'payload.mass:=-1.0'], 'payload mass must be finite and >= 0'),
    (['-p', 'payload.link:=tool0', '-p', 'payload.mass:=1.0', '-p', 'payload.inertia:=[1.0, 0.0, 0.0, 1.0, 0.0, 5.0]'],
     'payload inertia is not physically valid'),
])
def test_sim_node_refuses_bad_parameters(params, msg):
    r = subprocess.run([sys.executable, '-m', 'lie_dynamics.sim.sim_node', '--ros-args'] + params,
                       cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert r.returncode == 2, r.stdout + r.stderr
    assert 'sim_node: invalid configuration' in r.stderr and msg in r.stderr


def test_per_joint_values():
    np.testing.assert_array_equal(per_joint([0.5], 3, 'home'), [0.5, 0.5, 0.5])
    np.testing.assert_array_equal(per_joint([1.0, 2.0, 3.0], 3, 'home'), [1, 2, 3])
    with pytest.raises(ValueError, match=r'amplitude has 2 values for 3 joints \(give 1 or 3\)'):
        per_joint([1.0, 2.0], 3, 'amplitude')


def test_desired_state_starts_at_rest_and_is_consistent():
    home, amp, freq = np.array([0.1, -0.2]), np.array([0.4, 0.2]), np.array([0.3, 0.5])
    q, qd, _ = desired_state(0.0, home, amp, freq)
    np.testing.assert_allclose(q, home)
    np.testing.assert_allclose(qd, 0.0)
    h = 1e-6
    for t in (0.3, 1.7):
        qp, qdp, _ = desired_state(t + h, home, amp, freq)
        qm, qdm, _ = desired_state(t - h, home, amp, freq)
        _, qd, qdd = desired_state(t, home, amp, freq)
        np.testing.assert_allclose((qp - qm) / (2 * h), qd, atol=1e-8)
        np.testing.assert_allclose((qdp - qdm) / (2 * h), qdd, atol=1e-7)



def _sim_stack(**params):
    """A SimNode with `params` and a tester node (joint_states reader, command writer), one executor."""
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.parameter import Parameter
    from sensor_msgs.msg import JointState
    from std_msgs.msg import Float64MultiArray

    from lie_dynamics.sim.sim_node import SimNode
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    ex = SingleThreadedExecutor(context=ctx)
    tester = rclpy.create_node('sim_tester', context=ctx)
    states = []
    tester.create_subscription(JointState, 'joint_states', states.append, 1000)
    cmd = tester.create_publisher(Float64MultiArray, 'effort_controller/commands', 10)
    sim = SimNode(context=ctx, parameter_overrides=[Parameter(k, value=v) for k, v in params.items()])
    for n in (tester, sim):
        ex.add_node(n)

    def spin(cond, timeout):
        end = time.monotonic() + timeout
        while time.monotonic() < end and not cond():
            ex.spin_once(timeout_sec=0.01)
        return cond()

    def close():
        ex.shutdown()
        sim.destroy_node()
        tester.destroy_node()
        rclpy.shutdown(context=ctx)
    return sim, states, cmd, spin, close


@pytest.mark.parametrize('hold', [True, False])
def test_sim_node_holds_the_initial_state_until_the_first_command(hold):
    """Default (hold_until_command): an arm nobody commands stays where it started, its state
    re-sent for late readers, and steps once a command comes. hold_until_command:=false: it falls."""
    from std_msgs.msg import Float64MultiArray
    params = {} if hold else {'hold_until_command': False}
    sim, states, cmd, spin, close = _sim_stack(rate=500.0, **params)
    try:
        q0 = list(sim.sim.q)
        assert spin(lambda: len(states) >= 5, 30.0), 'no joint_states'
        if hold:
            spin(lambda: sim.steps > 0, 1.0)  # give it every chance to step: it must not
            assert sim.steps == 0 and sim.sim.t == 0.0
            assert all(list(m.position) == q0 and (m.header.stamp.sec, m.header.stamp.nanosec) == (0, 0)
                       for m in states)
            assert spin(lambda: cmd.get_subscription_count() >= 1, 30.0)
            cmd.publish(Float64MultiArray(data=[0.0] * len(q0)))
        assert spin(lambda: sim.steps >= 50, 30.0), 'the simulation did not run'
        assert list(states[-1].position) != q0  # uncompensated: it falls
    finally:
        close()


UR5 = next(iter(glob.glob(os.path.join(sys.prefix, 'lib', 'python3*', 'site-packages', 'cmeel.prefix', 'share',
                                       'example-robot-data', 'robots', 'ur_description', 'urdf',
                                       'ur5_robot.urdf'))), None)


@pytest.mark.skipif(UR5 is None, reason='example-robot-data is a test dependency (requirements-dev.txt)')
def test_sim_node_then_dynamics_node_with_defaults_hold_an_undamped_ur5():
    """The two nodes started one after the other with their defaults (the node takes the model
    from the simulator's robot_description): the arm waits for the controller instead of falling
    before the first command (with hold_until_command:=false it fell 3.4 rad), then stays where
    it started."""
    from rclpy.executors import SingleThreadedExecutor
    from sensor_msgs.msg import JointState

    procs = [subprocess.Popen([sys.executable, '-m', 'lie_dynamics.sim.sim_node', '--ros-args', '-p',
                               f'urdf_path:={UR5}', '-p', 'damping:=false'], cwd=ROOT, stdout=subprocess.PIPE,
                              stderr=subprocess.STDOUT, text=True)]
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    node = rclpy.create_node('pair_tester', context=ctx)
    ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(node)
    states = []
    node.create_subscription(JointState, 'joint_states', states.append, 1000)

    def spin(cond, timeout):
        end = time.monotonic() + timeout
        while time.monotonic() < end and not cond():
            ex.spin_once(timeout_sec=0.02)
        return cond()
    try:
        assert spin(lambda: len(states) > 0, 60.0), 'no joint_states from sim_node'
        spin(lambda: False, 1.0)  # the controller comes a while later
        procs.append(subprocess.Popen([sys.executable, '-m', 'lie_dynamics.dynamics_node'], cwd=ROOT,
                                      stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True))
        t = lambda m: m.header.stamp.sec + 1e-9 * m.header.stamp.nanosec  # noqa: E731
        assert spin(lambda: t(states[-1]) >= 2.0, 120.0), 'the simulation did not run for 2 s'
    finally:
        ex.shutdown()
        node.destroy_node()
        rclpy.shutdown(context=ctx)
        logs = []
        for p in procs:
            p.send_signal(signal.SIGINT)
            try:
                logs.append(p.communicate(timeout=30)[0])
            except subprocess.TimeoutExpired:
                p.kill()
                logs.append(p.communicate()[0])
    q = np.array([m.position for m in states])
    drift = np.max(np.abs(q - q[0]))
    assert drift < 1e-2, (drift, logs)
