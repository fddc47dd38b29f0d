"""Do heavy events stall the dynamics node's replies? The largest gap between replies, seen
from another process streaming joint_states at 500 Hz, during each event beside a quiet
stretch just before it.

    python -m bench.node_loads [--raised] [--busy N] [--repeat R] [--node-src DIR] [--nice N] [--quick] [--trace]

The node runs as `python -m lie_dynamics.dynamics_node` on the bundled arm (its own process,
default parameters: the EventsExecutor, the momentum observer on). A streaming process (Stream)
publishes serialized joint_states with velocities and efforts at 500 Hz from one thread and
stamps each reply (std_msgs/Float64MultiArray) as it arrives in another; nothing else runs
there, so its times show the node and not the work of making the events (publishing a 5,000-link
description from the measuring process widened its own send gaps by several ms). This process
makes the events and reads the node's log and diagnostics. Events, each after a pause of
QUIET_S seconds and followed by a quiet stretch as long as its window (the reference):
  * description: the arm with extra links on fixed joints up to the node's max_description_links
    (they fold into the arm's bodies: the model that swaps in serves as fast as the arm);
  * chain: a chain of as many links, another robot: built in full, then refused (the
    running model stays);
  * new structure: the arm with its first joint moved by a few micrometres, a kinematic structure
    no kernel cache has seen yet (its kernels are generated: traced, rendered and, where a C
    compiler works, compiled);
  * reloads: 20 ~/reload_model calls back to back;
  * trajectory: a 100,000-point trajectory on ~/trajectory_in (refused by the default
    max_trajectory_points from its header; filled and published with --raised), sent and its
    filled copy taken by a helper process (rclpy would stall this one while it takes 20 MB).
--raised starts the node with max_description_links 5,000, max_trajectory_points 200,000 and
max_description_bytes 20 MB (the description is then 5,000 links). An event's window lasts
from its start until the node is done (its diagnostics, every 0.1 s, say model_state 'ready'
again; a trajectory: ~/trajectory_out or its rejection in the log) plus 0.2 s. --busy N runs N
busy-loop processes beside it all along (killed at the end). Reported per event: the largest
gap in the event window and in the quiet stretch after it, their difference (the target: at
most 2 ms), the same difference for the streaming process's own sends (when the machine delays
that process, replies wait for states not yet sent: that part is not the node's), replies
against states sent, and how long the event took; with --repeat R every
event runs R times and each column is the median. --nice N (negative: needs the privilege)
runs this process and the node at that niceness, the busy loops at the usual one: on a machine
that others load, the gaps then show the node rather than the scheduler. --node-src DIR runs
the node of another checkout (the root that holds its lie_dynamics/), to compare before/after
under the same conditions. --trace runs the node through bench.probes.node_trace and adds, per event,
the node's side: its longest joint_states callback (wall ms), that callback's CPU time and its
wait for a CPU (ms), the most CPU any callback of the window used, and the longest log line.
This is a benchmark, not a test: the numbers depend on the machine and its load.
"""
import argparse
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time

import numpy as np

from bench.common import arm_xml, default_urdf, robot_urdf

JOINTS = [f'joint{i}' for i in range(1, 8)]
Q = np.array([0.1, 0.5, -0.2, 1.2, 0.3, 0.8, 0.1])
RATE = 500.0
QUIET_S = 3.0
CMD = '/node_loads/commands'
NODE = '/dynamics_node'
DEFAULT_CAPS = {'links': 256, 'points': 10_000}
RAISED_CAPS = {'links': 5_000, 'points': 200_000, 'bytes': 20_000_000}


def folded_description(links):
    """The arm's URDF with extra links on fixed joints, `links` <link> elements in all."""
    xml = arm_xml()
    extra = links - xml.count('<link')
    arm_links = re.findall(r'<link name="([^"]+)"', xml)
    parts = []
    for i in range(extra):
        parent = arm_links[1 + i % (len(arm_links) - 1)]
        parts.append(f'<link name="extra{i}"><inertial><mass value="0.001"/><inertia ixx="1e-7" ixy="0" ixz="0" '
                     f'iyy="1e-7" iyz="0" izz="1e-7"/></inertial></link>'
                     f'<joint name="extra_fixed{i}" type="fixed"><parent link="{parent}"/><child link="extra{i}"/>'
                     f'<origin xyz="0 0 {0.001 * (i % 50)!r}"/></joint>')
    return xml.replace('</robot>', '\n'.join(parts) + '\n</robot>')


