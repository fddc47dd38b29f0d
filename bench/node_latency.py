"""joint_states -> effort command latency of the dynamics node, beside a bare echo node.

    .venv/bin/python -m bench.node_latency [--seconds 5] [--rates 1000,2000] [--rounds 2]
                                           [--soak MINUTES] [--dynamics-topics] [--robot talos_reduced]
                                           [--out DIR]

A driver (this process) publishes sensor_msgs/JointState for the bundled 7-DoF arm at a fixed
rate and times each std_msgs/Float64MultiArray reply. The node under test runs in its own
process, as in a robot stack, under an executor chosen with LIE_DYNAMICS_EXECUTOR:
  * echo:     a bare rclpy node copying positions into a Float64MultiArray (the floor), under
              rclpy's default SingleThreadedExecutor and under the package's executor;
  * dynamics: `python -m lie_dynamics.dynamics_node` with config/arm7_gravity.yaml, under the
              package's executor (the EventsExecutor) and the fallback SingleThreadedExecutor.
Replies are matched to requests by value (the echo returns q, the dynamics node g(q),
which the driver precomputes), so drops and reordering are counted, not guessed. Candidates
run in interleaved rounds at each rate; per candidate: p50/p99/p99.9/max, the share of replies
later than one period, drops and the node's CPU (% of one core, from /proc). --soak runs the
dynamics node alone at the first rate for MINUTES and reports the RSS slope and drops.
--dynamics-topics adds a candidate with every feature on: the dynamics node (events) publishing its
four dynamics topics (gravity, coriolis, mass_matrix, jacobian) at every state (dynamics.rate 0) and
~/commanded_efforts, with the observer (on by default) and its two topics, nobody subscribed; the
states then carry velocities (0) and efforts (g(q): no contact) so that the observer runs, for the
echo nodes too. --robot talos_reduced: example-robot-data's Talos (reduced), its 32 joints but the
two grippers controlled (30), instead of the bundled 7-joint arm (the same parameters otherwise). Writes
node_latency.md/.csv/.json and a latency histogram (node_latency.png) to --out.
This is a benchmark, not a test: numbers depend on the machine and its load; compare the
ratios to the echo nodes measured in the same run. Every node runs with its production defaults
(config/arm7_gravity.yaml); the clock starts after a warm-up streamed without a pause (WARMUP_S).
"""
import argparse
import atexit
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
import warnings

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
JOINTS = [f'joint{i}' for i in range(1, 8)]
TALOS = 'talos_data/robots/talos_reduced.urdf'
CMD = '/effort_controller/commands'
TRAJECTORY_IN = '/dynamics_node/trajectory_in'   # the dynamics node's trajectory process subscribes it


def streamed_robot(name):
    """(URDF path, controlled joints, model, the node's extra parameters) of the robot streamed:
    the bundled arm ('arm7': the node's own configuration) or example-robot-data's Talos reduced
    without its two grippers ('talos_reduced', 30 joints)."""
    from lie_dynamics import load_urdf
    with warnings.catch_warnings():
        warnings.simplefilter('ignore')   # vendor inertias are warned about
        if name == 'talos_reduced':
            from bench.robots import robot_dir
            path = os.path.join(robot_dir(), TALOS)
            joints = [j for j in load_urdf(path).joint_names if 'gripper' not in j]
            base = {'urdf_path': path, 'joints': '[' + ','.join(joints) + ']'}
        else:
            path, joints, base = os.path.join(ROOT, 'config', 'arm7.urdf'), JOINTS, {}
        return path, joints, load_urdf(path, joints=joints), base


def postures(model, count, seed=0):
    """count random postures (count, n) within the joint limits and +-2.5 rad: the streamed states."""
    rng = np.random.default_rng(seed)
    lo, hi = np.maximum(model.position_lower, -2.5), np.minimum(model.position_upper, 2.5)
    return lo + (hi - lo) * rng.random((count, model.n))


