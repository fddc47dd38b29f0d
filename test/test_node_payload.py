"""Payload services, gravity from a topic and robot_compensates_gravity through the running node
over real DDS (test_node.Harness: own context, own ROS_DOMAIN_ID). Torques against Pinocchio."""
import math
import time

import numpy as np
import pytest

rclpy = pytest.importorskip('rclpy')

from geometry_msgs.msg import Vector3Stamped  # noqa: E402
from rcl_interfaces.srv import SetParametersAtomically  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from rclpy.qos import QoSProfile, ReliabilityPolicy  # noqa: E402
from sensor_msgs.msg import JointState  # noqa: E402
from std_srvs.srv import Trigger  # noqa: E402
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint  # noqa: E402

from lie_dynamics import default_urdf_path, load_urdf  # noqa: E402
from lie_dynamics.algorithms.identification import excitation_trajectory  # noqa: E402
from lie_dynamics.ros.node import SERVICE_QOS  # noqa: E402
from oracle import Oracle  # noqa: E402
from robots import with_payload  # noqa: E402
from test_node import TIMEOUT, TOL, wait_until  # noqa: E402

MASS, COM, INERTIA = 1.3, [0.01, -0.02, 0.05], [3e-3, 1e-4, 0.0, 4e-3, -2e-4, 2e-3]
JOINTS = [f'joint{i}' for i in range(1, 8)]



@pytest.fixture(scope='module')
def xml():
    with open(default_urdf_path()) as fh:
        return fh.read()


def send_stamped(ros, q, qd, effort, t):
    """Publish one stamped joint_states message and wait until the node has taken it (sent again
    if best-effort delivery lost it)."""
    msg = JointState(name=JOINTS, position=[float(x) for x in q], velocity=[float(x) for x in qd],
                     effort=[float(x) for x in effort])
    msg.header.stamp.sec, msg.header.stamp.nanosec = int(t), int(round((t - int(t)) * 1e9))
    return ros.publish_msg_processed(msg)


def call_async(ros, srv_type, name, request):
    cli = ros.t.create_client(srv_type, name)
    assert cli.wait_for_service(timeout_sec=TIMEOUT)
    return cli.call_async(request)


def identify_while_streaming(ros, samples, extra_calls=0, start=1000.0):
    """Call ~/identify_payload and stream `samples` (t, q, qd, effort) until it and the extra_calls
    calls made while it records have answered, stamped from `start` s on (later than any state the
node took before: it refuses older stamps). Returns (response, responses of the extra calls).
    (An extra call that the loaded machine delivers only after the first has finished is a new
    identification: the streaming goes on for it.)"""
    fut = call_async(ros, Trigger, '/dynamics_node/identify_payload', Trigger.Request())
    wait_until(lambda: ros.node.features.get('payload').ident.recording is not None, what='recording started')
    core, n0 = ros.node.core, len(ros.cmds)
    a0 = core.count.accepted
    # a client whose request history holds the whole flood (the default keeps 10 unacknowledged)
    cli = ros.t.create_client(Trigger, '/dynamics_node/identify_payload', qos_profile=SERVICE_QOS)
    assert cli.wait_for_service(timeout_sec=TIMEOUT)
    extra = [cli.call_async(Trigger.Request()) for _ in range(extra_calls)]   # a flood while it records
    for t, q, qd, e in zip(*samples, strict=True):
        if fut.done() and all(f.done() for f in extra):
            break
        send_stamped(ros, q, qd, e, start + t)
    wait_until(fut.done, timeout=4 * TIMEOUT, what='identify_payload answer')
    # the node kept answering every joint_states while it recorded and fitted: one command each
    wait_until(lambda: len(ros.cmds) - n0 == core.count.accepted - a0, what='a command per state')
    for f in extra:
        wait_until(f.done, what='concurrent identify_payload answer')
    return fut.result(), [f.result() for f in extra]


def payload_samples(model, seconds, payload=True, seed=0):
    t, q, qd, qdd = excitation_trajectory(model, duration=seconds, rate=200.0, seed=seed)
    loaded = model.with_body_inertias(model.J_links)
    if payload:
        loaded.set_payload('hand', MASS, COM, INERTIA)
    return t, q, qd, loaded.inverse_dynamics(q, qd, qdd)