def chain_description(links):
    """A random chain of `links` links whose first seven joints are named like the arm's, as
    another robot: built in full (one body per link, the rest locked), then refused by
    description_update 'same_robot', so the running model keeps serving."""
    xml = robot_urdf(links - 1, seed=1)
    for k in range(1, 8):
        xml = xml.replace(f'name="j{k:03d}"', f'name="joint{k}"')
    return xml


def new_structure_description():
    """The arm with joint1 moved by a few micrometres, different in every call (and every run):
    a structure whose kernels no cache holds."""
    nonce = 1e-6 * (1 + time.time_ns() % 999_983)
    xml = arm_xml()
    old = '<origin xyz="0 0 0.34" rpy="0 0 0"/>'
    if old not in xml:
        raise RuntimeError("the arm's joint1 origin is not where this benchmark expects it")
    return xml.replace(old, f'<origin xyz="0 0 {0.34 + nonce!r}" rpy="0 0 0"/>', 1)


def serialized_trajectory(n):
    """A serialized n-point trajectory of the arm at 1 kHz (written directly with trajectory_cdr)."""
    from rclpy.serialization import serialize_message
    from trajectory_msgs.msg import JointTrajectory

    from lie_dynamics.ros.trajectories import trajectory_cdr as cdr
    head = bytes(serialize_message(JointTrajectory(joint_names=JOINTS)))
    prefix = head[:-4] + n.to_bytes(4, 'little')
    k = np.arange(n)
    traj = dict(prefix=prefix, joint_names=JOINTS, sec=k // 1000, nanosec=(k % 1000) * 1_000_000,
                positions=np.tile(Q, (n, 1)), velocities=np.zeros((n, 7)), accelerations=None)
    return cdr.write(traj, np.zeros((n, 7)))


def spin_until(ex, stop, period):
    """Spin executor `ex` until threading.Event `stop` is set, waking every `period` s to look."""
    while not stop.is_set():
        ex.spin_once(timeout_sec=period)


