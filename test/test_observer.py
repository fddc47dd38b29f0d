"""The generalized-momentum observer against ground truth (known external torques added to
Pinocchio-checked inverse dynamics) and against Pinocchio's M, C and g."""
import glob
import os
import subprocess
import sys
import warnings
import zlib

import numpy as np
import pinocchio as pin
import pytest

from lie_dynamics import default_urdf_path, load_urdf
from lie_dynamics.algorithms.observer import MomentumObserver, estimate_external_torques, generalized_momentum
from lie_dynamics.codegen import kernel, native, runtime
from lie_dynamics.codegen.traced import observer as observer_kernel
from lie_dynamics.laws import friction_torque, make_friction
from oracle import Oracle
from robots import NAMED_CASES, named_urdf, with_payload

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


REAL_ROOT = next(iter(glob.glob(os.path.join(sys.prefix, 'lib', 'python3*', 'site-packages', 'cmeel.prefix', 'share',
                                             'example-robot-data', 'robots'))), None)


def step_model(name):
    """The bundled arm, a random tree with mimic joints, or a vendor robot (example-robot-data)."""
    if name == 'arm':
        return load_urdf(default_urdf_path())
    if name in NAMED_CASES:
        return load_urdf(named_urdf(name))
    if REAL_ROOT is None:
        pytest.skip('example-robot-data is not installed')
    with warnings.catch_warnings():
        warnings.simplefilter('ignore')   # vendor inertias are warned about
        return load_urdf(os.path.join(REAL_ROOT, name))


@pytest.mark.parametrize('backend', ['native', 'python'])
@pytest.mark.parametrize('name', ['arm', 'tree20_mimic', 'ur_description/urdf/ur5_robot.urdf'])
def test_step_kernel_equals_the_reference_step_by_step(name, backend):
    """MomentumObserver.step (the traced step: in C, or on Python floats with the native kernels
    off) against the numpy reference (momentum_terms + advance) on random states, with viscous
    and Coulomb friction, per-joint gains, jittered dt and a 0.3 s gap; a NaN effort, a time
    that does not increase and a list argument are declined with the state untouched."""
    model = step_model(name)
    if backend == 'native':
        if runtime.native(model, observer_kernel.OBSERVER_STEP) is None:
            pytest.skip('no working C compiler')
    else:
        runtime.use_native(model, False)
    n = model.n
    rng = np.random.default_rng(zlib.crc32(f'step {name}'.encode()))
    friction = make_friction(rng.uniform(0.0, 2.0, n), rng.uniform(0.0, 1.0, n), 0.05)
    gain = rng.uniform(5.0, 200.0, n)
    fast, ref = MomentumObserver(model, gain, friction), MomentumObserver(model, gain, friction)
    t = 1.0
    for k in range(150):
        t += 0.3 if k == 80 else rng.uniform(0.5e-3, 1.5e-3)
        q, qd = rng.uniform(-2, 2, (2, n))
        tau = rng.normal(0.0, 5.0, n)
        if k in (40, 41):   # a NaN effort, then a repeated time: declined, nothing changes
            bad = tau.copy()
            bad[k % n] = np.nan
            state = fast.state   # p(0), the integral, beta + r
            assert fast.step(t, q, qd, bad) is None
            assert fast.step(fast.last_time, q, qd, tau) is None
            if backend == 'native':   # the C call takes float64 arrays only (the Python floats: lists too)
                assert fast.step(t, q.tolist(), qd, tau) is None
            np.testing.assert_array_equal(fast.state, state)
            with pytest.raises(ValueError, match='tau_measured contains non-finite'):
                fast.update(t, q, qd, bad)
            continue
        r = fast.step(t, q, qd, tau)
        assert r is not None, k
        expect = ref.advance(t, *ref.momentum_terms(q, qd, tau))
        scale = max(1.0, np.abs(expect).max())
        assert np.abs(r - expect).max() <= 1e-9 * scale, (k, np.abs(r - expect).max() / scale)
        assert np.abs(fast.estimate - ref.estimate).max() <= 1e-9 * scale
    assert np.abs(r).max() > 1.0   # the estimates compared are not all near zero


