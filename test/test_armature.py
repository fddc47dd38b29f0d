"""Model.armature (rotor inertia reflected to each joint) in every algorithm, against Pinocchio 4.1
with `model.armature` set: its rnea, crba, aba and computeKineticEnergy all use it (rnea adds
armature * a, crba and aba put it on M's diagonal). Every evaluation path: the native kernels, the
Python kernels (float loop and numpy rows) and the vectorised references; one state and batches;
a chain, a tree, a tree with mimic joints and a vendor robot."""
import copy
import json
import os
import pickle
import subprocess
import sys
import textwrap
import warnings

import numpy as np
import pinocchio as pin
import pytest

from lie_dynamics import load_urdf
from lie_dynamics.algorithms import aba, aba_derivatives, crba, lagrangian, observer, rnea
from lie_dynamics.algorithms.identification import identify
from lie_dynamics.codegen import kernel, native, runtime
from lie_dynamics.codegen.traced import aba as traced_aba
from lie_dynamics.codegen.traced import observer as observer_kernel
from lie_dynamics.codegen.traced import rnea as traced_rnea
from dyn_cases import case_urdf as _xml
from oracle import Oracle

HERE = os.path.dirname(os.path.abspath(__file__))
ARM = os.path.join(HERE, '..', 'lie_dynamics', 'data', 'arm7.urdf')
UR5 = 'ur_description/urdf/ur5_robot.urdf'
ROBOTS = ['arm7', 'tree12', 'mixed_types', 'tree20_mimic', UR5]
RTOL = 1e-10
NATIVE = native.module() is not None
BACKENDS = ['native', 'python'] if NATIVE else ['python']


def _rel(a, b):
    a, b = np.asarray(a), np.asarray(b)
    return float(np.max(np.abs(a - b)) / max(1.0, float(np.max(np.abs(b)))))


def _setup(name, backend='python', seed=0):
    """(model with a random armature, Pinocchio oracle with the same armature, armature)."""
    xml = _xml(name)
    with warnings.catch_warnings():
        warnings.simplefilter('ignore')   # vendor inertias are warned about
        model = load_urdf(xml)
    runtime.use_native(model, backend == 'native')
    oracle = Oracle(xml, joints=model.joint_names)
    arm = np.random.default_rng(seed).uniform(0.02, 0.4, model.n)
    model.set_armature(arm)
    _pin_armature(oracle, arm)
    return model, oracle, arm


def _pin_armature(oracle, arm):
    """Pinocchio's armature per velocity: our value on each controlled joint's column, none on mimic
    joints (the master's value stands for the rotor inertia of its whole column)."""
    a = np.zeros(oracle.nv)
    for k in range(oracle.n):
        a[np.flatnonzero(oracle.E[:, k] == 1.0)[0]] = arm[k]
    oracle.model.armature = a


def _states(model, N, seed=1):
    rng = np.random.default_rng(seed)
    return rng.uniform(-1.0, 1.0, (3, N, model.n))