def test_identify_payload_sets_the_parameters(ros, xml):
    node = ros.start(robot_description=xml, **{'identify.link': 'hand', 'identify.duration': 2.0})
    model = load_urdf(xml)
    res, concurrent = identify_while_streaming(ros, payload_samples(model, 12.0), extra_calls=50)
    assert res.success, res.message
    assert "payload on 'hand': mass 1.3" in res.message and 'residual' in res.message
    busy = [r for r in concurrent if 'already running' in r.message]
    late = [r for r in concurrent if 'already running' not in r.message]   # taken after the first finished
    assert busy and all(not r.success for r in busy) and len(late) <= 2, [r.message for r in late]
    time.sleep(0.2)
    assert sum('identify_payload' in line for line in ros.logs) <= 1 + len(late)  # refusals are not logged
    mass, com = node.get_parameter('payload.mass').value, list(node.get_parameter('payload.com').value)
    inertia = list(node.get_parameter('payload.inertia').value)
    assert node.get_parameter('payload.link').value == 'hand'
    assert mass == pytest.approx(MASS, rel=5e-3) and np.allclose(com, COM, atol=3e-3) and len(inertia) == 6
    # the commands now carry the identified payload, exactly as a URDF with it would
    q = np.linspace(-0.6, 0.6, 7)
    ref = Oracle(with_payload(xml, 'hand', mass, com, inertia), joints=JOINTS).gravity(q)
    send_stamped(ros, q, np.zeros(7), np.zeros(7), 2000.0)
    wait_until(lambda: len(ros.cmds) and np.allclose(ros.cmds[-1], ref, atol=TOL, rtol=0), what='loaded command')

    # data without the payload: refused with the reason, the identified payload stays
    res, _ = identify_while_streaming(ros, payload_samples(model, 4.0, payload=False, seed=1), start=3000.0)
    assert not res.success and 'payload unchanged' in res.message, res.message
    assert 'not positive' in res.message or 'bad fit' in res.message, res.message   # the fit said no
    assert node.get_parameter('payload.mass').value == mass
    values = ros.diag_values
    wait_until(lambda: 'refused' in values().get('payload_identification_last', ''), what='diagnostics')
    assert values()['payload_identifications_total'] == str(1 + sum(r.success for r in late))


def test_identify_refused_at_once_without_link_or_efforts(ros, xml):
    ros.start(robot_description=xml, measured_effort='none', **{'identify.link': 'hand'})
    fut = call_async(ros, Trigger, '/dynamics_node/identify_payload', Trigger.Request())
    wait_until(fut.done, what='answer')
    assert not fut.result().success and "measured_effort is 'none'" in fut.result().message
    assert all(r.successful for r in ros.set_params(**{'measured_effort': 'total', 'identify.link': ''}))
    fut = call_async(ros, Trigger, '/dynamics_node/identify_payload', Trigger.Request())
    wait_until(fut.done, what='answer')
    assert not fut.result().success and 'set identify.link' in fut.result().message
    res = ros.set_params(**{'identify.link': 'base_link'})[0]   # checked on set against the model
    assert not res.successful and 'not a link that moves a controlled joint' in res.reason
    assert all(r.successful for r in ros.set_params(**{'identify.link': 'hand'}))


def _request(**values):
    req = SetParametersAtomically.Request()
    req.parameters = [Parameter(k.replace('__', '.'), value=v).to_parameter_msg() for k, v in values.items()]
    return req


def test_set_payload_service(ros, xml):
    node = ros.start(robot_description=xml)
    q = np.linspace(0.2, -0.4, 7)
    name = '/dynamics_node/set_payload'
    fut = call_async(ros, SetParametersAtomically, name,
                     _request(payload__link='hand', payload__mass=MASS, payload__com=COM, payload__inertia=INERTIA))
    wait_until(fut.done, what='set_payload')
    assert fut.result().result.successful, fut.result().result.reason
    assert node.get_parameter('payload.mass').value == MASS and list(node.get_parameter('payload.inertia').value) == \
        INERTIA
    ref = Oracle(with_payload(xml, 'hand', MASS, COM, INERTIA), joints=JOINTS).gravity(q)
    np.testing.assert_allclose(ros.send(JOINTS, q), ref, atol=TOL, rtol=0)
    for values, why in [(dict(payload__link='hand', payload__mass=2.0, payload__com=COM), 'payload.inertia required'),
                        (dict(payload__link='hand', payload__mass=2.0, payload__com=COM,
                              payload__inertia=[1e-3, 0.0, 0.0, 1e-3, 0.0, 1e-2]), 'triangle inequality'),
                        (dict(payload__link='no_link', payload__mass=2.0, payload__com=COM, payload__inertia=INERTIA),
                         'not a link')]:
        fut = call_async(ros, SetParametersAtomically, name, _request(**values))
        wait_until(fut.done, what='set_payload')
        assert not fut.result().result.successful and why in fut.result().result.reason
    assert node.get_parameter('payload.mass').value == MASS   # refused: unchanged
    np.testing.assert_allclose(ros.send(JOINTS, q), ref, atol=TOL, rtol=0)
    fut = call_async(ros, SetParametersAtomically, name, _request(payload__link='', payload__mass=0.0))
    wait_until(fut.done, what='clear')
    assert fut.result().result.successful
    np.testing.assert_allclose(ros.send(JOINTS, q), Oracle(xml, joints=JOINTS).gravity(q), atol=TOL, rtol=0)


