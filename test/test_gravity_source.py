"""Gravity from a topic with staleness and fallback, and robot_compensates_gravity, without ROS
(gravity_source.py and its hooks in the compensator), on a fake clock."""
import numpy as np
import pytest

from lie_dynamics import default_urdf_path, load_urdf
from lie_dynamics.laws import LAWS
from lie_dynamics.ros.core.compensator import Compensator
from core_cases import fill_trajectory
from lie_dynamics.ros.features.gravity_source import GRAVITY_NORM_MAX, GravitySource, check_vector


class Clock:
    def __init__(self):
        self.t = 100.0

    def __call__(self):
        return self.t


@pytest.fixture
def setup():
    clock = Clock()
    core = Compensator({'gravity_timeout': 0.5, 'ramp_time': 0.0}, clock=clock)
    core.set_model(load_urdf(default_urdf_path()))
    return core, GravitySource('/gravity', clock=clock), clock


def test_check_vector():
    model = load_urdf(default_urdf_path())
    assert np.array_equal(check_vector((0, -9.81, 0), '', model), [0, -9.81, 0])
    assert np.allclose(check_vector((0, 0, -9.81), 'base_link', model), [0, 0, -9.81])  # the root link itself
    for vec, frame, why in [((np.nan, 0, 0), '', 'non-finite'), ((0, 0, np.inf), '', 'non-finite'),
                            ((0, 0, -98.1), '', 'above'), ((0, 0, -9.81), 'hand', 'moves with the joints'),
                            ((0, 0, -9.81), 'nowhere', 'not a link')]:
        with pytest.raises(ValueError, match=why):
            check_vector(vec, frame, model)
    assert GRAVITY_NORM_MAX >= 2 * 9.81


def test_follows_the_topic_falls_back_once_and_resumes(setup):
    core, src, clock = setup
    q = np.linspace(-0.5, 0.5, 7)
    src.apply(core)
    assert np.allclose(core.model.gravity_vector, [0, 0, -9.81]) and not src.events  # nothing came yet: no fallback
    assert src.offer((0.0, -9.81, 0.0), '', core.model)
    src.apply(core)
    ref = load_urdf(default_urdf_path(), gravity=(0, -9.81, 0)).gravity(q)
    assert np.allclose(core.on_joint_state(core.layout, q), ref, atol=1e-12)
    version = core.model.version
    src.apply(core)
    assert core.model.version == version   # nothing changed: the model is not touched
    # rejected vectors leave the followed one in force
    assert not src.offer((np.nan, 0, 0), '', core.model) and not src.offer((0, 0, 500.0), '', core.model)
    assert src.rejected == 2 and [e[1] for e in src.events] == ['gravity:rejected'] * 2
    src.events.clear()
    clock.t += 0.4
    src.apply(core)
    assert np.allclose(core.model.gravity_vector, [0, -9.81, 0])
    clock.t += 0.2   # 0.6 s > gravity_timeout: the parameter again, said once
    for _ in range(5):
        src.apply(core)
    assert np.allclose(core.model.gravity_vector, [0, 0, -9.81])
    assert [e[1] for e in src.events] == ['gravity:stale']
    level, message, values = src.report(0, '')
    assert level == 1 and 'gravity topic stale' in message
    assert dict(values)['gravity_source'] == 'parameter (fallback: topic stale)'
    assert dict(values)['gravity_fallback_events'] == '1'
    src.offer((9.81, 0.0, 0.0), '', core.model)
    src.apply(core)
    assert np.allclose(core.model.gravity_vector, [9.81, 0, 0]) and src.events[-1][1] == 'gravity:resumed'
    assert dict(src.report(0, '')[2])['gravity_source'] == 'topic /gravity'