def ros_env():
    from lie_dynamics.sim.domains import reserve_domains

    os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    if 'ROS_DOMAIN_ID' not in os.environ:  # a domain no test run or other benchmark uses
        os.environ['ROS_DOMAIN_ID'] = str(reserve_domains(1)[0])
    if 'ROS_LOG_DIR' not in os.environ:  # the nodes' logs: nobody reads them, removed at exit
        os.environ['ROS_LOG_DIR'] = log_dir = tempfile.mkdtemp(prefix='lie_dynamics_bench_log_')
        atexit.register(shutil.rmtree, log_dir, ignore_errors=True)
    if signal.getsignal(signal.SIGTERM) == signal.SIG_DFL:  # SIGTERM exits through atexit, like Ctrl-C
        signal.signal(signal.SIGTERM, _interrupt)


def _interrupt(*_):
    raise KeyboardInterrupt


def echo_main():
    """The bare echo node (run in a subprocess with --echo-node)."""
    import rclpy
    from sensor_msgs.msg import JointState
    from std_msgs.msg import Float64MultiArray

    from lie_dynamics.ros.node import JOINT_STATES_QOS, NO_PUB_EVENTS, NO_SUB_EVENTS

    rclpy.init()
    node = rclpy.create_node('echo_node')
    # same transport settings as the dynamics node, so the comparison isolates the node's own work
    pub = node.create_publisher(Float64MultiArray, CMD, 10, event_callbacks=NO_PUB_EVENTS)

    def on_js(msg):
        out = Float64MultiArray()
        out.data = msg.position
        pub.publish(out)

    node.create_subscription(JointState, 'joint_states', on_js, JOINT_STATES_QOS, event_callbacks=NO_SUB_EVENTS)
    spin_echo(node)


def spin_echo(node, finish=None):
    """Spin an echo node (this one's and the probes') under the node's executor until shutdown or an
    interrupt, then finish() (a probe's record) and shut rclpy down."""
    import rclpy
    from rclpy.executors import ExternalShutdownException

    from lie_dynamics.ros.run import make_executor
    ex, _ = make_executor()
    ex.add_node(node)
    try:
        while rclpy.ok():  # spin_once: the EventsExecutor's spin() was seen busy-looping
            ex.spin_once(timeout_sec=0.1)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        if finish is not None:
            finish()
        rclpy.try_shutdown()


