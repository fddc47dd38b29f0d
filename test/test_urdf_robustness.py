"""URDFs as real robots ship them: the inertia policy, what the ROS parser accepts or refuses,
mimics of missing joints, free joints above the arm, folded locked subtrees, read-only arrays.
Each case is a small URDF shaped like the real one it is named after."""
import glob
import os
import sys
import warnings

import numpy as np
import pytest

from lie_dynamics import InertiaWarning, URDFWarning, load_urdf
from lie_dynamics.codegen import runtime
from lie_dynamics.model.inertia import repair, violations
from oracle import Oracle


def inertial(mass, ixx, iyy, izz, ixy=0.0, ixz=0.0, iyz=0.0, xyz='0 0 0'):
    return (f'<inertial><origin xyz="{xyz}"/><mass value="{mass}"/><inertia ixx="{ixx}" iyy="{iyy}" izz="{izz}" '
            f'ixy="{ixy}" ixz="{ixz}" iyz="{iyz}"/></inertial>')


ARM_LINK = inertial(3.0, 0.05, 0.05, 0.01, xyz='0 0 0.2')


def link(name, body=ARM_LINK):
    return f'<link name="{name}">{body}</link>'


def joint(name, parent, child, jtype='revolute', xyz='0 0 0.4', axis='0 1 0', extra=''):
    lim = '<limit effort="50" velocity="2" lower="-2" upper="2"/>' if jtype in ('revolute', 'prismatic') else ''
    return (f'<joint name="{name}" type="{jtype}"><origin xyz="{xyz}" rpy="0 0 0"/><parent link="{parent}"/>'
            f'<child link="{child}"/><axis xyz="{axis}"/>{lim}{extra}</joint>')


def robot(*parts, name='r'):
    return f'<robot name="{name}">' + ''.join(parts) + '</robot>'


def arm(extra_links=(), extra_joints=()):
    """base -> j1 -> l1 -> j2 -> l2 (a 2-joint arm) plus extra parts."""
    return robot(link('base'), link('l1'), link('l2'), *extra_links,
                 joint('j1', 'base', 'l1', axis='0 0 1'), joint('j2', 'l1', 'l2'), *extra_joints)


# PR2's sensor_mount_link: welded to a moving head link, principal moments [0.001, 0.001, 0.01].
PR2_LIKE = arm([link('sensor_mount_link', inertial(0.05, 0.001, 0.001, 0.01))],
               [joint('sensor_fix', 'l2', 'sensor_mount_link', 'fixed', xyz='0 0 0.1')])


def load_recording(xml, **kwargs):
    with warnings.catch_warnings(record=True) as rec:
        warnings.simplefilter('always')
        model = load_urdf(xml, **kwargs)
    return model, [w for w in rec if issubclass(w.category, (InertiaWarning, URDFWarning))]


def load_silently(xml, **kwargs):
    """Load and fail on any warning of ours (round-off must not be reported)."""
    with warnings.catch_warnings():
        warnings.simplefilter('error', InertiaWarning)
        warnings.simplefilter('error', URDFWarning)
        return load_urdf(xml, **kwargs)


def agree_with_pinocchio(model, xml, states=4, locked=None, tol=1e-10):
    oracle = (Oracle.reduced if locked else Oracle)(xml, joints=model.joint_names, locked=locked)
    rng = np.random.default_rng(0)
    for _ in range(states):
        q, qd, qdd = rng.normal(size=(3, model.n))
        ref = oracle.rnea(q, qd, qdd)
        assert np.allclose(model.inverse_dynamics(q, qd, qdd), ref, rtol=tol, atol=tol * max(1, np.abs(ref).max()))
        assert np.allclose(model.mass_matrix(q), oracle.crba(q), rtol=tol, atol=tol)


# ---------------------------------------------------------------------- inertia policy
def test_warn_names_the_link_the_rule_and_the_numbers():
    model, rec = load_recording(PR2_LIKE)
    assert len(rec) == 1 and rec[0].category is InertiaWarning
    text = str(rec[0].message)
    assert "link 'sensor_mount_link'" in text and 'triangle inequality' in text
    assert '0.001' in text and '0.01' in text
    report = model.physical_consistency()
    assert [(e['link'], e['rule'], e['repaired']) for e in report] == [('sensor_mount_link', 'triangle inequality',
                                                                       False)]
    agree_with_pinocchio(model, PR2_LIKE)  # computed with the tensor as written, like Pinocchio