def _pin_armature(oracle, arm):
    """Pinocchio's armature per velocity: each controlled joint's value on its own column (a
    mimic joint's column gets none: the master's value stands for the rotor of its column)."""
    a = np.zeros(oracle.nv)
    for k in range(oracle.n):
        a[np.flatnonzero(oracle.E[:, k] == 1.0)[0]] = arm[k]
    oracle.model.armature = a


@pytest.mark.parametrize('backend', ['native', 'python'])
@pytest.mark.parametrize('name', ['arm', 'tree20_mimic', 'ur_description/urdf/ur5_robot.urdf'])
def test_one_step_equals_the_python_observer_and_pinocchio_to_1e12(name, backend):
    """One call of the step kernel from a given observer state (p(0), the integral, beta + r,
    dt) against the Python observer (momentum_terms, advance) from the same state and against
    Pinocchio (p = M qd with the armature, tau + C^T qd - g less the friction law, the
    trapezoid's r), to 1e-12 relative: with an armature, then a payload and another gravity
    set on the same model, nothing traced or compiled again."""
    model = step_model(name)
    if backend == 'native':
        if runtime.native(model, observer_kernel.OBSERVER_STEP) is None:
            pytest.skip('no working C compiler')
    else:
        runtime.use_native(model, False)
    xml = named_urdf(name) if name in NAMED_CASES else open(default_urdf_path() if name == 'arm'
                                                            else os.path.join(REAL_ROOT, name)).read()
    n = model.n
    rng = np.random.default_rng(zlib.crc32(f'one step {name}'.encode()))
    arm = rng.uniform(0.02, 0.4, n)
    model.set_armature(arm)
    friction = make_friction(rng.uniform(0.0, 2.0, n), rng.uniform(0.0, 1.0, n), 0.05)
    gain = rng.uniform(5.0, 200.0, n)
    settings = np.concatenate([gain, friction.viscous, friction.coulomb, [friction.eps]])
    payload = (model.body_link_names[-1], 1.3, (0.02, -0.03, 0.05), (0.01, 0.001, 0.0, 0.02, 0.0, 0.015))
    warm = MomentumObserver(model, gain, friction)   # every kernel of the step and of its reference, made
    warm.momentum_terms(np.zeros(n), np.zeros(n), np.zeros(n))
    assert warm.step(0.0, np.zeros(n), np.zeros(n), np.zeros(n)) is not None
    builds, compiles = kernel.builds(), native.compile_count()
    for phase in ('armature', 'payload and gravity'):
        if phase == 'armature':
            oracle = Oracle(xml, joints=model.joint_names)
        else:
            model.set_payload(*payload)
            model.gravity_vector = (0.8, -1.5, -9.6)
            oracle = Oracle(with_payload(xml, *payload), joints=model.joint_names, gravity=(0.8, -1.5, -9.6))
        _pin_armature(oracle, arm)
        for _ in range(10):
            q, qd = rng.uniform(-2, 2, (2, n))
            tau, p0, c0 = rng.normal(0.0, 5.0, (3, n))
            dt = rng.uniform(0.5e-3, 1.5e-3)
            z = np.concatenate([p0, np.zeros(n), c0, [dt]])   # runtime.fast: the kernel bound to today's parameters
            out = runtime.fast(model, observer_kernel.OBSERVER_STEP)(q, qd, tau, z, settings)
            r, p, beta = out[3 * n + 1:4 * n + 1], out[4 * n + 1:5 * n + 1], out[5 * n + 1:]
            ref = MomentumObserver(model, gain, friction)
            ref.advance(1.0, p0, c0)   # the state the kernel was given: p(0) = p0, integral 0, beta + r = c0
            p_py, beta_py = ref.momentum_terms(q, qd, tau)
            r_py = ref.advance(1.0 + dt, p_py, beta_py)
            p_pin = oracle.crba(q) @ qd
            beta_pin = tau + qd @ oracle.coriolis_matrix(q, qd) - oracle.gravity(q) - friction_torque(qd, *friction)
            half = 0.5 * dt * gain
            r_pin = gain * (p_pin - p0 - 0.5 * dt * (c0 + beta_pin)) / (1.0 + half)
            for got, (py, pn) in ((p, (p_py, p_pin)), (beta, (beta_py, beta_pin)), (r, (r_py, r_pin))):
                for expect in (py, pn):
                    scale = max(1.0, np.abs(expect).max())
                    assert np.abs(got - expect).max() <= 1e-12 * scale, (phase, np.abs(got - expect).max() / scale)
    assert kernel.builds() == builds and native.compile_count() == compiles


