"""Inverse dynamics and gravity against Pinocchio: many robots, many states, reduced models."""
import os
import zlib

import numpy as np
import pinocchio as pin
import pytest

from lie_dynamics import load_urdf
from oracle import Oracle
from robots import NAMED_CASES, named_urdf, random_urdf

HERE = os.path.dirname(__file__)
ARM = os.path.join(HERE, '..', 'config', 'arm7.urdf')
STATES = 200


def _rel(a, b):
    return np.linalg.norm(a - b, axis=-1) / np.maximum(np.linalg.norm(b, axis=-1), 1e-12)


def _states(rng, model, N, scale=1.0):
    lo = np.where(np.isfinite(model.position_lower), model.position_lower, -np.pi)
    hi = np.where(np.isfinite(model.position_upper), model.position_upper, np.pi)
    q = rng.uniform(lo, hi, size=(N, model.n))
    return q, scale * rng.normal(size=(N, model.n)), scale * rng.normal(size=(N, model.n))


def _check(model, oracle, rng, N=STATES, tol=1e-10):
    q, qd, qdd = _states(rng, model, N)
    tau = model.inverse_dynamics(q, qd, qdd)
    g = model.gravity(q)
    tau_ref = np.array([oracle.rnea(*s) for s in zip(q, qd, qdd, strict=True)])
    g_ref = np.array([oracle.gravity(x) for x in q])
    assert tau.shape == (N, model.n) and g.shape == (N, model.n)
    assert np.max(_rel(tau, tau_ref)) < tol
    assert np.max(_rel(g, g_ref)) < tol
    # single-state calls give the batched answer
    for i in range(0, N, max(1, N // 10)):
        np.testing.assert_allclose(model.inverse_dynamics(q[i], qd[i], qdd[i]), tau[i], rtol=1e-13, atol=1e-12)
        np.testing.assert_allclose(model.gravity(q[i]), g[i], rtol=1e-13, atol=1e-12)


@pytest.mark.parametrize('case', sorted(NAMED_CASES))
def test_named_robots_match_pinocchio(case):
    xml = named_urdf(case)
    model = load_urdf(xml)
    _check(model, Oracle(xml, joints=model.joint_names), np.random.default_rng(zlib.crc32(case.encode())))


@pytest.mark.parametrize('seed', range(6))
def test_random_robots_1_to_30_joints(seed):
    rng = np.random.default_rng(100 + seed)
    n = int(rng.integers(1, 31))
    xml = random_urdf(seed + 1000, n, tree=bool(seed % 2), mimic=n > 2 and seed % 3 == 0)
    model = load_urdf(xml)
    _check(model, Oracle(xml, joints=model.joint_names), rng, N=STATES)


def test_bundled_arm_matches_pinocchio():
    model = load_urdf(ARM)
    assert model.n == 7 and model.joint_names == [f'joint{i}' for i in range(1, 8)]
    with open(ARM) as fh:
        oracle = Oracle(fh.read(), joints=model.joint_names)
    _check(model, oracle, np.random.default_rng(7), N=500)


def test_large_batch_is_chunked_consistently():
    """Batches larger than one work chunk give the same answers as small ones."""
    model = load_urdf(named_urdf('tree12'))
    rng = np.random.default_rng(3)
    q, qd, qdd = _states(rng, model, 1300)
    full = model.inverse_dynamics(q, qd, qdd)
    parts = np.vstack([model.inverse_dynamics(q[i:i + 97], qd[i:i + 97], qdd[i:i + 97]) for i in range(0, 1300, 97)])
    np.testing.assert_allclose(full, parts, rtol=1e-14, atol=1e-12)


@pytest.mark.parametrize('case', ['tree12', 'tree20_mimic', 'mixed_types', 'chain7'])
def test_reduced_model_matches_pinocchio_buildReducedModel(case):
    xml = named_urdf(case)
    full = load_urdf(xml)
    rng = np.random.default_rng(11)
    names = full.joint_names
    ctrl = sorted(rng.choice(names, size=max(1, len(names) // 2), replace=False), key=names.index)
    model = load_urdf(xml, joints=ctrl)
    assert model.joint_names == ctrl
    assert set(model.lockable_joint_names) == set(names) - set(ctrl)
    locked = {n: float(rng.uniform(-1, 1)) for n in model.lockable_joint_names}
    model.set_locked(locked)
    _check(model, Oracle.reduced(xml, joints=ctrl, locked=locked), rng, N=100)
    # changing locked values later needs no rebuild and tracks the reduced oracle
    locked2 = {n: v + 0.5 for n, v in locked.items()}
    model.set_locked(locked2)
    _check(model, Oracle.reduced(xml, joints=ctrl, locked=locked2), rng, N=50)
    assert model.nb <= full.nb


def test_reduction_drops_bodies_that_cannot_matter():
    """Two arms on a torso: controlling the left arm drops the right arm; the torso is kept (locked)."""
    arm = random_urdf(5, 3, fixed_links=False)
    import xml.etree.ElementTree as ET

    def part(prefix):
        root = ET.fromstring(arm)
        for el in root.iter():
            for key in ('name', 'link', 'joint'):
                if key in el.attrib and el.tag in ('link', 'joint', 'parent', 'child', 'mimic'):
                    el.attrib[key] = prefix + el.attrib[key]
        return root
    left, right = part('l_'), part('r_')
    robot = ET.Element('robot', name='two_arms')
    ET.SubElement(robot, 'link', name='world')
    torso = ET.SubElement(robot, 'link', name='torso')
    inertial = ET.SubElement(torso, 'inertial')
    ET.SubElement(inertial, 'mass', value='10')
    ET.SubElement(inertial, 'inertia', ixx='1', iyy='1', izz='1', ixy='0', ixz='0', iyz='0')
    tj = ET.SubElement(robot, 'joint', name='torso_joint', type='revolute')
    ET.SubElement(tj, 'parent', link='world')
    ET.SubElement(tj, 'child', link='torso')
    ET.SubElement(tj, 'axis', xyz='1 0 0')
    ET.SubElement(tj, 'limit', effort='100', velocity='1', lower='-1', upper='1')
    for side, root in (('l_', left), ('r_', right)):
        base = [ln for ln in root.findall('link') if not any(j.find('child').get('link') == ln.get('name')
                                                             for j in root.findall('joint'))][0]
        robot.extend(root)
        fj = ET.SubElement(robot, 'joint', name=side + 'mount', type='fixed')
        ET.SubElement(fj, 'parent', link='torso')
        ET.SubElement(fj, 'child', link=base.get('name'))
        ET.SubElement(fj, 'origin', xyz=f"0 {0.3 if side == 'l_' else -0.3} 0.5", rpy='0 0 0')
    xml = ET.tostring(robot, encoding='unicode')
    left_joints = [n for n in load_urdf(xml).joint_names if n.startswith('l_')]
    model = load_urdf(xml, joints=left_joints)
    assert model.nb == 1 + len(left_joints)  # torso (locked) + left arm; right arm dropped
    assert model.locked_joint_names == ['torso_joint']
    rng = np.random.default_rng(0)
    for torso_angle in (0.0, 0.4, -0.7):
        model.set_locked({'torso_joint': torso_angle, 'r_' + left_joints[0][2:]: 1.0})  # dropped joint: ignored
        _check(model, Oracle.reduced(xml, joints=left_joints, locked={'torso_joint': torso_angle}), rng, N=30)


def test_gravity_vector_is_settable():
    xml = named_urdf('chain7')
    model = load_urdf(xml, gravity=(0.0, 9.81, 0.0))
    rng = np.random.default_rng(5)
    _check(model, Oracle(xml, joints=model.joint_names, gravity=(0.0, 9.81, 0.0)), rng, N=50)
    model.gravity_vector = (1.0, -2.0, 3.0)
    _check(model, Oracle(xml, joints=model.joint_names, gravity=(1.0, -2.0, 3.0)), rng, N=50)
    model.gravity_vector = (0.0, 0.0, 0.0)
    np.testing.assert_array_equal(model.gravity(np.zeros(model.n)), np.zeros(model.n))


def _with_fixed_child(xml, parent_link, mass, com, inertia6):
    extra = (f'<link name="payload_link"><inertial><origin xyz="{com[0]} {com[1]} {com[2]}" rpy="0 0 0"/>'
             f'<mass value="{mass}"/><inertia ixx="{inertia6[0]}" ixy="{inertia6[1]}" ixz="{inertia6[2]}" '
             f'iyy="{inertia6[3]}" iyz="{inertia6[4]}" izz="{inertia6[5]}"/></inertial></link>'
             f'<joint name="payload_fix" type="fixed"><parent link="{parent_link}"/>'
             f'<child link="payload_link"/></joint>')
    return xml.replace('</robot>', extra + '</robot>')


def test_payload_equals_a_merged_fixed_link():
    model = load_urdf(ARM)
    with open(ARM) as fh:
        xml = fh.read()
    com, inertia6 = (0.01, -0.02, 0.08), (0.004, 0.0001, 0.0, 0.005, 0.0002, 0.003)
    model.set_payload('link7', 1.5, com, inertia6)
    oracle = Oracle(_with_fixed_child(xml, 'link7', 1.5, com, inertia6), joints=model.joint_names)
    rng = np.random.default_rng(8)
    _check(model, oracle, rng, N=50)
    # replacing the payload replaces it; clearing it restores the arm
    model.set_payload('link7', 0.5, com)
    _check(model, Oracle(_with_fixed_child(xml, 'link7', 0.5, com, (0,) * 6), joints=model.joint_names), rng, N=20)
    model.clear_payload()
    _check(model, Oracle(xml, joints=model.joint_names), rng, N=20)


@pytest.mark.parametrize('case', ['no_fixed', 'fixed_heavy', 'mimic'])
def test_external_wrenches_match_pinocchio_fext(case):
    """Wrenches on every link, fixed (merged) links included, expressed in the link frame."""
    xml = named_urdf(case)
    model = load_urdf(xml)
    oracle = Oracle(xml, joints=model.joint_names)
    pm, pdata = oracle.model, oracle.data
    rng = np.random.default_rng(9)
    frames = [f for f in pm.frames if f.type == pin.FrameType.BODY and f.parentJoint > 0]
    assert any(not np.allclose(f.placement.homogeneous, np.eye(4)) for f in frames) or case != 'fixed_heavy'
    for _ in range(50):
        q, qd, qdd = (x[0] for x in _states(rng, model, 1))
        w = {f.name: rng.normal(size=6) for f in frames}
        fext = pin.StdVec_Force()
        for _j in range(pm.njoints):
            fext.append(pin.Force.Zero())
        for f in frames:  # to the joint frame; Pinocchio orders (linear, angular)
            fext[f.parentJoint] += f.placement.act(pin.Force(w[f.name][3:], w[f.name][:3]))
        ref = oracle.E.T @ pin.rnea(pm, pdata, oracle.pin_q(q), oracle.pin_v(qd), oracle.pin_v(qdd), fext)
        tau = model.inverse_dynamics(q, qd, qdd, wrenches=w)
        assert _rel(tau, ref) < 1e-10


@pytest.mark.parametrize('bad, msg', [
    (lambda m: m.inverse_dynamics(np.zeros(m.n + 1), np.zeros(m.n), np.zeros(m.n)), r'q must have shape'),
    (lambda m: m.inverse_dynamics(np.zeros(m.n), np.zeros((2, m.n)), np.zeros(m.n)), r'qd has 2 states'),
    (lambda m: m.inverse_dynamics(np.full(m.n, np.nan), np.zeros(m.n), np.zeros(m.n)), r'q contains non-finite'),
    (lambda m: m.inverse_dynamics(np.zeros(m.n), np.zeros(m.n), [np.inf] * m.n), r'qdd contains non-finite'),
    (lambda m: m.gravity(np.zeros((3, m.n, 1))), r'q must have shape'),
    (lambda m: m.gravity(np.zeros(m.n - 1)), r'q must have shape'),
    (lambda m: m.inverse_dynamics(np.zeros(m.n), np.zeros(m.n), np.zeros(m.n), {'nope': np.zeros(6)}),
     r"unknown link 'nope'"),
    (lambda m: m.inverse_dynamics(np.zeros(m.n), np.zeros(m.n), np.zeros(m.n), {'link3': np.zeros(5)}),
     r"wrench on 'link3' must have shape"),
    (lambda m: m.inverse_dynamics(np.zeros(m.n), np.zeros(m.n), np.zeros(m.n), {'link3': [np.nan] * 6}),
     r"wrench on 'link3' contains non-finite"),
    (lambda m: setattr(m, 'gravity_vector', (0, 0)), r'gravity must have shape \(3,\)'),
    (lambda m: setattr(m, 'gravity_vector', (0, 0, np.nan)), r'gravity contains non-finite'),
    (lambda m: m.set_locked({'joint1': 0.1}), r"joint 'joint1' is controlled, not locked"),
    (lambda m: m.set_locked({'nope': 0.1}), r"unknown joint 'nope'"),
    (lambda m: m.set_payload('nope', 1.0, (0, 0, 0)), r"unknown link 'nope' for payload"),
    (lambda m: m.set_payload('link7', -1.0, (0, 0, 0)), r'payload mass must be finite and >= 0'),
    (lambda m: m.set_payload('link7', 1.0, (0, 0)), r'payload com must have shape'),
    (lambda m: m.set_payload('link7', 1.0, (0, 0, 0), (1, 0, 0, 1, 0, 5)), r'payload inertia is not physically'),
    (lambda m: m.set_payload('link7', 1.0, (0, 0, 0), (1, 2)), r'payload inertia must be a finite 3x3'),
])
def test_bad_inputs_raise_clear_errors(bad, msg):
    model = load_urdf(ARM)
    with pytest.raises(ValueError, match=msg):
        bad(model)