def test_strict_refuses_with_the_same_text():
    with pytest.raises(ValueError, match=r"link 'sensor_mount_link': triangle inequality: principal moments "
                                         r"\[0.001, 0.001, 0.01\]"):
        load_urdf(PR2_LIKE, inertia='strict')


def test_repair_is_consistent_keeps_axes_and_reports_before_and_after():
    rotated = PR2_LIKE.replace('ixy="0.0"', 'ixy="0.0004"')  # principal axes off the link axes
    model, rec = load_recording(rotated, inertia='repair')
    assert len(rec) == 1 and 'repaired to mass 0.05 kg' in str(rec[0].message)
    assert model.physical_consistency()[0]['repaired']
    # the documented rule, on the tensor itself
    I = np.array([[0.001, 0.0004, 0], [0.0004, 0.001, 0], [0, 0, 0.01]])
    m, I2 = repair(0.05, I)
    ev, R = np.linalg.eigh(I)
    ev2 = np.linalg.eigvalsh(I2)
    assert m == 0.05 and not violations(m, I2, 1e-15)
    assert np.allclose(np.sort([R[:, k] @ I2 @ R[:, k] for k in range(3)]), ev2)  # same principal axes
    assert ev2[2] == pytest.approx(ev2[0] + ev2[1]) and ev2[2] == pytest.approx(ev[2])  # smallest raised
    # repaired model equals the model written with the repaired tensor
    fixed = load_silently(arm([link('sensor_mount_link', inertial(0.05, *np.diag(I2), ixy=I2[0, 1]))],
                              [joint('sensor_fix', 'l2', 'sensor_mount_link', 'fixed', xyz='0 0 0.1')]))
    q = np.array([0.3, -0.7])
    assert np.allclose(model.gravity(q), fixed.gravity(q), atol=1e-12)


@pytest.mark.parametrize('body, rule', [
    (inertial(0.05, 0.001, 0.001, 0.01), 'triangle inequality'),
    (inertial(-0.5, 0.01, 0.01, 0.01), 'negative mass'),
    (inertial(1.0, 0.01, 0.01, 0.01, ixy=0.05), 'negative principal moment'),
    (inertial(0.0, 0.01, 0.01, 0.01), 'massless with inertia'),
])
def test_strict_refuses_exactly_what_warn_warns(body, rule):
    xml = arm([link('odd', body)], [joint('fix', 'l2', 'odd', 'fixed')])
    _, rec = load_recording(xml)
    assert len(rec) == 1 and f"link 'odd': {rule}" in str(rec[0].message)
    with pytest.raises(ValueError, match=f"link 'odd': {rule}"):
        load_urdf(xml, inertia='strict')
    _, rec = load_recording(xml, inertia="repair")
    assert len(rec) == 1 and 'repaired' in str(rec[0].message)
    assert load_silently(PR2_LIKE.replace('izz="0.01"', 'izz="0.0015"'), inertia='strict').n == 2  # consistent


def test_round_off_is_not_a_violation():
    # iCub's l_ankle_2: a zero tensor with 1e-20 noise; a HyQ-like foot: a 1e-6 placeholder tensor
    # (principal moments [-2.5e-22, 3.4e-23, 3e-6]) on a moving leg of a few kilograms.
    icub = inertial(0.2675, 0, 0, 0, ixz=1.35525e-20, xyz='0.008 0 0.0553')
    foot = inertial(1e-6, 1e-6, 1e-6, 1e-6, 1e-6, 1e-6, 1e-6)
    xml = arm([link('ankle', icub), link('foot', foot)],
              [joint('ankle_fix', 'l2', 'ankle', 'fixed'), joint('foot_fix', 'ankle', 'foot', 'fixed')])
    model = load_silently(xml, inertia='strict')
    assert model.physical_consistency() == []