@pytest.mark.parametrize('backend', BACKENDS)
@pytest.mark.parametrize('name', ROBOTS)
def test_inverse_dynamics_and_mass_matrix_against_pinocchio(name, backend):
    model, oracle, arm = _setup(name, backend)
    q, qd, qdd = _states(model, 40)
    tau = np.array([oracle.rnea(*s) for s in zip(q, qd, qdd)])
    g = np.array([oracle.gravity(x) for x in q])
    M = np.array([oracle.crba(x) for x in q])
    assert np.max(np.abs(tau - np.array([oracle.nonlinear(a, b) for a, b in zip(q, qd)])
                         - np.einsum('nij,nj->ni', M, qdd))) < 1e-9   # Pinocchio's rnea uses the armature
    # one state (the fast path), a batch, and each path forced
    assert _rel(model.inverse_dynamics(q[0], qd[0], qdd[0]), tau[0]) < RTOL
    assert _rel(model.inverse_dynamics(q, qd, qdd), tau) < RTOL
    assert _rel(model.inverse_dynamics(q, qd, qdd, with_gravity=False), tau - g) < RTOL
    assert _rel(model.inverse_dynamics(q[3], qd[3], qdd[3], with_gravity=False), tau[3] - g[3]) < RTOL
    assert _rel(rnea.inverse_dynamics_vectorized(model, q, qd, qdd), tau) < RTOL
    assert _rel(rnea.inverse_dynamics_vectorized(model, q, qd, qdd, with_gravity=False), tau - g) < RTOL
    for mode in ('loop', 'rows'):
        out = runtime.evaluate(model, traced_rnea.INVERSE_DYNAMICS, [q, qd, qdd], mode)
        assert out is None or _rel(out, tau) < RTOL
    assert _rel(model.mass_matrix(q[0]), M[0]) < RTOL
    assert _rel(model.mass_matrix(q), M) < RTOL
    assert _rel(model.mass_matrix(q, method='closed_form'), M) < RTOL
    assert _rel(crba.mass_matrix_vectorized(model, q), M) < RTOL
    for mode in ('loop', 'rows'):
        out = crba.mass_matrix_kernel(model, q, mode)
        assert out is None or _rel(out, M) < RTOL
    # M symmetric positive definite, and its diagonal exceeds the rigid-body one by the armature
    Mm = model.mass_matrix(q)
    assert np.array_equal(Mm, np.swapaxes(Mm, 1, 2))
    assert np.all(np.linalg.eigvalsh(Mm) > 0)
    bare = copy.deepcopy(model)
    bare.set_armature(0.0)
    assert np.allclose(np.diagonal(Mm, axis1=1, axis2=2) - np.diagonal(bare.mass_matrix(q), axis1=1, axis2=2),
                       arm, rtol=0, atol=1e-12)
    # the Coriolis matrix and gravity do not change
    assert _rel(model.coriolis_matrix(q[:5], qd[:5], method='recursive'), bare.coriolis_matrix(q[:5], qd[:5])) < RTOL
    assert _rel(model.gravity(q), bare.gravity(q)) < 1e-15
    assert _rel(model.coriolis_term(q, qd), bare.coriolis_term(q, qd)) < RTOL


@pytest.mark.parametrize('backend', BACKENDS)
@pytest.mark.parametrize('name', ROBOTS)
def test_forward_dynamics_against_pinocchio(name, backend):
    model, oracle, _ = _setup(name, backend)
    q, qd, qdd = _states(model, 40)
    tau = model.inverse_dynamics(q, qd, qdd)
    ref = np.array([oracle.aba(*s) for s in zip(q, qd, tau)])   # pin.aba with the armature (crba for mimics)
    assert _rel(ref, qdd) < 1e-9
    methods = ['cholesky'] + ([] if model.mimic_joints else ['aba'])
    for method in methods:
        assert _rel(model.forward_dynamics(q[0], qd[0], tau[0], method=method), ref[0]) < RTOL
        assert _rel(model.forward_dynamics(q, qd, tau, method=method), ref) < RTOL
        # forward(inverse(qdd)) == qdd
        assert _rel(model.forward_dynamics(q, qd, tau, method=method), qdd) < RTOL
    assert _rel(aba.forward_dynamics_vectorized(model, q, qd, tau), ref) < RTOL
    for mode in ('loop', 'rows'):
        out = aba.forward_dynamics_kernel(model, q, qd, tau, mode)
        assert out is None or _rel(out, ref) < RTOL
    if not model.mimic_joints:
        assert _rel(aba.aba_vectorized(model, q, qd, tau), ref) < RTOL
        for mode in ('loop', 'rows'):
            out = aba.aba_kernel(model, q, qd, tau, mode=mode)
            assert out is None or _rel(out, ref) < RTOL


@pytest.mark.parametrize('backend', BACKENDS)
@pytest.mark.parametrize('name', ['arm7', 'tree20_mimic'])
def test_forward_dynamics_with_wrenches(name, backend):
    """The bias with wrenches goes through the wrench kernels (Cholesky vectorised, ABA kernel)."""
    model, _, _ = _setup(name, backend)
    q, qd, qdd = _states(model, 6)
    link = [nm for nm, (b, _) in model.link_frames.items() if b >= 0][-1]
    w = {link: np.random.default_rng(5).normal(size=(6, 6))}
    tau = model.inverse_dynamics(q, qd, qdd, wrenches=w)
    for method in ['cholesky'] + ([] if model.mimic_joints else ['aba']):
        assert _rel(model.forward_dynamics(q, qd, tau, wrenches=w, method=method), qdd) < RTOL
        assert _rel(model.forward_dynamics(q[1], qd[1], tau[1], wrenches={link: w[link][1]}, method=method),
                    qdd[1]) < RTOL