class Driver:
    def __init__(self, joints=JOINTS, efforts=None):
        """efforts: {q row as bytes: effort row}, sent with zero velocities (None: positions only)."""
        import rclpy
        from rclpy.context import Context
        from rclpy.executors import SingleThreadedExecutor
        from sensor_msgs.msg import JointState
        from std_msgs.msg import Float64MultiArray

        self.rclpy = rclpy
        self.JointState = JointState
        self.ctx = Context()
        rclpy.init(context=self.ctx)
        self.node = rclpy.create_node('latency_driver', context=self.ctx)
        self.pub = self.node.create_publisher(JointState, 'joint_states', 10)
        self.node.create_subscription(Float64MultiArray, CMD, self._on_cmd, 100)
        self.ex = SingleThreadedExecutor(context=self.ctx)
        self.ex.add_node(self.node)
        self.replies = []
        self.joints, self.efforts = list(joints), efforts

    def _on_cmd(self, msg):
        self.replies.append((time.perf_counter(), bytes(msg.data)))

    def wait_ready(self, probe_q, timeout=60.0, joined=None):
        """Until the node under test is discovered and answers. joined: a topic whose subscriber
        (the dynamics node's trajectory process: TRAJECTORY_IN) this driver must have discovered
        too: Fast DDS's first send to a new peer can stop this process's sends for up to 1/3 s
        (ros/node.py, TRAJECTORIES_JOIN_S), which must not happen in the measured stream."""
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            if (self.pub.get_subscription_count() and self.node.count_publishers(CMD)
                    and (joined is None or self.node.count_subscribers(joined))):
                break
            self.ex.spin_once(timeout_sec=0.01)
        else:
            raise RuntimeError('node under test not discovered')
        self.replies.clear()
        while time.monotonic() < end:  # until the node answers (model loaded)
            self.publish(probe_q)
            t = time.monotonic() + 0.2
            while time.monotonic() < t:
                self.ex.spin_once(timeout_sec=0.01)
            if self.replies:
                self.replies.clear()
                return
        raise RuntimeError('node under test does not answer')

    def publish(self, q):
        if self.efforts is None:
            self.pub.publish(self.JointState(name=self.joints, position=q))
        else:
            e = self.efforts[np.asarray(q, dtype=float).tobytes()]
            self.pub.publish(self.JointState(name=self.joints, position=q, velocity=[0.0] * len(q), effort=e))

    def run(self, Q, rate, warmup=(), drain=0.3, clear=True):
        """Publish the rows of `warmup`, then those of Q, at `rate` in one stream (no gap: a pause
        longer than the node's stale_timeout would make it ramp back in, blending replies that are
        not g(q)); then spin `drain` s for the replies in flight. Returns (send times of the rows of
        warmup + Q, achieved rate). clear: forget earlier replies first."""
        period = 1.0 / rate
        rows = [q.tolist() for q in warmup] + [q.tolist() for q in Q]
        sent = np.full(len(rows), np.nan)
        if clear:
            self.replies.clear()
        t0 = time.perf_counter()
        nxt = t0
        k = 0
        spin = self.ex.spin_once
        while k < len(rows):
            now = time.perf_counter()
            if now >= nxt:
                sent[k] = time.perf_counter()
                self.publish(rows[k])
                k += 1
                nxt = max(nxt + period, now - period)  # never burst to catch up
            else:
                spin(timeout_sec=nxt - now)
        achieved = len(rows) / (time.perf_counter() - t0)
        end = time.perf_counter() + drain  # the replies still in flight
        while time.perf_counter() < end:
            spin(timeout_sec=0.01)
        return sent, achieved

    def close(self):
        self.ex.shutdown()
        self.node.destroy_node()
        self.ctx.try_shutdown()


def match(sent, replies, keys, first=0):
    """Latencies (s) of matched replies, count of requests without a reply. sent[i] is the send
    time of row first + i of Q (keys: reply value -> row)."""
    lat = np.full(len(sent), np.nan)
    for t, data in replies:
        k = keys.get(reply_key(np.frombuffer(data, dtype=float)))
        if k is not None and 0 <= k - first < len(sent) and np.isnan(lat[k - first]):
            lat[k - first] = t - sent[k - first]
    return lat, int(np.isnan(lat).sum())


def reply_key(x):
    return np.round(x, 6).tobytes()


def start(kind, cpu=None, params=None, executor=None):
    """params: extra dynamics-node parameters {name: value string}, after the file (they win).
    executor: LIE_DYNAMICS_EXECUTOR of the node's process (None: the package's default)."""
    if kind == 'echo':
        cmd = [sys.executable, '-m', 'bench.node_latency', '--echo-node']
    else:
        cmd = [sys.executable, '-m', 'lie_dynamics.dynamics_node', '--ros-args', '--params-file',
               os.path.join(ROOT, 'config', 'arm7_gravity.yaml')]
        for k, v in (params or {}).items():
            cmd += ['-p', f'{k}:={v}']
    pre = (lambda: os.sched_setaffinity(0, {cpu})) if cpu is not None else None
    env = dict(os.environ)
    if executor:
        env['LIE_DYNAMICS_EXECUTOR'] = executor
    return subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                            preexec_fn=pre)


