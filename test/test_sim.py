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
