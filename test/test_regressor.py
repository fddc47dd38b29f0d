"""Inertial-parameter regressor, parameter round trips and identification."""
import subprocess
import sys
import warnings

import numpy as np
import pytest

from dyn_cases import ARM, CASES, ROOT, case, pin_body_permutation, rel_err, states
from lie_dynamics.algorithms import identification
from lie_dynamics import load_urdf
from lie_dynamics.algorithms import regressor as rg
from lie_dynamics.codegen import runtime
from lie_dynamics.codegen.traced.regressor import REGRESSOR
from lie_dynamics.algorithms.regressor import physical_consistency
from lie_dynamics.model.inertia import inertia_to_parameters, parameters_to_inertia
from oracle import Oracle
from robots import random_urdf


@pytest.mark.parametrize('name', CASES)
def test_regressor_matches_pinocchio(name):
    model, oracle = case(name)
    q, qd, qdd = states(model, seed=13)
    Y = model.regressor(q, qd, qdd)
    perm = pin_body_permutation(model, oracle)
    ref = np.array([oracle.regressor(*s)[:, perm] for s in zip(q, qd, qdd, strict=True)])
    assert Y.shape == (len(q), model.n, 10 * model.nb)
    assert rel_err(Y, ref) < 1e-10
    pi = model.inertial_parameters()
    assert np.allclose(pi, oracle.dynamic_parameters()[perm], rtol=1e-12, atol=1e-14)
    assert rel_err(Y @ pi, model.inverse_dynamics(q, qd, qdd), 1e-6) < 1e-10
    assert np.allclose(model.regressor(q[2], qd[2], qdd[2]), Y[2], rtol=1e-12, atol=1e-12)


def _pin_regressor(model, oracle, q, qd, qdd):
    perm = pin_body_permutation(model, oracle)
    return np.array([oracle.regressor(*s)[:, perm] for s in zip(q, qd, qdd, strict=True)])


@pytest.mark.parametrize('name', CASES)
def test_regressor_kernel_paths_match_pinocchio(name):
    model, oracle = case(name)
    q, qd, qdd = states(model, seed=21)
    ref = _pin_regressor(model, oracle, q, qd, qdd)
    if name == 'chain30':   # above the compile cap: no kernel, the vectorised form throughout
        assert runtime.pairs(model) > runtime.THRESHOLDS['regressor'].compile_max
        assert rg.regressor_kernel(model, q, qd, qdd, 'rows') is None
        assert rel_err(model.regressor(q[0], qd[0], qdd[0])[None], ref[:1]) < 1e-10
        return
    for mode in ('loop', 'rows'):   # forced paths
        Y = rg.regressor_kernel(model, q, qd, qdd, mode)
        assert Y.shape == (len(q), model.n, 10 * model.nb) and rel_err(Y, ref) < 1e-10
    # default dispatch: a batch (numpy rows at this size), a small batch (float loop), one state
    assert rg.regressor_kernel(model, q, qd, qdd) is not None
    assert rel_err(model.regressor(q, qd, qdd), ref) < 1e-10
    assert rel_err(model.regressor(q[:3], qd[:3], qdd[:3]), ref[:3]) < 1e-10
    one = np.array([model.regressor(*s) for s in zip(q, qd, qdd, strict=True)])
    assert rel_err(one, ref) < 1e-10
    assert rel_err(one @ model.inertial_parameters(), model.inverse_dynamics(q, qd, qdd), 1e-6) < 1e-10
    # other input forms of one state: lists, integer arrays, a (1, n) batch
    assert np.array_equal(model.regressor(q[0].tolist(), list(qd[0]), tuple(qdd[0])), one[0])
    z = np.zeros(model.n, dtype=int)
    assert rel_err(model.regressor(z, z, z)[None], _pin_regressor(model, oracle, [z], [z], [z])) < 1e-10
    assert np.array_equal(model.regressor(q[:1], qd[:1], qdd[:1]), one[:1])


