"""The features' work after the command run in executor tasks (DynamicsNode._after_command, as
run.py spins the node with the EventsExecutor): over real DDS every dynamics topic and the
observer's estimates still come with the values of their state, in order, the newest state's
terms always; in process, with the tasks held back: a newer state's command goes out before the
older state's work, whose dynamics terms it replaces (the observer's steps are all kept), a
settings change runs the queued work first, and so do destroying the node and a backlog."""
import numpy as np
import pytest

rclpy = pytest.importorskip('rclpy')

from rclpy.serialization import serialize_message  # noqa: E402
from sensor_msgs.msg import JointState  # noqa: E402
from std_msgs.msg import Float64MultiArray  # noqa: E402

from lie_dynamics import default_urdf_path  # noqa: E402
from test_node import Harness, wait_until  # noqa: E402

TERMS = ('gravity', 'coriolis', 'mass_matrix', 'jacobian')
JOINTS = [f'joint{i}' for i in range(1, 8)]
T0_NS = 1_700_000_000 * 10 ** 9
EVERY = {'urdf_path': default_urdf_path(), 'joints': JOINTS, 'dynamics.publish': list(TERMS), 'dynamics.rate': 0.0,
         'publish_joint_state': True}


@pytest.fixture
def ros():
    """The harness (its executor's create_task runs the queued work, as the EventsExecutor's does
    when run.py spins the node) with subscribers of the dynamics topics and the estimates."""
    h = Harness()
    h.dyn = {t: [] for t in TERMS}
    for t in TERMS:
        h.t.create_subscription(JointState if t in ('gravity', 'coriolis') else Float64MultiArray,
                                f'/dynamics_node/dynamics/{t}', h.dyn[t].append, 1000)
    h.ext = []
    h.t.create_subscription(JointState, '/dynamics_node/external_torques', h.ext.append, 1000)
    yield h
    h.close()


def states(model, n, seed):
    """n stamped states 1 ms apart: (stamp ns, q, qd, efforts g(q))."""
    rng = np.random.default_rng(seed)
    lo, hi = np.maximum(model.position_lower, -2.0), np.minimum(model.position_upper, 2.0)
    out = []
    for k in range(n):
        q = rng.uniform(lo, hi)
        out.append((T0_NS + k * 1_000_000, q, rng.uniform(-0.5, 0.5, model.n), model.gravity(q)))
    return out


def message(stamp, q, qd, e):
    m = JointState(name=JOINTS, position=q.tolist(), velocity=qd.tolist(), effort=e.tolist())
    m.header.stamp.sec, m.header.stamp.nanosec = divmod(stamp, 10 ** 9)
    return m


def stamp_of(msg):
    return msg.header.stamp.sec * 10 ** 9 + msg.header.stamp.nanosec


def test_every_topic_after_the_command_over_dds(ros):
    node = ros.start(**EVERY)
    node.defer_to(ros.ex)   # as run.py does for the EventsExecutor
    wait_until(lambda: all(ros.t.count_publishers(f'/dynamics_node/dynamics/{t}') for t in TERMS)
               and ros.t.count_publishers('/dynamics_node/external_torques'), what='publishers')
    model, dyn = node.core.model, node.features.get('dynamics')
    sent = states(model, 60, 3)
    ros.publish_msg_processed(message(*sent[0]))
    for s in sent[1:]:   # a burst: states arrive while the last one's work is queued
        ros.js_pub.publish(message(*s))
    by_stamp = {s[0]: s for s in sent}
    last = sent[-1][0]
    # the newest state's terms always come (older ones may be replaced by it while queued)
    wait_until(lambda: all(ros.dyn[t] and stamp_of_term(ros, t, -1) == last for t in ('gravity', 'coriolis'))
               and len(ros.dyn['mass_matrix']) and ros.efforts and stamp_of(ros.efforts[-1]) == last,
               what="the last state's terms")
    commanded = [stamp_of(m) for m in ros.efforts]   # every command, with its state's stamp
    assert commanded == sorted(commanded) and len(commanded) == node.core.count.accepted
    for t in ('gravity', 'coriolis'):
        got = [stamp_of(m) for m in ros.dyn[t]]
        assert got == sorted(got) and set(got) <= set(commanded)
        for m in ros.dyn[t]:
            _, q, qd, _ = by_stamp[stamp_of(m)]
            want = model.gravity(q) if t == 'gravity' else model.coriolis_term(q, qd)
            np.testing.assert_array_equal(m.position, q)
            np.testing.assert_array_equal(m.effort, want)
    # the matrices carry no stamp: each is the model's at one of the states sent, the last the newest's
    for t, term in (('mass_matrix', lambda q: model.mass_matrix(q)),
                    ('jacobian', lambda q: model.jacobian(q, dyn.link, dyn.frame))):
        wanted = [term(s[1]).ravel() for s in sent]
        wait_until(lambda t=t, w=wanted[-1]: len(ros.dyn[t]) and np.array_equal(ros.dyn[t][-1].data, w), what=t)
        for m in ros.dyn[t]:
            assert any(np.array_equal(np.asarray(m.data), w) for w in wanted)
    # the observer's steps are never dropped: an estimate for every state it took, in order
    wait_until(lambda: len(ros.ext) == node.contact_monitor.samples and stamp_of(ros.ext[-1]) == last,
               what='the estimates')
    got = [stamp_of(m) for m in ros.ext]
    assert got == sorted(got) and set(got) == set(commanded)


