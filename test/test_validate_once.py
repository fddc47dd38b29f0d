"""One public call validates its per-state arguments once (lie_dynamics.validation), whatever path
it takes: the fast path (none), the kernels, or the references behind them, whose fallbacks call
the already-validated functions (runtime.call, crba.mass_matrix_validated, ...)."""
import copy
import warnings

import numpy as np
import pytest

from dyn_cases import case, states
from lie_dynamics import load_urdf, validation
from lie_dynamics.algorithms import aba, aba_derivatives, identification, observer, payload
from lie_dynamics.codegen import runtime
from lie_dynamics.codegen.traced.observer import OBSERVER_STEP


@pytest.fixture
def counted(monkeypatch):
    """Counts of validation.states (Model.validate) and validation.batch (Model.check_batch)."""
    calls = {'states': 0, 'batch': 0}
    for name in calls:
        real = getattr(validation, name)

        def count(*args, _real=real, _name=name, **kwargs):
            calls[_name] += 1
            return _real(*args, **kwargs)
        monkeypatch.setattr(validation, name, count)
    return calls


@pytest.fixture(scope='module')
def arm():
    model, oracle = case('arm7')
    return model, oracle


def _once(counted, fn, *args, fast=False, **kwargs):
    """fn(*args, **kwargs), asserting one validation (fast: at most one, as one state may take
    the fast path, which validates nothing)."""
    counted['states'] = counted['batch'] = 0
    out = fn(*args, **kwargs)
    assert (counted['states'], counted['batch']) in ({(0, 0), (1, 0)} if fast else {(1, 0)}), fn.__name__
    return out


def test_cholesky_forward_dynamics_fallback_validates_once(arm, counted):
    """With wrenches the Cholesky forward dynamics has no kernel: M, the bias and the solves run
    on the arrays validated once (before: three validations, the public crba.mass_matrix and
    rnea.inverse_dynamics). The result still inverts inverse dynamics."""
    model, _ = arm
    q, qd, qdd = states(model, 4, seed=3)
    link = model.body_link_names[-1]
    for sl in (0, slice(None)):   # one state and a batch
        w = {link: np.array([0.3, -0.2, 0.1, 2.0, -1.0, 0.5])}
        tau = model.inverse_dynamics(q[sl], qd[sl], qdd[sl], wrenches=w)
        got = _once(counted, model.forward_dynamics, q[sl], qd[sl], tau, wrenches=w)
        np.testing.assert_allclose(got, qdd[sl], rtol=1e-8, atol=1e-8)
        got = _once(counted, aba.forward_dynamics_vectorized, model, q[sl], qd[sl], tau, wrenches=w)
        np.testing.assert_allclose(got, qdd[sl], rtol=1e-8, atol=1e-8)


def test_forward_dynamics_derivatives_fallback_validates_once(arm, counted):
    """The derivatives' reference (M, the bias, the derivatives of inverse dynamics, the solves)
    validates once, and agrees with the kernel (checked against Pinocchio in
    test_forward_dynamics.py)."""
    model, _ = arm
    q, qd, tau = states(model, 3, seed=4)
    for sl in (1, slice(None)):
        got = _once(counted, aba_derivatives.forward_dynamics_derivatives_vectorized, model, q[sl], qd[sl], tau[sl])
        ref = _once(counted, aba_derivatives.forward_dynamics_derivatives_kernel, model, q[sl], qd[sl], tau[sl])
        for g, r in zip(got, ref, strict=True):
            np.testing.assert_allclose(g, r, rtol=1e-8, atol=1e-8)


def test_every_entry_validates_once_without_native(arm, counted):
    """The Python kernels' batches (the native fast path off: every batch takes the full path)
    and the references: one validation per call."""
    model, _ = arm
    py = copy.deepcopy(model)
    runtime.use_native(py, False)
    q, qd, qdd = states(py, 50, seed=5)
    link = py.body_link_names[3]
    w = {link: np.ones(6)}
    _once(counted, py.inverse_dynamics, q, qd, qdd)
    _once(counted, py.inverse_dynamics, q, qd, qdd, wrenches=w)
    _once(counted, py.gravity, q)
    _once(counted, py.mass_matrix, q)
    _once(counted, py.forward_dynamics, q, qd, qdd)
    _once(counted, py.forward_dynamics, q, qd, qdd, method='aba')
    _once(counted, py.inverse_dynamics_derivatives, q, qd, qdd, wrenches=w)
    _once(counted, py.forward_dynamics_derivatives, q, qd, qdd, wrenches=w)
    _once(counted, py.regressor, q, qd, qdd)
    _once(counted, py.coriolis_matrix, q, qd, method='recursive')
    _once(counted, observer.generalized_momentum, py, q, qd)
    _once(counted, py.jacobian, q, link)


