"""The calibration regressor (inertial + armature, friction, offsets) and the physically
consistent fit (lie_dynamics.calibration.regressor, .fit)."""
import numpy as np
import pytest

from dyn_cases import ARM, rel_err
from lie_dynamics import load_urdf
from lie_dynamics.algorithms.identification import excitation_trajectory
from lie_dynamics.calibration import fit as cfit
from lie_dynamics.calibration import regressor as creg
from lie_dynamics.laws import friction_torque
from lie_dynamics.model.inertia import parameter_consistency
from lie_dynamics.sim.calibration_demo import random_plant
from oracle import Oracle


def true_parameters(model, seed=0):
    """A robot that differs from its URDF (sim.calibration_demo.random_plant): CoMs moved by 1-2 cm
    per coordinate, armature, friction and offsets of its own."""
    return random_plant(model, seed, com_shift=(0.01, 0.02))


def measured(model, true, q, qd, qdd, eps=0.05):
    """Efforts from the library's own inverse dynamics on the true robot, plus armature * qdd,
    friction in the node's form and the offsets."""
    n, ni = model.n, 10 * model.nb
    a, b, fc, off = true[ni:].reshape(n, 4).T
    plant = model.with_inertial_parameters(true[:ni])
    return plant.inverse_dynamics(q, qd, qdd) + a * qdd + friction_torque(qd, b, fc, eps) + off


@pytest.fixture(scope='module')
def arm():
    return load_urdf(ARM)


def test_calibration_regressor_is_inverse_dynamics_plus_joint_terms(arm):
    rng = np.random.default_rng(1)
    q, qd, qdd = rng.uniform(-1, 1, (3, 20, arm.n))
    true = true_parameters(arm, 1)
    Y = creg.calibration_regressor(arm, q, qd, qdd, eps=0.07)
    assert Y.shape == (20, arm.n, creg.n_parameters(arm)) == (20, 7, 98)
    assert rel_err(Y @ true, measured(arm, true, q, qd, qdd, eps=0.07), 1.0) < 1e-12
    # the inertial block against the oracle, the prior against the URDF's <dynamics>
    with open(ARM) as fh:
        oracle = Oracle(fh.read())
    ref = np.array([oracle.rnea(*s) for s in zip(q, qd, qdd, strict=True)])
    prior = creg.prior_parameters(arm)
    assert rel_err(Y @ prior, ref + friction_torque(qd, arm.damping, arm.friction, 0.07), 1.0) < 1e-10
    one = creg.calibration_regressor(arm, q[3], qd[3], qdd[3])
    assert np.allclose(one, creg.calibration_regressor(arm, q, qd, qdd)[3])
    names = creg.parameter_names(arm)
    assert names[:2] == ['link1.m', 'link1.mcx'] and names[70:74] == [f'joint1.{t}' for t in creg.JOINT_TERMS]
    with pytest.raises(ValueError, match='eps'):
        creg.calibration_regressor(arm, q, qd, qdd, eps=0.0)


def test_structural_base_names_what_is_identifiable(arm):
    base = creg.structural_base(arm)
    status = dict(zip(base.names, base.status))
    # joint 1 turns about the vertical: its armature adds to link1's and link2's Izz
    assert status['joint1.armature'] == 'combination' and status['link1.Izz'] == 'combination'
    assert any(c.startswith('beta_') and 'joint1.armature' in c and 'link1.Izz' in c for c in base.combinations)
    assert status['link1.m'] == 'unidentified'      # the first link's mass never moves against gravity
    for j in ('joint3', 'joint7'):
        assert all(status[f'{j}.{t}'] == 'identified' for t in creg.JOINT_TERMS)
    assert base.rank == 69
    assert np.allclose(base.base_matrix[:, base.base_columns], np.eye(base.rank))