@pytest.mark.parametrize('backend', BACKENDS)
@pytest.mark.parametrize('name', ['arm7', 'tree20_mimic'])
def test_derivatives(name, backend):
    """dtau/dqdd = M with the armature; the forward-dynamics derivatives against central finite
    differences of forward dynamics, and against Pinocchio's computeABADerivatives."""
    model, oracle, _ = _setup(name, backend)
    q, qd, qdd = _states(model, 3)
    h = 1e-6
    eye = np.eye(model.n)
    for s in range(3):
        # tau is affine in qdd: its finite difference is M exactly up to rounding
        fd = np.array([(model.inverse_dynamics(q[s], qd[s], qdd[s] + h * e)
                        - model.inverse_dynamics(q[s], qd[s], qdd[s] - h * e)) / (2 * h) for e in eye]).T
        assert _rel(fd, model.mass_matrix(q[s])) < 1e-7
        tau = model.inverse_dynamics(q[s], qd[s], qdd[s])
        dq, dv, dtau = model.forward_dynamics_derivatives(q[s], qd[s], tau)
        assert _rel(dtau, np.linalg.inv(oracle.crba(q[s]))) < RTOL

        def f(x, v, t):
            return model.forward_dynamics(x, v, t)
        nq = np.array([(f(q[s] + h * e, qd[s], tau) - f(q[s] - h * e, qd[s], tau)) / (2 * h) for e in eye]).T
        nv = np.array([(f(q[s], qd[s] + h * e, tau) - f(q[s], qd[s] - h * e, tau)) / (2 * h) for e in eye]).T
        assert _rel(dq, nq) < 1e-6 and _rel(dv, nv) < 1e-6
    tau = model.inverse_dynamics(q, qd, qdd)
    dq, dv, dtau = model.forward_dynamics_derivatives(q, qd, tau)   # batch
    vq, vv, vt = aba_derivatives.forward_dynamics_derivatives_vectorized(model, q, qd, tau)
    assert _rel(dq, vq) < RTOL and _rel(dv, vv) < RTOL and _rel(dtau, vt) < RTOL
    for mode in ('loop', 'rows'):
        out = aba_derivatives.forward_dynamics_derivatives_kernel(model, q, qd, tau, mode)
        assert out is None or all(_rel(a, b) < RTOL for a, b in zip(out, (vq, vv, vt)))
    if not model.mimic_joints:   # Pinocchio's ABA derivatives in the arm's own coordinates
        tau = model.inverse_dynamics(q[0], qd[0], qdd[0])
        dq, dv, dtau = model.forward_dynamics_derivatives(q[0], qd[0], tau)
        pin.computeABADerivatives(oracle.model, oracle.data, oracle.pin_q(q[0]), oracle.pin_v(qd[0]), oracle.E @ tau)
        P = oracle.E
        assert _rel(dq, P.T @ oracle.data.ddq_dq @ P) < RTOL
        assert _rel(dv, P.T @ oracle.data.ddq_dv @ P) < RTOL
        Minv = np.triu(oracle.data.Minv) + np.triu(oracle.data.Minv, 1).T
        assert _rel(dtau, P.T @ Minv @ P) < RTOL


@pytest.mark.parametrize('backend', BACKENDS)
@pytest.mark.parametrize('name', ['arm7', 'tree20_mimic'])
def test_energy_and_momentum(name, backend):
    """The kinetic energy and the observer's generalized momentum p = M qd carry the armature;
    C^T qd does not change. (Pinocchio 4.1.0's computeKineticEnergy adds the armature of joints
    along a coordinate axis but not of JointModelRevoluteUnaligned ones, two of the arm's: the
    energy is checked against its crba, 1/2 qd^T M qd.)"""
    model, oracle, arm = _setup(name, backend)
    q, qd, _ = _states(model, 8)
    M = model.mass_matrix(q)
    assert _rel(model.kinetic_energy(q, qd), [0.5 * b @ oracle.crba(a) @ b for a, b in zip(q, qd)]) < RTOL
    p, ctqd = observer.generalized_momentum(model, q, qd)
    assert _rel(p, np.einsum('nij,nj->ni', M, qd)) < RTOL
    p1, c1 = observer.generalized_momentum(model, q[2], qd[2])
    assert _rel(p1, M[2] @ qd[2]) < RTOL
    bare = copy.deepcopy(model)
    bare.set_armature(np.zeros(model.n))
    pb, cb = observer.generalized_momentum(bare, q, qd)
    assert _rel(p - pb, qd * arm) < RTOL and _rel(ctqd, cb) < RTOL
    assert _rel(ctqd, np.einsum('nji,nj->ni', model.coriolis_matrix(q, qd), qd)) < RTOL


