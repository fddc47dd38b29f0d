"""The dynamics terms for other nodes (~/dynamics/*, dynamics_topics.py) over real DDS (own domain,
conftest.py), against Pinocchio at the state sent: a Panda with its fingers locked (a mimic
pair) and a payload on the hand, on a wall; the bundled arm for the rate, the refusals and the
non-finite guard, and gravity from a topic with robot_compensates_gravity."""
import glob
import math
import os
import re
import subprocess
import sys

import numpy as np
import pytest

rclpy = pytest.importorskip('rclpy')

from rclpy.parameter import Parameter  # noqa: E402
from sensor_msgs.msg import JointState  # noqa: E402
from std_msgs.msg import Float64MultiArray  # noqa: E402

from lie_dynamics import default_urdf_path, load_urdf  # noqa: E402
from lie_dynamics.ros.features.dynamics_topics import tip_link  # noqa: E402
from oracle import Oracle  # noqa: E402
from robots import with_payload  # noqa: E402
from test_node import Harness, wait_until  # noqa: E402

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
ERD = next(iter(glob.glob(os.path.join(sys.prefix, 'lib', 'python3*', 'site-packages', 'cmeel.prefix', 'share',
                                       'example-robot-data', 'robots'))), None)
TERMS = ('gravity', 'coriolis', 'mass_matrix', 'jacobian')
ALL = list(TERMS)
T0_NS = 1_700_000_000 * 10 ** 9
ARM_JOINTS = [f'joint{i}' for i in range(1, 8)]
PANDA = [f'panda_joint{i}' for i in range(1, 8)]
PAYLOAD = dict(link='panda_hand', mass=1.3, com=[0.01, -0.02, 0.08], inertia=[0.004, 0.0002, 0.0, 0.005, 0.0001, 0.003])
WALL = (0.0, -9.81, 0.0)
TOL = 1e-10


@pytest.fixture
def ros():
    h = Harness()
    h.dyn = {t: [] for t in TERMS}
    for t in TERMS:
        msg_type = JointState if t in ('gravity', 'coriolis') else Float64MultiArray
        h.t.create_subscription(msg_type, f'/dynamics_node/dynamics/{t}', h.dyn[t].append, 1000)
    yield h
    h.close()


def stamped(names, q, qd, ns):
    msg = JointState(name=list(names), position=[float(x) for x in q], velocity=[float(x) for x in qd])
    msg.header.stamp.sec, msg.header.stamp.nanosec = ns // 10 ** 9, ns % 10 ** 9
    return msg


def send(ros, msg):
    """Publish one joint_states message and wait until the node took it (re-sent if lost while
    discovery completes)."""
    return ros.publish_msg_processed(msg)


def stamp_ns(msg):
    return msg.header.stamp.sec * 10 ** 9 + msg.header.stamp.nanosec


def counts(ros):
    return [len(ros.dyn[t]) for t in TERMS]


def wait_publishers(ros, terms):
    wait_until(lambda: all(ros.t.count_publishers(f'/dynamics_node/dynamics/{t}') >= 1 for t in terms)
               and all(ros.t.count_subscribers(f'/dynamics_node/dynamics/{t}') >= 1 for t in terms),
               what='dynamics publishers')


def matrix(msg):
    rows, cols = msg.layout.dim
    assert rows.stride == rows.size * cols.size and cols.stride == cols.size and msg.layout.data_offset == 0
    return np.asarray(msg.data).reshape(rows.size, cols.size), rows.label, cols.label


def close(a, b):
    a, b = np.asarray(a), np.asarray(b)
    assert a.shape == b.shape, (a.shape, b.shape)
    np.testing.assert_allclose(a, b, rtol=0, atol=TOL * max(1.0, np.abs(b).max()))


def docs_snippet():
    """The Python block of docs/node.md's 'Dynamics for other nodes' section."""
    with open(os.path.join(ROOT, 'docs', 'node.md'), encoding='utf-8') as fh:
        text = fh.read()
    section = text.split('## Dynamics for other nodes', 1)[1]
    return re.search(r'```python\n(.*?)```', section, re.S).group(1)


