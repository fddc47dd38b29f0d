"""joint_states -> effort command latency of the dynamics node, beside a bare echo node.

    .venv/bin/python -m bench.node_latency [--seconds 5] [--rate 1000] [--rounds 2]

A driver (this process, SingleThreadedExecutor) publishes sensor_msgs/JointState for the
bundled 7-DoF arm at a fixed rate and times each std_msgs/Float64MultiArray reply. The
node under test runs in its own process, as in a robot stack:
  * echo:     a bare rclpy node copying positions into a Float64MultiArray (the floor);
  * dynamics: `python -m lie_dynamics.dynamics_node` with config/arm7_gravity.yaml.
Replies are matched to requests by value (the echo returns q, the dynamics node g(q),
which the driver precomputes), so drops and reordering are counted, not guessed.
Then the rate is stepped up to find the highest rate each node sustains without a drop.
This is a benchmark, not a test: numbers depend on the machine and its load.
"""
import argparse
import os
import subprocess
import sys
import tempfile
import time

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
JOINTS = [f'joint{i}' for i in range(1, 8)]
CMD = '/effort_controller/commands'


def _ros_env():
    os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    if 'ROS_DOMAIN_ID' not in os.environ:
        os.environ['ROS_DOMAIN_ID'] = str(150 + os.getpid() % 80)  # away from the tests' 1..100
    if 'ROS_LOG_DIR' not in os.environ:
        os.environ['ROS_LOG_DIR'] = tempfile.mkdtemp(prefix='lie_dynamics_bench_log_')


def echo_main():
    """The bare echo node (run in a subprocess with --echo-node)."""
    import rclpy
    from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
    from sensor_msgs.msg import JointState
    from std_msgs.msg import Float64MultiArray

    from lie_dynamics.ros.node import JOINT_STATES_QOS
    from lie_dynamics.ros.node import NO_PUB_EVENTS as _NO_PUB_EVENTS, NO_SUB_EVENTS as _NO_SUB_EVENTS

    rclpy.init()
    node = rclpy.create_node('echo_node')
    # same transport settings as the dynamics node, so the comparison isolates the node's own work
    pub = node.create_publisher(Float64MultiArray, CMD, 10, event_callbacks=_NO_PUB_EVENTS)

    def on_js(msg):
        out = Float64MultiArray()
        out.data = msg.position
        pub.publish(out)

    node.create_subscription(JointState, 'joint_states', on_js, JOINT_STATES_QOS, event_callbacks=_NO_SUB_EVENTS)
    ex = SingleThreadedExecutor()
    ex.add_node(node)
    try:
        ex.spin()
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        rclpy.try_shutdown()


class Driver:
    def __init__(self):
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

    def _on_cmd(self, msg):
        self.replies.append((time.perf_counter(), bytes(msg.data)))

    def wait_ready(self, probe_q, timeout=60.0):
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            if self.pub.get_subscription_count() and self.node.count_publishers(CMD):
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
        self.pub.publish(self.JointState(name=JOINTS, position=q))

    def run(self, Q, rate):
        """Publish rows of Q at `rate`; return (send times, achieved rate)."""
        period = 1.0 / rate
        sent = np.full(len(Q), np.nan)
        rows = [q.tolist() for q in Q]
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
        end = time.perf_counter() + 0.3  # drain the replies still in flight
        while time.perf_counter() < end:
            spin(timeout_sec=0.01)
        return sent, achieved

    def close(self):
        self.ex.shutdown()
        self.node.destroy_node()
        self.ctx.try_shutdown()


def match(sent, replies, keys):
    """Latencies (s) of matched replies, count of requests without a reply."""
    lat = np.full(len(sent), np.nan)
    for t, data in replies:
        k = keys.get(_key(np.frombuffer(data, dtype=float)))
        if k is not None and np.isnan(lat[k]):
            lat[k] = t - sent[k]
    return lat, int(np.isnan(lat).sum())


def _key(x):
    return np.round(x, 6).tobytes()


def start(kind, cpu=None, params=None):
    """params: extra dynamics-node parameters {name: value string}, after the file (they win)."""
    if kind == 'echo':
        cmd = [sys.executable, '-m', 'bench.node_latency', '--echo-node']
    else:
        cmd = [sys.executable, '-m', 'lie_dynamics.dynamics_node', '--ros-args', '--params-file',
               os.path.join(ROOT, 'config', 'arm7_gravity.yaml')]
        for k, v in (params or {}).items():
            cmd += ['-p', f'{k}:={v}']
    pre = (lambda: os.sched_setaffinity(0, {cpu})) if cpu is not None else None
    return subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, preexec_fn=pre)


def stop(proc):
    proc.send_signal(2)
    try:
        proc.wait(timeout=10)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


