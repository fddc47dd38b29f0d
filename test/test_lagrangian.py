"""Closed-form Lagrangian dynamics (paper section 3.3): M, Christoffel/Coriolis, potential gravity."""
import numpy as np
import pytest

from dyn_cases import ARM, CASES, case, oracle_stack, rel_err, states
from lie_dynamics.algorithms import crba, lagrangian
from lie_dynamics.codegen import runtime
from lie_dynamics import load_urdf


@pytest.mark.parametrize('name', CASES)
def test_mass_matrix_matches_crba_and_pinocchio(name):
    model, oracle = case(name)
    q, _, _ = states(model)
    M = model.mass_matrix(q, method='closed_form')
    ref = oracle_stack(oracle.crba, q)
    assert rel_err(M, ref) < 1e-10
    assert rel_err(model.mass_matrix(q), ref) < 1e-10               # CRBA, generated kernel if small
    assert rel_err(crba.mass_matrix_vectorized(model, q), ref) < 1e-10
    assert rel_err(model.mass_matrix(q[:5]), ref[:5]) < 1e-10       # small batch: kernel per state
    assert np.array_equal(M, np.swapaxes(M, 1, 2)) or rel_err(M, np.swapaxes(M, 1, 2)) < 1e-14
    assert np.all(np.linalg.eigvalsh(M)[:, 0] > 0)
    # single state gives the batch row
    for method in ('crba', 'closed_form'):
        assert np.allclose(model.mass_matrix(q[3], method), M[3], rtol=0, atol=1e-13 * np.abs(M[3]).max())
        assert np.allclose(model.mass_matrix(q[3].tolist(), method), M[3], rtol=0,
                           atol=1e-13 * np.abs(M[3]).max())


@pytest.mark.parametrize('name', ['chain7', 'tree20_mimic', 'arm7'])
def test_block_factors_reproduce_eq39(name):
    model, _ = case(name)
    q, _, _ = states(model, 3)
    for qs in q:
        S, G, J = lagrangian.block_factors(model, qs)
        assert S.shape == (6 * model.nb, model.nb) and G.shape == J.shape == (6 * model.nb,) * 2
        Mx = S.T @ G.T @ J @ G @ S
        assert rel_err((model.E.T @ Mx @ model.E)[None], model.mass_matrix(qs)[None]) < 1e-12
        # G is lower block-triangular with identity diagonal blocks
        Gb = G.reshape(model.nb, 6, model.nb, 6)
        for i in range(model.nb):
            assert np.allclose(Gb[i, :, i, :], np.eye(6), atol=1e-12)
            assert np.all(Gb[i, :, i + 1:, :] == 0)


@pytest.mark.parametrize('name', CASES)
def test_coriolis_matrix_matches_pinocchio_and_rnea(name):
    model, oracle = case(name)
    q, qd, _ = states(model)
    C = model.coriolis_matrix(q, qd)
    ref = oracle_stack(oracle.coriolis_matrix, q, qd)
    M = model.mass_matrix(q)
    floor = 1e-6 * np.abs(M).max()
    assert rel_err(C, ref, floor) < 1e-10
    # C qd = inverse_dynamics(q, qd, 0) - g(q)
    g = model.gravity(q)
    h = model.inverse_dynamics(q, qd, np.zeros_like(qd)) - g
    assert rel_err(np.einsum('nij,nj->ni', C, qd), h, max(floor, 1e-5 * np.abs(g).max())) < 1e-10
    # the same matrix as 1/2 dtau/dqd of the differentiated recursion: generated kernel state by
    # state, on numpy rows, the vectorised form in between, and one state
    limits = runtime.THRESHOLDS['inverse_dynamics_derivatives']
    for N in (limits.loop_below - 1, limits.loop_below, len(q)):
        assert rel_err(model.coriolis_matrix(q[:N], qd[:N], method='recursive'), ref[:N], floor) < 1e-10
    rows = model.coriolis_matrix(np.tile(q, (2, 1)), np.tile(qd, (2, 1)), method='recursive')
    assert len(rows) >= limits.rows_from and rel_err(rows[:len(q)], ref, floor) < 1e-10
    assert rel_err(model.coriolis_matrix(q[0], qd[0], method='recursive')[None], ref[:1], floor) < 1e-10