def test_gravity_topic_follow_stale_fallback(ros, xml):
    ros.start(robot_description=xml, gravity_topic='/base_gravity', gravity_timeout=0.5, diagnostics_period=0.1)
    pub = ros.t.create_publisher(Vector3Stamped, '/base_gravity', QoSProfile(depth=10,
                                                                            reliability=ReliabilityPolicy.RELIABLE))
    wait_until(lambda: pub.get_subscription_count() >= 1, what='gravity subscriber')
    q = np.linspace(-0.3, 0.5, 7)
    down, wall = Oracle(xml, joints=JOINTS).gravity(q), Oracle(xml, joints=JOINTS, gravity=(0, -9.81, 0)).gravity(q)
    np.testing.assert_allclose(ros.send(JOINTS, q), down, atol=TOL, rtol=0)

    def publish(x, y, z, frame=''):
        msg = Vector3Stamped()
        msg.header.frame_id = frame
        msg.vector.x, msg.vector.y, msg.vector.z = float(x), float(y), float(z)
        pub.publish(msg)

    def follows(ref):
        def ok():
            publish(0.0, -9.81, 0.0) if ref is wall else None
            return np.allclose(ros.send(JOINTS, q), ref, atol=TOL, rtol=0)
        wait_until(ok, what='commands with the expected gravity')

    follows(wall)
    # a flood of bad vectors: rejected, counted, logged boundedly; the last valid one stays
    src = ros.node.features.get('gravity').source

    def settled():   # the valid vectors follows() published are all in (one arriving in the flood would count)
        r0 = src.received
        time.sleep(0.3)
        return src.received == r0
    wait_until(settled, what='valid vectors delivered')
    accepted, t0 = src.received - src.rejected, time.monotonic()
    for k in range(200):  # one at a time: depth 1 keeps only the newest
        r0 = src.received
        publish(*[(math.nan, 0.0, 0.0), (0.0, 0.0, 1e3), (0.0, 0.0, -9.81, 'hand')][k % 3])
        wait_until(lambda r0=r0: src.received > r0, what='gravity message taken')
    assert src.rejected >= 200
    time.sleep(0.2)  # the log lines reach /rosout
    lines = sum('rejected' in line and 'gravity' in line for line in ros.logs)
    assert 1 <= lines <= 2 + (time.monotonic() - t0) / 2.0   # one per 2 s (LOG_THROTTLE_S)
    assert np.allclose(src.vector, [0, -9.81, 0]) and src.received - src.rejected == accepted  # the last valid one
    # stale: back to the gravity parameter, said once and shown in the diagnostics
    wait_until(lambda: np.allclose(ros.send(JOINTS, q), down, atol=TOL, rtol=0), what='fallback')
    wait_until(lambda: ros.diag_values().get('gravity_source') == 'parameter (fallback: topic stale)',
               what='fallback diagnostics')
    assert ros.diag_level() >= 1
    wait_until(lambda: any('using the gravity parameter' in line for line in ros.logs), what='fallback log')
    assert sum('using the gravity parameter' in line for line in ros.logs) == 1
    follows(wall)   # and back
    wait_until(lambda: ros.diag_values().get('gravity_source') == 'topic /base_gravity',
               what='following diagnostics')


def test_robot_compensates_gravity_matches_rnea_minus_g(ros, xml):
    node = ros.start(robot_description=xml, robot_compensates_gravity=True, include_velocity_terms=True)
    o = Oracle(xml, joints=JOINTS)
    rng = np.random.default_rng(4)
    for _ in range(3):
        q, qd = rng.uniform(-1, 1, 7), rng.uniform(-1, 1, 7)
        np.testing.assert_allclose(ros.send(JOINTS, q, qd), o.rnea(q, qd, np.zeros(7)) - o.gravity(q),
                                   atol=TOL, rtol=0)
    # feedforward: the law's gravity term (at the desired state) is left out as well
    desired = ros.t.create_publisher(JointTrajectory, '/dynamics_node/desired', 10)
    wait_until(lambda: desired.get_subscription_count() >= 1, what='desired subscriber')
    assert all(r.successful for r in ros.set_params(mode='feedforward', kp=[5.0], desired_timeout=60.0))
    qd_, q_d, qd_d, qdd_d = rng.uniform(-1, 1, 7), rng.uniform(-1, 1, 7), rng.uniform(-1, 1, 7), rng.uniform(-1, 1, 7)
    desired.publish(JointTrajectory(joint_names=JOINTS, points=[JointTrajectoryPoint(
        positions=q_d.tolist(), velocities=qd_d.tolist(), accelerations=qdd_d.tolist())]))
    wait_until(lambda: node.core.desired is not None, what='desired state')
    ref = o.rnea(q_d, qd_d, qdd_d) - o.gravity(q_d) + 5.0 * (q_d - q)
    np.testing.assert_allclose(ros.send(JOINTS, q, qd_), ref, atol=TOL, rtol=0)
    # off again: gravity is back in the command
    assert all(r.successful for r in ros.set_params(robot_compensates_gravity=False))
    np.testing.assert_allclose(ros.send(JOINTS, q, qd_), ref + o.gravity(q_d), atol=TOL, rtol=0)