def cpu_seconds(proc):
    """User + system CPU time (s) of a running process, from /proc (None where unavailable)."""
    try:
        with open(f'/proc/{proc.pid}/stat') as fh:
            fields = fh.read().rsplit(')', 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf('SC_CLK_TCK')
    except (OSError, ValueError, IndexError):
        return None


def rss_mb(proc):
    """Resident set size (MB) of a running process, from /proc (None where unavailable)."""
    try:
        with open(f'/proc/{proc.pid}/status') as fh:
            for line in fh:
                if line.startswith('VmRSS:'):
                    return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return None


def stop(proc):
    proc.send_signal(2)
    try:
        proc.wait(timeout=10)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


def callback_cost(model, Q, joints=JOINTS):
    """In-process cost of the node's decision logic per message (no DDS): median, p99 in us."""
    import array

    from lie_dynamics.ros.core.compensator import Compensator
    c = Compensator({'joints': joints, 'friction.viscous': [0.0], 'friction.coulomb': [0.0]})
    c.set_model(model)
    rows = [array.array('d', q) for q in Q[:2000]]
    t = []
    for r in rows:
        t0 = time.perf_counter()
        c.on_joint_state(joints, r, (), ())
        t.append(time.perf_counter() - t0)
    t = np.array(t[100:]) * 1e6
    return np.median(t), np.percentile(t, 99)


# (label, kind, executor): the peers and the node, each under the executors compared
CANDIDATES = (('echo, default executor', 'echo', 'single_threaded'), ('echo, events', 'echo', 'events'),
              ('dynamics, events', 'dynamics', 'events'), ('dynamics, default executor', 'dynamics', 'single_threaded'))
PEER, CHOSEN = CANDIDATES[0][0], CANDIDATES[2][0]
# --dynamics-topics: the chosen node again with every feature on (every dynamics term at every state)
TOPICS_CANDIDATE = ('dynamics, every feature on (4 topics at every state), events', 'dynamics', 'events',
                    {'dynamics.publish': '[gravity,coriolis,mass_matrix,jacobian]', 'dynamics.rate': '0.0',
                     'publish_joint_state': 'true'})
# the events-executor echo node: the floor the node's p50 and p99 are compared with (issue target: <= 1.0x)
EVENTS_ECHO = CANDIDATES[1][0]
# Warm-up before the clock starts, in the same stream as the measurement: longer than ramp_time
# (0.2 s by default: the node blends its first commands in after start-up and after stale input).
WARMUP_S = 0.5
# the targets at 1 kHz (p50 relative to the default-executor echo node of the same run)
TARGETS = {'drops': 0, 'p50_x_echo': 0.9, 'p99_ms': 0.8, 'late_pct': 0.5, 'cpu_pct': 30.0}


def summarize(lat_s, drops, rate, cpu):
    ok = lat_s[~np.isnan(lat_s)] * 1e3
    late = 100.0 * (np.sum(ok > 1e3 / rate) + drops) / max(1, len(lat_s))
    return dict(sent=len(lat_s), drops=drops, p50_ms=float(np.median(ok)), p99_ms=float(np.percentile(ok, 99)),
                p999_ms=float(np.percentile(ok, 99.9)), max_ms=float(ok.max()), late_pct=float(late),
                cpu_pct=float(cpu) if cpu is not None else float('nan'))


def measure(driver, Q, keys, rate, seconds, node_cpu, rounds, candidates=CANDIDATES, base=None):
    """Interleaved rounds of every candidate (label, kind, executor[, params]) at `rate`:
    {label: (latencies, drops, cpu %)}. base: the dynamics node's parameters for every candidate."""
    N, W = int(seconds * rate), int(WARMUP_S * rate)
    out = {c[0]: [[], 0, [], 0] for c in candidates}
    for _ in range(rounds):
        for label, kind, executor, *params in candidates:
            proc = start(kind, node_cpu, params={**(base or {}), **(params[0] if params else {})}, executor=executor)
            try:
                driver.wait_ready(Q[0].tolist(), joined=TRAJECTORY_IN if kind == 'dynamics' else None)
                c0, t0 = cpu_seconds(proc), time.perf_counter()
                # warm-up rows Q[N:N + W], then the measured ones Q[:N]
                sent, _ = driver.run(Q[:N], rate, warmup=Q[N:N + W])
                c1, t1 = cpu_seconds(proc), time.perf_counter()
                replies = list(driver.replies)
                lat, drops = match(sent[W:], replies, keys[kind])
                out[label][0].append(lat)
                out[label][1] += drops
                # once the clock runs, a reply that is no state's g(q) (or q) is a blended one: not steady
                out[label][3] += sum(reply_key(np.frombuffer(d, dtype=float)) not in keys[kind]
                                     for t, d in replies if t >= sent[W])
                if c0 is not None and c1 is not None:
                    out[label][2].append(100.0 * (c1 - c0) / (t1 - t0))
            finally:
                stop(proc)
    return {label: (np.concatenate(v[0]), v[1], np.median(v[2]) if v[2] else None, v[3]) for label, v in out.items()}


def soak(driver, Q, keys, rate, minutes, node_cpu):
    """The dynamics node alone at `rate` for `minutes`: RSS samples every 5 s, slope, drops.
    One gapless stream (see Driver.run) of 5 s chunks taking turns on two halves of Q; the
    replies are matched at the end (matching between chunks would pause the stream), each chunk
    against the replies from its start to the start of the next chunk on the same half."""
    import bisect
    proc = start('dynamics', node_cpu)
    samples, chunks = [], []   # chunks: (send times, first row of Q)
    n = int(5 * rate)
    assert len(Q) >= 2 * n + int(WARMUP_S * rate)
    try:
        driver.wait_ready(Q[0].tolist(), joined=TRAJECTORY_IN)
        driver.run(Q[2 * n:2 * n + int(WARMUP_S * rate)], rate, drain=0.0)  # warm-up, not counted
        t_end = time.monotonic() + 60.0 * minutes
        t0 = time.monotonic()
        while time.monotonic() < t_end:
            first = (len(chunks) % 2) * n
            sent, _ = driver.run(Q[first:first + n], rate, drain=0.0, clear=False)
            chunks.append((sent, first))
            samples.append((time.monotonic() - t0, rss_mb(proc)))
        driver.run(Q[:0], rate, drain=0.3, clear=False)  # the last replies in flight
    finally:
        stop(proc)
    replies = list(driver.replies)
    times = [r[0] for r in replies]
    drops = 0
    for j, (sent, first) in enumerate(chunks):
        lo = bisect.bisect_left(times, sent[0])
        hi = bisect.bisect_left(times, chunks[j + 2][0][0]) if j + 2 < len(chunks) else len(replies)
        drops += match(sent, replies[lo:hi], keys['dynamics'], first=first)[1]
    sent_total = sum(len(c[0]) for c in chunks)
    t = np.array([s[0] for s in samples]) / 60.0
    rss = np.array([s[1] if s[1] is not None else np.nan for s in samples])
    half = len(rss) // 2  # the slope after start-up transients
    slope = float(np.polyfit(t[half:], rss[half:], 1)[0]) if len(rss) - half >= 2 else float('nan')
    return dict(minutes=minutes, sent=sent_total, drops=drops, rss_start_mb=float(rss[0]), rss_end_mb=float(rss[-1]),
                rss_slope_mb_per_min=slope)


def markdown(rows, targets_at, soak_result, callback):
    lines = ['# joint_states -> effort round trip: the dynamics node beside bare echo nodes', '',
             f'In-process decision logic + g(q) (no DDS): median {callback[0]:.1f} µs, p99 {callback[1]:.1f} µs per '
             'message.', '',
             '| rate Hz | node | sent | drops | of which blended | p50 ms | p99 ms | p99.9 ms | max ms | late % '
             '| CPU % | p50 × echo | p50, p99 × events echo |',
             '|---|---|---|---|---|---|---|---|---|---|---|---|---|']
    for r in rows:
        lines.append(f"| {r['rate']:.0f} | {r['node']} | {r['sent']} | {r['drops']} | {r['blended']} | "
                     f"{r['p50_ms']:.3f} | "
                     f"{r['p99_ms']:.3f} | {r['p999_ms']:.3f} | {r['max_ms']:.3f} | {r['late_pct']:.2f} | "
                     f"{r['cpu_pct']:.0f} | {r['p50_x_echo']:.2f} | "
                     f"{r['p50_x_events_echo']:.2f}, {r['p99_x_events_echo']:.2f} |")
    lines += ['', 'late % = replies later than one period, drops included; p50 × echo: against the echo node under '
              "rclpy's default executor in the same run. Each run streams a warm-up of "
              f'{WARMUP_S:g} s (longer than the node\'s ramp_time) and then the measured states without a pause. '
              'drops = states without their exact answer; of which blended = replies that were no state\'s exact '
              'answer: the node ramping back in after a pause longer than stale_timeout (a stall of the driver, '
              'the node or DDS), as in production.', '',
              f'Targets at {targets_at:.0f} Hz ({CHOSEN}):', '']
    for name, ok, text in targets_status(rows, targets_at):
        lines.append(f"- {'met' if ok else 'NOT met'}: {name} ({text})")
    if soak_result:
        s = soak_result
        lines += ['', f"Soak ({CHOSEN}, {s['minutes']:g} min): {s['sent']} sent, {s['drops']} drops, RSS "
                  f"{s['rss_start_mb']:.0f} -> {s['rss_end_mb']:.0f} MB, "
                  f"slope {s['rss_slope_mb_per_min']:+.3f} MB/min."]
    return '\n'.join(lines) + '\n'


def targets_status(rows, rate):
    at = {r['node']: r for r in rows if r['rate'] == rate}
    r = at.get(CHOSEN)
    if r is None:
        return []
    out = [('zero drops', r['drops'] == TARGETS['drops'], f"{r['drops']} drops"),
           ('p50 <= 0.9 x default-executor echo p50', r['p50_x_echo'] <= TARGETS['p50_x_echo'],
            f"{r['p50_x_echo']:.2f} x"),
           ('p99 <= 0.8 ms', r['p99_ms'] <= TARGETS['p99_ms'], f"{r['p99_ms']:.3f} ms"),
           ('<= 0.5% later than one period', r['late_pct'] <= TARGETS['late_pct'], f"{r['late_pct']:.2f} %"),
           ('node CPU <= 30% of a core', r['cpu_pct'] <= TARGETS['cpu_pct'], f"{r['cpu_pct']:.0f} %")]
    fast = [x for x in rows if x['node'] == CHOSEN and x['rate'] > rate]
    if fast:
        out.append((f"drop-free at {fast[0]['rate']:.0f} Hz", fast[0]['drops'] == 0, f"{fast[0]['drops']} drops"))
    return out


def plot(lat_by, path):
    from bench import common
    plt = common.setup_matplotlib()
    fig, ax = plt.subplots(figsize=(8, 4))
    bins = np.logspace(-1.3, 1.5, 80)
    for label, lat in lat_by.items():
        ok = lat[~np.isnan(lat)] * 1e3
        ax.hist(ok, bins=bins, histtype='step', lw=1.2, label=f'{label} (p50 {np.median(ok):.2f} ms)')
    ax.set_xscale('log')
    ax.set_yscale('log')
    ax.set_xlabel('round trip joint_states -> command (ms)')
    ax.set_ylabel('replies')
    ax.axvline(1.0, color='k', lw=0.8, ls='--')
    ax.set_title('Round-trip latency at 1 kHz (dashed: one period)')
    ax.legend(fontsize=7)
    fig.tight_layout()
    common.savefig(fig, path)


def run(quick=False, out=None, argv=None):
    args = parse(argv if argv is not None else (['--seconds', '1', '--rounds', '1'] if quick else []))
    if out:
        args.out = out
    return measure_all(args)


def parse(argv):
    ap = argparse.ArgumentParser(prog='python -m bench.node_latency', description=__doc__.split('\n')[0])
    ap.add_argument('--seconds', type=float, default=5.0, help='duration of each latency run, s')
    ap.add_argument('--rates', default='1000,2000', help='rates of the latency runs, Hz (the first is the target)')
    ap.add_argument('--rounds', type=int, default=2, help='interleaved rounds of every candidate')
    ap.add_argument('--soak', type=float, default=0.0, metavar='MINUTES',
                    help='also run the dynamics node alone for MINUTES: RSS slope and drops')
    ap.add_argument('--no-pin', action='store_true',
                    help='do not pin the driver to CPU 0 and the node under test to CPU 1')
    ap.add_argument('--dynamics-topics', action='store_true',
                    help='add the dynamics node with every feature on (its four dynamics topics at every state)')
    ap.add_argument('--robot', choices=('arm7', 'talos_reduced'), default='arm7',
                    help='the bundled arm, or Talos reduced (30 joints, example-robot-data)')
    ap.add_argument('--out', default=os.path.join(ROOT, 'bench', 'out'), help='output folder')
    ap.add_argument('--echo-node', action='store_true', help=argparse.SUPPRESS)
    return ap.parse_args(argv)


def main(argv=None):
    args = parse(argv)
    if args.echo_node:
        ros_env()
        return echo_main()
    measure_all(args)
    return 0


def measure_all(args):
    from bench import common
    from lie_dynamics.laws import clamp, effort_limits

    ros_env()
    rates = [float(x) for x in args.rates.split(',')]
    _, joints, model, base = streamed_robot(args.robot)
    Q = postures(model, max(int(args.seconds * max(rates)) + int(max(rates)), 12000))
    # the node's answer: g(q) clamped to the effort limits (laws.clamp; the bundled arm never reaches them)
    expected = {'echo': Q, 'dynamics': clamp(model.gravity(Q), effort_limits(model.effort_limits, 1.0))[0]}
    assert args.robot != 'arm7' or np.all(np.abs(expected['dynamics']) < model.effort_limits)
    keys = {kind: {reply_key(x): k for k, x in enumerate(v)} for kind, v in expected.items()}
    callback = callback_cost(model, Q, joints)
    cpus = sorted(os.sched_getaffinity(0))
    node_cpu = None
    if not args.no_pin and len(cpus) >= 2:
        os.sched_setaffinity(0, {cpus[0]})
        node_cpu = cpus[1]
    efforts = None
    if args.dynamics_topics:   # the observer's input: no contact (the efforts are g(q))
        efforts = {q.tobytes(): e.tolist() for q, e in zip(Q, expected['dynamics'], strict=True)}
    driver = Driver(joints, efforts)
    rows, hist, soak_result = [], {}, None
    try:
        for rate in rates:
            res = measure(driver, Q, keys, rate, args.seconds, node_cpu, args.rounds,
                          CANDIDATES + ((TOPICS_CANDIDATE,) if args.dynamics_topics else ()), base)
            peer = summarize(*res[PEER][:2], rate, res[PEER][2])
            events = summarize(*res[EVENTS_ECHO][:2], rate, res[EVENTS_ECHO][2])
            for label, (lat, drops, cpu, blended) in res.items():
                r = dict(rate=rate, node=label, **summarize(lat, drops, rate, cpu), blended=blended)
                r['p50_x_echo'] = r['p50_ms'] / peer['p50_ms']
                r['p50_x_events_echo'] = r['p50_ms'] / events['p50_ms']
                r['p99_x_events_echo'] = r['p99_ms'] / events['p99_ms']
                rows.append(r)
                if rate == rates[0]:
                    hist[label] = lat
        if args.soak > 0:
            soak_result = soak(driver, Q, keys, rates[0], args.soak, node_cpu)
    finally:
        driver.close()
    md = markdown(rows, rates[0], soak_result, callback)
    print(md)
    common.write_tables(args.out, 'node_latency', md, dict(rows=rows, soak=soak_result, targets=TARGETS), rows)
    plot(hist, os.path.join(args.out, 'node_latency.png'))
    return rows, soak_result


if __name__ == '__main__':
    sys.exit(main())
