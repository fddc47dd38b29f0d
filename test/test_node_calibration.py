"""The node's calibration_file in its plain-Python core: planned and applied like the other model
settings (the calibrated model's inertias, armature and friction, the effort offsets subtracted
from measured efforts), refused with the reason and the old values kept."""
import numpy as np
import pytest
import yaml

from dyn_cases import ARM
from lie_dynamics import load_urdf
from lie_dynamics.calibration import CalibrationResult
from lie_dynamics.ros.core.compensator import Compensator
from lie_dynamics.ros.features.contact import effort_offset, motor_torque
from test_calibration_fit import true_parameters


def calibration_of(model, seed=0, **changes):
    """A CalibrationResult for `model`: a robot that differs from its URDF (masses, CoMs,
    armature, friction, offsets: test_calibration_fit.true_parameters)."""
    p = true_parameters(model, seed)
    fields = dict(robot=model.name, joint_names=list(model.joint_names), link_names=list(model.link_frames),
                  body_links=list(model.body_link_names), parameters=p, std=np.full(len(p), np.nan),
                  source=['identified'] * len(p))
    fields.update(changes)
    return CalibrationResult(**fields)


def core():
    c = Compensator({'ramp_time': 0.0})
    c.set_model(load_urdf(ARM))
    return c


Q = np.array([0.3, -0.5, 0.2, 1.1, 0.4, 0.6, -0.2])


def gravity_command(c, q=Q):
    cmd = c.on_joint_state(c.model.joint_names, q, np.zeros(len(q)))
    assert c.result.accepted, c.result
    return cmd


def test_calibration_file_sets_inertias_armature_friction_and_offsets(tmp_path):
    c = core()
    arm = load_urdf(ARM)
    cal = calibration_of(arm)
    path = str(cal.save(tmp_path / 'calibration.yaml'))
    before = gravity_command(c)
    assert np.allclose(before, arm.gravity(Q), rtol=0, atol=1e-12)
    c.update({'calibration_file': path})
    want = arm.with_calibration(path)
    assert np.allclose(c.model.inertial_parameters(), cal.inertial.reshape(-1), rtol=1e-12, atol=1e-15)
    assert np.allclose(c.model.armature, cal.armature, rtol=1e-12, atol=0)
    after = gravity_command(c)
    assert np.allclose(after, want.gravity(Q), rtol=0, atol=1e-12)
    assert np.max(np.abs(after - before)) > 0.1
    # friction.viscous / friction.coulomb empty: the calibration's values (where the URDF's were)
    assert np.allclose(c.friction.viscous, cal.viscous) and np.allclose(c.friction.coulomb, cal.coulomb)
    # explicitly set friction parameters win over the calibration
    c.update({'friction.viscous': [0.25]})
    assert np.allclose(c.friction.viscous, 0.25) and np.allclose(c.friction.coulomb, cal.coulomb)
    # effort offsets: measured = true + offset, subtracted wherever a measured effort is read
    effort = np.linspace(-3.0, 3.0, 7)
    assert np.allclose(effort_offset(c.model), cal.offset)
    assert np.allclose(motor_torque(c.model, Q, effort, 'total'), effort - cal.offset, rtol=0, atol=1e-15)
    assert np.allclose(motor_torque(c.model, Q, effort, 'gravity_removed'),
                       effort - cal.offset + want.gravity(Q), rtol=0, atol=1e-12)
    # a new description gets the calibration too
    c.set_model(load_urdf(ARM))
    assert np.allclose(gravity_command(c), want.gravity(Q), rtol=0, atol=1e-12)
    # cleared: the URDF's model again, no offsets
    c.update({'calibration_file': ''})
    assert np.allclose(gravity_command(c), arm.gravity(Q), rtol=0, atol=1e-12)
    assert effort_offset(c.model) is None and c.calibration is None
    assert np.allclose(c.friction.viscous, 0.25) and np.allclose(c.friction.coulomb, arm.friction)


def test_calibration_composes_with_a_payload(tmp_path):
    c = core()
    arm = load_urdf(ARM)
    path = str(calibration_of(arm, seed=1).save(tmp_path / 'calibration.yaml'))
    payload = {'payload.link': 'link7', 'payload.mass': 1.5, 'payload.com': [0.0, 0.0, 0.05]}
    c.update(payload)
    c.update({'calibration_file': path})
    want = arm.with_calibration(path)
    want.set_payload('link7', 1.5, [0.0, 0.0, 0.05])
    assert np.allclose(gravity_command(c), want.gravity(Q), rtol=0, atol=1e-12)
    c.update({'payload.mass': 0.0})
    assert np.allclose(gravity_command(c), arm.with_calibration(path).gravity(Q), rtol=0, atol=1e-12)