@pytest.mark.parametrize('name', ['chain2', 'chain7', 'tree12', 'tree20_mimic', 'mixed_types', 'arm7'])
def test_christoffel_symbols_identities(name):
    model, _ = case(name)
    q, qd, _ = states(model, 10, seed=1)
    G = model.christoffel(q)
    n = model.n
    assert G.shape == (10, n, n, n)
    scale = np.abs(G).max()
    assert np.max(np.abs(G - np.swapaxes(G, 1, 2))) < 1e-12 * scale          # Gamma_ijk = Gamma_jik
    C = model.coriolis_matrix(q, qd)
    assert rel_err(np.einsum('nijk,ni->nkj', G, qd), C, 1e-6) < 1e-11       # C_kj = sum_i Gamma_ijk qd_i
    # eq 40 against central differences of M
    h = 1e-6
    dM = np.stack([(model.mass_matrix(q + h * e) - model.mass_matrix(q - h * e)) / (2 * h)
                   for e in np.eye(n)], axis=1)                               # dM[n, i] = dM/dq_i
    assert rel_err(model.mass_matrix_derivatives(q), dM, 1e-6) < 1e-7
    G_fd = 0.5 * (np.einsum('nikj->nijk', dM) + np.einsum('njki->nijk', dM) - np.einsum('nkij->nijk', dM))
    assert rel_err(G, G_fd, 1e-6) < 1e-7
    # single state
    assert np.allclose(model.christoffel(q[0]), G[0], atol=1e-13 * scale, rtol=0)


@pytest.mark.parametrize('name', ['chain7', 'tree20_mimic', 'mixed_types', 'arm7'])
def test_mdot_minus_2c_is_skew(name):
    model, _ = case(name)
    q, qd, _ = states(model, 20, seed=2)
    h = 1e-6
    Mdot = (model.mass_matrix(q + h * qd) - model.mass_matrix(q - h * qd)) / (2 * h)
    K = Mdot - 2 * model.coriolis_matrix(q, qd)
    scale = np.abs(Mdot).max(axis=(1, 2)) + np.abs(K).max(axis=(1, 2))
    assert np.all(np.abs(K + np.swapaxes(K, 1, 2)).max(axis=(1, 2)) < 1e-7 * scale)


@pytest.mark.parametrize('name', CASES)
def test_potential_gravity_matches_rnea_and_pinocchio(name):
    model, oracle = case(name)
    q, _, _ = states(model)
    g = model.gravity_potential(q)
    assert rel_err(g, model.gravity(q)) < 1e-10
    assert rel_err(g, oracle_stack(oracle.gravity, q)) < 1e-10
    U = model.potential_energy(q)
    assert np.allclose(U, oracle_stack(oracle.potential_energy, q), rtol=1e-10, atol=1e-10)
    # g = dU/dq
    h = 1e-6
    dU = np.stack([(model.potential_energy(q + h * e) - model.potential_energy(q - h * e)) / (2 * h)
                   for e in np.eye(model.n)], axis=1)
    assert rel_err(g, dU, 1e-3) < 1e-6


def test_gravity_follows_the_model_setting():
    model = load_urdf(ARM, gravity=(0.0, 9.81, 0.0))
    q, qd, _ = states(model, 5)
    assert rel_err(model.gravity_potential(q), model.gravity(q)) < 1e-10
    model.set_gravity((0.0, 0.0, 0.0))
    assert np.all(model.gravity_potential(q) == 0) and np.all(model.potential_energy(q) == 0)


def test_kinetic_energy_matches_pinocchio():
    model, oracle = case('tree20_mimic')
    q, qd, _ = states(model, 10)
    T = model.kinetic_energy(q, qd)
    assert np.allclose(T, oracle_stack(oracle.kinetic_energy, q, qd), rtol=1e-10)
    assert isinstance(model.kinetic_energy(q[0], qd[0]), float)
    assert isinstance(model.potential_energy(q[0]), float)


