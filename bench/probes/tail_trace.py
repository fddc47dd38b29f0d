"""What sets the round trip's tail (p99) and its stalls: per state, the driver's send and reply
times beside a timeline of the node's executor thread (joint_states callbacks, the tasks of the
work after the command, the timer, the collector's passes) and of the machine (steal, run-queue
wait, CPU and I/O pressure), all on the monotonic clock (perf_counter_ns, one clock for every
process on Linux):

    python -m bench.probes.tail_trace [--seconds 3] [--rounds 3] [--rate 1000]
                                      [--candidates echo,every] [--robot talos_reduced]
                                      [--stall-ms 30] [--no-trajectories] [--out DIR]

The candidates are those of bench.probes.latency_split (the same stream as bench.node_latency:
warm-up without a pause, the node on its own core). Per candidate, for the replies above the
events echo's p99 of the same round: where the time went (to the callback, the node's Python up
to the published command, the way back) and, for the wait before the callback, what the node's
thread was busy with meanwhile (an earlier callback, a task, the timer, a collection) and how
long it waited for a CPU while ready. In each node a sampler thread wakes every 10 ms and notes
when it woke late (the process could not run), with the executor thread's Python stack when a
callback or task had been running for more than --stall-ms. The driver notes the machine's
steal time and pressure every 10 ms and, once no reply came for 50 ms, the system call and wait
channel of each thread of the node and its children (/proc). Every gap of --stall-ms or more
between two replies is printed with what each side did in it, and per run the median length of
each kind of span, the steps of the work after the command among them (the observer; the
dynamics terms, one step per state). --no-trajectories: the dynamics node without its trajectory
process (an experiment: ros/node.py, TRAJECTORIES_JOIN_S). --out keeps the raw timelines (JSON per run).
The probe's own records cost each callback a few µs and two reads of /proc, the echo's too, so
its ratios are not bench.node_latency's: read the parts. A benchmark probe, not a test.
"""
import argparse
import gc
import json
import os
import struct
import sys
import threading
import time
import traceback

import numpy as np

TRACE_ENV = 'LIE_DYNAMICS_TAIL_TRACE'
STALL_ENV = 'LIE_DYNAMICS_TAIL_STALL_MS'
NO_CHILD_ENV = 'LIE_DYNAMICS_TAIL_NO_TRAJECTORIES'
SAMPLE_S = 0.010


def _stamp(buf):
    sec, nsec = struct.unpack_from('<iI', buf, 4)
    return sec * 1_000_000_000 + nsec


def _run_delay_ns(tid):
    """ns this thread has waited on a run queue while ready (schedstat's second field), or 0."""
    try:
        with open(f'/proc/self/task/{tid}/schedstat') as fh:
            return int(fh.read().split()[1])
    except (OSError, IndexError, ValueError):
        return 0


class Timeline:
    """The node process's records: spans (kind, start, end, extra) of its executor thread, the
    sampler's late wake-ups and stacks."""

    def __init__(self):
        self.spans = []
        self.busy = None            # (kind, start) of the span running now on the executor thread
        self.main = threading.get_ident()
        self.main_tid = threading.get_native_id()
        self.late = []              # (expected, woke) of the sampler
        self.stacks = []            # (time, kind, span start, stack text)
        self.stall_ns = int(float(os.environ.get(STALL_ENV, '30')) * 1e6)
        self._stop = False
        gc.callbacks.append(self._gc)
        threading.Thread(target=self._sample, daemon=True, name='tail_sampler').start()

    def _gc(self, phase, info):
        now = time.perf_counter_ns()
        if phase == 'start':
            self._gc_start = now
        else:
            self.spans.append(('gc', self._gc_start, now, info.get('generation', -1)))

    def span(self, kind, fn, *args, extra=None):
        t0 = time.perf_counter_ns()
        d0 = _run_delay_ns(self.main_tid)
        self.busy = (kind, t0)
        try:
            return fn(*args)
        finally:
            self.busy = None
            t1 = time.perf_counter_ns()
            self.spans.append((kind, t0, t1, (extra() if extra else 0), _run_delay_ns(self.main_tid) - d0))

    def step(self, kind, fn, *args):
        """A span inside another one, without its wait for a CPU (no /proc read: a few µs less)."""
        t0 = time.perf_counter_ns()
        try:
            return fn(*args)
        finally:
            self.spans.append((kind, t0, time.perf_counter_ns(), 0, 0))

    def _sample(self):
        step = int(SAMPLE_S * 1e9)
        nxt = time.perf_counter_ns() + step
        noted = None
        while not self._stop:
            time.sleep(max(0.0, (nxt - time.perf_counter_ns()) * 1e-9))
            woke = time.perf_counter_ns()
            if woke - nxt > 2 * step:
                self.late.append((nxt, woke))
            nxt = max(nxt + step, woke)
            busy = self.busy
            if busy is not None and woke - busy[1] > self.stall_ns and noted != busy[1]:
                noted = busy[1]
                frame = sys._current_frames().get(self.main)
                text = ''.join(traceback.format_stack(frame)) if frame is not None else ''
                self.stacks.append((woke, busy[0], busy[1], text))

    def dump(self, path):
        self._stop = True
        with open(path, 'w') as fh:
            json.dump({'spans': self.spans, 'late': self.late, 'stacks': self.stacks}, fh)


