"""sim_node's plant: the effort reported with a state is the torque acting at that state; a plant
with a calibration applied differs from the URDF's by exactly the calibrated terms; effort offsets
and seeded noise on the reported effort."""
import numpy as np
import pytest

from lie_dynamics import default_urdf_path, load_urdf
from lie_dynamics.calibration import CalibrationResult, with_calibration
from lie_dynamics.calibration.regressor import calibration_regressor, parameter_names, prior_parameters
from lie_dynamics.calibration.result import parameters_of, physical
from lie_dynamics.sim.arm import ArmSim, EffortSensor
from lie_dynamics.sim.demo import HOME

rclpy = pytest.importorskip('rclpy')

RATE = 500.0


def _calibration(model):
    """A plant that is not the URDF: masses and CoMs changed, armature, friction, offsets."""
    rng = np.random.default_rng(7)
    pi = model.inertial_parameters().reshape(model.nb, 10)
    inertial = []
    for p in pi:
        m, c, i = physical(p)
        inertial.append(parameters_of(m * rng.uniform(0.85, 1.15), c + rng.uniform(-0.02, 0.02, 3), i))
    joints = np.stack([rng.uniform(0.05, 0.3, model.n), rng.uniform(0.2, 1.0, model.n),
                       rng.uniform(0.3, 1.5, model.n), rng.uniform(-0.8, 0.8, model.n)], axis=1)
    params = np.concatenate([np.ravel(inertial), joints.ravel()])
    k = len(parameter_names(model))
    return CalibrationResult(robot=model.name, joint_names=list(model.joint_names),
                             link_names=list(model.link_frames), body_links=list(model.body_link_names),
                             parameters=params, std=np.full(k, np.nan), source=['identified'] * k)


def _run_sim(params, steps, command):
    """SimNode in lockstep with an in-process controller answering every state with
    command(k, msg); the distinct states received (one per step)."""
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.parameter import Parameter
    from sensor_msgs.msg import JointState
    from std_msgs.msg import Float64MultiArray

    from lie_dynamics.sim.sim_node import SimNode
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    ex = SingleThreadedExecutor(context=ctx)
    ctl = rclpy.create_node('plant_tester', context=ctx)
    states = []
    pub = ctl.create_publisher(Float64MultiArray, 'effort_controller/commands', 10)

    def on_state(msg):
        if states and (msg.header.stamp.sec, msg.header.stamp.nanosec) == (states[-1].header.stamp.sec,
                                                                          states[-1].header.stamp.nanosec):
            return   # a re-sent state
        states.append(msg)
        pub.publish(Float64MultiArray(data=list(command(len(states) - 1, msg))))
    ctl.create_subscription(JointState, 'joint_states', on_state, 1000)
    sim = SimNode(context=ctx, parameter_overrides=[Parameter(k, value=v) for k, v in dict(
        rate=RATE, lockstep=True, initial_positions=list(HOME), min_subscribers=1, max_steps=steps,
        **params).items()])
    ex.add_node(ctl)
    ex.add_node(sim)
    try:
        import time
        end = time.monotonic() + 60.0
        while time.monotonic() < end and len(states) <= steps:
            ex.spin_once(timeout_sec=0.01)
        assert len(states) == steps + 1, len(states)
        return sim, states
    finally:
        ex.shutdown()
        sim.destroy_node()
        ctl.destroy_node()
        rclpy.shutdown(context=ctx)


def _arrays(states):
    q, qd, e = (np.array([getattr(m, k) for m in states]) for k in ('position', 'velocity', 'effort'))
    return q, qd, e


def _varying(model):
    g = model.gravity(np.asarray(HOME))
    return lambda k, msg: g * (1.0 + 0.3 * np.sin(0.37 * k)) + 2.0 * np.cos(0.23 * k + np.arange(model.n))


def test_reported_effort_is_the_torque_acting_at_that_state():
    """A command that changes every step: each state's effort is the torque that drives the step
    from it, i.e. M(q_k) (qd_{k+1} - qd_k) / dt + h(q_k, qd_k) + damping qd_k = effort_k. A torque
    reported with the state after the one it acted at misses this by a step's change of torque.
    (State 0 is the held initial state, reported before the first command released it.)"""
    model = load_urdf(default_urdf_path())
    _, states = _run_sim({}, 40, _varying(model))
    q, qd, e = _arrays(states[1:])
    qdd = np.diff(qd, axis=0) * RATE
    tau = model.inverse_dynamics(q[:-1], qd[:-1], qdd) + model.damping * qd[:-1]
    np.testing.assert_allclose(tau, e[:-1], rtol=0, atol=1e-8 * np.max(np.abs(e)))


