"""The generalized-momentum observer against ground truth (known external torques added to
Pinocchio-checked inverse dynamics) and against Pinocchio's M, C and g."""
import numpy as np
import pinocchio as pin
import pytest

from lie_dynamics import default_urdf_path, load_urdf
from lie_dynamics.algorithms.observer import MomentumObserver, estimate_external_torques, generalized_momentum
from lie_dynamics.codegen import runtime
from lie_dynamics.laws import make_friction
from oracle import Oracle
from robots import named_urdf, with_payload

DT = 1e-3
GAIN = 40.0


def trajectory(model, seconds=1.5, seed=0):
    """A smooth motion with exact qd, qdd: q = a sin(w t + phi)."""
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, seconds, DT)
    a, w, phi = rng.uniform(0.2, 0.6, model.n), rng.uniform(0.5, 2.0, model.n), rng.uniform(0, 6, model.n)
    arg = np.outer(t, w) + phi
    return t, a * np.sin(arg), a * w * np.cos(arg), -a * w * w * np.sin(arg)


def discrete_response(t, ext, gain):
    """The trapezoid observer's exact response to tau_ext samples (module docstring)."""
    out = np.zeros_like(ext)
    for k in range(1, len(t)):
        h = 0.5 * gain * (t[k] - t[k - 1])
        a, b = (1 - h) / (1 + h), h / (1 + h)
        out[k] = a * out[k - 1] + b * (ext[k] + ext[k - 1])
    return out


MODELS = {'arm': lambda: load_urdf(default_urdf_path()), 'tree': lambda: load_urdf(named_urdf('tree20_mimic')),
          'chain': lambda: load_urdf(named_urdf('chain30'))}


@pytest.mark.parametrize('name', sorted(MODELS))
def test_converges_to_a_known_step_with_the_predicted_first_order_response(name):
    model = MODELS[name]()
    t, q, qd, qdd = trajectory(model)
    step = np.linspace(-2.0, 2.0, model.n)
    ext = np.where(t[:, None] >= 0.3, step, 0.0)
    tau_motor = model.inverse_dynamics(q, qd, qdd) - ext  # the motors supply what the contact does not
    r = estimate_external_torques(model, t, q, qd, tau_motor, GAIN)
    scale = np.abs(model.inverse_dynamics(q, qd, qdd)).max()
    assert np.abs(r - discrete_response(t, ext, GAIN)).max() < 1e-6 * scale  # integration error only
    settled = t >= 0.3 + 8 / GAIN
    assert np.allclose(r[settled], step, atol=2e-3 * np.abs(step).max())
    # continuous first order: 63% of the step one time constant after it
    k = np.searchsorted(t, 0.3 + 1 / GAIN)
    assert np.allclose(r[k], step * (1 - np.exp(-1)), atol=0.03 * np.abs(step).max())


def test_without_contact_the_estimate_stays_at_integration_error():
    model = MODELS['arm']()
    t, q, qd, qdd = trajectory(model, seconds=3.0, seed=4)
    tau = model.inverse_dynamics(q, qd, qdd)
    r = estimate_external_torques(model, t, q, qd, tau, GAIN)
    assert np.abs(r).max() < 1e-6 * np.abs(tau).max()


def test_streaming_equals_batch_and_friction_is_not_contact():
    model = MODELS['arm']()
    t, q, qd, qdd = trajectory(model, seconds=0.4, seed=2)
    friction = make_friction(model.damping, model.friction, 0.05)
    f = model.damping * qd + model.friction * np.tanh(qd / 0.05)
    tau_motor = model.inverse_dynamics(q, qd, qdd) + f  # the motors also overcome friction
    batch = estimate_external_torques(model, t, q, qd, tau_motor, GAIN, friction=friction)
    obs = MomentumObserver(model, GAIN, friction=friction)
    stream = np.array([obs.update(t[k], q[k], qd[k], tau_motor[k]) for k in range(len(t))])
    assert np.allclose(stream, batch, atol=1e-12)
    assert np.abs(batch).max() < 1e-6 * np.abs(tau_motor).max()
    unaware = estimate_external_torques(model, t, q, qd, tau_motor, GAIN)  # friction then looks like contact
    assert np.abs(unaware).max() > 0.1 * np.abs(f).max()


def test_momentum_terms_match_pinocchio():
    """p = M qd and beta = tau + C^T qd - g from our M, C, g against Pinocchio's, to 1e-9."""
    model = MODELS['arm']()
    pm = pin.buildModelFromUrdf(default_urdf_path())
    pm.gravity.linear = model.gravity_vector
    pd = pm.createData()
    obs = MomentumObserver(model, GAIN)
    rng = np.random.default_rng(3)
    for _ in range(20):
        q, qd, tau = rng.normal(size=(3, model.n))
        p, beta = obs.momentum_terms(q, qd, tau)
        M = pin.crba(pm, pd, q)
        M = np.triu(M) + np.triu(M, 1).T
        C = pin.computeCoriolisMatrix(pm, pd, q, qd)
        g = pin.computeGeneralizedGravity(pm, pd, q)
        scale = max(1.0, np.abs(tau).max(), np.abs(g).max())
        assert np.allclose(p, M @ qd, rtol=1e-9, atol=1e-9 * scale)
        assert np.allclose(beta, tau + C.T @ qd - g, rtol=1e-9, atol=1e-9 * scale)