def test_streaming_steps_follow_a_model_change_between_samples():
    """The observer keeps its step kernel between samples (no lookup per sample): a payload and
    a gravity set on the model between two samples are used by the next one, as by the
    reference (momentum_terms, advance) on the same samples."""
    model = load_urdf(default_urdf_path())
    n = model.n
    rng = np.random.default_rng(zlib.crc32(b'kept step kernel'))
    friction = make_friction(model.damping, None, 0.05)
    obs, ref = MomentumObserver(model, GAIN, friction), MomentumObserver(model, GAIN, friction)
    for k in range(8):
        if k == 3:
            model.set_payload(model.body_link_names[-1], 2.0, (0.0, 0.01, 0.05))
        if k == 5:
            model.gravity_vector = (0.5, 0.0, -9.7)
        q, qd, tau = rng.uniform(-1.0, 1.0, (3, n))
        r = obs.update(DT * k, q, qd, tau)
        expect = ref.advance(DT * k, *ref.momentum_terms(q, qd, tau))
        assert np.abs(r - expect).max() <= 1e-12 * max(1.0, np.abs(expect).max()), k
    assert np.abs(expect).max() > 1.0   # the steps after the changes estimate something


def test_one_state_through_the_validating_path_stays_one_state_with_friction():
    """Arguments the fast paths decline (misaligned float64 views, as a serialized message's
    arrays) are validated; with friction the terms and the estimate stay (n,) and equal those
    of the same state given as plain arrays."""
    model = load_urdf(default_urdf_path())
    n = model.n
    rng = np.random.default_rng(zlib.crc32(b'misaligned one state'))
    friction = make_friction(model.damping, rng.uniform(0.0, 1.0, n), 0.05)
    plain = rng.uniform(-1.0, 1.0, (2, 3, n))

    def misaligned(x):
        return np.frombuffer(b'\0\0\0\0' + x.tobytes(), dtype=float, offset=4)
    assert not misaligned(plain[0, 0]).flags.aligned
    ref, obs = MomentumObserver(model, GAIN, friction), MomentumObserver(model, GAIN, friction)
    for k in range(2):
        q, qd, tau = plain[k]
        p, beta = obs.momentum_terms(*(misaligned(x) for x in plain[k]))
        p_ref, beta_ref = ref.momentum_terms(q, qd, tau)
        assert p.shape == beta.shape == (n,)
        np.testing.assert_allclose(np.concatenate([p, beta]), np.concatenate([p_ref, beta_ref]), rtol=1e-12, atol=1e-12)
        r = obs.update(DT * k, *(misaligned(x) for x in plain[k]))
        r_ref = ref.update(DT * k, q, qd, tau)
        assert r.shape == (n,)
        np.testing.assert_allclose(r, r_ref, rtol=1e-12, atol=1e-12)