def test_identify_static_poses_gives_a_point_mass(ros, xml):
    """identify.mode static: the arm held still in a few poses; mass and CoM only, so payload.inertia
    is set empty (a point mass) and the summary says what was not determined."""
    node = ros.start(robot_description=xml, **{'identify.link': 'hand', 'identify.duration': 1.2,
                                               'identify.mode': 'static'})
    model = load_urdf(xml)
    loaded = model.with_body_inertias(model.J_links)
    loaded.set_payload('hand', MASS, COM, INERTIA)
    rng = np.random.default_rng(6)
    poses = rng.uniform(model.position_lower * 0.7, model.position_upper * 0.7, (8, 7))
    t = np.arange(8 * 40) * 0.005                     # 40 samples (0.2 s) per pose
    q = np.repeat(poses, 40, axis=0)
    zero = np.zeros_like(q)
    res, _ = identify_while_streaming(ros, (t, q, zero, loaded.inverse_dynamics(q, zero, zero)))
    assert res.success and 'inertia not determined (point mass)' in res.message, res.message
    assert node.get_parameter('payload.mass').value == pytest.approx(MASS, rel=1e-6)
    assert np.allclose(node.get_parameter('payload.com').value, COM, atol=1e-6)
    assert len(node.get_parameter('payload.inertia').value) == 0


def test_one_payload_rule_three_ways(ros, xml):
    """The same payloads through ~/set_payload, a parameter set of payload.* over DDS (the
    node's parameter services, as `ros2 param set` uses them) and Model.set_payload: the same
    answer each way (Model.check_payload is the one rule). A link that no controlled joint
    moves was refused by the service and taken by the parameters before."""
    from rclpy.parameter_client import AsyncParameterClient
    ros.start(robot_description=xml)
    params = AsyncParameterClient(ros.t, '/dynamics_node')
    assert params.wait_for_services(timeout_sec=TIMEOUT)
    bad_inertia = [1e-3, 0.0, 0.0, 1e-3, 0.0, 1e-2]   # triangle inequality
    cases = [('hand', MASS, COM, INERTIA, True),
             ('base_link', MASS, COM, INERTIA, False),     # fixed to the world: changes no torque
             ('no_link', MASS, COM, INERTIA, False),
             ('hand', MASS, COM, bad_inertia, False),
             ('hand', -1.0, COM, INERTIA, False),
             ('link3', 0.4, [0.0, 0.0, 0.1], INERTIA, True)]

    def by_service(link, mass, com, inertia):
        fut = call_async(ros, SetParametersAtomically, '/dynamics_node/set_payload',
                         _request(payload__link=link, payload__mass=mass, payload__com=com, payload__inertia=inertia))
        wait_until(fut.done, what='set_payload')
        return fut.result().result.successful

    def by_parameters(link, mass, com, inertia):
        fut = params.set_parameters_atomically([
            Parameter('payload.link', value=link), Parameter('payload.mass', value=float(mass)),
            Parameter('payload.com', value=[float(v) for v in com]),
            Parameter('payload.inertia', value=[float(v) for v in inertia])])
        wait_until(fut.done, what='set_parameters_atomically')
        return fut.result().result.successful

    def by_model(link, mass, com, inertia):
        try:
            load_urdf(xml).set_payload(link, mass, com, inertia)
        except ValueError:
            return False
        return True

    for link, mass, com, inertia, expected in cases:
        answers = [way(link, mass, com, inertia) for way in (by_service, by_parameters, by_model)]
        assert answers == [expected] * 3, (link, mass, inertia, answers)
    # `ros2 param set payload.link <link>` alone, on the payload set last: the same rule
    for link, expected in (('base_link', False), ('hand', True)):
        fut = params.set_parameters([Parameter('payload.link', value=link)])
        wait_until(fut.done, what='set_parameters')
        assert fut.result().results[0].successful == expected == by_model(link, 0.4, [0.0, 0.0, 0.1], INERTIA), link
    node = ros.node
    assert node.get_parameter('payload.link').value == 'hand' and node.get_parameter('payload.mass').value == 0.4
    q = np.linspace(0.2, -0.4, 7)
    ref = Oracle(with_payload(xml, 'hand', 0.4, [0.0, 0.0, 0.1], INERTIA), joints=JOINTS).gravity(q)
    np.testing.assert_allclose(ros.send(JOINTS, q), ref, atol=TOL, rtol=0)