def test_noise_free_recovery(arm):
    """Noise-free efforts at exact (q, qd, qdd): base parameters, friction, armature and offsets
    to 1e-6 relative, every body physically valid."""
    true = true_parameters(arm, 0)
    _, q, qd, qdd = excitation_trajectory(arm, duration=10.0, rate=100.0, seed=3)
    res = cfit.fit(arm, q, qd, qdd, measured(arm, true, q, qd, qdd))
    beta, beta_true = res.base.of(res.parameters), res.base.of(true)
    assert np.max(np.abs(beta - beta_true) / np.abs(beta_true)) < 1e-6
    ident = np.flatnonzero(np.array(res.source) == 'identified')
    ni = 10 * arm.nb
    joint_terms = ident[ident >= ni]
    assert len(joint_terms) == 26     # all but the armature of joints 1 and 2 (in combinations)
    assert np.max(np.abs(res.parameters[ident] - true[ident]) / np.abs(true[ident])) < 1e-6
    assert all(ok for ok, _ in parameter_consistency(res.parameters[:ni].reshape(arm.nb, 10)))
    assert np.all(res.parameters[ni:].reshape(arm.n, 4)[:, :3] >= 0)
    assert np.all(res.residual_rms < 1e-6)


def test_noisy_fit_is_physically_consistent_with_honest_std(arm):
    true = true_parameters(arm, 2)
    _, q, qd, qdd = excitation_trajectory(arm, duration=20.0, rate=100.0, seed=5)
    sigma = 0.005 * arm.effort_limits
    tau = measured(arm, true, q, qd, qdd) + np.random.default_rng(3).normal(size=q.shape) * sigma
    res = cfit.fit(arm, q, qd, qdd, tau, weights=1 / sigma)
    ni = 10 * arm.nb
    assert all(ok for ok, _ in parameter_consistency(res.parameters[:ni].reshape(arm.nb, 10)))
    assert np.all(res.parameters[ni:].reshape(arm.n, 4)[:, :3] >= 0)
    ident = np.array(res.source) == 'identified'
    assert np.all(np.isfinite(res.std[ident]) & (res.std[ident] > 0)) and np.all(np.isnan(res.std[~ident]))
    z = (res.parameters[ident] - true[ident]) / res.std[ident]
    assert np.mean(np.abs(z) < 3) > 0.9
    assert np.all(res.residual_rms < 1.3 * sigma) and np.all(res.residual_rms > 0.7 * sigma)


def test_a_joint_that_never_moves_warns_and_keeps_its_prior(arm):
    true = true_parameters(arm, 4)
    _, q, qd, qdd = excitation_trajectory(arm, duration=10.0, rate=100.0, seed=6)
    q[:, 6], qd[:, 6], qdd[:, 6] = 0.3, 0.0, 0.0
    with pytest.warns(cfit.UnidentifiableWarning, match=r'joints that never move: joint7') as rec:
        res = cfit.fit(arm, q, qd, qdd, measured(arm, true, q, qd, qdd))
    assert issubclass(cfit.UnidentifiableWarning, Warning)
    msg = str(rec[0].message)
    assert 'armature, viscous and Coulomb friction keep their prior values' in msg and 'joint7.viscous' in msg
    names = creg.parameter_names(arm)
    prior = creg.prior_parameters(arm)
    for t in ('armature', 'viscous', 'coulomb'):
        k = names.index(f'joint7.{t}')
        assert res.source[k] == 'prior' and res.parameters[k] == prior[k]
    assert res.still_joints == ['joint7']


def test_a_recording_too_short_warns(arm):
    _, q, qd, qdd = excitation_trajectory(arm, duration=0.1, rate=100.0, seed=6)
    with pytest.warns(cfit.UnidentifiableWarning, match=r'recording too short: 10 samples x 7 joints = 70 '
                                                         r'equations for 98 parameters'):
        res = cfit.fit(arm, q, qd, qdd, measured(arm, true_parameters(arm), q, qd, qdd))
    assert all(ok for ok, _ in parameter_consistency(res.parameters[:70].reshape(arm.nb, 10)))


def test_log_cholesky_round_trip(arm):
    pi = arm.inertial_parameters().reshape(arm.nb, 10)
    assert np.allclose(cfit.theta_to_parameters(cfit.parameters_to_theta(pi)), pi, rtol=1e-12, atol=1e-15)
    theta = np.random.default_rng(0).normal(size=(50, 10))
    assert all(ok for ok, _ in parameter_consistency(cfit.theta_to_parameters(theta)))
    bad = pi[:1].copy()
    bad[0, 0] = -1.0
    with pytest.raises(ValueError, match='body 0: the parameters are not strictly physically valid'):
        cfit.parameters_to_theta(bad)