def stamp_of_term(ros, t, k):
    return stamp_of(ros.dyn[t][k])


class HeldTasks:
    """An executor whose tasks run only when the test says (create_task, as the EventsExecutor's)."""

    def __init__(self):
        self.tasks = []

    def create_task(self, fn):
        self.tasks.append(fn)

    def run(self):
        while self.tasks:
            self.tasks.pop(0)()


@pytest.fixture
def held():
    h = Harness()
    yield h
    h.close()


def test_a_newer_state_replaces_queued_terms_not_estimates(held):
    node = held.start(**EVERY)
    ex = HeldTasks()
    node.defer_to(ex)
    dyn, monitor = node.features.get('dynamics'), node.contact_monitor
    sent = [bytes(serialize_message(message(*s))) for s in states(node.core.model, 6, 5)]
    node.on_joint_state(sent[0])
    assert node.core.count.accepted == 1 and len(ex.tasks) == 1   # the command is out, its work queued
    assert sum(dyn.published.values()) == 0 and monitor.samples == 0
    node.on_joint_state(sent[1])   # before the first state's work ran
    assert node.dropped_steps == 1 and len(ex.tasks) == 1   # the terms' one step
    ex.run()
    assert dyn.published == {t: 1 for t in TERMS}   # only the newer state's terms
    assert monitor.samples == 2   # both estimates
    # a settings change: the queued work runs first, under the settings it was queued with
    node.on_joint_state(sent[2])
    assert all(r.successful for r in held.set_params(**{'dynamics.publish': ['gravity']}))
    node.on_joint_state(sent[3])   # runs state 2's four terms, then queues state 3's gravity
    assert dyn.published == {t: 2 for t in TERMS} and monitor.samples == 3
    ex.run()
    assert dyn.published == {'gravity': 3, 'coriolis': 2, 'mass_matrix': 2, 'jacobian': 2}
    assert monitor.samples == 4
    # what is still queued when the node goes is run, while its publishers exist
    node.on_joint_state(sent[4])
    assert monitor.samples == 4 and ex.tasks
    held.on_spin_thread(held.ex.remove_node, node)
    node.destroy_node()
    held.node = None
    assert monitor.samples == 5 and dyn.published['gravity'] == 4


def test_a_backlog_is_run_in_the_callback(held):
    node = held.start(**EVERY)
    ex = HeldTasks()
    node.defer_to(ex)
    monitor = node.contact_monitor
    from lie_dynamics.ros.node import LATER_MAX_STEPS
    first = LATER_MAX_STEPS - 1   # queued: one observer step per state, the newest state's terms (one step)
    for k, s in enumerate(states(node.core.model, first + 3, 9)):   # the tasks never run
        node.on_joint_state(bytes(serialize_message(message(*s))))
        assert monitor.samples == (0 if k < first else first + 1)   # all run in the callback once, then queued


def test_without_a_later_executor_the_work_runs_at_once(held):
    node = held.start(**EVERY)
    dyn, monitor = node.features.get('dynamics'), node.contact_monitor
    for k, s in enumerate(states(node.core.model, 3, 7)):
        node.on_joint_state(bytes(serialize_message(message(*s))))
        assert dyn.published == {t: k + 1 for t in TERMS} and monitor.samples == k + 1