@pytest.mark.parametrize('backend', BACKENDS)
def test_observer_with_armature(backend):
    """The observer's step kernel and its numpy reference agree with an armature, and on a motion
    of the arm (with its armature) under known torques and no contact the estimate stays near 0,
    while the same observer on the model without armature reports the rotor torques as contact."""
    model, _, arm = _setup('arm7', backend)
    dt, steps = 1e-3, 400
    t = np.arange(steps) * dt
    w = 2 * np.pi * np.array([0.5, 0.7, 0.9, 1.1, 1.3, 1.5, 1.7])
    q = 0.3 * np.sin(np.outer(t, w))
    qd = 0.3 * np.cos(np.outer(t, w)) * w
    qdd = -0.3 * np.sin(np.outer(t, w)) * w * w
    tau = model.inverse_dynamics(q, qd, qdd)
    kern, ref = observer.MomentumObserver(model, 50.0), observer.MomentumObserver(model, 50.0)
    bare = copy.deepcopy(model)
    bare.set_armature(0.0)
    blind = observer.MomentumObserver(bare, 50.0)
    for k in range(steps):
        r = kern.update(t[k], q[k], qd[k], tau[k])
        r_ref = ref.advance(t[k], *ref.momentum_terms(q[k], qd[k], tau[k]))
        assert _rel(r, r_ref) < 1e-9
        r_blind = blind.update(t[k], q[k], qd[k], tau[k])
    assert runtime.fast(model, observer_kernel.OBSERVER_STEP) is not None
    scale = np.max(np.abs(arm * qdd))
    assert np.max(np.abs(r)) < 1e-3 * scale      # trapezoid error of the exact motion only
    assert np.max(np.abs(r_blind)) > 0.3 * scale  # the rotor torque looks like contact without the armature


def test_set_armature_takes_effect_without_recompiling():
    """A set_armature after the kernels ran bumps the version and changes every result, with no
    kernel traced, rendered or compiled again."""
    model, oracle, _ = _setup('arm7', 'native' if NATIVE else 'python')
    q, qd, qdd = _states(model, 20)
    calls = [lambda: model.inverse_dynamics(q, qd, qdd), lambda: model.inverse_dynamics(q[0], qd[0], qdd[0]),
             lambda: model.inverse_dynamics(q[0], qd[0], qdd[0], with_gravity=False),
             lambda: model.mass_matrix(q), lambda: model.mass_matrix(q[0]),
             lambda: model.forward_dynamics(q, qd, qdd), lambda: model.forward_dynamics(q[0], qd[0], qdd[0]),
             lambda: model.forward_dynamics(q, qd, qdd, method='aba'),
             lambda: model.forward_dynamics(q[0], qd[0], qdd[0], method='aba'),
             lambda: model.forward_dynamics_derivatives(q[0], qd[0], qdd[0]),
             lambda: observer.generalized_momentum(model, q[0], qd[0])]
    before = [c() for c in calls]
    builds, compiles, version = kernel.builds(), native.compile_count(), model.version
    arm = np.random.default_rng(9).uniform(0.5, 1.0, model.n)
    model.set_armature(arm)
    assert model.version > version
    after = [c() for c in calls]
    assert kernel.builds() == builds and native.compile_count() == compiles
    for a, b in zip(before, after):
        a, b = (a[0], b[0]) if isinstance(a, tuple) else (a, b)
        assert not np.allclose(a, b)
    _pin_armature(oracle, arm)
    assert _rel(model.inverse_dynamics(q, qd, qdd), [oracle.rnea(*s) for s in zip(q, qd, qdd)]) < RTOL
    assert _rel(model.forward_dynamics(q[0], qd[0], qdd[0], method='aba'), oracle.aba(q[0], qd[0], qdd[0])) < RTOL
    assert _rel(model.mass_matrix(q[0]), oracle.crba(q[0])) < RTOL
    if NATIVE:
        assert runtime.native(model, traced_rnea.INVERSE_DYNAMICS) is not None   # still the C kernel