class Stream:
    """The measuring side, a process of its own (`--stream`): one thread publishes serialized
    joint_states at RATE, an executor thread stamps each reply as it arrives; nothing else runs
    there (events are made by the benchmark's main process and the trajectory sender), so its
    send and reply times show the node, not this benchmark's own work. It says 'ready' once
    replies flow; at the end of its input it prints its send and reply times (JSON)."""

    def __init__(self, env):
        self.proc = subprocess.Popen([sys.executable, '-m', 'bench.node_loads', '--stream'], env=env,
                                     stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
        line = self.proc.stdout.readline().strip()
        if line != 'ready':
            raise RuntimeError(f'the streaming process did not start ({line!r})')

    def times(self):
        """Ends the stream: (send times, reply times), time.monotonic() seconds."""
        out, _ = self.proc.communicate('', timeout=60)
        data = json.loads(out.strip().splitlines()[-1])
        return np.array(data['sends']), np.array(data['replies'])

    def close(self):
        if self.proc.poll() is None:
            try:
                self.proc.communicate('', timeout=20)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.communicate()


def stream():
    """(--stream) The streaming process of Stream."""
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from rclpy.serialization import serialize_message
    from sensor_msgs.msg import JointState
    from std_msgs.msg import Float64MultiArray

    rclpy.init()
    node = rclpy.create_node('node_loads_stream')
    sends, replies = [], []
    deep = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
    node.create_subscription(Float64MultiArray, CMD, lambda m: replies.append(time.monotonic()), deep, raw=True)
    js = node.create_publisher(JointState, 'joint_states', 1)
    # with velocities and efforts, as a robot sends them: the observer runs (production defaults)
    state = bytes(serialize_message(JointState(name=JOINTS, position=Q.tolist(), velocity=[0.0] * 7,
                                               effort=[0.0] * 7)))
    ex = SingleThreadedExecutor()
    ex.add_node(node)
    stop = threading.Event()

    def publish():
        period, t = 1.0 / RATE, time.monotonic()
        while not stop.is_set():
            js.publish(state)
            sends.append(time.monotonic())
            t += period
            pause = t - time.monotonic()
            if pause > 0:
                time.sleep(pause)
            else:
                t = time.monotonic()
    threads = [threading.Thread(target=spin_until, args=(ex, stop, 0.05)), threading.Thread(target=publish)]
    threads[0].start()
    end = time.monotonic() + 60
    while not (js.get_subscription_count() and node.count_publishers(CMD)) and time.monotonic() < end:
        time.sleep(0.01)
    threads[1].start()
    while len(replies) <= 100 and time.monotonic() < end:
        time.sleep(0.01)
    print('ready' if len(replies) > 100 else 'no replies', flush=True)
    sys.stdin.read()   # until the end of input
    stop.set()
    for th in threads:
        th.join()
    print(json.dumps({'sends': sends, 'replies': replies}), flush=True)
    ex.shutdown()
    node.destroy_node()
    rclpy.try_shutdown()


class Driver:
    """The event side: the node's log and diagnostics, robot_description, the reload client."""

    def __init__(self, ctx):
        import rclpy
        from diagnostic_msgs.msg import DiagnosticArray
        from rcl_interfaces.msg import Log
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        from std_msgs.msg import String

        from lie_dynamics.ros.node import DESCRIPTION_QOS
        self.node = rclpy.create_node('node_loads_driver', context=ctx)
        self.ex = SingleThreadedExecutor(context=ctx)
        self.ex.add_node(self.node)
        self.logs, self.filled, self.states = [], [], []
        deep = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
        self.node.create_subscription(Log, '/rosout', self._on_log, deep)
        self.node.create_subscription(DiagnosticArray, '/diagnostics', self._on_diag, deep)
        self.desc = self.node.create_publisher(String, 'robot_description', DESCRIPTION_QOS)
        self.stop = threading.Event()
        self.thread = threading.Thread(target=spin_until, args=(self.ex, self.stop, 0.05), daemon=True)
        self.thread.start()

    def _on_log(self, msg):
        if msg.name == NODE.strip('/'):
            self.logs.append((time.monotonic(), msg.msg))

    def _on_diag(self, msg):
        for st in msg.status:
            for kv in st.values:
                if kv.key == 'model_state':
                    self.states.append((time.monotonic(), kv.value))

    def ready_after(self, t0):
        """When the diagnostics first said model_state 'ready' after t0 (no load running or waiting)."""
        return next((t for t, v in list(self.states) if t >= t0 and v == 'ready'), None)

    def wait(self, pred, timeout, what):
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            if pred():
                return
            time.sleep(0.01)
        raise RuntimeError(f'timed out waiting for {what}')

    def log_after(self, t0, pattern):
        return next((t for t, m in list(self.logs) if t >= t0 and re.search(pattern, m)), None)

    def close(self):
        self.stop.set()
        self.thread.join(timeout=5)
        self.node.destroy_node()


def _window(times, t0, t1):
    return times[(times >= t0) & (times <= t1)]


def gap(replies, t0, t1):
    """(largest gap between replies in [t0, t1] in s, replies in it)."""
    r = _window(replies, t0, t1)
    return (float(np.max(np.diff(r))) if len(r) > 1 else float('inf')), len(r)


def _row(name, t0, t_done, t1, sends, replies):
    """The event's window [t0, t1] against the quiet stretch as long right after it."""
    t2 = 2 * t1 - t0
    busy, n_busy = gap(replies, t0, t1)
    quiet, n_quiet = gap(replies, t1, t2)
    # the streaming process's own largest gap between sends: when the machine delays it, the
    # replies wait for states that were not sent yet, whatever the node does
    own = (gap(sends, t0, t1)[0] - gap(sends, t1, t2)[0]) * 1e3
    return {'event': name, 'quiet_gap_ms': quiet * 1e3, 'event_gap_ms': busy * 1e3, 'widened_ms': (busy - quiet) * 1e3,
            'send_widened_ms': own, 'replies': n_busy, 'sent': len(_window(sends, t0, t1)), 'event_s': t_done - t0,
            'quiet_replies': n_quiet, 'quiet_sent': len(_window(sends, t1, t2))}


def _event(driver, windows, name, start, done, timeout):
    """The event, then a quiet stretch as long as its window (the largest gap grows with the
    window's length): its window is kept for a result row."""
    time.sleep(QUIET_S)
    t0 = time.monotonic()
    start()
    driver.wait(lambda: done(t0) is not None, timeout, name)
    t_done = done(t0)
    time.sleep(0.2)
    t1 = time.monotonic()
    time.sleep(t1 - t0)
    windows.append((name, t0, t_done, t1))


def _node_side(trace, t0, t1):
    """--trace: what the node's own callbacks and log lines did in [t0, t1] (bench.probes.node_trace)."""
    calls = [c for c in trace['callbacks'] if t0 <= c[0] <= t1]
    lines = [w for t, w in trace['lines'] if t0 <= t <= t1]
    if not calls:
        return {}
    longest = max(calls, key=lambda c: c[1])
    return {'cb_wall_ms': longest[1] * 1e3, 'cb_cpu_ms': longest[2] * 1e3, 'cb_wait_ms': longest[3] * 1e3,
            'cb_max_cpu_ms': max(c[2] for c in calls) * 1e3, 'line_ms': max(lines, default=0.0) * 1e3}


def run(raised=False, busy=0, quick=False, repeat=1, node_src=None, nice=0, trace=False):
    import rclpy
    from rclpy.context import Context
    from std_msgs.msg import String
    from std_srvs.srv import Trigger

    from lie_dynamics.sim.domains import reserve_domains
    tmp = tempfile.mkdtemp(prefix='lie_dynamics_node_loads_')
    env = dict(os.environ, ROS_LOG_DIR=os.path.join(tmp, 'log'))
    env.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    env.setdefault('ROS_DOMAIN_ID', str(reserve_domains(1)[0]))
    if node_src:
        env['PYTHONPATH'] = os.pathsep.join(p for p in (os.path.abspath(node_src), env.get('PYTHONPATH')) if p)
    # this process talks to the node on its domain; its own log stays where rclpy put it (the
    # temporary folder is removed at the end, and rclpy may log after that)
    for k in ('ROS_AUTOMATIC_DISCOVERY_RANGE', 'ROS_DOMAIN_ID'):
        os.environ.setdefault(k, env[k])
    caps = RAISED_CAPS if raised else DEFAULT_CAPS
    params = ['-p', f'urdf_path:={default_urdf()}', '-p', f'command_topic:={CMD}', '-p', 'diagnostics_period:=0.1',
              '-p', f"max_description_links:={caps['links']}", '-p', f"max_trajectory_points:={caps['points']}"]
    if 'bytes' in caps:
        params += ['-p', f"max_description_bytes:={caps['bytes']}"]
    base = os.getpriority(os.PRIO_PROCESS, 0)
    if nice:
        os.nice(nice)   # before any child: the node inherits it
    burners = [subprocess.Popen([sys.executable, '-c', 'while True: pass']) for _ in range(busy)]
    for b in burners:
        os.setpriority(os.PRIO_PROCESS, b.pid, base)
    helpers = []
    # `-m` puts the working directory first on the path: run there the checkout to be measured
    trace_file = os.path.join(tmp, 'trace.json')
    if trace:
        env['LIE_DYNAMICS_NODE_TRACE'] = trace_file
    module = 'bench.probes.node_trace' if trace else 'lie_dynamics.dynamics_node'
    proc = subprocess.Popen([sys.executable, '-m', module, '--ros-args', *params], env=env,
                            cwd=os.path.abspath(node_src) if node_src else None,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    ctx = Context()
    rclpy.init(context=ctx)
    driver = streamer = None
    windows = []
    try:
        driver = Driver(ctx)
        streamer = Stream(env)
        cli = driver.node.create_client(Trigger, f'{NODE}/reload_model')
        cli.wait_for_service(timeout_sec=30)
        xml = folded_description(caps['links'])
        xmls = [xml.replace('</robot>', f'<!-- {k} --></robot>') for k in range(repeat)]   # each one new
        for k in range(repeat):
            _event(driver, windows, f"description ({caps['links']} links)",
                   lambda k=k: driver.desc.publish(String(data=xmls[k])), lambda t0: driver.ready_after(t0 + 0.3), 300)
        chain = chain_description(caps['links'])
        for k in range(repeat):
            _event(driver, windows, f"chain, refused after its build ({caps['links']} links)",
                   lambda k=k: driver.desc.publish(String(data=chain + f'<!-- {k} -->')),
                   lambda t0: driver.ready_after(t0 + 0.3), 300)
        for _ in range(repeat):
            _event(driver, windows, 'new structure (kernels generated)',
                   lambda: driver.desc.publish(String(data=new_structure_description())),
                   lambda t0: driver.ready_after(t0 + 0.3), 300)

        def reloads():
            for _ in range(20):
                fut = cli.call_async(Trigger.Request())
                driver.wait(fut.done, 30, 'reload answer')
            driver.reloads_sent = time.monotonic()

        def reloads_done(t0):
            sent = getattr(driver, 'reloads_sent', None)   # loads run (or wait) from each answer on
            return None if sent is None else driver.ready_after(sent)
        for _ in range(repeat):
            driver.reloads_sent = None
            _event(driver, windows, '20 reloads', reloads, reloads_done, 300)
        if not quick:
            # sent, and the filled one taken, by a process of its own: rclpy keeps the interpreter
            # lock while it publishes or takes 20 MB, which would stall this process's log and
            # diagnostics readers (the times that end an event window)
            sender = subprocess.Popen([sys.executable, '-m', 'bench.node_loads', '--send-trajectory'], env=env,
                                      stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
            helpers.append(sender)
            if sender.stdout.readline().strip() != 'ready':
                raise RuntimeError('the trajectory sender did not start')
            sent = threading.Event()

            def read_sender():
                for line in sender.stdout:
                    if line.strip() == 'filled':
                        driver.filled.append(time.monotonic())
                    elif line.strip() == 'sent':
                        sent.set()
            threading.Thread(target=read_sender, daemon=True).start()

            def send():
                sent.clear()
                sender.stdin.write('send\n')
                sender.stdin.flush()
                sent.wait(60)
            for _ in range(repeat):
                n_filled = len(driver.filled)
                _event(driver, windows, '100,000-point trajectory', send,
                       lambda t0, n=n_filled: (driver.filled[n] if len(driver.filled) > n
                                               else driver.log_after(t0, 'trajectory rejected')), 120)
        sends, replies = streamer.times()
    finally:
        if streamer is not None:
            streamer.close()
        if driver is not None:
            driver.close()
        ctx.try_shutdown()
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        for h in helpers:   # end of its input: it leaves the DDS graph (a kill -9 would leave its
            try:            # shared-memory files behind)
                h.stdin.close()
                h.wait(timeout=20)
            except (OSError, subprocess.TimeoutExpired):
                pass
        for b in burners + helpers:
            if b.poll() is None:
                b.kill()
            b.wait()
        traced = None
        if trace and os.path.exists(trace_file):
            with open(trace_file) as fh:
                traced = json.load(fh)
        shutil.rmtree(tmp, ignore_errors=True)
    rows = [_row(*w, sends, replies) for w in windows]
    if traced is not None:
        for r, w in zip(rows, windows, strict=True):
            r.update(_node_side(traced, w[1], w[3]))
    return _medians(rows)


def _medians(rows):
    out = []
    for name in dict.fromkeys(r['event'] for r in rows):
        same = [r for r in rows if r['event'] == name]
        out.append({k: (name if k == 'event' else float(np.median([r[k] for r in same]))) for k in same[0]})
        out[-1]['runs'] = len(same)
    return out


def markdown(rows, raised, busy):
    head = (f"caps {'raised' if raised else 'default'}, {busy} busy loops beside; joint_states at {RATE:g} Hz; "
            f'niceness {os.getpriority(os.PRIO_PROCESS, 0)}; quiet stretch after each event, as long as its window')
    traced = all('cb_wall_ms' in r for r in rows)
    extra = (' node: longest callback ms (its CPU / its wait for a CPU) | most CPU in one callback ms | longest log '
             'line ms |') if traced else ''
    lines = [head, '', '| event | runs | quiet gap ms | event gap ms | widened ms | sends widened ms | replies / sent '
             '| event s |' + extra, '|---|---|---|---|---|---|---|---|' + ('---|---|---|' if traced else '')]
    for r in rows:
        line = (f"| {r['event']} | {r['runs']} | {r['quiet_gap_ms']:.1f} | {r['event_gap_ms']:.1f} | "
                f"{r['widened_ms']:+.1f} | {r['send_widened_ms']:+.1f} | {r['replies']:.0f} / {r['sent']:.0f} | "
                f"{r['event_s']:.2f} |")
        if traced:
            line += (f" {r['cb_wall_ms']:.2f} ({r['cb_cpu_ms']:.2f} / {r['cb_wait_ms']:.2f}) | "
                     f"{r['cb_max_cpu_ms']:.2f} | {r['line_ms']:.2f} |")
        lines.append(line)
    return '\n'.join(lines)


def send_trajectories():
    """(--send-trajectory) Publish the 100,000-point trajectory once per line on stdin ('sent'
    once published); 'filled' for every filled trajectory from the node."""
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from trajectory_msgs.msg import JointTrajectory

    from lie_dynamics.ros.node import TRAJECTORY_QOS
    rclpy.init()
    node = rclpy.create_node('node_loads_trajectory_sender')
    pub = node.create_publisher(JointTrajectory, f'{NODE}/trajectory_in', TRAJECTORY_QOS)
    lock = threading.Lock()

    def say(text):
        with lock:
            print(text, flush=True)
    node.create_subscription(JointTrajectory, f'{NODE}/trajectory_out', lambda m: say('filled'), TRAJECTORY_QOS,
                             raw=True)
    ex = SingleThreadedExecutor()
    ex.add_node(node)
    stop = threading.Event()
    # joined before the executor, the node and the context go: rclpy's Executor.shutdown does not
    # wait for a thread in spin(), which then ran on into the destroyed node and context (an abort
    # at exit, 'terminate called without an active exception', and the DDS participant's
    # shared-memory files left behind)
    spinner = threading.Thread(target=spin_until, args=(ex, stop, 0.1), name='trajectory_sender_spin')
    spinner.start()
    try:
        data = serialized_trajectory(100_000)
        while not (pub.get_subscription_count() and node.count_publishers(f'{NODE}/trajectory_out')):
            time.sleep(0.05)
        say('ready')
        for _ in sys.stdin:
            pub.publish(data)
            say('sent')
    finally:
        stop.set()
        spinner.join()
        ex.shutdown()
        node.destroy_node()
        rclpy.try_shutdown()


def main(argv=None):
    ap = argparse.ArgumentParser(prog='python -m bench.node_loads', description=__doc__.split('\n')[0])
    ap.add_argument('--raised', action='store_true', help='caps raised to 5,000 links and 200,000 points')
    ap.add_argument('--busy', type=int, default=0, help='busy-loop processes beside the node')
    ap.add_argument('--repeat', type=int, default=1, help='runs of each event (medians reported)')
    ap.add_argument('--node-src', help='run the node of this checkout instead')
    ap.add_argument('--nice', type=int, default=0, help='niceness of this process and the node')
    ap.add_argument('--quick', action='store_true', help='no trajectory event')
    ap.add_argument('--trace', action='store_true',
                    help="the node's callbacks and log lines timed (bench.probes.node_trace)")
    ap.add_argument('--send-trajectory', action='store_true', help=argparse.SUPPRESS)
    ap.add_argument('--stream', action='store_true', help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    if a.stream:
        return stream()
    if a.send_trajectory:
        return send_trajectories()
    print(markdown(run(a.raised, a.busy, a.quick, a.repeat, a.node_src, a.nice, a.trace), a.raised, a.busy))
    return 0


if __name__ == '__main__':
    sys.exit(main())
