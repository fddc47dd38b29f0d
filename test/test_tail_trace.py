"""bench.probes.tail_trace's analysis on a hand-written run: a reply above the threshold is split
into its parts and the node's work that overlapped its wait for the callback is named by kind;
a gap between replies is reported with what the driver sent and what the node ran in it."""
from bench.probes.tail_trace import gaps, hook_steps, tails

US, MS = 1_000, 1_000_000
STALL = range(9, 28)   # states sent while the node is stopped: never answered


def _run():
    """40 states 1 ms apart (two of warm-up). Each is taken 50 µs after its send, published 100 µs
    later and answered 150 µs after that, but: state 5 waits behind a task of state 4's work
    (4.25-5.25 ms) and is answered 900 µs after its send; the node stops 20 ms inside state 8's
    callback (its sampler thread woke 19 ms late), so states 9-27 get no answer."""
    send = [k * MS for k in range(40)]
    spans, reply = [], []
    for k, s in enumerate(send):
        if k in STALL:
            reply.append(0)
            continue
        start = s + (400 if k == 5 else 50) * US
        published = start + (20 * MS - 10 * US if k == 8 else 100 * US)
        spans.append(('callback', start, published + 100 * US, (s, published), 0))
        reply.append(published + (400 if k == 5 else 150) * US)
    spans.append(('task', 4 * MS + 250 * US, 5 * MS + 250 * US, 2, 0))
    spans.append(('gc', 4 * MS + 300 * US, 4 * MS + 350 * US, 0))
    return dict(send=send, reply=reply, W=2, reply_times=sorted(r for r in reply if r),
                node={'spans': spans, 'late': [(9 * MS, 28 * MS)], 'stacks': []},
                machine=[[0, 0, 0, 0, 0], [40 * MS, 1, 2000, 0, 0]])


def test_a_tail_reply_names_the_work_it_waited_behind():
    out = tails(_run(), threshold_ns=500 * US)
    assert [round(x[0]) for x in out] == [900, 20190]   # states 5 and 8, µs
    total, to_callback, to_command, back, busy, _ = out[0]
    assert (round(to_callback), round(to_command), round(back)) == (400, 100, 400)
    assert busy == {'task': 250.0}   # the task until 5.25 ms; the collection was over before 5 ms


def test_a_gap_between_replies_says_which_side_stopped():
    (line,) = gaps(_run(), 15 * MS)
    assert line.startswith('  gap 20.9 ms at 5 ms: 21 states sent (longest send gap 1.0 ms); '
                           "node spans > 1 ms [('callback', 0.8, 20.1)]; sampler late [(1.7, 19.0)]; "
                           'machine: steal 10 ms')


def test_the_step_hooks_wrap_the_features_steps_and_come_off():
    """The probe's spans of the work after the command wrap the features' step methods as they
    are now (a renamed step would otherwise fail only when the probe's node starts)."""
    from lie_dynamics.ros.features.contact_topics import ContactTopics
    from lie_dynamics.ros.features.dynamics_topics import DynamicsTopics
    before = (DynamicsTopics._publish, ContactTopics.on_sample)
    seen = []

    class Recorder:
        def step(self, kind, fn, *args):
            seen.append((kind, fn, args))

    undo = hook_steps(Recorder())
    try:
        DynamicsTopics._publish('feature', 'sample')
        ContactTopics.on_sample('feature', 'sample')
    finally:
        undo()
    assert seen == [('step:dynamics', before[0], ('feature', 'sample')),
                    ('step:observer', before[1], ('feature', 'sample'))]
    assert (DynamicsTopics._publish, ContactTopics.on_sample) == before