@pytest.mark.parametrize('backend', BACKENDS)
@pytest.mark.parametrize('name', ['arm7', 'tree12', 'mixed_types'])
def test_aba_switches_to_the_rigid_kernel_while_the_armature_is_zero(name, backend):
    """forward_dynamics(method='aba') runs the rigid variant (the armature folded away as the
    constant 0.0) while the armature is all zero and the armature kernel otherwise: zero, non-zero
    and zero again, each against pin.aba with model.armature set, every path, one state and a
    batch, with and without wrenches (against the Cholesky method)."""
    model, oracle, arm = _setup(name, backend)
    q, qd, tau = _states(model, 12, seed=4)
    fext = {model.body_link_names[-1]: np.array([0.3, -0.2, 0.1, 2.0, -1.0, 0.5])}
    for values, spec in ((np.zeros(model.n), traced_aba.ABA_RIGID), (arm, traced_aba.ABA),
                         (np.zeros(model.n), traced_aba.ABA_RIGID)):
        model.set_armature(values)
        _pin_armature(oracle, values)
        assert traced_aba.spec(model) is spec and traced_aba.spec(model, True) is {
            traced_aba.ABA_RIGID: traced_aba.ABA_WRENCH_RIGID, traced_aba.ABA: traced_aba.ABA_WRENCH}[spec]
        ref = np.array([oracle.aba(*s) for s in zip(q, qd, tau)])
        assert _rel(model.forward_dynamics(q, qd, tau, method='aba'), ref) < RTOL
        assert _rel(model.forward_dynamics(q[3], qd[3], tau[3], method='aba'), ref[3]) < RTOL
        for mode in ('loop', 'rows'):
            assert _rel(aba.aba_kernel(model, q, qd, tau, mode=mode), ref) < RTOL
        if backend == 'native':
            assert runtime.native(model, spec) is not None
        with_wrench = model.forward_dynamics(q, qd, tau, wrenches=fext, method='aba')
        assert _rel(with_wrench, model.forward_dynamics(q, qd, tau, wrenches=fext)) < RTOL
        assert not np.allclose(with_wrench, ref)


def test_setter_validation_and_read_only():
    model = load_urdf(_xml('arm7'))
    n = model.n
    assert model.armature.shape == (n,) and not model.armature.any()
    model.set_armature(0.25)   # one value for every joint
    assert np.array_equal(model.armature, np.full(n, 0.25))
    with pytest.raises(ValueError):
        model.armature[0] = 1.0   # read-only: an in-place edit no kernel would see
    for bad, match in [(-0.1, 'armature must be >= 0'), ([0.1] * (n - 1) + [-1.0], model.joint_names[-1]),
                       (float('nan'), 'finite'), ([0.0] * (n - 1) + [float('inf')], 'finite'),
                       ([0.1] * (n + 1), f'one value or {n} values'), (np.ones((n, 1)), f'one value or {n} values'),
                       ([], f'one value or {n} values'), ('heavy', 'numbers')]:
        version = model.version
        with pytest.raises(ValueError, match=match):
            model.set_armature(bad)
        assert model.version == version and np.array_equal(model.armature, np.full(n, 0.25))   # unchanged


def test_pickle_and_copies_carry_the_armature():
    """The node ships models between processes pickled."""
    model = load_urdf(_xml('tree12'))
    arm = np.linspace(0.1, 0.5, model.n)
    model.set_armature(arm)
    q, qd, qdd = _states(model, 4)
    for other in (pickle.loads(pickle.dumps(model, protocol=pickle.HIGHEST_PROTOCOL)), copy.deepcopy(model),
                  model.with_body_inertias(model.J)):
        assert np.array_equal(other.armature, arm) and not other.armature.flags.writeable
        assert _rel(other.inverse_dynamics(q, qd, qdd), model.inverse_dynamics(q, qd, qdd)) < 1e-14


def test_regressor_and_identification_take_the_armature_as_known():
    """inverse_dynamics = Y pi + armature * qdd; identify subtracts the known armature term and
    recovers the parameters, predict adds it back."""
    model = load_urdf(_xml('arm7'))
    model.set_armature(np.linspace(0.05, 0.3, model.n))
    q, qd, qdd = _states(model, 300, seed=4)
    tau = model.inverse_dynamics(q, qd, qdd)
    pi = model.inertial_parameters()
    assert _rel(model.regressor(q, qd, qdd) @ pi + qdd * model.armature, tau) < RTOL
    with warnings.catch_warnings():
        warnings.simplefilter('ignore')   # the arm's structurally unidentifiable directions
        res = identify(model, q, qd, qdd, tau, prior=pi)
    assert _rel(res.predict(model, q, qd, qdd), tau) < 1e-9
    assert _rel(res.parameters, pi) < 1e-8


