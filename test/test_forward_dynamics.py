"""Forward dynamics (Cholesky solve and articulated body algorithm) and its derivatives."""
import copy

import numpy as np
import pinocchio as pin
import pytest

from dyn_cases import ARM, CASES, case, oracle_stack, rel_err, states, xml_of
from lie_dynamics.algorithms import aba, cholesky
from lie_dynamics.codegen import runtime
from lie_dynamics.codegen.traced import aba as traced_aba
from lie_dynamics.codegen.traced import derivatives as traced_derivatives
from lie_dynamics import InertiaWarning, load_urdf
from oracle import Oracle
from robots import random_urdf, with_payload

MASSLESS_TIP = """<robot name="massless_tip">
  <link name="base"/>
  <joint name="j1" type="revolute"><parent link="base"/><child link="l1"/>
    <axis xyz="0 0 1"/><limit effort="1" velocity="1" lower="-1" upper="1"/></joint>
  <link name="l1"><inertial><origin xyz="0.1 0 0"/><mass value="1"/>
    <inertia ixx="0.01" ixy="0" ixz="0" iyy="0.01" iyz="0" izz="0.01"/></inertial></link>
  <joint name="j2" type="revolute"><parent link="l1"/><child link="l2"/>
    <origin xyz="0.2 0 0"/><axis xyz="0 1 0"/><limit effort="1" velocity="1" lower="-1" upper="1"/></joint>
  <link name="l2"/>
</robot>"""


def _has_mimic(model):
    return bool(model.mimic_joints)


@pytest.mark.parametrize('name', CASES)
def test_forward_dynamics_matches_pinocchio_aba(name):
    model, oracle = case(name)
    q, qd, tau = states(model, seed=4)
    tau = tau * 10
    ref = oracle_stack(oracle.aba, q, qd, tau)
    assert rel_err(model.forward_dynamics(q, qd, tau), ref) < 1e-10
    if _has_mimic(model):
        with pytest.raises(ValueError, match="method='aba' does not support mimic joints"):
            model.forward_dynamics(q, qd, tau, method='aba')
    else:
        assert rel_err(model.forward_dynamics(q, qd, tau, method='aba'), ref) < 1e-10
    # small batches (generated kernel state by state), the vectorised form, single states
    assert rel_err(model.forward_dynamics(q[:5], qd[:5], tau[:5]), ref[:5]) < 1e-10
    M = model.mass_matrix(q)
    h = model.inverse_dynamics(q, qd, np.zeros_like(qd))
    assert rel_err(cholesky.cho_solve(cholesky.cholesky(M), tau - h), ref) < 1e-10
    for method in ('cholesky',) if _has_mimic(model) else ('cholesky', 'aba'):
        one = model.forward_dynamics(q[5], qd[5], tau[5], method=method)
        assert one.shape == (model.n,) and rel_err(one[None], ref[5:6]) < 1e-10