def hook_steps(tl):
    """Time the steps of the work after the command, each a span 'step:<what>' inside its task:
    the observer's sample and the dynamics terms of a state (one step). Returns the undo."""
    from lie_dynamics.ros.features.contact_topics import ContactTopics
    from lie_dynamics.ros.features.dynamics_topics import DynamicsTopics
    terms, observe = DynamicsTopics._publish, ContactTopics.on_sample
    DynamicsTopics._publish = lambda self, s: tl.step('step:dynamics', terms, self, s)
    ContactTopics.on_sample = lambda self, s: tl.step('step:observer', observe, self, s)

    def undo():
        DynamicsTopics._publish, ContactTopics.on_sample = terms, observe
    return undo


def serve_dynamics():
    from lie_dynamics.ros import node as node_module
    from lie_dynamics.ros.outputs import Outputs
    tl = Timeline()
    published = [0]
    cls = node_module.DynamicsNode
    on_joint_state, run_later, on_timer = cls.on_joint_state, cls._run_later, cls._on_timer
    command, publish = Outputs.command, Outputs.publish

    def timed_callback(self, msg):
        published[0] = 0
        tl.span('callback', on_joint_state, self, msg, extra=lambda: (_stamp(msg), published[0]))

    def timed_command(self, *args, **kwargs):
        out = command(self, *args, **kwargs)
        published[0] = time.perf_counter_ns()
        return out

    def timed_publish(self, *args):
        out = publish(self, *args)
        published[0] = time.perf_counter_ns()
        return out

    def timed_task(self):
        n = len(self._later)
        tl.span('task', run_later, self, extra=lambda: n - len(self._later))

    def timed_timer(self):
        tl.span('timer', on_timer, self)
    cls.on_joint_state, cls._run_later, cls._on_timer = timed_callback, timed_task, timed_timer
    hook_steps(tl)
    if os.environ.get(NO_CHILD_ENV):   # no trajectory process (an experiment)
        node_module.child_config = lambda node: None
    Outputs.command, Outputs.publish = timed_command, timed_publish
    try:
        return node_module.main(sys.argv[:1] + sys.argv[sys.argv.index('--ros-args'):])
    finally:
        tl.dump(os.environ[TRACE_ENV])


def serve_echo():
    import rclpy
    from sensor_msgs.msg import JointState
    from std_msgs.msg import Float64MultiArray

    from bench.node_latency import CMD, spin_echo
    from lie_dynamics.ros.node import JOINT_STATES_QOS, NO_PUB_EVENTS, NO_SUB_EVENTS
    rclpy.init()
    tl = Timeline()
    node = rclpy.create_node('echo_node')
    pub = node.create_publisher(Float64MultiArray, CMD, 10, event_callbacks=NO_PUB_EVENTS)
    published = [0]

    def echo(msg):
        out = Float64MultiArray()
        out.data = msg.position
        pub.publish(out)
        published[0] = time.perf_counter_ns()

    def on_js(msg):
        s = msg.header.stamp
        tl.span('callback', echo, msg, extra=lambda: (s.sec * 1_000_000_000 + s.nanosec, published[0]))

    node.create_subscription(JointState, 'joint_states', on_js, JOINT_STATES_QOS, event_callbacks=NO_SUB_EVENTS)
    spin_echo(node, lambda: tl.dump(os.environ[TRACE_ENV]))