@pytest.mark.skipif(ERD is None, reason='example-robot-data is a test dependency')
def test_the_four_topics_match_pinocchio_at_the_state_sent(ros):
    path = os.path.join(ERD, 'panda_description', 'urdf', 'panda.urdf')
    xml = open(path, encoding='utf-8').read()
    node = ros.start(urdf_path=path, joints=PANDA, gravity=list(WALL),
                     **{'payload.link': PAYLOAD['link'], 'payload.mass': PAYLOAD['mass'],
                        'payload.com': PAYLOAD['com'], 'payload.inertia': PAYLOAD['inertia'],
                        'dynamics.publish': ALL, 'dynamics.rate': 0.0})
    wait_publishers(ros, TERMS)
    # the documented subscriber, on the tester node
    latest = {}
    exec(docs_snippet(), {'node': ros.t, 'latest': latest})  # noqa: S102 - the docs' own lines
    xml_p = with_payload(xml, PAYLOAD['link'], PAYLOAD['mass'], PAYLOAD['com'], PAYLOAD['inertia'])
    tip = tip_link(node.core.model)
    rng = np.random.default_rng(23)
    k = 0
    for frame, link in (('world_aligned', ''), ('local', 'panda_hand_tcp'), ('world', 'panda_link5')):
        if frame != 'world_aligned':
            assert all(r.successful for r in ros.set_params(**{'dynamics.jacobian_frame': frame,
                                                                'dynamics.link': link}))
        for _ in range(3):
            q = rng.uniform(-1.5, 1.5, 7)
            q[3] = rng.uniform(-2.5, -0.5)
            qd = rng.uniform(-1.5, 1.5, 7)
            finger = float(rng.uniform(0.0, 0.04))   # locked joint, measured; its mimic follows
            ns = T0_NS + k * 1_000_000
            want = [c + 1 for c in counts(ros)]
            send(ros, stamped(PANDA + ['panda_finger_joint1'], list(q) + [finger], list(qd) + [0.0], ns))
            wait_until(lambda want=want: counts(ros) == want, what='one message per topic')
            oracle = Oracle(xml_p, joints=PANDA, locked={'panda_finger_joint1': finger}, gravity=WALL)
            g, c = ros.dyn['gravity'][-1], ros.dyn['coriolis'][-1]
            for msg in (g, c):
                assert stamp_ns(msg) == ns and list(msg.name) == PANDA
                assert np.array_equal(msg.position, q) and np.array_equal(msg.velocity, qd)
            close(g.effort, oracle.gravity(q))
            close(c.effort, oracle.nonlinear(q, qd) - oracle.gravity(q))
            M, rows, cols = matrix(ros.dyn['mass_matrix'][-1])
            assert rows == 'rows: ' + ','.join(PANDA) and cols == 'cols: ' + ','.join(PANDA)
            close(M, oracle.crba(q))
            J, rows, cols = matrix(ros.dyn['jacobian'][-1])
            assert rows == f"rows: vx,vy,vz,wx,wy,wz; frame: {frame}; link: {link or tip}"
            assert cols == 'cols: ' + ','.join(PANDA)
            close(J, oracle.frame_jacobian(q, link or tip, frame))
            wait_until(lambda: 'J' in latest and latest['J'].shape == (6, 7) and 'M' in latest, what='snippet')
            k += 1
        wait_until(lambda J=J, M=M: np.abs(latest['J'] - J).max() == 0 and np.abs(latest['M'] - M).max() == 0,
                   what='the snippet rebuilt M and J')
    assert node.core.count.rejected == 0
    wait_until(lambda: ros.diag_values().get('dynamics_topics', '').startswith('gravity, coriolis'),
               what='diagnostics')


def start_arm(ros, **params):
    node = ros.start(urdf_path=default_urdf_path(), **params)
    return node


def arm_state(k, qd=None):
    q = np.linspace(-0.5, 0.7, 7) + 0.01 * k
    return stamped(ARM_JOINTS, q, np.full(7, 0.3) if qd is None else qd, T0_NS + k * 1_000_000)


def test_rate_zero_is_one_message_per_accepted_state_and_the_rate_thins_by_stamp(ros):
    start_arm(ros, **{'dynamics.publish': ALL, 'dynamics.rate': 0.0})
    wait_publishers(ros, TERMS)
    for k in range(5):
        send(ros, arm_state(k))
    wait_until(lambda: counts(ros) == [5] * 4, what='one per state')
    assert [stamp_ns(m) for m in ros.dyn['gravity']] == [T0_NS + k * 1_000_000 for k in range(5)]
    # rejected: a NaN position, and a state older than the last accepted one
    bad = arm_state(5)
    bad.position[2] = math.nan
    send(ros, bad)
    send(ros, arm_state(1))
    send(ros, arm_state(6))
    wait_until(lambda: counts(ros) == [6] * 4, what='the next good state')
    assert stamp_ns(ros.dyn['coriolis'][-1]) == T0_NS + 6 * 1_000_000
    assert ros.node.core.count.rejected == 2
    # 100 Hz on 1 kHz stamps: every tenth state; only the terms listed
    assert all(r.successful for r in ros.set_params(**{'dynamics.rate': 100.0, 'dynamics.publish': ['gravity']}))
    for k in range(7, 57):
        send(ros, arm_state(k))
    wait_until(lambda: len(ros.dyn['gravity']) == 11, what='five more')
    assert [stamp_ns(m) for m in ros.dyn['gravity'][6:]] == [T0_NS + k * 1_000_000 for k in range(7, 57, 10)]
    assert counts(ros)[1:] == [6] * 3
    # off: nothing more
    off = Parameter('dynamics.publish', Parameter.Type.STRING_ARRAY, [])  # an empty list has no type of its own
    assert ros.node.set_parameters([off])[0].successful
    for k in range(57, 80):
        send(ros, arm_state(k))
    assert len(ros.dyn['gravity']) == 11
    wait_until(lambda: ros.diag_values().get('dynamics_topics') == 'off', what='diagnostics off')