def _refused(c, path, match):
    model, settings, cmd = c.model, c.settings, gravity_command(c)
    with pytest.raises(ValueError, match=match):
        c.update({'calibration_file': str(path)})
    assert c.model is model and c.settings is settings
    assert np.array_equal(gravity_command(c), cmd)


def test_refusals_keep_the_old_values(tmp_path):
    c = core()
    arm = load_urdf(ARM)
    good = str(calibration_of(arm).save(tmp_path / 'good.yaml'))
    c.update({'calibration_file': good})
    calibrated = c.model
    # another robot: its links differ
    other = calibration_of(arm, robot='other_arm', link_names=list(arm.link_frames)[:-1] + ['gripper'])
    _refused(c, other.save(tmp_path / 'other.yaml'), r'another robot .*other_arm.*not in the model: gripper')
    # a joint the model does not control
    names = list(arm.joint_names)
    names[2] = 'elbow_x'
    _refused(c, calibration_of(arm, joint_names=names).save(tmp_path / 'joint.yaml'),
             'joints the model does not control: elbow_x')
    # malformed, missing, physically invalid
    (tmp_path / 'bad.yaml').write_text('format: [unclosed\n')
    _refused(c, tmp_path / 'bad.yaml', 'not YAML')
    (tmp_path / 'other_format.yaml').write_text('a: 1\n')
    _refused(c, tmp_path / 'other_format.yaml', 'not a calibration file')
    _refused(c, tmp_path / 'missing.yaml', 'missing.yaml: No such file')
    data = yaml.safe_load(open(good))
    data['links'][arm.body_link_names[1]]['mass']['value'] = -1.0
    (tmp_path / 'negative.yaml').write_text(yaml.safe_dump(data))
    _refused(c, tmp_path / 'negative.yaml', 'mass must be > 0')
    assert c.model is calibrated and c.settings.calibration_file == good
    # larger than max_description_bytes: refused unread
    c.update({'max_description_bytes': 1000})
    _refused(c, other.save(tmp_path / 'other.yaml'), 'bytes, more than max_description_bytes')
    assert len(list(tmp_path.iterdir())) == 6


def test_the_observer_reads_efforts_without_the_offsets(tmp_path):
    """Efforts of the calibrated robot plus its offsets: the observer's estimate stays at zero
    (without the subtraction it would settle at the offsets, 0.1-1 N m here)."""
    from lie_dynamics.ros.core.settings import Settings
    from lie_dynamics.ros.features.contact import ContactMonitor
    from test_contact import motion
    arm = load_urdf(ARM)
    cal = calibration_of(arm, seed=3)
    model = arm.with_calibration(cal)
    assert np.min(np.abs(cal.offset)) > 0.01
    mon = ContactMonitor(clock=lambda: 0.0)
    mon.adopt(Settings({'observer.enabled': True}), model, None, list(model.joint_names))
    for k in range(400):
        q, qd, qdd = motion(k * 1e-3)
        effort = model.inverse_dynamics(q, qd, qdd) + cal.offset
        mon.on_state(q, qd, effort, k * 1_000_000 + 5 * 10 ** 18)
    assert mon.samples > 390
    assert np.max(np.abs(mon.estimate)) < 1e-3, mon.estimate


def test_payload_identification_reads_efforts_without_the_offsets():
    """static poses of the calibrated robot carrying a point mass, efforts with the offsets: the
    fit finds the mass and CoM (the offsets are taken out by the one rule, motor_torque)."""
    from lie_dynamics.ros.features.payload_service import fit
    arm = load_urdf(ARM)
    cal = calibration_of(arm, seed=4)
    model = arm.with_calibration(cal)
    loaded = arm.with_calibration(cal)
    loaded.set_payload('link7', 1.2, [0.01, -0.02, 0.05])
    rng = np.random.default_rng(5)
    poses = rng.uniform(arm.position_lower * 0.7, arm.position_upper * 0.7, (8, 7))
    t = np.arange(8 * 40) * 0.005
    q = np.repeat(poses, 40, axis=0)
    zero = np.zeros_like(q)
    effort = loaded.inverse_dynamics(q, zero, zero) + cal.offset
    res, changes, _ = fit(model, 'link7', t, q, zero, effort, 'static', 'total', 0.3)
    assert changes['payload.mass'] == pytest.approx(1.2, rel=1e-6)
    assert np.allclose(changes['payload.com'], [0.01, -0.02, 0.05], atol=1e-6)


def test_calibration_file_set_at_start_up(tmp_path):
    arm = load_urdf(ARM)
    path = str(calibration_of(arm, seed=5).save(tmp_path / 'calibration.yaml'))
    c = Compensator({'ramp_time': 0.0, 'calibration_file': path})
    c.set_model(load_urdf(ARM))
    assert np.allclose(gravity_command(c), arm.with_calibration(path).gravity(Q), rtol=0, atol=1e-12)