def _machine():
    """(steal ticks, cpu some us, io some us, io full us) now."""
    with open('/proc/stat') as fh:
        steal = int(fh.readline().split()[8])
    out = [steal]
    for name in ('cpu', 'io'):
        try:
            with open(f'/proc/pressure/{name}') as fh:
                lines = fh.read().split('\n')
            out += [int(line.rsplit('total=', 1)[1]) for line in lines[:2 if name == 'io' else 1]]
        except (OSError, IndexError, ValueError):
            out += [0] * (2 if name == 'io' else 1)
    return out


def _threads_now(pid):
    """[(pid, tid, comm, syscall line, wchan)] of pid and its children, from /proc."""
    out = []
    pids = [pid]
    try:
        with open(f'/proc/{pid}/task/{pid}/children') as fh:
            pids += [int(x) for x in fh.read().split()]
    except OSError:
        pass
    for p in pids:
        try:
            tids = os.listdir(f'/proc/{p}/task')
        except OSError:
            continue
        for tid in tids:
            row = [p, int(tid)]
            for name in ('comm', 'syscall', 'wchan'):
                try:
                    with open(f'/proc/{p}/task/{tid}/{name}') as fh:
                        row.append(fh.read().strip()[:60])
                except OSError:
                    row.append('')
            out.append(row)
    return out


class MachineSampler:
    """The machine's counters every SAMPLE_S; when no reply came for STALL_WATCH_S while the
    stream runs, the node's (and its children's) threads: syscall and wait channel."""

    STALL_WATCH_S = 0.05

    def __init__(self, replies=None, pid=None):
        self.rows, self._stop = [], False
        self.replies, self.pid, self.stalls = replies, pid, []
        self._t = threading.Thread(target=self._run, daemon=True)
        self._t.start()

    def _run(self):
        seen, last, noted = 0, time.perf_counter_ns(), 0
        while not self._stop:
            now = time.perf_counter_ns()
            self.rows.append([now] + _machine())
            if self.replies is not None:
                n = len(self.replies)
                if n != seen:
                    seen, last, noted = n, now, 0
                elif now - last > self.STALL_WATCH_S * 1e9 and noted < 3:
                    noted += 1
                    self.stalls.append((now, last, _threads_now(self.pid)))
            time.sleep(SAMPLE_S)

    def stop(self):
        self._stop = True
        self._t.join()
        return np.array(self.rows, dtype=np.int64)


def start(kind, cpu, trace, params, stall_ms, no_child=False):
    import subprocess

    from bench.node_latency import ROOT
    cmd = [sys.executable, '-m', 'bench.probes.tail_trace', '--serve-echo' if kind == 'echo' else '--serve-dynamics']
    if kind != 'echo':
        cmd += ['--ros-args', '--params-file', os.path.join(ROOT, 'config', 'arm7_gravity.yaml')]
        for k, v in params.items():
            cmd += ['-p', f'{k}:={v}']
    env = dict(os.environ, **{TRACE_ENV: trace, STALL_ENV: str(stall_ms), NO_CHILD_ENV: '1' if no_child else ''})
    return subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                            preexec_fn=(lambda: os.sched_setaffinity(0, {cpu})) if cpu is not None else None)


def measure(names, seconds, rounds, rate, robot, stall_ms, out=None, no_child=False):
    import tempfile

    from bench import node_latency as nl
    from bench.probes.latency_split import CANDIDATES, StampedDriver, stream_setup
    base, Q, keys, N, W, node_cpu, driver = stream_setup(robot, seconds, rate)
    stamped = StampedDriver(driver)
    tmp = out or tempfile.mkdtemp(prefix='tail_trace_')
    os.makedirs(tmp, exist_ok=True)
    runs = []
    try:
        for r in range(rounds):
            for name in names:
                kind, params = CANDIDATES[name]
                trace = os.path.join(tmp, f'{r}-{name}.node.json')
                proc = start(kind, node_cpu, trace, {**base, **params}, stall_ms, no_child)
                try:
                    driver.wait_ready(Q[0].tolist(), joined=None if kind == 'echo' or no_child else nl.TRAJECTORY_IN)
                    machine = MachineSampler(driver.replies, proc.pid)
                    sent, _ = driver.run(Q[:N], rate, warmup=Q[N:N + W])
                    rows = machine.stop()
                    replies = list(driver.replies)
                finally:
                    nl.stop(proc)
                try:
                    with open(trace) as fh:
                        node = json.load(fh)
                except (OSError, ValueError):   # the node did not stop in time (killed): no record
                    print(f'tail_trace: round {r} {name}: the node left no record (killed?), skipped',
                          file=sys.stderr)
                    continue
                key = keys['echo' if kind == 'echo' else 'dynamics']
                send = np.array([stamped.stamps[q.tobytes()] for q in Q[N:N + W]] +
                                [stamped.stamps[q.tobytes()] for q in Q[:N]], dtype=np.int64)
                reply = np.zeros(N + W, dtype=np.int64)
                for t, data in replies:
                    k = key.get(nl.reply_key(np.frombuffer(data, dtype=float)))
                    if k is not None:
                        j = k - N if k >= N else k + W   # row of the stream
                        if reply[j] == 0:
                            reply[j] = int(t * 1e9)
                run = dict(round=r, name=name, send=send.tolist(), reply=reply.tolist(), W=W, node=node,
                           machine=rows.tolist(), reply_times=[int(t * 1e9) for t, _ in replies],
                           threads=machine.stalls)
                if out:
                    with open(os.path.join(tmp, f'{r}-{name}.json'), 'w') as fh:
                        json.dump(run, fh)
                runs.append(run)
    finally:
        driver.close()
        if not out:
            import shutil
            shutil.rmtree(tmp, ignore_errors=True)
    return runs