def test_the_fast_path_validates_nothing(arm, counted):
    """One state of finite float64 arrays is taken as given (the kernel checks what it needs)."""
    model, _ = arm
    q, qd, qdd = (x[0] for x in states(model, 1, seed=6))
    tau = model.inverse_dynamics(q, qd, qdd)
    counted['states'] = counted['batch'] = 0
    np.testing.assert_allclose(model.forward_dynamics(q, qd, tau), qdd, rtol=1e-9, atol=1e-9)
    assert (counted['states'], counted['batch']) == (0, 0)


@pytest.mark.parametrize('native', [True, False])
def test_callers_of_the_algorithms_validate_once(arm, counted, native):
    """The observer's momentum terms, identification and the payload fit validate their data
    once and then call the functions that take validated arrays (rnea.gravity_validated,
    regressor.regressor_validated, rnea.inverse_dynamics_validated, ...): once for a batch, at most
    once for one state (it may take the fast path); before, two or three times."""
    model, _ = arm
    m = copy.deepcopy(model)
    runtime.use_native(m, native)
    q, qd, qdd = states(m, 40, seed=7)
    tau = m.inverse_dynamics(q, qd, qdd)
    obs = observer.MomentumObserver(m, 5.0)
    for sl in (slice(None), 0):
        p, beta = _once(counted, obs.momentum_terms, q[sl], qd[sl], tau[sl], fast=sl == 0)
        np.testing.assert_allclose(p, np.einsum('...ij,...j->...i', m.mass_matrix(q[sl]), qd[sl]), rtol=1e-9,
                                   atol=1e-9)
        # beta = tau + C^T qd - g
        C = m.coriolis_matrix(q[sl], qd[sl], method='recursive')
        ctqd = np.einsum('...ji,...j->...i', C, qd[sl])
        np.testing.assert_allclose(beta + m.gravity(q[sl]) - ctqd, tau[sl], rtol=1e-9, atol=1e-9)
    with warnings.catch_warnings():   # random states leave structural directions unidentified
        warnings.simplefilter('ignore', identification.UnidentifiableWarning)
        got = _once(counted, identification.identify, m, q, qd, qdd, tau)
    np.testing.assert_allclose(np.einsum('nij,j->ni', m.regressor(q, qd, qdd), got.parameters)
                               + qdd * m.armature, tau, rtol=1e-7, atol=1e-7)
    link = [ln for ln, (b, _) in m.link_frames.items() if b == m.nb - 1][0]
    loaded = m.with_body_inertias(m.J_links)
    loaded.set_payload(link, 0.8, [0.02, -0.01, 0.05])
    runtime.use_native(loaded, native)
    fit = _once(counted, payload.identify_payload, m, link, q, qd, qdd, loaded.inverse_dynamics(q, qd, qdd))
    assert fit.mass == pytest.approx(0.8, rel=1e-6)


@pytest.mark.parametrize('native', [True, False])
def test_observer_step_is_a_fast_path(arm, counted, native):
    """MomentumObserver.update: its step kernel (runtime.fast, as every entry) validates nothing;
    when the native kernel declines (here a non-contiguous q), update validates once (at most
    once without it: the float kernels take such a q) and gives the same estimate."""
    model, _ = arm
    m = copy.deepcopy(model)
    runtime.use_native(m, native)
    native = runtime.native(m, OBSERVER_STEP) is not None   # off under LIE_DYNAMICS_NATIVE=0
    q, qd, tau = states(m, 3, seed=8)
    fast, slow = observer.MomentumObserver(m, 5.0), observer.MomentumObserver(m, 5.0)
    for k in range(3):
        counted['states'] = counted['batch'] = 0
        r = fast.update(0.01 * k, q[k], qd[k], tau[k])
        assert (counted['states'], counted['batch']) == (0, 0)
        strided = np.repeat(q[k], 2)[::2]
        ref = _once(counted, slow.update, 0.01 * k, strided, qd[k], tau[k], fast=not native)
        np.testing.assert_allclose(r, ref, rtol=1e-9, atol=1e-9)


WELDED = ('<robot name="welded"><link name="base"/><link name="rotor"><inertial><mass value="1"/>'
          '<inertia ixx="0.1" iyy="0.1" izz="0.1" ixy="0" ixz="0" iyz="0"/></inertial></link>'
          '<joint name="fix" type="fixed"><parent link="base"/><child link="rotor"/></joint></robot>')


def test_a_robot_without_joints_validates_once(counted):
    """A model without movable joints checks its state arguments with the one validation (once)
    and returns empty results of the usual shapes; a bad one is named."""
    model = load_urdf(WELDED)
    assert model.n == 0
    for lead in ((), (3,)):
        z = np.zeros(lead + (0,))
        for fn, args, shape in ((model.inverse_dynamics, (z, z, z), (0,)), (model.gravity, (z,), (0,)),
                                (model.mass_matrix, (z,), (0, 0)), (model.kinetic_energy, (z, z), ()),
                                (model.forward_dynamics, (z, z, z), (0,)), (model.regressor, (z, z, z), (0, 0))):
            assert _once(counted, fn, *args).shape == lead + shape
    with pytest.raises(ValueError, match='qd must have shape'):
        model.inverse_dynamics(np.zeros(0), np.zeros(1), np.zeros(0))