def test_a_non_finite_term_is_not_published(ros):
    start_arm(ros, **{'dynamics.publish': ['gravity', 'coriolis'], 'dynamics.rate': 0.0})
    wait_publishers(ros, ('gravity', 'coriolis'))
    send(ros, arm_state(0))
    send(ros, arm_state(1, qd=np.full(7, 1e200)))   # C(q, qd) qd overflows; g(q) does not
    send(ros, arm_state(2))
    wait_until(lambda: len(ros.dyn['gravity']) == 3 and len(ros.dyn['coriolis']) == 2, what='messages')
    assert [stamp_ns(m) for m in ros.dyn['coriolis']] == [T0_NS, T0_NS + 2_000_000]
    assert all(np.all(np.isfinite(m.effort)) for m in ros.dyn['coriolis'])
    wait_until(lambda: any('~/dynamics/coriolis not published' in line for line in ros.logs), what='log line')


def test_bad_parameters_are_refused_and_the_old_values_kept(ros):
    node = start_arm(ros, **{'dynamics.publish': ['jacobian'], 'dynamics.link': 'flange'})
    for change, why in (({'dynamics.publish': ['gravity', 'inertia']}, "unknown 'inertia'"),
                        ({'dynamics.publish': ['gravity', 'gravity']}, 'twice'),
                        ({'dynamics.rate': -1.0}, 'dynamics.rate'),
                        ({'dynamics.link': 'no_such_link'}, "dynamics.link 'no_such_link'"),
                        ({'dynamics.jacobian_frame': 'global'}, 'dynamics.jacobian_frame')):
        res = node.set_parameters_atomically([Parameter(k, value=v) for k, v in change.items()])
        assert not res.successful and why in res.reason, (change, res.reason)
    assert node.get_parameter('dynamics.publish').value == ['jacobian']
    assert node.get_parameter('dynamics.rate').value == 100.0
    assert node.get_parameter('dynamics.link').value == 'flange'
    assert node.get_parameter('dynamics.jacobian_frame').value == 'world_aligned'
    wait_publishers(ros, ('jacobian',))
    send(ros, arm_state(0))
    wait_until(lambda: len(ros.dyn['jacobian']) == 1, what='a Jacobian')
    J, rows, _ = matrix(ros.dyn['jacobian'][0])
    assert rows.endswith('frame: world_aligned; link: flange')
    model = load_urdf(default_urdf_path(), joints=ARM_JOINTS)
    close(J, Oracle(open(default_urdf_path()).read(), joints=ARM_JOINTS).frame_jacobian(
        np.asarray(arm_state(0).position), 'flange', 'world_aligned'))
    assert tip_link(model) == 'tool0'


@pytest.mark.parametrize('arg, why', [('dynamics.link:=no_such_link', "dynamics.link 'no_such_link'"),
                                      ('dynamics.publish:=[gravity,torque]', "unknown 'torque'")])
def test_start_up_refuses_bad_dynamics_parameters(arg, why):
    proc = subprocess.run([sys.executable, '-m', 'lie_dynamics.dynamics_node', '--ros-args', '-p',
                           f'urdf_path:={default_urdf_path()}', '-p', arg],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2, proc.stderr[-2000:]
    assert why in proc.stderr, proc.stderr[-2000:]


def test_gravity_from_a_topic_and_its_scale_apply_and_robot_compensates_gravity_does_not_zero_g(ros):
    from geometry_msgs.msg import Vector3Stamped
    node = start_arm(ros, gravity_topic='/tilted_gravity', gravity_timeout=60.0, gravity_scale=0.5,
                     robot_compensates_gravity=True, **{'dynamics.publish': ['gravity', 'coriolis'],
                                                        'dynamics.rate': 0.0})
    pub = ros.t.create_publisher(Vector3Stamped, '/tilted_gravity', 10)
    wait_until(lambda: pub.get_subscription_count() >= 1, what='gravity subscriber')
    tilted = (1.2, -0.7, -9.7)
    msg = Vector3Stamped()
    msg.vector.x, msg.vector.y, msg.vector.z = tilted
    pub.publish(msg)
    wait_until(lambda: np.allclose(node.core.model.gravity_vector, 0.5 * np.array(tilted)), what='topic gravity')
    wait_publishers(ros, ('gravity', 'coriolis'))
    state = arm_state(0, qd=np.linspace(-1.0, 1.0, 7))
    send(ros, state)
    wait_until(lambda: len(ros.dyn['gravity']) == 1 and len(ros.dyn['coriolis']) == 1, what='messages')
    q, qd = np.asarray(state.position), np.asarray(state.velocity)
    oracle = Oracle(open(default_urdf_path()).read(), joints=ARM_JOINTS, gravity=tuple(0.5 * np.array(tilted)))
    close(ros.dyn['gravity'][0].effort, oracle.gravity(q))          # the model's g(q), not the (zero) command's
    close(ros.dyn['coriolis'][0].effort, oracle.nonlinear(q, qd) - oracle.gravity(q))
    assert np.abs(ros.dyn['gravity'][0].effort).max() > 1.0
