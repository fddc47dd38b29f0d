"""Inertial-parameter regressor, parameter round trips and identification."""
import subprocess
import sys
import warnings

import numpy as np
import pytest

from dyn_cases import ARM, CASES, ROOT, case, pin_body_permutation, rel_err, states
from lie_dynamics import identification, load_urdf
from lie_dynamics.regressor import inertia_to_parameters, parameters_to_inertia, physical_consistency


@pytest.mark.parametrize('name', CASES)
def test_regressor_matches_pinocchio(name):
    model, oracle = case(name)
    q, qd, qdd = states(model, seed=13)
    Y = model.regressor(q, qd, qdd)
    perm = pin_body_permutation(model, oracle)
    ref = np.array([oracle.regressor(*s)[:, perm] for s in zip(q, qd, qdd)])
    assert Y.shape == (len(q), model.n, 10 * model.nb)
    assert rel_err(Y, ref) < 1e-10
    pi = model.inertial_parameters()
    assert np.allclose(pi, oracle.dynamic_parameters()[perm], rtol=1e-12, atol=1e-14)
    assert rel_err(Y @ pi, model.inverse_dynamics(q, qd, qdd), 1e-6) < 1e-10
    assert np.allclose(model.regressor(q[2], qd[2], qdd[2]), Y[2], rtol=1e-12, atol=1e-12)


def test_parameter_round_trip_and_new_model():
    model = load_urdf(ARM)
    model.set_payload('link7', 0.8, (0.01, 0.0, 0.05))
    pi = model.inertial_parameters()
    assert np.allclose(inertia_to_parameters(parameters_to_inertia(pi.reshape(-1, 10))).reshape(-1), pi)
    assert np.allclose(parameters_to_inertia(pi.reshape(-1, 10)), model.J)
    q, qd, qdd = states(model, 10, seed=14)
    same = model.with_inertial_parameters(pi)
    assert np.allclose(same.inverse_dynamics(q, qd, qdd), model.inverse_dynamics(q, qd, qdd), rtol=1e-12)
    # a different parameter set: torques follow Y pi2, the original model is untouched
    pi2 = pi.copy()
    pi2[10 * 3:10 * 4] *= 1.7
    other = model.with_inertial_parameters(pi2.reshape(-1, 10))
    assert rel_err(other.inverse_dynamics(q, qd, qdd), model.regressor(q, qd, qdd) @ pi2, 1e-6) < 1e-12
    assert rel_err(other.mass_matrix(q), other.mass_matrix(q, method='crba')) < 1e-12
    assert np.allclose(model.inertial_parameters(), pi)
    assert other.joint_names == model.joint_names and other is not model


def test_physical_consistency_checks():
    model = load_urdf(ARM)
    pi = model.inertial_parameters().reshape(-1, 10)
    assert all(ok for ok, _ in physical_consistency(pi))
    bad = pi.copy()
    bad[2, 0] = -1.0
    with pytest.raises(ValueError, match='body 2: negative mass'):
        model.with_inertial_parameters(bad)
    bad = pi.copy()
    bad[1, 4] = -1.0   # I_xx < 0
    with pytest.raises(ValueError, match='body 1: inertia about the CoM is not positive semidefinite'):
        model.with_inertial_parameters(bad)
    bad = pi.copy()
    bad[0, 4:] = 0
    bad[0, 4], bad[0, 6], bad[0, 9] = 1.0, 1.0, 3.0   # about the CoM roughly (1, 1, 3): triangle fails
    with pytest.raises(ValueError, match='body 0: principal moments .* violate the triangle inequality'):
        model.with_inertial_parameters(bad)
    assert model.with_inertial_parameters(bad, check=False).nb == model.nb
    zero = pi.copy()
    zero[0] = 0
    zero[0, 1] = 0.1
    with pytest.raises(ValueError, match='body 0: zero mass with non-zero first moment'):
        model.with_inertial_parameters(zero)
    with pytest.raises(ValueError, match=r'inertial parameters must have shape \(70,\) or \(7, 10\)'):
        model.with_inertial_parameters(np.zeros(69))
    nan = pi.copy()
    nan[0, 0] = np.nan
    with pytest.raises(ValueError, match='inertial parameters contain non-finite values'):
        model.with_inertial_parameters(nan)
    assert not physical_consistency(nan)[0][0]


def _data(model, seed, duration, noise):
    _, q, qd, qdd = identification.excitation_trajectory(model, duration=duration, rate=50.0, seed=seed)
    tau = model.inverse_dynamics(q, qd, qdd)
    rng = np.random.default_rng(seed)
    return q, qd, qdd, tau, tau + noise * rng.normal(size=tau.shape)