def _callbacks(run):
    """{stamp: (start, published, end, run delay)} of the node's joint_states callbacks."""
    return {s[3][0]: (s[1], s[3][1], s[2], s[4]) for s in run['node']['spans'] if s[0] == 'callback'}


def tails(run, threshold_ns):
    """Per reply above threshold: (total, to callback, to command, back, busy before the callback by
    kind {kind: ns}, ready-wait of the callback) in µs."""
    send, reply, W = np.array(run['send']), np.array(run['reply']), run['W']
    cbs = _callbacks(run)
    spans = sorted((s for s in run['node']['spans']), key=lambda s: s[1])
    starts = np.array([s[1] for s in spans])
    out = []
    for j in range(W, len(send)):
        if reply[j] == 0 or reply[j] - send[j] <= threshold_ns:
            continue
        cb = cbs.get(int(send[j]))
        if cb is None or cb[1] == 0:
            continue
        busy = {}
        lo = max(0, np.searchsorted(starts, send[j]) - 5)
        for s in spans[lo:np.searchsorted(starts, cb[0])]:
            ov = min(s[2], cb[0]) - max(s[1], send[j])
            if ov > 0 and not (s[0] == 'callback' and s[1] == cb[0]) and not s[0].startswith('step:'):
                busy[s[0]] = busy.get(s[0], 0) + ov / 1e3
        out.append(((reply[j] - send[j]) / 1e3, (cb[0] - send[j]) / 1e3, (cb[1] - cb[0]) / 1e3,
                    (reply[j] - cb[1]) / 1e3, busy, cb[3] / 1e3))
    return out


def gaps(run, gap_ns):
    """Gaps of gap_ns or more between two replies after the warm-up: what each side did in them."""
    send, reply_times = np.array(run['send']), np.array(sorted(run['reply_times']))
    reply_times = reply_times[(reply_times >= send[run['W']]) & (reply_times <= send[-1] + gap_ns)]
    lines = []
    for a, b in zip(reply_times[:-1], reply_times[1:], strict=True):
        if b - a < gap_ns:
            continue
        sends = send[(send > a) & (send < b)]
        longest_send_gap = np.diff(np.concatenate([[a], sends, [b]])).max() / 1e6
        spans = [(s[0], round(float(s[1] - a) / 1e6, 1), round(float(s[2] - s[1]) / 1e6, 1))
                 for s in run['node']['spans'] if s[2] > a and s[1] < b and s[2] - s[1] > 1e6]
        late = [(round(float(e - a) / 1e6, 1), round(float(w - e) / 1e6, 1))
                for e, w in run['node']['late'] if w > a and e < b]
        stacks = [(k, round(float(t - s0) / 1e6, 1), st.strip().splitlines()[-6:])
                  for t, k, s0, st in run['node']['stacks'] if a - 1e9 < t < b + 1e9]
        m = np.array(run['machine'])
        inside = m[(m[:, 0] >= a - 2e7) & (m[:, 0] <= b + 2e7)]
        d = (inside[-1, 1:] - inside[0, 1:]) if len(inside) > 1 else np.zeros(4)
        lines.append(f"  gap {(b - a) / 1e6:.1f} ms at {(a - send[run['W']]) / 1e6:.0f} ms: {len(sends)} states sent "
                     f"(longest send gap {longest_send_gap:.1f} ms); node spans > 1 ms {spans}; sampler late "
                     f"{late}; machine: steal {d[0] * 10} ms, cpu some {d[1] / 1e3:.1f} ms, io some "
                     f"{d[2] / 1e3:.1f} ms, io full {d[3] / 1e3:.1f} ms; stacks {stacks}")
    return lines