@pytest.mark.parametrize('name', ['arm7', 'tree12', 'tree20_mimic'])
def test_forward_dynamics_inverts_inverse_dynamics_with_wrenches(name):
    model, _ = case(name)
    q, qd, tau = states(model, 20, seed=5)
    rng = np.random.default_rng(0)
    links = [ln for ln, (b, _) in model.link_frames.items() if b >= 0]
    w = {links[-1]: rng.normal(size=6), links[len(links) // 2]: rng.normal(size=(20, 6))}
    methods = ('cholesky',) if _has_mimic(model) else ('cholesky', 'aba')
    for method in methods:
        qdd = model.forward_dynamics(q, qd, tau, w, method=method)
        assert rel_err(model.inverse_dynamics(q, qd, qdd, w), tau, 1.0) < 1e-10


def test_forward_dynamics_with_locked_joints():
    xml = random_urdf(21, 9, tree=True)
    full = load_urdf(xml)
    ctrl = full.joint_names[::2]
    model = load_urdf(xml, joints=ctrl)
    locked = {nm: 0.3 * (k + 1) for k, nm in enumerate(model.locked_joint_names)}
    assert locked, 'the case must lock some joints'
    model.set_locked(locked)
    oracle = Oracle(xml, joints=ctrl, locked=locked)
    q, qd, tau = states(model, 30, seed=6)
    ref = oracle_stack(oracle.aba, q, qd, tau)
    assert rel_err(model.forward_dynamics(q, qd, tau), ref) < 1e-10
    assert rel_err(model.forward_dynamics(q, qd, tau, method='aba'), ref) < 1e-10


def test_large_batches_use_the_substitution_solver():
    model, oracle = case('chain7')
    q, qd, tau = states(model, 300, seed=7)   # N > 2n: vectorised triangular solves
    ref = oracle_stack(oracle.aba, q, qd, tau)
    assert rel_err(model.forward_dynamics(q, qd, tau), ref) < 1e-10
    M = model.mass_matrix(q)
    B = np.random.default_rng(1).normal(size=(300, 7, 3))
    X = cholesky.cho_solve(cholesky.cholesky(M), B)
    assert rel_err(M @ X, B, 1.0) < 1e-12


def _pin_aba_derivatives(oracle, q, qd, tau):
    E = oracle.E
    dq, dv, Minv = pin.computeABADerivatives(oracle.model, oracle.data, oracle.pin_q(q), oracle.pin_v(qd), E @ tau)
    Minv = np.triu(Minv) + np.triu(Minv, 1).T
    return E.T @ dq @ E, E.T @ dv @ E, E.T @ Minv @ E


@pytest.mark.parametrize('name', ['chain7', 'tree12', 'mixed_types', 'continuous_only', 'arm7'])
def test_forward_dynamics_derivatives_match_pinocchio(name):
    model, oracle = case(name)
    q, qd, tau = states(model, seed=8)
    dq, dv, Minv = model.forward_dynamics_derivatives(q, qd, tau)
    ref = [np.array(r) for r in zip(*(_pin_aba_derivatives(oracle, *s) for s in zip(q, qd, tau, strict=True)),
                                    strict=True)]
    assert rel_err(dq, ref[0]) < 1e-8
    assert rel_err(dv, ref[1]) < 1e-8
    assert rel_err(Minv, ref[2]) < 1e-8
    # the generated kernel forced state by state and on numpy rows (None: no kernel for this
    # model's size), and one state through the default dispatch
    from lie_dynamics.algorithms import aba_derivatives
    for mode in ('loop', 'rows'):
        out = aba_derivatives.forward_dynamics_derivatives_kernel(model, q, qd, tau, mode)
        assert (out is None) == (model.nb > runtime.THRESHOLDS['forward_dynamics_derivatives'].compile_max)
        if out is not None:
            assert all(rel_err(o, r) < 1e-8 for o, r in zip(out, ref, strict=True))
    one = model.forward_dynamics_derivatives(q[0], qd[0], tau[0])
    assert all(rel_err(o[None], r[:1]) < 1e-8 for o, r in zip(one, ref, strict=True))


@pytest.mark.parametrize('name', ['tree20_mimic', 'arm7'])
def test_forward_dynamics_derivatives_match_finite_differences(name):
    model, _ = case(name)
    q, qd, tau = states(model, 5, seed=9)
    links = [ln for ln, (b, _) in model.link_frames.items() if b >= 0]
    w = {links[-1]: np.array([0.3, -0.2, 0.1, 1.0, -2.0, 0.5])}
    dq, dv, Minv = model.forward_dynamics_derivatives(q, qd, tau, w)
    h = 1e-6
    n = model.n

    def fd(fun):
        return np.stack([(fun(h * e) - fun(-h * e)) / (2 * h) for e in np.eye(n)], axis=-1)

    assert rel_err(dq, fd(lambda d: model.forward_dynamics(q + d, qd, tau, w)), 1e-3) < 1e-7
    assert rel_err(dv, fd(lambda d: model.forward_dynamics(q, qd + d, tau, w)), 1e-3) < 1e-7
    assert rel_err(Minv, fd(lambda d: model.forward_dynamics(q, qd, tau + d, w)), 1e-3) < 1e-7
    one = model.forward_dynamics_derivatives(q[0], qd[0], tau[0], w)
    assert all(o.shape == (n, n) for o in one) and np.allclose(one[0], dq[0], rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize('name', ['mimic', 'fixed_heavy'])
def test_forward_dynamics_derivatives_kernel_matches_finite_differences(name):
    """The generated kernel (no wrenches) on models Pinocchio's ABA derivatives do not cover
    directly (mimic joints couple the coordinates)."""
    from lie_dynamics.algorithms import aba_derivatives
    model, _ = case(name)
    assert runtime.kernel(model, traced_derivatives.FORWARD_DYNAMICS_DERIVATIVES)
    q, qd, tau = states(model, 5, seed=19)
    h, n = 1e-6, model.n

    def fd(fun):
        return np.stack([(fun(h * e) - fun(-h * e)) / (2 * h) for e in np.eye(n)], axis=-1)

    for mode in ('loop', 'rows'):
        dq, dv, Minv = aba_derivatives.forward_dynamics_derivatives_kernel(model, q, qd, tau, mode)
        assert rel_err(dq, fd(lambda d: model.forward_dynamics(q + d, qd, tau)), 1e-3) < 1e-7
        assert rel_err(dv, fd(lambda d: model.forward_dynamics(q, qd + d, tau)), 1e-3) < 1e-7
        assert rel_err(Minv, np.linalg.inv(model.mass_matrix(q))) < 1e-10


def test_massless_chain_raises():
    with pytest.warns(InertiaWarning, match="massless moving body: joint 'j2'"):
        model = load_urdf(MASSLESS_TIP)
    q = np.array([0.1, 0.2])
    with pytest.raises(ValueError, match='mass matrix is not positive definite'):
        model.forward_dynamics(q, np.zeros(2), np.zeros(2))
    with pytest.raises(ValueError, match=r'mass matrix is not positive definite at state 0 '):
        model.forward_dynamics(np.zeros((2, 2)), np.zeros((2, 2)), np.zeros((2, 2)))
    with pytest.raises(ValueError, match=r'mass matrix is not positive definite at state 1 '):
        cholesky.cholesky(np.array([np.eye(2), [[1.0, 0.0], [0.0, -1.0]]]))
    many = np.zeros((60, 2))   # the generated kernel on rows: NaN pivots are caught, then reported
    with pytest.raises(ValueError, match='mass matrix is not positive definite at state 0'):
        model.forward_dynamics(many, many, many)
    with pytest.raises(ValueError, match="articulated inertia about joint 'j2' is zero"):
        model.forward_dynamics(q, np.zeros(2), np.zeros(2), method='aba')
    with pytest.raises(ValueError, match='mass matrix is not positive definite'):
        model.forward_dynamics_derivatives(q, np.zeros(2), np.zeros(2))
    for N in (3, 60):   # the derivative kernel state by state and on rows: caught, then reported
        with pytest.raises(ValueError, match='mass matrix is not positive definite at state 0'):
            model.forward_dynamics_derivatives(np.zeros((N, 2)), np.zeros((N, 2)), np.zeros((N, 2)))
    # a singular matrix that LAPACK's Cholesky still factors is caught by the pivot test
    with pytest.raises(ValueError, match='mass matrix is not positive definite'):
        cholesky.cholesky(np.array([[[1.0, 1.0], [1.0, 1.0 + 1e-15]]]))


def test_forward_dynamics_error_paths():
    model, _ = case('chain7')
    z = np.zeros(7)
    with pytest.raises(ValueError, match="unknown forward dynamics method 'lu'"):
        model.forward_dynamics(z, z, z, method='lu')
    with pytest.raises(ValueError, match=r'tau must have shape \(7,\)'):
        model.forward_dynamics(z, z, np.zeros(3))
    with pytest.raises(ValueError, match="unknown link 'nope' in wrenches"):
        model.forward_dynamics(z, z, z, {'nope': np.zeros(6)}, method='aba')
    with pytest.raises(ValueError, match='wrenches must be a dict'):
        model.forward_dynamics(z, z, z, [np.zeros(6)], method='aba')
    link = [ln for ln, (b, _) in model.link_frames.items() if b >= 0][0]
    with pytest.raises(ValueError, match=f"wrench on '{link}' must have shape"):
        model.forward_dynamics(z, z, z, {link: np.zeros(5)}, method='aba')
    with pytest.raises(ValueError, match=f"wrench on '{link}' contains non-finite values"):
        model.forward_dynamics(z, z, z, {link: np.full(6, np.inf)}, method='aba')


def test_arm_file_in_package_matches_config():
    from lie_dynamics import default_urdf_path
    with open(default_urdf_path(), encoding='utf-8') as fh:
        packaged = fh.read()
    assert packaged == xml_of('arm7') or load_urdf(packaged).n == load_urdf(ARM).n


# ---------------------------------------------------------------------------- generated ABA kernel
ABA_CASES = [nm for nm in CASES if not load_urdf(xml_of(nm)).mimic_joints]


def _aba_paths(model, q, qd, tau, wrenches=None):
    """qdd from the ABA kernel forced to Python floats and to numpy rows (both must exist)."""
    out = {}
    for mode in ('loop', 'rows'):
        out[mode] = aba.aba_kernel(model, q, qd, tau, wrenches, mode)
        assert out[mode] is not None, mode
    return out


@pytest.mark.parametrize('name', ABA_CASES)
def test_aba_kernel_paths_match_pinocchio(name):
    model, oracle = case(name)
    assert runtime.kernel(model, traced_aba.ABA), 'every supported case is within the size cap'
    assert traced_aba.spec(model) is traced_aba.ABA_RIGID and runtime.kernel(model, traced_aba.ABA_RIGID)
    q, qd, tau = states(model, seed=21)
    tau = tau * 10
    ref = oracle_stack(oracle.aba, q, qd, tau)
    paths = _aba_paths(model, q, qd, tau)
    for mode, out in paths.items():
        assert rel_err(out, ref) < 1e-10, mode
    # default dispatch (the kernel, not the vectorised form): one state at a time on floats,
    # a small batch state by state, a large batch on rows
    # (the straight-line C kernel is the float kernel to the bit; the looped one, from
    # THRESHOLDS looped_from, agrees to rounding: codegen/looped.py)
    looped = runtime.looped(model, traced_aba.ABA_RIGID)

    def same(a, b):
        return rel_err(a, b) <= 1e-12 if looped else np.array_equal(a, b)
    one = np.array([model.forward_dynamics(a, b, c, method='aba') for a, b, c in zip(q, qd, tau, strict=True)])
    assert same(one, paths['loop']) and rel_err(one, ref) < 1e-10
    assert same(model.forward_dynamics(q[:5].tolist(), qd[:5], tau[:5], method='aba'), paths['loop'][:5])
    batch = model.forward_dynamics(q, qd, tau, method='aba')
    assert len(q) >= runtime.THRESHOLDS['aba'].rows_from and same(batch, paths['rows'])
    assert rel_err(aba.aba_vectorized(model, q, qd, tau), ref) < 1e-10


def test_aba_kernel_follows_payload_gravity_and_locked_joints_without_recompiling(monkeypatch):
    xml = xml_of('arm7')
    model = load_urdf(xml)
    ctrl = model.joint_names[1::2]
    part = load_urdf(xml, joints=ctrl)
    for m in (model, part):
        assert runtime.kernel(m, traced_aba.spec(m))

    def no_compile(*args, **kw):
        raise AssertionError('the ABA kernel was rebuilt')
    for spec in (traced_aba.ABA, traced_aba.ABA_RIGID):
        monkeypatch.setattr(spec, 'build', no_compile)
    payload = ('link7', 1.7, (0.05, -0.02, 0.1), (0.01, 0.001, 0.0, 0.02, 0.0, 0.015))
    model.set_payload(*payload)
    model.set_gravity((1.0, -2.0, -9.0))
    oracle = Oracle(with_payload(xml, *payload), joints=model.joint_names, gravity=(1.0, -2.0, -9.0))
    q, qd, tau = states(model, seed=22)
    ref = oracle_stack(oracle.aba, q, qd, tau)
    for mode, out in _aba_paths(model, q, qd, tau).items():
        assert rel_err(out, ref) < 1e-10, mode
    assert rel_err(model.forward_dynamics(q[3], qd[3], tau[3], method='aba')[None], ref[3:4]) < 1e-10
    assert part.locked_joint_names
    for k, values in enumerate(((0.0,) * 4, (0.4, -1.1, 2.0, 0.3))):
        part.set_locked(dict(zip(part.locked_joint_names, values, strict=True)))
        oracle = Oracle(xml, joints=ctrl, locked=part.locked_values)
        q, qd, tau = states(part, seed=23 + k)
        ref = oracle_stack(oracle.aba, q, qd, tau)
        for mode, out in _aba_paths(part, q, qd, tau).items():
            assert rel_err(out, ref) < 1e-10, mode
        assert rel_err(part.forward_dynamics(q, qd, tau, method='aba'), ref) < 1e-10
        assert rel_err(part.forward_dynamics(q[0], qd[0], tau[0], method='aba')[None], ref[:1]) < 1e-10


@pytest.mark.parametrize('name', ['arm7', 'tree12', 'mixed_types'])
def test_aba_kernel_with_wrenches(name):
    model, _ = case(name)
    N = 60
    q, qd, tau = states(model, N, seed=24)
    rng = np.random.default_rng(2)
    links = [ln for ln, (b, _) in model.link_frames.items() if b >= 0]
    w = {links[-1]: rng.normal(size=6), links[len(links) // 2]: rng.normal(size=(N, 6))}
    ref = aba.aba_vectorized(model, q, qd, tau, w)
    for mode, out in _aba_paths(model, q, qd, tau, w).items():
        assert rel_err(out, ref) < 1e-10, mode
        assert rel_err(model.inverse_dynamics(q, qd, out, w), tau, 1.0) < 1e-10
    w1 = {k: (v if v.ndim == 1 else v[0]) for k, v in w.items()}
    assert rel_err(model.forward_dynamics(q[0], qd[0], tau[0], w1, method='aba')[None], ref[:1]) < 1e-10


def test_aba_falls_back_to_the_vectorised_form(monkeypatch):
    model, oracle = case('chain7')
    q, qd, tau = states(model, 40, seed=25)
    ref = oracle_stack(oracle.aba, q, qd, tau)
    # beyond the size cap
    monkeypatch.setitem(runtime.THRESHOLDS, 'aba', runtime.THRESHOLDS['aba']._replace(compile_max=model.nb - 1))
    runtime.forget(model)   # its cached routes
    assert not runtime.kernel(model, traced_aba.ABA) and not runtime.kernel(model, traced_aba.ABA_RIGID)
    assert aba.aba_kernel(model, q, qd, tau, None, 'rows') is None
    assert rel_err(model.forward_dynamics(q, qd, tau, method='aba'), ref) < 1e-10
    assert rel_err(model.forward_dynamics(q[0], qd[0], tau[0], method='aba')[None], ref[:1]) < 1e-10
    monkeypatch.undo()
    runtime.forget(model)
    # screws that are not unit revolute / prismatic axes: no kernel
    other = copy.deepcopy(model)
    other.S = other.S * 1.5
    assert not runtime.kernel(other, traced_aba.ABA) and not runtime.kernel(other, traced_aba.ABA_RIGID)
    got = other.forward_dynamics(q, qd, tau, method='aba')
    assert np.array_equal(got, aba.aba_vectorized(other, q, qd, tau)) and not np.allclose(got, ref)
    # mimic joints: the same error on every path
    mimic, _ = case('mimic')
    z = np.zeros(mimic.n)
    for args in ((z, z, z), (z[None], z[None], z[None]), (np.zeros((40, mimic.n)),) * 3):
        with pytest.raises(ValueError, match="method='aba' does not support mimic joints"):
            mimic.forward_dynamics(*args, method='aba')


def test_aba_massless_chain_raises_on_every_path():
    with pytest.warns(InertiaWarning, match="massless moving body: joint 'j2'"):
        model = load_urdf(MASSLESS_TIP)
    msg = "articulated inertia about joint 'j2' is zero"
    for N in (1, 3, 60):   # float kernel, float kernel in a loop, numpy rows
        z = np.zeros((N, 2))
        q = np.full((N, 2), 0.3)
        for mode in ('loop', 'rows'):
            assert aba.aba_kernel(model, q, z, z, None, mode) is None
        with pytest.raises(ValueError, match=msg):
            model.forward_dynamics(q, z, z, method='aba')
        with pytest.raises(ValueError, match=msg):
            model.forward_dynamics(q[0], z[0], z[0], method='aba')


def test_aba_bad_inputs_name_the_argument():
    model, _ = case('arm7')
    z = np.zeros(7)
    bad = z.copy()
    bad[3] = np.nan
    with pytest.raises(ValueError, match='q contains non-finite values'):
        model.forward_dynamics(bad, z, z, method='aba')
    with pytest.raises(ValueError, match='qd contains non-finite values'):
        model.forward_dynamics(z, bad, z, method='aba')
    with pytest.raises(ValueError, match='tau contains non-finite values'):
        model.forward_dynamics(np.zeros((30, 7)), np.zeros((30, 7)), np.full((30, 7), np.inf), method='aba')
    with pytest.raises(ValueError, match=r'qd must have shape \(7,\)'):
        model.forward_dynamics(z, np.zeros(6), z, method='aba')
    with pytest.raises(ValueError, match=r'tau must have shape \(7,\)'):
        model.forward_dynamics(z.tolist(), z.tolist(), [0.0] * 8, method='aba')
    with pytest.raises(ValueError, match='tau has 3 states, expected 2'):
        model.forward_dynamics(np.zeros((2, 7)), np.zeros((2, 7)), np.zeros((3, 7)), method='aba')


def test_forward_dynamics_derivatives_bad_inputs_name_the_argument():
    """Every dispatch (one state on the kernel, a small batch, the general path, rows) validates."""
    model, _ = case('arm7')
    for N in (None, 3, 20, 100):
        z = np.zeros(7) if N is None else np.zeros((N, 7))
        for k, name in enumerate(('q', 'qd', 'tau')):
            args = [z.copy(), z.copy(), z.copy()]
            args[k][..., 2] = np.nan
            with pytest.raises(ValueError, match=f'{name} contains non-finite values'):
                model.forward_dynamics_derivatives(*args)
            args = [z, z, z]
            args[k] = z[..., :6]
            with pytest.raises(ValueError, match=fr'{name} must have shape \(7,\)'):
                model.forward_dynamics_derivatives(*args)
    with pytest.raises(ValueError, match='tau has 2 states, expected 3'):
        model.forward_dynamics_derivatives(np.zeros((3, 7)), np.zeros((3, 7)), np.zeros((2, 7)))
