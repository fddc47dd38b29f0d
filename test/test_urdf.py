"""URDF loading: supported features, every rejection path with its message, no scene built."""
import os

import numpy as np
import pytest

from lie_dynamics import default_urdf_path, load_urdf
from robots import named_urdf

ARM = os.path.join(os.path.dirname(__file__), '..', 'config', 'arm7.urdf')
INERTIAL = ('<inertial><mass value="1"/><inertia ixx="0.1" iyy="0.1" izz="0.1" ixy="0" ixz="0" iyz="0"/>'
            '</inertial>')


def link(name, inertial=INERTIAL):
    return f'<link name="{name}">{inertial}</link>'


def joint(name, parent, child, jtype='revolute', extra=''):
    lim = '<limit effort="10" velocity="1" lower="-1" upper="1"/>' if jtype in ('revolute', 'prismatic') else ''
    return (f'<joint name="{name}" type="{jtype}"><parent link="{parent}"/><child link="{child}"/>'
            f'<axis xyz="0 0 1"/>{lim}{extra}</joint>')


def robot(*parts):
    return '<robot name="r">' + ''.join(parts) + '</robot>'


GOOD = robot(link('base'), link('a'), link('b'), joint('j1', 'base', 'a'), joint('j2', 'a', 'b'))


def test_good_robot_loads_from_string_and_file(tmp_path):
    m = load_urdf(GOOD)
    assert m.joint_names == ['j1', 'j2'] and m.n == 2 and m.name == 'r'
    p = tmp_path / 'r.urdf'
    p.write_text(GOOD)
    assert load_urdf(str(p)).joint_names == ['j1', 'j2']
    assert load_urdf(p).joint_names == ['j1', 'j2']


def test_bundled_arm_contents():
    m = load_urdf(ARM)
    assert os.path.isfile(default_urdf_path())
    assert load_urdf(default_urdf_path()).joint_names == m.joint_names
    assert m.n == 7 and m.nb == 7
    assert np.all(m.effort_limits > 0) and np.all(np.isfinite(m.effort_limits))
    assert np.all(m.position_lower < m.position_upper)
    assert np.all(m.damping > 0) and np.all(m.friction > 0)
    # the fixed hand is merged into link7's body: the last body is heavier than link7 alone
    b, T = m.link_frames['hand']
    assert b == 6 and not np.allclose(T, np.eye(4))
    assert m.J[6][3, 3] > 0.7


def test_no_scene_and_no_meshes_are_built(monkeypatch):
    """Loading never builds yourdfpy's trimesh scene (trimesh is not even imported by us)."""
    import yourdfpy

    def boom(*a, **k):
        raise AssertionError('scene graph built')
    monkeypatch.setattr(yourdfpy.URDF, '_create_scene', boom, raising=False)
    monkeypatch.setattr(yourdfpy.URDF, '_build_scene_graph', boom, raising=False)
    xml = GOOD.replace('<link name="a">', '<link name="a"><visual><geometry><mesh filename="package://x/none.stl"/>'
                                          '</geometry></visual>')
    assert load_urdf(xml).n == 2


def test_fixed_links_merged_and_missing_inertial_is_zero_mass():
    xml = robot(link('base'), link('a', ''), link('tool'), joint('j1', 'base', 'a'), joint('fix', 'a', 'tool', 'fixed'))
    m = load_urdf(xml)
    assert m.nb == 1 and m.J[0][3, 3] == pytest.approx(1.0)  # only the fixed tool carries mass


def test_continuous_and_prismatic_limits():
    xml = robot(link('base'), link('a'), link('b'), joint('c', 'base', 'a', 'continuous'),
                joint('p', 'a', 'b', 'prismatic'))
    m = load_urdf(xml)
    assert m.joint_types == ['continuous', 'prismatic']
    assert np.isinf(m.position_lower[0]) and m.position_lower[1] == -1


def test_missing_axis_defaults_to_x():
    xml = GOOD.replace('<axis xyz="0 0 1"/>', '', 1)
    m = load_urdf(xml)
    np.testing.assert_array_equal(m.S[0], [1, 0, 0, 0, 0, 0])


def test_mimic_joint_is_not_controlled_and_follows_master():
    xml = robot(link('base'), link('a'), link('b'), joint('j1', 'base', 'a'),
                joint('j2', 'a', 'b', extra='<mimic joint="j1" multiplier="-2" offset="0.1"/>'))
    m = load_urdf(xml)
    assert m.joint_names == ['j1'] and m.mimic_joints == {'j2': ('j1', -2.0, 0.1)}
    np.testing.assert_allclose(m.body_coordinates(np.array([[0.3]])), [[0.3, -0.5]])