@pytest.mark.parametrize('name', ['arm', 'tree20_mimic', 'mixed_types', 'prismatic_only', 'chain30'])
def test_generalized_momentum_matches_pinocchio_on_every_path(name, monkeypatch):
    """p = M qd and C^T qd of the O(n) kernel (one state, rows batch) and of the reference
    (M and C) against Pinocchio's crba and computeCoriolisMatrix, to 1e-10 relative."""
    xml = open(default_urdf_path()).read() if name == 'arm' else named_urdf(name)
    model, oracle = load_urdf(xml), Oracle(xml)
    rng = np.random.default_rng(7)
    q, qd = rng.uniform(-2, 2, size=(2, 40, model.n))
    M = np.array([oracle.crba(x) for x in q])
    C = np.array([oracle.coriolis_matrix(x, v) for x, v in zip(q, qd, strict=True)])
    p_ref, c_ref = np.einsum('nij,nj->ni', M, qd), np.einsum('nji,nj->ni', C, qd)

    def check(p, c):
        assert np.abs(p - p_ref).max() <= 1e-10 * np.abs(p_ref).max()
        assert np.abs(c - c_ref).max() <= 1e-10 * np.abs(c_ref).max()
    check(*np.array([generalized_momentum(model, x, v) for x, v in zip(q, qd, strict=True)]).transpose(1, 0, 2))
    assert runtime.route(model, 'inverse_dynamics', len(q)) == 'rows'
    check(*generalized_momentum(model, q, qd))          # the kernel's rows form
    monkeypatch.setitem(runtime.THRESHOLDS, 'inverse_dynamics',
                        runtime.THRESHOLDS['inverse_dynamics']._replace(loop_below=1000))
    runtime.forget(model)
    check(*generalized_momentum(model, q, qd))          # the float kernel, state by state
    monkeypatch.setitem(runtime.THRESHOLDS, 'inverse_dynamics',
                        runtime.THRESHOLDS['inverse_dynamics']._replace(compile_max=0))
    runtime.forget(model)
    check(*generalized_momentum(model, q, qd))          # the reference: M and C
    with pytest.raises(ValueError, match='qd'):
        generalized_momentum(model, q[0], np.full(model.n, np.nan))


def test_generalized_momentum_follows_payload_and_locked_joints():
    """The kernel's parameters follow set_payload and set_locked (no stale values)."""
    xml = open(default_urdf_path()).read()
    payload = ('link7', 1.7, (0.05, -0.02, 0.1), (0.01, 0.001, 0.0, 0.02, 0.0, 0.015))
    names = load_urdf(xml).joint_names
    rng = np.random.default_rng(11)
    for ctrl, locked in ((names, {}), (names[1::2], {n: 0.3 * k - 0.5 for k, n in enumerate(names[0::2])})):
        model = load_urdf(xml, joints=ctrl)
        generalized_momentum(model, np.zeros(model.n), np.ones(model.n))    # kernel bound before the changes
        model.set_payload(*payload)
        if locked:
            model.set_locked(locked)
        oracle = Oracle(with_payload(xml, *payload), joints=ctrl, locked=locked)
        for _ in range(10):
            q, qd = rng.uniform(-2, 2, size=(2, model.n))
            p, c = generalized_momentum(model, q, qd)
            p_ref, c_ref = oracle.crba(q) @ qd, qd @ oracle.coriolis_matrix(q, qd)
            assert np.abs(p - p_ref).max() <= 1e-10 * np.abs(p_ref).max()
            assert np.abs(c - c_ref).max() <= 1e-10 * np.abs(c_ref).max()


@pytest.mark.parametrize('kwargs, msg', [
    ({'gain': 0.0}, 'observer gain must be'),
    ({'gain': [1.0, 2.0]}, 'observer gain must be'),
    ({'gain': np.nan}, 'observer gain must be'),
])
def test_bad_gains_are_refused(kwargs, msg):
    with pytest.raises(ValueError, match=msg):
        MomentumObserver(MODELS['arm'](), **kwargs)


def test_bad_samples_are_refused_and_lose_nothing():
    model = MODELS['arm']()
    obs = MomentumObserver(model, GAIN)
    z = np.zeros(model.n)
    obs.update(0.0, z, z, model.gravity(z))  # at rest, the motors hold gravity: no contact
    with pytest.raises(ValueError, match='times must increase'):
        obs.update(0.0, z, z, z)
    with pytest.raises(ValueError, match='tau_measured contains non-finite'):
        obs.update(0.001, z, z, np.full(model.n, np.nan))
    with pytest.raises(ValueError, match='update takes one state'):
        obs.update(0.001, np.zeros((2, model.n)), np.zeros((2, model.n)), np.zeros((2, model.n)))
    assert np.all(obs.update(0.001, z, z, model.gravity(z)) == 0)  # the integral was not touched
    with pytest.raises(ValueError, match=r't must have shape \(3,\)'):
        estimate_external_torques(model, [0.0, 1.0], np.zeros((3, model.n)), np.zeros((3, model.n)),
                                  np.zeros((3, model.n)), GAIN)