def report(runs, names, stall_ms):
    lines = []
    by_round = {}
    for run in runs:
        by_round.setdefault(run['round'], {})[run['name']] = run
    summary = {n: [] for n in names}
    for r, rr in sorted(by_round.items()):
        echo = rr.get('echo')
        if echo is None:
            continue
        e = np.array(echo['reply']) - np.array(echo['send'])
        e = e[echo['W']:][np.array(echo['reply'])[echo['W']:] > 0]
        thr = np.percentile(e, 99)
        for name, run in rr.items():
            lat = (np.array(run['reply']) - np.array(run['send']))[run['W']:]
            lat = lat[np.array(run['reply'])[run['W']:] > 0]
            t = tails(run, thr)
            busy = {}
            for x in t:
                for k, v in x[4].items():
                    busy[k] = busy.get(k, 0) + v
            n = max(1, len(t))
            a = np.array([x[:4] + (x[5],) for x in t]).reshape(-1, 5)
            summary[name].append((np.median(lat) / np.median(e), np.percentile(lat, 99) / thr))
            lines.append(f'round {r} {name}: p50 {np.median(lat) / 1e3:.0f} µs, p99 {np.percentile(lat, 99) / 1e3:.0f} '
                         f'µs ({np.percentile(lat, 99) / thr:.2f}x echo p99 {thr / 1e3:.0f} µs); {len(t)} replies '
                         f'above it: mean to callback {a[:, 1].mean() if len(a) else 0:.0f}, to command '
                         f'{a[:, 2].mean() if len(a) else 0:.0f}, back {a[:, 3].mean() if len(a) else 0:.0f} µs; '
                         f'node busy before the callback (mean µs per tail reply) '
                         f"{ {k: round(v / n, 1) for k, v in busy.items()} }; callback ready-wait mean "
                         f'{a[:, 4].mean() if len(a) else 0:.1f} µs')
            steps = {}
            for sp in run['node']['spans']:
                if sp[0].startswith('step:') or sp[0] in ('callback', 'task', 'timer', 'gc'):
                    steps.setdefault(sp[0], []).append((sp[2] - sp[1]) / 1e3)
            lines.append('  spans, p50 µs (count): ' + ', '.join(
                f'{k} {np.median(v):.0f} ({len(v)})' for k, v in sorted(steps.items())))
            lines += gaps(run, stall_ms * 1e6)
    lines.append('')
    for name, v in summary.items():
        if v:
            v = np.array(v)
            lines.append(f'{name}: p50 x events echo {np.round(v[:, 0], 2).tolist()}, '
                         f'p99 x {np.round(v[:, 1], 2).tolist()}')
    return '\n'.join(lines)


def main(argv=None):
    argv = sys.argv[1:] if argv is None else argv
    if argv and argv[0] in ('--serve-echo', '--serve-dynamics'):
        from bench.node_latency import ros_env
        ros_env()
        return serve_echo() if argv[0] == '--serve-echo' else serve_dynamics()
    p = argparse.ArgumentParser(prog='python -m bench.probes.tail_trace', description=__doc__.splitlines()[0])
    p.add_argument('--seconds', type=float, default=3.0)
    p.add_argument('--rounds', type=int, default=3)
    p.add_argument('--rate', type=float, default=1000.0)
    p.add_argument('--candidates', default='echo,every')
    p.add_argument('--robot', choices=('arm7', 'talos_reduced'), default='arm7')
    p.add_argument('--stall-ms', type=float, default=30.0)
    p.add_argument('--out', help='keep the raw timelines here')
    p.add_argument('--no-trajectories', action='store_true',
                   help='the dynamics node without its trajectory process (an experiment)')
    a = p.parse_args(argv)
    names = a.candidates.split(',')
    if 'echo' not in names:
        names = ['echo'] + names
    runs = measure(names, a.seconds, a.rounds, a.rate, a.robot, a.stall_ms, a.out, a.no_trajectories)
    print(report(runs, names, a.stall_ms))
    return 0


if __name__ == '__main__':
    sys.exit(main())
