"""Where the round trip joint_states -> command goes, in the dynamics node and in the echo node:
the same stream as bench.node_latency, each state stamped with the driver's monotonic clock
(time.perf_counter_ns, the same clock in every process on Linux), and inside the node under test
a wrapper around its joint_states callback recording when it starts, when the command is
published and when it returns, with its thread's CPU time. Per state, then:

  to callback   stamp -> callback start   (DDS, the executor's wake-up and dispatch)
  to command    callback start -> command published   (the node's own Python)
  back          command published -> reply in the driver   (DDS back, the driver's dispatch)
  after         command published -> callback return   (the work after the command)

and the share of the commands the fused command path made (ros/core/fused.py; the rest by the
Python path), and per candidate, each thread of the node's process: CPU time and context switches during the
measured stream (/proc), so a thread that wakes beside the callback shows. Candidates run in
interleaved rounds, the node on its own core (as bench.node_latency):

    python -m bench.probes.latency_split [--seconds 3] [--rounds 3] [--rate 1000]
                                         [--candidates echo,dynamics,bare,every] [--robot talos_reduced]

  echo      the events-executor echo node of bench.node_latency
  dynamics  the dynamics node, config/arm7_gravity.yaml (its defaults: the observer on)
  bare      the same without per-sample features (FEATURES empty: no helper nodes, no observer)
  every     every feature on, as bench.node_latency --dynamics-topics

Prints the medians and p99 of each part per candidate, and each one's ratio to the echo's.
A benchmark, not a test: read the ratios between rows of one run.
"""
import argparse
import json
import os
import struct
import sys
import tempfile
import time

import numpy as np

TRACE_ENV = 'LIE_DYNAMICS_SPLIT_TRACE'
SRC_ENV = 'LIE_DYNAMICS_SPLIT_SRC'


def _dump(path, rows):
    with open(path, 'w') as fh:
        json.dump(rows, fh)


def _stamp(buf):
    """The header stamp (ns) of a serialized JointState (after the 4-byte encapsulation)."""
    sec, nsec = struct.unpack_from('<iI', buf, 4)
    return sec * 1_000_000_000 + nsec


def serve_dynamics(bare):
    """The dynamics node, its callback and command timed (rows: stamp, start, published, end, cpu ns)."""
    from lie_dynamics.ros import node as node_module
    from lie_dynamics.ros.outputs import Outputs
    rows, now, cpu = [], time.perf_counter_ns, time.thread_time_ns
    published = [0]
    on_joint_state, command = node_module.DynamicsNode.on_joint_state, Outputs.command

    publish = getattr(Outputs, 'publish', None)   # the fused command path's (a checkout before it: none)

    def timed_callback(self, msg):
        t0, c0 = now(), cpu()
        published[0] = 0
        fused = getattr(self, 'fused', None)
        taken = fused.taken if fused is not None else 0
        try:
            return on_joint_state(self, msg)
        finally:
            rows.append((_stamp(msg), t0, published[0], now(), cpu() - c0,
                         (fused.taken if fused is not None else 0) - taken))

    def timed_command(self, tau, names, stamp=None):
        out = command(self, tau, names, stamp)
        published[0] = now()
        return out

    def timed_publish(self, *args):
        out = publish(self, *args)
        published[0] = now()
        return out
    node_module.DynamicsNode.on_joint_state = timed_callback
    Outputs.command = timed_command
    if publish is not None:
        Outputs.publish = timed_publish
    if bare:
        node_module.FEATURES = ()
        defaults = list(node_module.DynamicsNode.__init__.__defaults__)
        defaults[1] = ()
        node_module.DynamicsNode.__init__.__defaults__ = tuple(defaults)
    try:
        return node_module.main(sys.argv[:1] + sys.argv[sys.argv.index('--ros-args'):])
    finally:
        _dump(os.environ[TRACE_ENV], rows)