def test_links_that_cannot_move_a_controlled_joint_are_not_checked():
    # HyQ/ANYmal: a placeholder on the root link; TIAGo: antennas with a negative moment welded to
    # the base; iCub: a bad link on a leg that the arm's reduction drops.
    bad = inertial(1e-6, 1e-6, -1e-3, 1e-6)
    xml = robot(link('base', bad), link('antenna', bad), link('l1'), link('l2'), link('leg'), link('foot', bad),
                joint('antenna_fix', 'base', 'antenna', 'fixed'), joint('j1', 'base', 'l1', axis='0 0 1'),
                joint('j2', 'l1', 'l2'), joint('hip', 'base', 'leg'), joint('foot_fix', 'leg', 'foot', 'fixed'))
    model = load_silently(xml, joints=['j1', 'j2'], inertia='strict')
    assert model.nb == 2 and model.physical_consistency() == []
    with pytest.raises(ValueError, match="link 'foot'"):  # once the leg is controlled, the foot counts
        load_urdf(xml, inertia='strict')


def test_forward_dynamics_still_refuses_an_indefinite_mass_matrix():
    xml = robot(link('base'), link('wheel', inertial(1.0, 0.01, 0.01, -0.5)), joint('j', 'base', 'wheel', axis='0 0 1'))
    model, rec = load_recording(xml)
    assert rec and model.mass_matrix(np.zeros(1))[0, 0] < 0
    for method in ('cholesky', 'aba'):
        with pytest.raises(ValueError):
            model.forward_dynamics(np.zeros(1), np.zeros(1), np.zeros(1), method=method)


def test_a_joint_that_moves_nothing_is_reported():
    xml = arm([link('finger', '')], [joint('jf', 'l2', 'finger', 'prismatic', axis='1 0 0')])
    model, rec = load_recording(xml)
    assert [str(w.message).split(':')[0] for w in rec] == ["link 'finger'"]
    assert model.physical_consistency()[0]['rule'] == 'massless moving body'
    with pytest.raises(ValueError, match="joint 'jf' moves no mass"):
        load_urdf(xml, inertia='strict')
    with pytest.raises(ValueError):
        model.forward_dynamics(np.zeros(3), np.zeros(3), np.zeros(3))


def test_payload_uses_the_same_check():
    model = load_silently(PR2_LIKE.replace('izz="0.01"', 'izz="0.0015"'))
    with pytest.raises(ValueError, match='payload inertia is not physically valid: triangle inequality'):
        model.set_payload('l2', 1.0, (0, 0, 0), (0.001, 0, 0, 0.001, 0, 0.01))
    model.set_payload('l2', 1.0, (0, 0, 0), (0.001, 0, 0, 0.001, 0, 1e-9 + 0.002))


# ---------------------------------------------------------------------- parsing like urdfdom
def test_undeclared_prefixes_blank_lines_and_unknown_tags_load():
    clean = arm()
    vendor = ('\n\n  <?xml version="1.0"?>\n' + clean.replace('<robot name="r">', '<robot name="r">'
              '<drake:collision_filter_group name="g"><drake:member link="l1"/></drake:collision_filter_group>'
              '<gazebo reference="l1"><mu1>0.2</mu1></gazebo>')
              .replace('<joint name="j2"', '<joint drake:acceleration="2.0" name="j2"')
              .replace('<link name="l2">', '<link name="l2"><unknown_tag foo="1"/>'))
    a, b = load_silently(clean), load_silently(vendor)
    q = np.array([0.4, -0.2])
    assert np.array_equal(a.gravity(q), b.gravity(q))


@pytest.mark.parametrize('doctype', [
    '<!DOCTYPE robot [<!ENTITY a "0.5"><!ENTITY b "&a;&a;&a;&a;&a;&a;&a;&a;">]>',
    '<!DOCTYPE robot [<!ENTITY secret SYSTEM "file:///etc/hostname">]>',
])
def test_entities_are_refused(doctype):
    with pytest.raises(ValueError, match='XML entities'):
        load_urdf('<?xml version="1.0"?>' + doctype + arm())