def _rk4_energy_run(model, q0, qd0, torque, dt, steps):
    """RK4 on (q, qd, W) with W = integral of qd . tau; returns the energy-balance defect."""
    n = model.n

    def f(t, y):
        q, qd = y[:, :n], y[:, n:2 * n]
        tau = torque(t, q.shape[0])
        qdd = model.forward_dynamics(q, qd, tau)
        return np.concatenate([qd, qdd, np.sum(qd * tau, axis=1, keepdims=True)], axis=1)

    y = np.concatenate([q0, qd0, np.zeros((len(q0), 1))], axis=1)

    def energy(y):
        return model.kinetic_energy(y[:, :n], y[:, n:2 * n]) + model.potential_energy(y[:, :n])

    E0 = energy(y)
    t = 0.0
    for _ in range(steps):
        k1 = f(t, y)
        k2 = f(t + dt / 2, y + dt / 2 * k1)
        k3 = f(t + dt / 2, y + dt / 2 * k2)
        k4 = f(t + dt, y + dt * k3)
        y = y + dt / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
        t += dt
    return energy(y) - E0 - y[:, -1], np.abs(y[:, -1]) + np.abs(E0)


@pytest.mark.parametrize('name', ['arm7', 'tree12'])
def test_energy_balance_along_simulated_trajectory(name):
    """d/dt (1/2 qd^T M qd + U) = qd^T tau: the defect shrinks like dt^4 (RK4)."""
    model, _ = case(name)
    rng = np.random.default_rng(3)
    q0 = rng.uniform(-1, 1, size=(4, model.n))
    qd0 = rng.normal(size=(4, model.n))
    amp = rng.normal(size=model.n) * 2.0

    def torque(t, N):
        return np.broadcast_to(amp * np.sin(3.0 * t + np.arange(model.n)), (N, model.n))

    d1, scale = _rk4_energy_run(model, q0, qd0, torque, 2e-3, 100)
    d2, _ = _rk4_energy_run(model, q0, qd0, torque, 1e-3, 200)
    assert np.all(np.abs(d2) < 1e-6 * (1 + scale))
    # fourth order: halving dt divides the defect by ~16
    big = np.abs(d1) > 1e-11 * (1 + scale)
    assert np.all(np.abs(d2[big]) < np.abs(d1[big]) / 8)


def test_error_paths():
    model, _ = case('chain7')
    with pytest.raises(ValueError, match="unknown mass matrix method 'lu'"):
        model.mass_matrix(np.zeros(model.n), method='lu')
    with pytest.raises(ValueError, match='block_factors takes a single state'):
        lagrangian.block_factors(model, np.zeros((2, model.n)))
    with pytest.raises(ValueError, match=r'q must have shape \(7,\)'):
        model.coriolis_matrix(np.zeros(6), np.zeros(6))
    with pytest.raises(ValueError, match='qd has 1 states, expected 2'):
        model.coriolis_matrix(np.zeros((2, 7)), np.zeros(7))
    with pytest.raises(ValueError, match='q contains non-finite values'):
        model.christoffel(np.full(7, np.nan))
    with pytest.raises(ValueError, match="unknown Coriolis matrix method 'lu'"):
        model.coriolis_matrix(np.zeros(7), np.zeros(7), method='lu')
    for bad in (np.full(7, np.nan), [0.0] * 6, np.zeros((2, 6))):
        with pytest.raises(ValueError, match='qd'):
            model.coriolis_matrix(np.zeros(7) if np.ndim(bad) == 1 else np.zeros((2, 7)), bad, method='recursive')


def test_chunked_batches_agree(monkeypatch):
    model, _ = case('tree12')
    q, qd, _ = states(model, 9)
    C = model.coriolis_matrix(q, qd)
    M = model.mass_matrix(q)
    monkeypatch.setitem(runtime.THRESHOLDS, 'vectorized_budget', 1)  # one state per chunk
    assert np.array_equal(model.coriolis_matrix(q, qd), C)
    assert np.array_equal(model.mass_matrix(q), M)


def test_payload_changes_are_seen():
    model = load_urdf(ARM)
    q, qd, _ = states(model, 3)
    M0 = model.mass_matrix(q)
    model.set_payload('link7', 2.0, (0.0, 0.0, 0.1))
    M1 = model.mass_matrix(q)
    assert not np.allclose(M0, M1)
    assert rel_err(M1, model.mass_matrix(q, method='closed_form')) < 1e-12
    assert rel_err(model.mass_matrix(q[0])[None], M1[:1]) < 1e-12
    assert rel_err(model.gravity_potential(q), model.gravity(q)) < 1e-10
