"""The simulated arm: free fall conserves energy (to integrator order), gravity command holds, limits act."""
import numpy as np
import pytest

from lie_dynamics import default_urdf_path, load_urdf
from lie_dynamics.sim.demo import HOME
from lie_dynamics.sim.arm import ArmSim


@pytest.fixture(scope='module')
def arm():
    return load_urdf(default_urdf_path())


def test_free_fall_energy_drift_is_first_order_in_dt(arm):
    """Zero damping, no limits: the sim's free fall is the library's forward dynamics integrated;
    semi-implicit Euler keeps the energy error O(dt)."""
    drifts = []
    for dt in (1e-3, 5e-4, 2.5e-4):
        sim = ArmSim(arm, dt=dt, q0=HOME, damping=False, limits=False)
        e0 = sim.energy()
        sim.step(int(round(0.1 / dt)))
        assert np.max(np.abs(sim.q - HOME)) > 0.01  # it really fell
        drifts.append(abs(sim.energy() - e0))
    assert drifts[0] < 0.05  # J, against |U| ~ 100 J
    assert 1.6 < drifts[0] / drifts[1] < 2.5 and 1.6 < drifts[1] / drifts[2] < 2.5


def test_energy_matches_model(arm):
    sim = ArmSim(arm, q0=HOME, qd0=np.linspace(-1, 1, 7))
    ref = arm.kinetic_energy(sim.q, sim.qd) + arm.potential_energy(sim.q)
    assert sim.energy() == pytest.approx(ref, rel=1e-12)


def test_gravity_command_holds_and_zero_command_falls(arm):
    sim = ArmSim(arm, q0=HOME)
    sim.set_command(arm.gravity(np.asarray(HOME)))
    sim.step(1000)
    assert np.max(np.abs(sim.q - HOME)) < 1e-9
    sim = ArmSim(arm, q0=HOME)
    sim.step(1000)
    assert np.max(np.abs(sim.q - HOME)) > 0.1


def test_damping_dissipates():
    """No gravity, no command: dE/dt = -qd^T D qd < 0; without damping E stays (to O(dt))."""
    model = load_urdf(default_urdf_path(), gravity=(0.0, 0.0, 0.0))
    damped = ArmSim(model, q0=HOME, qd0=np.full(7, 0.5))
    free = ArmSim(model, q0=HOME, qd0=np.full(7, 0.5), damping=False)
    e0 = damped.energy()
    damped.step(300)
    free.step(300)
    assert damped.energy() < 0.9 * e0
    assert abs(free.energy() - e0) < 1e-2 * e0


def test_effort_limits_and_hard_stops(arm):
    sim = ArmSim(arm, q0=HOME)
    sim.set_command(np.full(7, 1e6))
    sim.step(1)
    np.testing.assert_array_equal(sim.applied, arm.effort_limits)
    sim.step(3000)
    assert np.all(sim.q <= arm.position_upper) and np.all(sim.q >= arm.position_lower)
    at_stop = np.isclose(sim.q, arm.position_upper)
    assert at_stop.any() and np.all(sim.qd[at_stop] <= 0)


@pytest.mark.parametrize('bad, msg', [
    (lambda s: s.set_command(np.zeros(6)), r'command must have 7 values'),
    (lambda s: s.set_command([np.nan] * 7), r'command contains non-finite'),
])
def test_bad_commands(arm, bad, msg):
    with pytest.raises(ValueError, match=msg):
        bad(ArmSim(arm))
    with pytest.raises(ValueError, match='dt must be a positive'):
        ArmSim(arm, dt=0)


def test_external_wrench_acts_in_its_window_and_reports_its_joint_torques(arm):
    """A wrench on the flange during [0.1, 0.2) s: the motion equals forward dynamics with tau + J^T F,
    and external_torque is J^T F, which Pinocchio's rnea with fext confirms."""
    import pinocchio as pin
    w = np.array([0.5, -0.2, 0.1, 5.0, -3.0, 8.0])
    sim = ArmSim(arm, q0=HOME, damping=False)
    sim.set_command(arm.gravity(np.asarray(HOME)))
    sim.set_external('hand', w, start=0.1, duration=0.1)
    sim.step(100)
    assert np.max(np.abs(sim.q - HOME)) < 1e-9 and not sim.external_torque.any()  # before the window
    q, qd = sim.q.copy(), sim.qd.copy()
    sim.step(1)
    zero = np.zeros(7)
    jtf = arm.inverse_dynamics(q, qd, zero) - arm.inverse_dynamics(q, qd, zero, {'hand': w})
    np.testing.assert_allclose(sim.external_torque, jtf, rtol=1e-12, atol=1e-12)
    pm = pin.buildModelFromUrdf(default_urdf_path())
    pd = pm.createData()
    fid = pm.getFrameId('hand')
    pin.forwardKinematics(pm, pd, q)
    pin.updateFramePlacements(pm, pd)
    fext = [pin.Force.Zero() for _ in range(pm.njoints)]
    frame = pm.frames[fid]
    fext[frame.parentJoint] = frame.placement.act(pin.Force(w[3:], w[:3]))
    tau_pin = pin.rnea(pm, pd, q, qd, zero) - pin.rnea(pm, pd, q, qd, zero, fext)
    np.testing.assert_allclose(jtf, tau_pin, rtol=1e-9, atol=1e-9)
    assert np.max(np.abs(sim.qd)) > 0  # it pushes
    sim.step(99)
    sim.step(1)
    assert not sim.external_torque.any()  # after the window
    assert np.all(np.abs(sim.motor) <= arm.effort_limits)


def test_external_wrench_errors(arm):
    sim = ArmSim(arm)
    with pytest.raises(ValueError, match="unknown link 'nope'"):
        sim.set_external('nope', np.zeros(6))
    with pytest.raises(ValueError, match='6 finite numbers'):
        sim.set_external('hand', [1.0, 2.0])
    with pytest.raises(ValueError, match='semi_implicit_euler'):
        ArmSim(arm, integrator='rk4').set_external('hand', np.zeros(6))