def callback_cost(model, Q):
    """In-process cost of the node's decision logic per message (no DDS): median, p99 in us."""
    import array

    from lie_dynamics.ros.compensator import Compensator
    c = Compensator({'joints': JOINTS, 'friction.viscous': [0.0], 'friction.coulomb': [0.0]})
    c.set_model(model)
    rows = [array.array('d', q) for q in Q[:2000]]
    t = []
    for r in rows:
        t0 = time.perf_counter()
        c.on_joint_state(JOINTS, r, (), ())
        t.append(time.perf_counter() - t0)
    t = np.array(t[100:]) * 1e6
    return np.median(t), np.percentile(t, 99)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('--seconds', type=float, default=3.0, help='duration of each latency run')
    ap.add_argument('--rate', type=float, default=1000.0, help='rate of the latency runs, Hz')
    ap.add_argument('--rounds', type=int, default=3, help='alternating echo/dynamics rounds')
    ap.add_argument('--no-pin', action='store_true',
                    help='do not pin the driver to CPU 0 and the node under test to CPU 1')
    ap.add_argument('--max-rates', default='1000,2000,3000,4000,6000',
                    help='rates tried for the sustained-rate search (2 s each)')
    ap.add_argument('--echo-node', action='store_true', help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    _ros_env()
    if args.echo_node:
        return echo_main()

    from lie_dynamics import load_urdf
    model = load_urdf(os.path.join(ROOT, 'config', 'arm7.urdf'), joints=JOINTS)
    rng = np.random.default_rng(0)
    lo, hi = np.maximum(model.position_lower, -2.5), np.minimum(model.position_upper, 2.5)
    N = int(args.seconds * args.rate)
    Q = lo + (hi - lo) * rng.random((max(N, 12000), 7))
    expected = {'echo': Q, 'dynamics': np.array([model.gravity(q) for q in Q])}
    assert np.all(np.abs(expected['dynamics']) < model.effort_limits)  # no clamping in the table
    keys = {kind: {_key(x): k for k, x in enumerate(v)} for kind, v in expected.items()}
    med, p99 = callback_cost(model, Q)
    print(f'decision logic + g(q) in-process (no DDS): median {med:.1f} us, p99 {p99:.1f} us per message')

    cpus = sorted(os.sched_getaffinity(0))
    node_cpu = None
    if not args.no_pin and len(cpus) >= 2:
        os.sched_setaffinity(0, {cpus[0]})
        node_cpu = cpus[1]
    driver = Driver()
    results = {'echo': [], 'dynamics': []}
    sustained = {}
    try:
        for r in range(args.rounds):
            for kind in ('echo', 'dynamics'):
                proc = start(kind, node_cpu)
                try:
                    driver.wait_ready(Q[0].tolist())
                    warm = int(0.5 * args.rate)
                    driver.run(Q[N:N + warm], args.rate)  # warm-up, discarded
                    sent, achieved = driver.run(Q[:N], args.rate)
                    lat, drops = match(sent, list(driver.replies), keys[kind])
                    results[kind].append((lat, drops, achieved))
                    if r == args.rounds - 1:
                        best = None
                        for rate in [float(x) for x in args.max_rates.split(',')]:
                            n = int(2 * rate)
                            s, ach = driver.run(Q[:n], rate)
                            _, d = match(s, list(driver.replies), keys[kind])
                            if d or ach < 0.95 * rate:
                                sustained[kind] = (best, rate, d, ach)
                                break
                            best = ach
                        else:
                            sustained[kind] = (best, None, 0, best)
                finally:
                    stop(proc)
    finally:
        driver.close()

    pin = f'driver on CPU {cpus[0]}, node on CPU {node_cpu}' if node_cpu is not None else 'not pinned'
    print(f'\nround trip joint_states -> node -> command, {args.rate:.0f} Hz, {args.seconds:g} s x '
          f'{args.rounds} alternating rounds, arm7 (7 joints), SingleThreadedExecutor everywhere, {pin}')
    print(f"{'node':<10}{'sent':>8}{'drops':>7}{'rate Hz':>9}{'median ms':>11}{'p99 ms':>9}{'max ms':>9}"
          f"{'x echo med':>12}{'x echo p99':>12}")
    stats = {}
    for kind in ('echo', 'dynamics'):
        lat = np.concatenate([x[0] for x in results[kind]])
        drops = sum(x[1] for x in results[kind])
        ach = np.mean([x[2] for x in results[kind]])
        ok = lat[~np.isnan(lat)] * 1e3
        stats[kind] = (np.median(ok), np.percentile(ok, 99), ok.max(), drops, len(lat), ach)
    for kind in ('echo', 'dynamics'):
        m, p, mx, drops, n, ach = stats[kind]
        print(f'{kind:<10}{n:>8}{drops:>7}{ach:>9.0f}{m:>11.3f}{p:>9.3f}{mx:>9.3f}'
              f'{m / stats["echo"][0]:>12.2f}{p / stats["echo"][1]:>12.2f}')
    per_round = [np.nanmedian(d[0]) / np.nanmedian(e[0]) for e, d in zip(results['echo'], results['dynamics'])]
    print('median ratio per round: ' + ', '.join(f'{r:.2f}' for r in per_round))
    print('\nhighest sustained rate without a drop (2 s steps):')
    for kind, (best, failed, d, ach) in sustained.items():
        tail = (f'; at {failed:.0f} Hz: {d} drops, driver reached {ach:.0f} Hz' if failed else
                '; all steps passed (limit not reached)')
        print(f'  {kind:<10}{(f"{best:.0f} Hz" if best else "< first step"):>10}{tail}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