def test_calibrated_plant_differs_by_exactly_the_calibrated_terms(tmp_path):
    """With a calibration file, Coulomb friction on and offsets: the reported effort equals the
    calibration regressor of the URDF model times the file's parameters (inertias, armature,
    viscous, Coulomb with its eps, offset), and the URDF's own parameters (prior_parameters)
    miss it; without noise the reported effort minus the held torque is the offset."""
    model = load_urdf(default_urdf_path())
    cal = _calibration(model)
    path = cal.save(str(tmp_path / 'plant.yaml'))
    sim, states = _run_sim({'calibration_file': path, 'coulomb_friction': True}, 40, _varying(model))
    q, qd, e = _arrays(states[1:])
    qdd = np.diff(qd, axis=0) * RATE
    Y = calibration_regressor(model, q[:-1], qd[:-1], qdd, cal.eps)
    scale = np.max(np.abs(e))
    np.testing.assert_allclose(Y @ cal.parameters, e[:-1], rtol=0, atol=1e-8 * scale)
    assert np.max(np.abs(Y @ prior_parameters(model) - e[:-1])) > 0.05 * scale
    np.testing.assert_allclose(e[-1] - sim.sim.held_torque, cal.offset, rtol=0, atol=1e-12)
    plant = with_calibration(model, cal)
    np.testing.assert_array_equal(sim.sim.model.armature, cal.armature)
    np.testing.assert_allclose(sim.sim.model.inertial_parameters(), plant.inertial_parameters(), rtol=1e-12)


def test_effort_noise_is_seeded_and_has_its_std():
    model = load_urdf(default_urdf_path())
    runs = [_run_sim({'effort_noise': [0.5], 'effort_offset': [0.1], 'noise_seed': s}, 60, _varying(model))
            for s in (3, 3, 4)]
    e = [_arrays(states)[2] for _, states in runs]
    np.testing.assert_array_equal(e[0], e[1])
    assert np.all(e[0] != e[2])
    held = runs[0][0].sim.held_torque
    np.testing.assert_allclose(e[0][-1], held + 0.1 + 0.5 * np.random.default_rng(3).standard_normal((61, 7))[-1],
                               rtol=0, atol=1e-12)


def test_sensor_and_coulomb_options_are_checked():
    model = load_urdf(default_urdf_path())
    with pytest.raises(ValueError, match='noise finite and >= 0'):
        EffortSensor(model.n, noise=-1.0)
    with pytest.raises(ValueError, match='Coulomb friction must be finite'):
        ArmSim(model, coulomb=-1.0)
    with pytest.raises(ValueError, match='semi_implicit_euler integrator only'):
        ArmSim(model, coulomb=1.0, integrator='rk4')
    # Coulomb friction is the model's smooth form: laws.friction_torque
    sim = ArmSim(model, q0=HOME, qd0=np.full(model.n, 0.02), damping=False, coulomb=2.0, eps=0.05)
    sim.step()
    np.testing.assert_allclose(sim.applied, -2.0 * np.tanh(0.02 / 0.05), rtol=1e-15)


@pytest.mark.parametrize('params, msg', [
    (['-p', 'calibration_file:=/nonexistent/plant.yaml'], "calibration_file '/nonexistent/plant.yaml': No such file"),
    (['-p', 'effort_noise:=[-1.0]'], 'noise finite and >= 0'),
    (['-p', 'effort_offset:=[1.0, 2.0]'], 'effort_offset and effort_noise need one value or 7'),
])
def test_sim_node_refuses_bad_plant_parameters(params, msg):
    import os
    import subprocess
    import sys
    r = subprocess.run([sys.executable, '-m', 'lie_dynamics.sim.sim_node', '--ros-args'] + params,
                       cwd=os.path.join(os.path.dirname(__file__), '..'), capture_output=True, text=True, timeout=120)
    assert r.returncode == 2, r.stdout + r.stderr
    assert 'sim_node: invalid configuration' in r.stderr and msg in r.stderr, r.stderr