def test_regressor_kernel_follows_payload_gravity_and_locked_joints(monkeypatch):
    xml = random_urdf(22, 8, tree=True)
    ctrl = load_urdf(xml).joint_names[1::2]
    model = load_urdf(xml, joints=ctrl)
    locked = {nm: -0.4 + 0.25 * k for k, nm in enumerate(model.locked_joint_names)}
    assert locked
    model.set_locked(locked)
    q, qd, qdd = states(model, 100, seed=22)
    # builds the Python kernel (model.regressor may take the native one, loaded from the disk
    # cache without tracing)
    rg.regressor_kernel(model, q[:1], qd[:1], qdd[:1], 'loop')
    model.regressor(q[0], qd[0], qdd[0])          # and the native one, where there is a compiler

    def no_build(*args):
        raise AssertionError('the regressor kernel was rebuilt')
    monkeypatch.setattr(REGRESSOR, 'build', no_build)

    def check(oracle):
        ref = _pin_regressor(model, oracle, q, qd, qdd)
        for mode in ('loop', 'rows'):
            assert rel_err(rg.regressor_kernel(model, q, qd, qdd, mode), ref) < 1e-10
        one = np.array([model.regressor(*s) for s in zip(q, qd, qdd, strict=True)])
        assert rel_err(one, ref) < 1e-10
        assert rel_err(one @ model.inertial_parameters(), model.inverse_dynamics(q, qd, qdd), 1e-6) < 1e-10
        return one

    Y0 = check(Oracle(xml, joints=ctrl, locked=locked))
    # a payload changes the parameters, not the regressor
    link = next(ln for ln, (b, _) in model.link_frames.items() if b == model.nb - 1)
    model.set_payload(link, 0.9, (0.03, -0.02, 0.1), (0.002, 0.0, 0.0, 0.003, 0.0, 0.001))
    assert np.array_equal(check(Oracle(xml, joints=ctrl, locked=locked)), Y0)
    g = (1.5, -2.0, -9.0)
    model.set_gravity(g)
    check(Oracle(xml, joints=ctrl, locked=locked, gravity=g))
    locked2 = {nm: v + 0.7 for nm, v in locked.items()}
    model.set_locked(locked2)
    check(Oracle(xml, joints=ctrl, locked=locked2, gravity=g))


def test_regressor_dispatch_by_size(monkeypatch):
    model, oracle = case('arm7')
    limits = runtime.THRESHOLDS['regressor']
    assert runtime.pairs(model) == 28 and 2 <= limits.loop_below < limits.rows_from
    mid = limits.loop_below                              # a batch between the crossovers
    q, qd, qdd = states(model, mid, seed=23)
    ref = _pin_regressor(model, oracle, q, qd, qdd)
    routes = [runtime.route(model, 'regressor', N) for N in (None, mid - 1, mid, limits.rows_from)]
    assert routes == ['loop', 'loop', None, 'rows']      # float kernel, vectorised, numpy rows
    assert rel_err(model.regressor(q[:mid - 1], qd[:mid - 1], qdd[:mid - 1]), ref[:mid - 1]) < 1e-10
    assert rel_err(np.array([model.regressor(*s) for s in zip(q, qd, qdd, strict=True)]), ref) < 1e-10
    assert rel_err(model.regressor(q, qd, qdd), ref) < 1e-10
    # as if the arm were larger: one state and small batches vectorised, rows from mid states
    monkeypatch.setitem(runtime.THRESHOLDS, 'regressor',
                        limits._replace(float_max=27, large=27, rows_from_large=mid))
    runtime.forget(model)
    assert [runtime.route(model, 'regressor', N) for N in (None, 1, mid)] == [None, None, 'rows']
    assert rel_err(model.regressor(q[0], qd[0], qdd[0])[None], ref[:1]) < 1e-10
    assert rel_err(model.regressor(q[:1], qd[:1], qdd[:1]), ref[:1]) < 1e-10
    assert rel_err(model.regressor(q, qd, qdd), ref) < 1e-10
    monkeypatch.setitem(runtime.THRESHOLDS, 'regressor_rows_chunk', 4)   # rows in chunks, last one short
    assert rel_err(rg.regressor_kernel(model, q, qd, qdd, 'rows'), ref) < 1e-10
    monkeypatch.undo()
    runtime.forget(model)