def test_a_robot_without_joints_has_an_empty_observer():
    """A model without movable joints (a valid model: every algorithm returns empty results) has
    an observer that checks its arguments and estimates nothing, as the rest of the library."""
    model = load_urdf('<robot name="welded"><link name="base"/><link name="rotor"><inertial><mass value="1"/>'
                      '<inertia ixx="0.1" iyy="0.1" izz="0.1" ixy="0" ixz="0" iyz="0"/></inertial></link>'
                      '<joint name="fix" type="fixed"><parent link="base"/><child link="rotor"/></joint></robot>')
    assert model.n == 0
    obs, z = MomentumObserver(model, 50.0, make_friction([], [], 0.05)), np.zeros(0)
    for t in (0.0, 1e-3, 2e-3):
        assert obs.update(t, z, z, z).shape == (0,)
    assert [a.shape for a in generalized_momentum(model, np.zeros((4, 0)), np.zeros((4, 0)))] == [(4, 0), (4, 0)]
    assert estimate_external_torques(model, [0.0, 1e-3], np.zeros((2, 0)), np.zeros((2, 0)), np.zeros((2, 0)),
                                     50.0).shape == (2, 0)
    with pytest.raises(ValueError, match=r'q must have shape \(0,\)'):
        obs.update(3e-3, [0.1], z, z)
    with pytest.raises(ValueError, match='observer times must increase'):
        obs.update(1e-3, z, z, z)


def test_step_kernel_in_c_equals_its_python_floats():
    """The C rendering of the observer step against its Python-float rendering (same trace)."""
    model = step_model('mixed_types')
    nk = runtime.native(model, observer_kernel.OBSERVER_STEP)
    if nk is None:
        pytest.skip('no working C compiler')
    n = model.n
    rng = np.random.default_rng(zlib.crc32(b'step c python'))
    q, qd, tau = (np.ascontiguousarray(x) for x in rng.uniform(-2, 2, (3, 6, n)))
    z = rng.normal(size=(6, 3 * n + 1))
    o = np.hstack([rng.uniform(1, 100, (6, n)), rng.uniform(0, 2, (6, 2 * n)), np.full((6, 1), 20.0)])
    ref = runtime.evaluate(model, observer_kernel.OBSERVER_STEP, [q, qd, tau, z, o], 'loop')
    for i in range(6):
        out = nk(q[i], qd[i], tau[i], z[i], o[i])
        assert np.abs(out - ref[i]).max() <= 1e-12 * max(1.0, np.abs(ref[i]).max())


def test_update_without_native_kernels_in_a_fresh_process():
    """LIE_DYNAMICS_NATIVE=0: the Python-float step, the same estimates as the reference."""
    code = ('import numpy as np\n'
            'from lie_dynamics import default_urdf_path, load_urdf\n'
            'from lie_dynamics.algorithms.observer import MomentumObserver\n'
            'from lie_dynamics.codegen import runtime\n'
            'from lie_dynamics.codegen.traced.observer import OBSERVER_STEP\n'
            'm = load_urdf(default_urdf_path())\n'
            'assert runtime.native(m, OBSERVER_STEP) is None\n'
            'a, b = MomentumObserver(m, 30.0), MomentumObserver(m, 30.0)\n'
            'rng = np.random.default_rng(5)\n'
            'for k in range(50):\n'
            '    q, qd, tau = rng.normal(size=(3, m.n))\n'
            '    r = a.step(0.001 * k, q, qd, tau)\n'
            '    e = b.advance(0.001 * k, *b.momentum_terms(q, qd, tau))\n'
            '    assert r is not None and np.abs(r - e).max() <= 1e-9 * max(1.0, np.abs(e).max())\n'
            'print("ok")\n')
    here = os.path.dirname(os.path.abspath(__file__))
    env = dict(os.environ, LIE_DYNAMICS_NATIVE='0',
               PYTHONPATH=os.pathsep.join([os.path.join(here, '..'), os.environ.get('PYTHONPATH', '')]))
    out = subprocess.run([sys.executable, '-c', code], env=env, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0 and out.stdout.strip() == 'ok', out.stderr[-2000:]