def test_identification_recovers_base_parameters_and_warns():
    model = load_urdf(ARM)
    pi_true = model.inertial_parameters()
    q, qd, qdd, tau, noisy = _data(model, 1, 20.0, 0.0)
    with pytest.warns(identification.UnidentifiableWarning,
                      match=r'27 of 70 inertial-parameter directions are not identifiable'):
        res = identification.identify(model, q, qd, qdd, tau)
    assert not res.fully_identifiable and res.rank == 43 and res.n_unidentifiable == 27
    # noise-free data: base parameters exact, any full solution predicts torques exactly
    assert np.allclose(res.base_parameters, res.base_of(pi_true), rtol=1e-7, atol=1e-9)
    qh, qdh, qddh, tauh, _ = _data(model, 2, 5.0, 0.0)
    assert rel_err(res.predict(model, qh, qdh, qddh), tauh, 1.0) < 1e-7
    # the base map is the identity on the chosen columns and annihilates the null space
    assert np.allclose(res.base_matrix[:, res.base_columns], np.eye(res.rank))
    Y = model.regressor(q, qd, qdd).reshape(-1, 70)
    null = np.linalg.svd(Y, full_matrices=False)[2][43:]
    assert np.abs(res.base_matrix @ null.T).max() < 1e-6 * np.abs(res.base_matrix).max()
    # a prior is kept along unidentifiable directions
    with warnings.catch_warnings():
        warnings.simplefilter('ignore', identification.UnidentifiableWarning)
        res_p = identification.identify(model, q, qd, qdd, tau, prior=pi_true)
    assert np.allclose(res_p.parameters, pi_true, rtol=1e-6, atol=1e-8)


def test_identification_with_noise_predicts_held_out_torques():
    model = load_urdf(ARM)
    sigma = 0.002 * model.effort_limits
    q, qd, qdd, tau, _ = _data(model, 3, 20.0, 0.0)
    noisy = tau + np.random.default_rng(5).normal(size=tau.shape) * sigma
    with warnings.catch_warnings():
        warnings.simplefilter('ignore', identification.UnidentifiableWarning)
        res = identification.identify(model, q, qd, qdd, noisy, weights=1 / sigma)
    beta = res.base_of(model.inertial_parameters())
    z = (res.base_parameters - beta) / res.base_std
    assert np.mean(np.abs(z) < 3) > 0.95                    # consistent uncertainty
    assert np.all(res.residual_rms < 1.5 * sigma) and np.all(res.residual_rms > 0.5 * sigma)
    qh, qdh, qddh, tauh, _ = _data(model, 4, 5.0, 0.0)
    err = np.sqrt(np.mean((res.predict(model, qh, qdh, qddh) - tauh) ** 2, axis=0))
    assert np.all(err < 0.3 * sigma)


def test_rcond_sets_the_rank_threshold():
    model = load_urdf(ARM)
    q, qd, qdd, tau, _ = _data(model, 6, 10.0, 0.0)
    with pytest.warns(identification.UnidentifiableWarning) as rec:
        loose = identification.identify(model, q, qd, qdd, tau, rcond=0.3)
    assert loose.rank < 43 and f'{70 - loose.rank} of 70' in str(rec[-1].message)
    assert loose.base_parameters.shape == (loose.rank,) and loose.parameters.shape == (70,)


def test_identification_error_paths():
    model = load_urdf(ARM)
    q, qd, qdd, tau, _ = _data(model, 7, 2.0, 0.0)
    with pytest.raises(ValueError, match=r'prior must be a finite vector of shape \(70,\)'):
        identification.identify(model, q, qd, qdd, tau, prior=np.zeros(3))
    with pytest.raises(ValueError, match='weights must be 7 finite positive numbers'):
        identification.identify(model, q, qd, qdd, tau, weights=-np.ones(7))
    with pytest.raises(ValueError, match=r'rcond must be in \(0, 1\)'):
        identification.identify(model, q, qd, qdd, tau, rcond=2.0)
    model.set_gravity((0.0, 0.0, 0.0))
    z = np.zeros((20, 7))
    with pytest.raises(ValueError, match='the stacked regressor is zero'):
        identification.identify(model, z, z, z, z)
    with pytest.warns(identification.UnidentifiableWarning, match='3 samples x 7 joints = 21 equations'):
        with pytest.raises(ValueError, match='the stacked regressor is zero'):
            identification.identify(model, z[:3], z[:3], z[:3], z[:3])
    with pytest.raises(ValueError, match='duration, rate, base_frequency must be > 0'):
        identification.excitation_trajectory(model, duration=0)


def test_excitation_trajectory_respects_limits():
    model = load_urdf(ARM)
    t, q, qd, qdd = identification.excitation_trajectory(model, duration=10.0, rate=200.0, seed=3)
    assert np.all(q >= model.position_lower) and np.all(q <= model.position_upper)
    assert np.all(np.abs(qd) <= model.velocity_limits)
    # derivatives are consistent
    assert rel_err(np.gradient(q, t, axis=0)[5:-5][None], qd[5:-5][None], 1.0) < 1e-3


def test_identification_script_runs():
    out = subprocess.run([sys.executable, '-m', 'lie_dynamics.identification', '--quick'], cwd=ROOT,
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert 'base parameters' in out.stdout and 'held-out' in out.stdout
    assert 'not identifiable' in out.stdout