def serve_echo():
    """bench.node_latency's echo node, its callback timed the same way."""
    import rclpy
    from sensor_msgs.msg import JointState
    from std_msgs.msg import Float64MultiArray

    from bench.node_latency import CMD, spin_echo
    from lie_dynamics.ros.node import JOINT_STATES_QOS, NO_PUB_EVENTS, NO_SUB_EVENTS
    rows, now, cpu = [], time.perf_counter_ns, time.thread_time_ns
    rclpy.init()
    node = rclpy.create_node('echo_node')
    pub = node.create_publisher(Float64MultiArray, CMD, 10, event_callbacks=NO_PUB_EVENTS)

    def on_js(msg):
        t0, c0 = now(), cpu()
        out = Float64MultiArray()
        out.data = msg.position
        pub.publish(out)
        t1 = now()
        s = msg.header.stamp
        rows.append((s.sec * 1_000_000_000 + s.nanosec, t0, t1, now(), cpu() - c0, 0))

    node.create_subscription(JointState, 'joint_states', on_js, JOINT_STATES_QOS, event_callbacks=NO_SUB_EVENTS)
    spin_echo(node, lambda: _dump(os.environ[TRACE_ENV], rows))


def threads(pid):
    """{thread id: (name, cpu s, context switches)} of a running process, from /proc."""
    out, tck = {}, os.sysconf('SC_CLK_TCK')
    try:
        tids = os.listdir(f'/proc/{pid}/task')
    except OSError:
        return out
    for tid in tids:
        try:
            with open(f'/proc/{pid}/task/{tid}/stat') as fh:
                head, rest = fh.read().rsplit(')', 1)
            f = rest.split()
            switches = 0
            with open(f'/proc/{pid}/task/{tid}/status') as fh:
                for line in fh:
                    if line.endswith('ctxt_switches:', 0, line.find(':') + 1):
                        switches += int(line.split()[1])
            out[int(tid)] = (head.split('(', 1)[1], (int(f[11]) + int(f[12])) / tck, switches)
        except (OSError, ValueError, IndexError):
            pass
    return out


CANDIDATES = {'echo': ('echo', {}), 'dynamics': ('dynamics', {}), 'bare': ('bare', {}),
              'every': ('dynamics', {'dynamics.publish': '[gravity,coriolis,mass_matrix,jacobian]',
                                     'dynamics.rate': '0.0', 'publish_joint_state': 'true'})}


class StampedDriver:
    """bench.node_latency.Driver, each state's header stamped with perf_counter_ns."""

    def __init__(self, driver):
        self.d = driver
        self.stamps = {}   # row of Q (bytes) -> the stamp it was last sent with
        driver.publish = self.publish

    def publish(self, q):
        d, ns = self.d, time.perf_counter_ns()
        m = d.JointState(name=d.joints, position=q)
        key = np.asarray(q, dtype=float).tobytes()
        self.stamps[key] = ns
        if d.efforts is not None:
            m.velocity, m.effort = [0.0] * len(q), d.efforts[key]
        m.header.stamp.sec, m.header.stamp.nanosec = divmod(ns, 1_000_000_000)
        d.pub.publish(m)


def start(kind, cpu, trace, params, src=None):
    from bench.node_latency import ROOT
    serve = '--serve-echo' if kind == 'echo' else ('--serve-bare' if kind == 'bare' else '--serve-dynamics')
    cmd = [sys.executable, '-m', 'bench.probes.latency_split', serve]
    if kind != 'echo':
        cmd += ['--ros-args', '--params-file', os.path.join(ROOT, 'config', 'arm7_gravity.yaml')]
        for k, v in params.items():
            cmd += ['-p', f'{k}:={v}']
    env = dict(os.environ, **{TRACE_ENV: trace, SRC_ENV: src or ''})
    import subprocess
    return subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                            preexec_fn=(lambda: os.sched_setaffinity(0, {cpu})) if cpu is not None else None)