@pytest.mark.parametrize('old, new, msg', [
    ('<origin xyz="0 0 0.4" rpy="0 0 0"/><parent link="l1"/>',
     '<origin xyz="0 0 0.4" rpy="0 0 0 0"/><parent link="l1"/>',
     r"joint 'j2' <origin> rpy: expected three numbers, got '0 0 0 0'"),
    ('<origin xyz="0 0 0.4" rpy="0 0 0"/><parent link="l1"/>', '<origin xyz="0 0.4" rpy="0 0 0"/><parent link="l1"/>',
     r"joint 'j2' <origin> xyz: expected three numbers"),
    ('<axis xyz="0 1 0"/>', '<axis xyz="0 1 0 1"/>', r"joint 'j2' <axis> xyz: expected three numbers"),
    ('<origin xyz="0 0 0.2"/>', '<origin xyz="0 0 a"/>', r"link 'base' <origin> xyz: expected three numbers"),
    ('<origin xyz="0 0 0.4" rpy="0 0 0"/><parent link="l1"/>',
     '<origin xyz="0 0 0.4" rpy="0 ${pi/2} 0"/><parent link="l1"/>',
     r"joint 'j2' <origin> rpy='0 \$\{pi/2\} 0': unexpanded xacro expression: run the file through xacro first"),
    ('<link name="l2">', '<link name="l2"><visual><geometry><mesh filename="$(find pkg)/m.stl"/></geometry></visual>',
     r"link 'l2' <mesh> filename=.*unexpanded xacro"),
    ('<robot name="r">', '<robot name="r" xmlns:xacro="http://www.ros.org/wiki/xacro"><xacro:include filename="x"/>',
     r'<include>: unexpanded xacro element: run the file through xacro first'),
])
def test_what_urdfdom_refuses_is_refused_naming_the_place(old, new, msg):
    xml = arm()
    assert old in xml
    with pytest.raises(ValueError, match=msg):
        load_urdf(xml.replace(old, new, 1))


def test_mimic_of_a_missing_joint_is_an_independent_joint():
    xml = arm([link('finger', inertial(0.1, 1e-4, 1e-4, 1e-4, xyz='0.05 0 0'))],
              [joint('jf', 'l2', 'finger', extra='<mimic joint="index_q1" multiplier="1.0"/>')])
    model, rec = load_recording(xml)
    assert len(rec) == 1 and rec[0].category is URDFWarning
    assert "joint 'jf' mimics 'index_q1'" in str(rec[0].message)
    assert model.joint_names == ['j1', 'j2', 'jf'] and model.mimic_joints == {}
    agree_with_pinocchio(model, xml)


def test_floating_joint_above_the_arm_is_fixed_at_identity():
    mobile = robot(link('world', ''), link('base'), link('l1'), link('l2'),
                   joint('world_joint', 'world', 'base', 'floating', xyz='0 0 0'),
                   joint('j1', 'base', 'l1', axis='0 0 1'), joint('j2', 'l1', 'l2'))
    model, rec = load_recording(mobile)
    assert len(rec) == 1 and rec[0].category is URDFWarning and "'world_joint'" in str(rec[0].message)
    fixed = mobile.replace('type="floating"', 'type="fixed"')
    assert model.joint_names == ['j1', 'j2'] and model.nb == 2
    agree_with_pinocchio(model, fixed)
    planar = mobile.replace('type="floating"', 'type="planar"')
    assert load_recording(planar)[0].nb == 2
    below = robot(link('base'), link('l1'), link('l2'), joint('j1', 'base', 'l1'),
                  joint('loose', 'l1', 'l2', 'floating'))
    with pytest.raises(ValueError, match="joint 'loose' is floating and sits inside the subtree"):
        load_urdf(below)


def test_a_robot_without_movable_joints_loads():
    model = load_silently(robot(link('base'), link('rotor'), joint('fix', 'base', 'rotor', 'fixed')))
    assert model.n == 0 and model.nb == 0
    assert model.inverse_dynamics(np.zeros(0), np.zeros(0), np.zeros(0)).shape == (0,)
    assert model.mass_matrix(np.zeros((4, 0))).shape == (4, 0, 0)
    with pytest.raises(ValueError, match=r'q must have shape \(0,\)'):
        model.gravity([0.1])


