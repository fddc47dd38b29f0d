"""Forward dynamics (Cholesky solve and articulated body algorithm) and its derivatives."""
import numpy as np
import pinocchio as pin
import pytest

from dyn_cases import ARM, CASES, case, oracle_stack, rel_err, states, xml_of
from lie_dynamics import aba, load_urdf
from oracle import Oracle
from robots import random_urdf

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
    assert rel_err(aba.cho_solve(aba.cholesky(M), tau - h), ref) < 1e-10
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
    X = aba.cho_solve(aba.cholesky(M), B)
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
    ref = [np.array(r) for r in zip(*(_pin_aba_derivatives(oracle, *s) for s in zip(q, qd, tau)))]
    assert rel_err(dq, ref[0]) < 1e-8
    assert rel_err(dv, ref[1]) < 1e-8
    assert rel_err(Minv, ref[2]) < 1e-8


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


def test_massless_chain_raises():
    model = load_urdf(MASSLESS_TIP)
    q = np.array([0.1, 0.2])
    with pytest.raises(ValueError, match='mass matrix is not positive definite'):
        model.forward_dynamics(q, np.zeros(2), np.zeros(2))
    with pytest.raises(ValueError, match=r'mass matrix is not positive definite at state 0 '):
        model.forward_dynamics(np.zeros((2, 2)), np.zeros((2, 2)), np.zeros((2, 2)))
    with pytest.raises(ValueError, match=r'mass matrix is not positive definite at state 1 '):
        aba.cholesky(np.array([np.eye(2), [[1.0, 0.0], [0.0, -1.0]]]))
    many = np.zeros((60, 2))   # the generated kernel on rows: NaN pivots are caught, then reported
    with pytest.raises(ValueError, match='mass matrix is not positive definite at state 0'):
        model.forward_dynamics(many, many, many)
    with pytest.raises(ValueError, match="articulated inertia about joint 'j2' is zero"):
        model.forward_dynamics(q, np.zeros(2), np.zeros(2), method='aba')
    with pytest.raises(ValueError, match='mass matrix is not positive definite'):
        model.forward_dynamics_derivatives(q, np.zeros(2), np.zeros(2))
    # a singular matrix that LAPACK's Cholesky still factors is caught by the pivot test
    with pytest.raises(ValueError, match='mass matrix is not positive definite'):
        aba.cholesky(np.array([[[1.0, 1.0], [1.0, 1.0 + 1e-15]]]))


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