def stream_setup(robot, seconds, rate):
    """The stream of bench.node_latency for `robot` ('arm' or 'talos_reduced'): (base parameters of
    the candidates, the states Q (N measured, then W warm-up, then one), the replies' keys per kind
    ('echo': Q, 'dynamics': the clamped g(Q)), N, W, the CPU left to the node or None, the driver);
    this process is pinned to the first CPU when there are two."""
    from bench import node_latency as nl
    from lie_dynamics.laws import clamp, effort_limits
    nl.ros_env()
    _, joints, model, base = nl.streamed_robot(robot)
    N, W = int(seconds * rate), int(nl.WARMUP_S * rate)
    Q = nl.postures(model, N + W + 1)
    g = clamp(model.gravity(Q), effort_limits(model.effort_limits, 1.0))[0]
    keys = {'echo': {nl.reply_key(x): k for k, x in enumerate(Q)}}
    keys['dynamics'] = {nl.reply_key(x): k for k, x in enumerate(g)}
    cpus = sorted(os.sched_getaffinity(0))
    node_cpu = None
    if len(cpus) >= 2:
        os.sched_setaffinity(0, {cpus[0]})
        node_cpu = cpus[1]
    driver = nl.Driver(joints, {q.tobytes(): e.tolist() for q, e in zip(Q, g, strict=True)})
    return base, Q, keys, N, W, node_cpu, driver


def measure(names, seconds, rounds, rate, robot, before=None):
    from bench import node_latency as nl
    base, Q, keys, N, W, node_cpu, driver = stream_setup(robot, seconds, rate)
    stamped = StampedDriver(driver)
    runs = [(n, n, None) for n in names]   # (label, candidate, source tree)
    if before:
        runs += [(f'{n} (before)', n, before) for n in names if n != 'echo']
    res = {label: {'parts': [], 'threads': []} for label, _, _ in runs}
    tmp = tempfile.mkdtemp(prefix='latency_split_')
    try:
        for _ in range(rounds):
            for label, name, src in runs:
                kind, params = CANDIDATES[name]
                trace = os.path.join(tmp, f'{len(os.listdir(tmp))}.json')
                proc = start(kind, node_cpu, trace, {**base, **params}, src)
                try:
                    driver.wait_ready(Q[0].tolist(), joined=None if kind == 'echo' or src else nl.TRAJECTORY_IN)
                    t_before = threads(proc.pid)
                    sent, _ = driver.run(Q[:N], rate, warmup=Q[N:N + W])
                    t_after = threads(proc.pid)
                    replies = list(driver.replies)
                finally:
                    nl.stop(proc)
                with open(trace) as fh:
                    rows = np.array(json.load(fh), dtype=np.int64).reshape(-1, 6)
                key = keys['echo' if kind == 'echo' else 'dynamics']
                res[label]['parts'].append(parts(rows, sent[W:], replies, key, Q, stamped.stamps))
                res[label]['threads'].append({tid: (v[0], v[1] - t_before.get(tid, (0, 0, 0))[1],
                                                   v[2] - t_before.get(tid, (0, 0, 0))[2])
                                             for tid, v in t_after.items()})
    finally:
        driver.close()
        import shutil
        shutil.rmtree(tmp, ignore_errors=True)
    return res


def parts(rows, sent, replies, keys, Q, stamps):
    """Per answered measured state: (to callback, to command, back, after, total, callback cpu) in µs,
    and 1 where the fused command path made the command (else 0)."""
    by_stamp = {int(r[0]): r for r in rows}
    out = []
    for t, data in replies:
        k = keys.get(np.round(np.frombuffer(data, dtype=float), 6).tobytes())
        if k is None or k >= len(sent):
            continue
        r = by_stamp.get(stamps.get(Q[k].tobytes()))
        if r is None or r[2] == 0:
            continue
        t_reply = int(t * 1e9)   # perf_counter and perf_counter_ns: the same clock
        out.append(((r[1] - r[0]) / 1e3, (r[2] - r[1]) / 1e3, (t_reply - r[2]) / 1e3, (r[3] - r[2]) / 1e3,
                    (t_reply - r[0]) / 1e3, r[4] / 1e3, r[5]))
    return np.array(out).reshape(-1, 7)