# ---------------------------------------------------------------------- folded locked subtrees
GRIPPER = arm([link('hand', inertial(0.7, 1e-3, 1e-3, 1e-3, xyz='0 0 0.05')),
               link('finger1', inertial(0.02, 1e-5, 1e-5, 1e-5, xyz='0.01 0 0.02')),
               link('finger2', inertial(0.02, 1e-5, 1e-5, 1e-5, xyz='-0.01 0 0.02')),
               link('tip', inertial(0.01, 1e-6, 1e-6, 1e-6, xyz='0 0 0.01'))],
              [joint('hand_fix', 'l2', 'hand', 'fixed', xyz='0 0 0.4'),
               joint('f1', 'hand', 'finger1', 'prismatic', xyz='0 0.02 0.06', axis='0 1 0'),
               joint('f2', 'hand', 'finger2', 'prismatic', xyz='0 -0.02 0.06', axis='0 -1 0',
                     extra='<mimic joint="f1" multiplier="1.0" offset="0.001"/>'),
               joint('tipj', 'finger1', 'tip', xyz='0 0 0.04', axis='1 0 0')])


def test_locked_leaf_subtrees_are_folded_and_follow_set_locked():
    model = load_silently(GRIPPER, joints=['j1', 'j2'])
    assert model.nb == 2 and set(model.locked_joint_names) == {'f1', 'tipj'}
    assert model.folded_joint_names == ['f1', 'tipj', 'f2']
    q, qd, qdd = np.array([0.3, -0.4]), np.array([0.5, 0.2]), np.array([-1.0, 0.7])
    model.gravity(q), model.mass_matrix(q), model.forward_dynamics(q, qd, qdd)  # build the kernels
    model.inverse_dynamics(q, qd, qdd)
    builds = runtime.cache_info()['builds']
    for locked in ({'f1': 0.0, 'tipj': 0.0}, {'f1': 0.03, 'tipj': 0.8}, {'f1': -0.01, 'tipj': -1.2}):
        model.set_locked(locked)
        oracle = Oracle.reduced(GRIPPER, joints=['j1', 'j2'], locked=locked)
        assert np.allclose(model.inverse_dynamics(q, qd, qdd), oracle.rnea(q, qd, qdd), rtol=1e-12, atol=1e-12)
        assert np.allclose(model.mass_matrix(q), oracle.crba(q), rtol=1e-12, atol=1e-12)
        assert np.allclose(model.link_pose('tip', q), oracle.frame_pose(q, 'tip'), atol=1e-12)
    assert runtime.cache_info()['builds'] == builds  # set_locked never recompiles


def test_panda_fingers_are_folded():
    path = next(iter(glob.glob(os.path.join(sys.prefix, 'lib', 'python3*', 'site-packages', 'cmeel.prefix',
                                            'share', 'example-robot-data', 'robots', 'panda_description', 'urdf',
                                            'panda.urdf'))))
    arm_joints = [f'panda_joint{k}' for k in range(1, 8)]
    model = load_urdf(path, joints=arm_joints)
    assert model.nb == 7 and model.folded_joint_names == ['panda_finger_joint1', 'panda_finger_joint2']
    model.set_locked({'panda_finger_joint1': 0.035})
    with open(path, encoding='utf-8') as fh:
        xml = fh.read()
    agree_with_pinocchio(model, xml, locked={'panda_finger_joint1': 0.035}, tol=1e-10)


# ---------------------------------------------------------------------- read-only arrays
@pytest.mark.parametrize('name', ['J', 'J_links', 'M', 'S', 'E', 'parent', 'effort_limits', 'e0'])
def test_public_arrays_are_read_only(name):
    model = load_silently(arm())
    with pytest.raises(ValueError, match='read-only'):
        getattr(model, name)[0] *= 2
    # supported ways to change inertia keep working
    model.set_payload('l2', 1.0, (0, 0, 0.1))
    other = model.with_inertial_parameters(model.inertial_parameters() * 1.5)
    q = np.array([0.2, 0.4])
    assert np.allclose(other.gravity(q), 1.5 * model.gravity(q))