def test_lagrangian_mass_matrix_is_eq_39_plus_the_armature():
    model = load_urdf(_xml('mixed_types'))
    q = _states(model, 3)[0]
    bare = lagrangian.mass_matrix(model, q)
    model.set_armature(0.7)
    assert _rel(lagrangian.mass_matrix(model, q) - bare, np.broadcast_to(0.7 * np.eye(model.n), bare.shape)) < 1e-15


def test_a_joint_that_moves_no_mass_is_defined_with_armature():
    """A rotor alone gives the joint a positive row of M: massless_joints no longer lists it and
    forward dynamics (both methods) is tau / armature."""
    xml = """<robot name="rotor"><link name="base"/><link name="disc"/>
      <joint name="spin" type="continuous"><parent link="base"/><child link="disc"/><axis xyz="0 0 1"/>
      <limit effort="1" velocity="1"/></joint></robot>"""
    with warnings.catch_warnings():
        warnings.simplefilter('ignore')   # the massless moving body is reported
        model = load_urdf(xml)
    assert model.massless_joints() == ['spin']
    with pytest.raises(ValueError, match='not positive definite'):
        model.forward_dynamics([0.0], [0.0], [1.0])
    model.set_armature(0.5)
    assert model.massless_joints() == []
    for method in ('cholesky', 'aba'):
        assert np.allclose(model.forward_dynamics([0.3], [2.0], [1.0], method=method), [2.0], rtol=1e-15)
        ones = np.ones((4, 1))
        assert np.allclose(model.forward_dynamics(0 * ones, ones, ones, method=method), 2.0)
    assert np.allclose(model.inverse_dynamics([0.3], [2.0], [4.0]), [2.0], rtol=1e-15)


def test_native_switched_off(tmp_path):
    """LIE_DYNAMICS_NATIVE=0 (a process that never compiles): the Python kernels give the same
    results with an armature as this process (native where a compiler works)."""
    model, _, arm = _setup('arm7')
    runtime.use_native(model, True)
    q, qd, qdd = _states(model, 5)
    script = textwrap.dedent(f'''
        import json, numpy as np
        from lie_dynamics import load_urdf
        from lie_dynamics.codegen import native
        m = load_urdf({ARM!r})
        m.set_armature({arm.tolist()!r})
        q, qd, qdd = (np.array(x) for x in json.loads(input()))
        tau = m.inverse_dynamics(q, qd, qdd)
        out = [tau, m.inverse_dynamics(q[0], qd[0], qdd[0]), m.mass_matrix(q[0]),
               m.forward_dynamics(q, qd, tau), m.forward_dynamics(q[1], qd[1], tau[1], method='aba'),
               m.forward_dynamics(q, qd, tau, method='aba')]
        print(json.dumps([np.asarray(x).tolist() for x in out]), native.compile_count())
    ''')
    env = dict(os.environ, LIE_DYNAMICS_NATIVE='0', LIE_DYNAMICS_CACHE_DIR=str(tmp_path / 'cache'),
               PYTHONPATH=os.pathsep.join([os.path.join(HERE, '..'), os.environ.get('PYTHONPATH', '')]))
    r = subprocess.run([sys.executable, '-c', script], input=json.dumps([q.tolist(), qd.tolist(), qdd.tolist()]),
                       env=env, capture_output=True, text=True, timeout=300, check=True)
    values, compiles = r.stdout.rsplit(' ', 1)
    got = [np.array(x) for x in json.loads(values)]
    tau = model.inverse_dynamics(q, qd, qdd)
    ref = [tau, model.inverse_dynamics(q[0], qd[0], qdd[0]), model.mass_matrix(q[0]),
           model.forward_dynamics(q, qd, tau), model.forward_dynamics(q[1], qd[1], tau[1], method='aba'),
           model.forward_dynamics(q, qd, tau, method='aba')]
    assert int(compiles) == 0 and not (tmp_path / 'cache').exists()
    assert all(_rel(a, b) < 1e-12 for a, b in zip(got, ref, strict=True))
    assert _rel(got[3], qdd) < RTOL and _rel(got[5], qdd) < RTOL