def test_scale_and_parameter_changes_keep_following(setup):
    core, src, clock = setup
    src.offer((0.0, -9.81, 0.0), '', core.model)
    src.apply(core)
    core.update({'gravity_scale': 0.5, 'payload.link': 'hand', 'payload.mass': 1.0})  # resets the model's gravity
    assert np.allclose(core.model.gravity_vector, [0, 0, -4.905])
    src.apply(core)
    assert np.allclose(core.model.gravity_vector, [0, -4.905, 0])


@pytest.mark.parametrize('mode', ['gravity', 'feedforward', 'computed_torque', 'pd'])
def test_without_gravity_is_the_law_at_zero_gravity(mode):
    model = load_urdf(default_urdf_path())
    flat = load_urdf(default_urdf_path(), gravity=(0, 0, 0))
    rng = np.random.default_rng(2)
    q, qd = rng.uniform(-1, 1, 7), rng.uniform(-1, 1, 7)
    desired = tuple(rng.uniform(-1, 1, 7) for _ in range(3))
    kp, kd = np.full(7, 3.0), np.full(7, 0.5)
    np.testing.assert_allclose(LAWS[mode](model, q, qd, desired, kp, kd, None, True, gravity=False),
                               LAWS[mode](flat, q, qd, desired, kp, kd, None, True), atol=1e-12)


def test_robot_compensates_gravity_in_the_compensator():
    clock = Clock()
    core = Compensator({'robot_compensates_gravity': True, 'include_velocity_terms': True, 'ramp_time': 0.0,
                        'stale_timeout': 0.1, 'friction.viscous': [0.0], 'friction.coulomb': [0.0]}, clock=clock)
    core.set_model(load_urdf(default_urdf_path()))
    q, qd = np.full(7, 0.3), np.full(7, 0.7)
    flat = load_urdf(default_urdf_path(), gravity=(0, 0, 0))
    np.testing.assert_allclose(core.on_joint_state(core.layout, q, qd), flat.inverse_dynamics(q, qd, np.zeros(7)),
                               atol=1e-12)
    clock.t += 1.0   # stale: hold_gravity_at_last_state holds nothing, the robot holds gravity
    np.testing.assert_array_equal(core.tick(), np.zeros(7))


def test_trajectory_efforts_leave_gravity_out_too():
    from lie_dynamics.ros.trajectories.trajectory_msgs import trajectory_message
    core = Compensator({'robot_compensates_gravity': True, 'friction.viscous': [0.0], 'friction.coulomb': [0.0]})
    core.set_model(load_urdf(default_urdf_path()))
    flat = load_urdf(default_urdf_path(), gravity=(0, 0, 0))
    rng = np.random.default_rng(5)
    q, qd, qdd = (rng.uniform(-1, 1, (20, 7)) for _ in range(3))
    msg = trajectory_message(core.layout, np.arange(20) * 0.1, q, qd, qdd)
    np.testing.assert_allclose(fill_trajectory(core, msg.joint_names, msg.points), flat.inverse_dynamics(q, qd, qdd),
                               atol=1e-12)


def test_a_frame_fixed_to_the_root_is_rotated_into_it():
    xml = ('<robot name="mounted"><link name="world"/><link name="mount"/>'
           '<joint name="fix" type="fixed"><parent link="world"/><child link="mount"/>'
           '<origin xyz="0 0 1" rpy="1.5707963267948966 0 0"/></joint>'
           '<link name="arm"><inertial><mass value="1"/><inertia ixx="0.01" ixy="0" ixz="0" iyy="0.01" iyz="0" '
           'izz="0.01"/></inertial></link><joint name="j" type="revolute"><parent link="mount"/><child link="arm"/>'
           '<axis xyz="0 0 1"/><limit effort="10" velocity="1" lower="-1" upper="1"/></joint></robot>')
    model = load_urdf(xml)
    # the mount is turned +90 deg about x: its y axis is the root's z axis
    assert np.allclose(check_vector((0.0, -9.81, 0.0), 'mount', model), [0.0, 0.0, -9.81], atol=1e-12)
    with pytest.raises(ValueError, match='moves with the joints'):
        check_vector((0.0, -9.81, 0.0), 'arm', model)