@pytest.mark.parametrize('xml, kwargs, msg', [
    ('<robot name="r"><link name="a"></robot>', {}, r'malformed URDF'),
    ('<notarobot/>', {}, r'root element is <notarobot>'),
    ('/no/such/file.urdf', {}, r'URDF file not found'),
    (robot(link('a'), link('b')), {}, r'several root links'),
    (robot(link('a'), link('b'), joint('j1', 'a', 'b'), joint('j2', 'b', 'a')), {}, r'two parent joints|cycle'),
    (robot(link('a'), link('b'), link('c'), joint('j1', 'a', 'c'), joint('j2', 'b', 'c')), {},
     r"link 'c' has two parent"),
    (robot(link('a'), joint('j1', 'a', 'zz')), {}, r"joint 'j1' refers to unknown link 'zz'"),
    (robot(link('base'), link('a'), link('b'), joint('j1', 'base', 'a'), joint('p', 'a', 'b', 'planar')), {},
     r"joint 'p' is planar and sits inside the subtree"),
    (GOOD, {'joints': ['j1', 'nope']}, r"unknown joint 'nope'"),
    (GOOD, {'joints': ['j1', 'j1']}, r'joints lists a name twice'),
    (GOOD, {'joints': 'j1'}, r'joints must be a list'),
    (robot(link('base'), link('a'), link('b'), joint('j1', 'base', 'a'), joint('fx', 'a', 'b', 'fixed')),
     {'joints': ['fx']}, r"joint 'fx' is fixed and cannot be controlled"),
    (GOOD.replace('ixx="0.1" ', '', 1), {}, r"link 'base': <inertia> lacks ixx"),
    (GOOD.replace('<mass value="1"/>', '<mass value="-1"/>', 2), {'inertia': 'strict'},
     r"link 'a': negative mass"),
    (GOOD.replace('ixx="0.1" iyy="0.1" izz="0.1"', 'ixx="0.1" iyy="0.1" izz="0.5"', 2), {'inertia': 'strict'},
     r"link 'a': triangle inequality"),
    (GOOD.replace('ixx="0.1" iyy="0.1" izz="0.1" ixy="0"', 'ixx="0.1" iyy="0.1" izz="0.1" ixy="0.5"', 2),
     {'inertia': 'strict'}, r"link 'a': negative principal moment"),
    (GOOD, {'inertia': 'lenient'}, r'inertia policy must be one of warn, strict, repair'),
    (GOOD.replace('<axis xyz="0 0 1"/>', '<axis xyz="0 0 0"/>', 1), {}, r"joint 'j1': axis must be a non-zero"),
    (GOOD.replace('type="revolute"', 'type="spherical"', 1), {}, r"joint 'j1': unknown type 'spherical'"),
    (robot(link('base'), link('a'), link('b'), joint('j1', 'base', 'a'),
           joint('j2', 'a', 'b', extra='<mimic joint="j1"/>')), {'joints': ['j2']}, r"'j2' is a mimic joint of 'j1'"),
    (12, {}, r'URDF source must be a file path or an XML string'),
])
def test_rejections_name_the_culprit(xml, kwargs, msg):
    with pytest.raises(ValueError, match=msg):
        load_urdf(xml, **kwargs)


def test_mimic_set_locked_message():
    xml = robot(link('base'), link('a'), link('b'), joint('j1', 'base', 'a'),
                joint('j2', 'a', 'b', extra='<mimic joint="j1"/>'))
    m = load_urdf(xml)
    with pytest.raises(ValueError, match=r"joint 'j2' is a mimic joint: set its master 'j1'"):
        m.set_locked({'j2': 0.0})
    with pytest.raises(ValueError, match=r"non-finite"):
        load_urdf(GOOD, joints=['j1']).set_locked({'j2': np.nan})


def test_floating_joint_outside_modelled_part_is_fine():
    xml = robot(link('base'), link('a'), link('b'), joint('j1', 'base', 'a'), joint('f', 'base', 'b', 'floating'))
    assert load_urdf(xml).joint_names == ['j1']


def test_named_cases_load():
    for name in ('tree20_mimic', 'fixed_heavy', 'chain30'):
        m = load_urdf(named_urdf(name))
        assert m.n >= 1 and np.all(np.linalg.eigvalsh(m.J[:, 3:, 3:]) >= 0)


def test_default_joint_order_is_depth_first_in_file_order():
    """base -> (jb -> b -> jc -> c), (ja -> a): a joint's subtree precedes its next sibling,
    siblings keep file order (not Pinocchio's alphabetical order)."""
    xml = robot(link('base'), link('a'), link('b'), link('c'),
                joint('jb', 'base', 'b'), joint('ja', 'base', 'a'), joint('jc', 'b', 'c'))
    m = load_urdf(xml)
    assert m.joint_names == ['jb', 'jc', 'ja']
    assert list(m.parent) == [-1, 0, -1]