def test_regressor_kernel_copies_and_unsupported_screws():
    import copy
    import pickle
    model, _ = case('chain7')
    q, qd, qdd = states(model, 4, seed=25)
    Y = model.regressor(q, qd, qdd)
    # copies (pickle, deepcopy, new parameters) have the same structure: same kernel, no rebuild
    for other in (pickle.loads(pickle.dumps(model)), copy.deepcopy(model),
                  model.with_inertial_parameters(1.3 * model.inertial_parameters())):
        assert runtime.kernel(other, REGRESSOR) is runtime.kernel(model, REGRESSOR)
        assert np.array_equal(other.regressor(q, qd, qdd), Y)
    # a screw that is not a unit URDF axis: no kernel, the vectorised form
    odd = copy.deepcopy(model)
    odd.S = odd.S * 1.5
    assert rg.regressor_kernel(odd, q, qd, qdd, 'loop') is None
    Yo = odd.regressor(q[0], qd[0], qdd[0])
    assert np.array_equal(Yo, rg.regressor_vectorized(odd, q[0], qd[0], qdd[0]))
    assert not np.allclose(Yo, Y[0])


@pytest.mark.parametrize('kind', ['default', 'loop', 'rows', 'vectorized'])
def test_regressor_rejects_bad_inputs(kind):
    model, _ = case('arm7')
    fn = {'default': model.regressor, 'vectorized': lambda *a: rg.regressor_vectorized(model, *a),
          'loop': lambda *a: rg.regressor_kernel(model, *a, mode='loop'),
          'rows': lambda *a: rg.regressor_kernel(model, *a, mode='rows')}[kind]
    q, qd, qdd = states(model, 4, seed=24)
    for k, name in enumerate(('q', 'qd', 'qdd')):
        for args in ([q, qd, qdd], [q[0], qd[0], qdd[0]], [q[0].tolist(), qd[0].tolist(), qdd[0].tolist()]):
            for bad_value in (np.nan, np.inf):
                bad = [np.array(a, dtype=float) for a in args]
                bad[k][..., 2] = bad_value
                if isinstance(args[0], list):
                    bad = [b.tolist() for b in bad]
                with pytest.raises(ValueError, match=f'^{name} contains non-finite values'):
                    fn(*bad)
            short = list(args)
            short[k] = np.asarray(args[k])[..., :-1]
            with pytest.raises(ValueError, match=rf'^{name} must have shape \(7,\) or \(N, 7\)'):
                fn(*short)
    with pytest.raises(ValueError, match='^qdd has 3 states, expected 4'):
        fn(q, qd, qdd[:3])
    with pytest.raises(ValueError, match='^q must have shape'):
        fn(np.zeros((2, 3, 7)), qd[:2], qdd[:2])
    if kind == 'default':
        with pytest.raises(ValueError, match="mode must be 'loop', 'rows' or None, got 'fast'"):
            rg.regressor_kernel(model, q, qd, qdd, mode='fast')


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
    with pytest.raises(ValueError, match='body 1: negative principal moment'):
        model.with_inertial_parameters(bad)
    bad = pi.copy()
    bad[0, 4:] = 0
    bad[0, 4], bad[0, 6], bad[0, 9] = 1.0, 1.0, 3.0   # about the CoM roughly (1, 1, 3): triangle fails
    with pytest.raises(ValueError, match='body 0: triangle inequality: principal moments'):
        model.with_inertial_parameters(bad)
    assert model.with_inertial_parameters(bad, check=False).nb == model.nb
    zero = pi.copy()
    zero[0] = 0
    zero[0, 1] = 0.1
    with pytest.raises(ValueError, match='body 0: massless with inertia: mass 0 with non-zero first moment'):
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
    # the mass table: labelled columns, one row per moving body named after its link
    lines = out.stdout.splitlines()
    header = ['body', '(link)', 'true', 'kg', 'identified', 'kg']
    head = next(i for i, line in enumerate(lines) if line.split() == header)
    rows = [line.split() for line in lines[head + 1:head + 8]]
    assert [r[0] for r in rows] == load_urdf(ARM).body_link_names == [f'link{i}' for i in range(1, 8)]