def report(res, rate, seconds):
    cols = ('to callback', 'to command', 'back', 'after', 'total', 'callback CPU')
    echo = np.concatenate(res['echo']['parts']) if 'echo' in res else None
    lines = ['| candidate | part | p50 µs | p99 µs | p50 × echo | p99 × echo |', '|---|---|---:|---:|---:|---:|']
    for name, v in res.items():
        a = np.concatenate(v['parts'])
        for j, c in enumerate(cols):
            p50, p99 = np.median(a[:, j]), np.percentile(a[:, j], 99)
            if echo is not None:
                e50, e99 = np.median(echo[:, j]), np.percentile(echo[:, j], 99)
                ratio = f'{p50 / e50:.2f} | {p99 / e99:.2f}'
            else:
                ratio = '- | -'
            lines.append(f'| {name} ({len(a)} replies) | {c} | {p50:.1f} | {p99:.1f} | {ratio} |')
        if a[:, 6].any():
            lines.append(f'| {name} | commands by the fused path | {100 * a[:, 6].mean():.0f} % | | | |')
    lines += ['', f'Threads of each candidate, summed over the rounds (CPU %, context switches per second of '
              f'the {seconds:g} s stream at {rate:g} Hz, warm-up included):', '',
              '| candidate | thread | CPU % | switches/s |', '|---|---|---:|---:|']
    for name, v in res.items():
        agg = {}
        for t in v['threads']:
            for tname, c, s in t.values():
                a = agg.setdefault(tname, [0.0, 0, 0])
                a[0] += c
                a[1] += s
            for tname in {x[0] for x in t.values()}:
                agg[tname][2] += 1
        span = (seconds + 0.5 + 0.3) * len(v['threads'])
        for tname, (c, s, _) in sorted(agg.items(), key=lambda kv: -kv[1][1]):
            lines.append(f'| {name} | {tname} | {100 * c / span:.1f} | {s / span:.0f} |')
    return '\n'.join(lines)


def main(argv=None):
    argv = sys.argv[1:] if argv is None else argv
    if argv and argv[0] in ('--serve-echo', '--serve-dynamics', '--serve-bare'):
        if os.environ.get(SRC_ENV):   # the node of another checkout (--before)
            sys.path.insert(0, os.environ[SRC_ENV])
        from bench.node_latency import ros_env
        ros_env()
        return serve_echo() if argv[0] == '--serve-echo' else serve_dynamics(argv[0] == '--serve-bare')
    p = argparse.ArgumentParser(prog='python -m bench.probes.latency_split', description=__doc__.splitlines()[0])
    p.add_argument('--seconds', type=float, default=3.0)
    p.add_argument('--rounds', type=int, default=3)
    p.add_argument('--rate', type=float, default=1000.0)
    p.add_argument('--candidates', default='echo,dynamics,bare,every')
    p.add_argument('--robot', choices=('arm7', 'talos_reduced'), default='arm7')
    p.add_argument('--before', metavar='SRC', help='also run each dynamics candidate from this checkout '
                   '(e.g. `git archive` of a commit unpacked), labelled "(before)"')
    a = p.parse_args(argv)
    names = a.candidates.split(',')
    for n in names:
        if n not in CANDIDATES:
            print(f'latency_split: error: unknown candidate {n!r} (one of {", ".join(CANDIDATES)})', file=sys.stderr)
            return 2
    res = measure(names, a.seconds, a.rounds, a.rate, a.robot, a.before and os.path.abspath(a.before))
    print(report(res, a.rate, a.seconds))
    return 0


if __name__ == '__main__':
    sys.exit(main())
