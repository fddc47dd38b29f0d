"""Feedforward benchmark: trajectory effort fill next to a Pinocchio loop, and the dynamics
node's streaming latency in feedforward mode next to gravity mode.

    .venv/bin/python -m bench.feedforward [--quick] [--no-latency] [--out DIR]
    (or bench.feedforward.run(quick=..., out=...) from an aggregating runner)

1. Trajectory fill, bundled 7-DoF arm, N = 100, 1 000, 10 000 points of a smooth trajectory:
   * batched: `fill_trajectory_efforts` with positions, velocities and accelerations given
     (validation + one batched inverse-dynamics call);
   * batched, accelerations derived: the same without accelerations (np.gradient first);
   * message path: what the node does per trajectory_msgs/JointTrajectory - message to
     arrays, fill, friction / clamp, efforts written back into the message's points;
   * Pinocchio loop: a Python loop of pin.rnea over the points (arrays prepared beforehand).
   Implementations are timed once per round, rounds interleaved; medians over rounds, and
   the speed-up is the median of per-round ratios (Pinocchio loop / batched fill).
2. Streaming latency (bench/node_latency.py's driver and matching): a driver publishes
   joint_states and, alongside each, a one-point desired state (constant) at a fixed rate; the
   node runs in its own process with mode gravity (tau = g(q)) or feedforward with kp = 1
   (tau = ID(q_d, qd_d, qdd_d) + (q_d - q), distinct per message so replies match by value).
   Also the in-process cost of the decision logic per message for both modes (no DDS).
Writes bench/out/feedforward.md and feedforward.csv. Numbers depend on the machine and its load.
"""
import argparse
import csv
import os
import platform
import sys
import time

import numpy as np

from bench import node_latency as nl

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
ARM = os.path.join(ROOT, 'config', 'arm7.urdf')
SIZES = (100, 1_000, 10_000)
DESIRED = '/dynamics_node/desired'
FILL_CASES = ('batched', 'batched_derived', 'message', 'pinocchio')
FILL_LABELS = {'batched': 'batched fill (q, qd, qdd given)', 'batched_derived': 'batched fill, qdd derived',
               'message': 'message path (node)', 'pinocchio': 'Pinocchio rnea loop'}


def smooth(N, n=7, T=10.0):
    t = np.linspace(0.0, T, N)
    w = 2 * np.pi / T * np.arange(1, n + 1) / 2
    s, c = np.sin(np.outer(t, w)), np.cos(np.outer(t, w))
    return t, 0.5 * s, 0.5 * c * w, -0.5 * s * w ** 2


# ---------------------------------------------------------------- 1. trajectory fill

def fill_bench(quick=False):
    import pinocchio as pin

    from lie_dynamics import load_urdf
    from lie_dynamics.ros.core.compensator import Compensator
    from lie_dynamics.ros.trajectories.fill import TrajectoryInput
    from lie_dynamics.ros.trajectories.trajectory_msgs import set_point_efforts, trajectory_arrays, trajectory_message
    from lie_dynamics.trajectory import fill_trajectory_efforts

    xml = open(ARM).read()
    model = load_urdf(xml)
    pmodel = pin.buildModelFromXML(xml)
    pdata = pmodel.createData()
    pin_names = [pmodel.names[i] for i in range(1, pmodel.njoints)]
    assert pin_names == model.joint_names and pmodel.nq == pmodel.nv == model.n, 'joint orders differ'
    comp = Compensator({'friction.viscous': [0.0], 'friction.coulomb': [0.0]})
    comp.set_model(load_urdf(xml))
    side = TrajectoryInput(comp)   # the node's checks and counts of a fill
    rounds = 5 if quick else 15
    result = {'rounds': rounds, 'sizes': {}}
    for N in SIZES:
        t, q, qd, qdd = smooth(N)
        traj = {'joint_names': model.joint_names, 'time_from_start': t, 'positions': q, 'velocities': qd,
                'accelerations': qdd}
        traj_d = {k: v for k, v in traj.items() if k != 'accelerations'}
        msg = trajectory_message(model.joint_names, t, q, qd, qdd)
        rows = [(np.ascontiguousarray(a), np.ascontiguousarray(b), np.ascontiguousarray(c))
                for a, b, c in zip(q, qd, qdd)]

        def pin_loop():
            out = np.empty((N, model.n))
            for k, (a, b, c) in enumerate(rows):
                out[k] = pin.rnea(pmodel, pdata, a, b, c)
            return out

        def message_path():   # what the trajectory process does with a message the node lets it fill
            eff, note = side.job(len(msg.points)).fill(msg.joint_names, trajectory_arrays(msg.joint_names, msg.points))
            side.done(None, note)
            set_point_efforts(msg.points, eff)
            return eff

        fns = {'batched': lambda: fill_trajectory_efforts(model, traj)['efforts'],
               'batched_derived': lambda: fill_trajectory_efforts(model, traj_d)['efforts'],
               'message': message_path, 'pinocchio': pin_loop}
        ref = pin_loop()
        scale = max(1.0, np.max(np.abs(ref)))
        err = {k: float(np.max(np.abs(fns[k]() - ref)) / scale) for k in ('batched', 'message')}
        times = {k: [] for k in fns}
        for _ in range(rounds):
            for k, fn in fns.items():
                t0 = time.perf_counter()
                fn()
                times[k].append(time.perf_counter() - t0)
        times = {k: np.array(v) for k, v in times.items()}
        result['sizes'][N] = {
            'median_ms': {k: float(np.median(v) * 1e3) for k, v in times.items()},
            'speedup': {k: float(np.median(times['pinocchio'] / v)) for k, v in times.items() if k != 'pinocchio'},
            'rel_err': err,
        }
    return result


# ---------------------------------------------------------------- 2. streaming latency

class FeedforwardDriver(nl.Driver):
    """node_latency's driver, also publishing the (constant) desired state before each joint_states."""

    def __init__(self, desired):
        super().__init__()
        from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint
        q_d, qd_d, qdd_d = desired
        self.desired = JointTrajectory(joint_names=nl.JOINTS, points=[JointTrajectoryPoint(
            positions=q_d.tolist(), velocities=qd_d.tolist(), accelerations=qdd_d.tolist())])
        self.des_pub = self.node.create_publisher(JointTrajectory, DESIRED, 10)

    def publish(self, q):
        self.des_pub.publish(self.desired)
        super().publish(q)

    def wait_ready(self, probe_q, timeout=60.0):
        end = time.monotonic() + timeout
        while not self.des_pub.get_subscription_count():
            if time.monotonic() > end:
                raise RuntimeError('desired-state subscription not discovered')
            self.ex.spin_once(timeout_sec=0.01)
        super().wait_ready(probe_q, timeout=max(1.0, end - time.monotonic()))


def callback_cost(model, Q, desired, mode):
    """Decision logic + torque law in-process per joint_states message (no DDS): median, p99 in us."""
    import array

    from lie_dynamics.ros.core.compensator import Compensator
    from trajectory_msgs.msg import JointTrajectoryPoint
    c = Compensator({'joints': nl.JOINTS, 'friction.viscous': [0.0], 'friction.coulomb': [0.0], 'mode': mode,
                     'kp': [1.0], 'desired_timeout': 60.0})
    c.set_model(model)
    q_d, qd_d, qdd_d = desired
    pt = JointTrajectoryPoint(positions=q_d.tolist(), velocities=qd_d.tolist(), accelerations=qdd_d.tolist())
    c.on_desired(nl.JOINTS, [pt])
    rows = [array.array('d', q) for q in Q[:2000]]
    t = []
    for r in rows:
        t0 = time.perf_counter()
        c.on_joint_state(nl.JOINTS, r, (), ())
        t.append(time.perf_counter() - t0)
    t0 = time.perf_counter()
    for _ in range(2000):
        c.on_desired(nl.JOINTS, [pt])
    des = (time.perf_counter() - t0) / 2000
    t = np.array(t[100:]) * 1e6
    return float(np.median(t)), float(np.percentile(t, 99)), des * 1e6


def latency_bench(seconds, rate, rounds, pin_cpus=True):
    nl.ros_env()
    from lie_dynamics import load_urdf
    model = load_urdf(ARM, joints=nl.JOINTS)
    rng = np.random.default_rng(0)
    lo, hi = np.maximum(model.position_lower, -2.5), np.minimum(model.position_upper, 2.5)
    N = int(seconds * rate)
    warm = int(0.5 * rate)
    Q = lo + (hi - lo) * rng.random((N + warm, 7))
    desired = (0.5 * (lo + hi), np.full(7, 0.5), np.full(7, 1.0))
    tau_ff = model.inverse_dynamics(*desired)
    expected = {'gravity': model.gravity(Q), 'feedforward': tau_ff + (desired[0] - Q)}
    for v in expected.values():
        assert np.all(np.abs(v) < model.effort_limits)  # no clamping
    keys = {m: {nl.reply_key(x): k for k, x in enumerate(v[:N])} for m, v in expected.items()}
    params = {'gravity': {'mode': 'gravity'},
              'feedforward': {'mode': 'feedforward', 'kp': '[1.0]', 'kd': '[0.0]', 'desired_timeout': '1.0'}}
    cost = {m: callback_cost(model, Q, desired, m) for m in params}

    cpus = sorted(os.sched_getaffinity(0))
    node_cpu = None
    if pin_cpus and len(cpus) >= 2:
        os.sched_setaffinity(0, {cpus[0]})
        node_cpu = cpus[1]
    driver = FeedforwardDriver(desired)
    runs = {m: [] for m in params}
    try:
        for _ in range(rounds):
            for mode, p in params.items():
                proc = nl.start('dynamics', node_cpu, p)
                try:
                    driver.wait_ready(Q[0].tolist())
                    driver.run(Q[N:N + warm], rate)  # warm-up (also makes the desired state fresh)
                    sent, achieved = driver.run(Q[:N], rate)
                    lat, drops = nl.match(sent, list(driver.replies), keys[mode])
                    runs[mode].append((lat, drops, achieved))
                finally:
                    nl.stop(proc)
    finally:
        driver.close()
        if node_cpu is not None:
            os.sched_setaffinity(0, set(cpus))
    stats = {}
    for mode, rs in runs.items():
        lat = np.concatenate([r[0] for r in rs])
        ok = lat[~np.isnan(lat)] * 1e3
        stats[mode] = {'sent': int(len(lat)), 'drops': int(sum(r[1] for r in rs)),
                       'rate_hz': float(np.mean([r[2] for r in rs])),
                       'median_ms': float(np.median(ok)) if len(ok) else float('nan'),
                       'p99_ms': float(np.percentile(ok, 99)) if len(ok) else float('nan'),
                       'max_ms': float(ok.max()) if len(ok) else float('nan'),
                       'inproc_median_us': cost[mode][0], 'inproc_p99_us': cost[mode][1],
                       'inproc_desired_us': cost[mode][2]}
    pin = f'driver on CPU {cpus[0]}, node on CPU {node_cpu}' if node_cpu is not None else 'not pinned'
    return {'seconds': seconds, 'rate': rate, 'rounds': rounds, 'pinning': pin, 'modes': stats}


# ---------------------------------------------------------------- output

def markdown(fill, lat):
    import numpy
    try:
        import pinocchio
        pv = pinocchio.__version__
    except Exception:  # noqa: BLE001
        pv = '?'
    lines = ['# Feedforward benchmark: lie_arm7 (7 DoF)', '',
             f'Python {platform.python_version()}, numpy {numpy.__version__}, Pinocchio {pv}, '
             f'{os.cpu_count()} cores.', '',
             '## Trajectory effort fill', '',
             f"Median over {fill['rounds']} interleaved rounds, ms per trajectory; speed-up = median of "
             'per-round (Pinocchio loop time / this time), > 1 means faster than the Pinocchio loop.', '',
             '| points | ' + ' | '.join(FILL_LABELS[k] + ' ms' for k in FILL_CASES)
             + ' | batched speed-up | derived speed-up | message-path speed-up | µs/point batched | max rel. diff |',
             '|---' * (len(FILL_CASES) + 6) + '|']
    for N, r in fill['sizes'].items():
        m, s = r['median_ms'], r['speedup']
        lines.append(f'| {N} | ' + ' | '.join(f'{m[k]:.3g}' for k in FILL_CASES)
                     + f" | {s['batched']:.2f} | {s['batched_derived']:.2f} | {s['message']:.2f}"
                     + f" | {1e3 * m['batched'] / N:.3g} | {max(r['rel_err'].values()):.1e} |")
    big = fill['sizes'][max(fill['sizes'])]
    verdict = 'met' if big['speedup']['batched'] > 1 else 'NOT met'
    lines += ['', f"Target (batched fill of {max(fill['sizes'])} points faster than the Pinocchio loop): {verdict} "
              f"({big['speedup']['batched']:.2f}x).", '']
    if lat:
        lines += ['## Streaming latency', '',
                  f"joint_states (+ one desired state each) -> node -> command round trip, {lat['rate']:.0f} Hz, "
                  f"{lat['seconds']:g} s x {lat['rounds']} alternating rounds, SingleThreadedExecutor, "
                  f"{lat['pinning']}. In-process: decision logic + torque law per joint_states message, "
                  'and per desired message, without DDS.', '',
                  '| mode | sent | drops | rate Hz | median ms | p99 ms | max ms | in-process median µs | '
                  'in-process p99 µs | desired msg µs |', '|---' * 10 + '|']
        for mode, s in lat['modes'].items():
            lines.append(f"| {mode} | {s['sent']} | {s['drops']} | {s['rate_hz']:.0f} | {s['median_ms']:.3f} | "
                         f"{s['p99_ms']:.3f} | {s['max_ms']:.3f} | {s['inproc_median_us']:.1f} | "
                         f"{s['inproc_p99_us']:.1f} | {s['inproc_desired_us']:.1f} |")
        g, f = lat['modes']['gravity'], lat['modes']['feedforward']
        lines += ['', f"feedforward / gravity median latency: {f['median_ms'] / g['median_ms']:.2f}", '']
    return '\n'.join(lines)


def write(fill, lat, out_dir):
    os.makedirs(out_dir, exist_ok=True)
    md = markdown(fill, lat)
    with open(os.path.join(out_dir, 'feedforward.md'), 'w') as fh:
        fh.write(md + '\n')
    with open(os.path.join(out_dir, 'feedforward.csv'), 'w', newline='') as fh:
        w = csv.writer(fh)
        w.writerow(['benchmark', 'case', 'n', 'median_ms', 'p99_ms', 'max_ms', 'speedup_vs_pinocchio_loop',
                    'drops', 'max_rel_diff'])
        for N, r in fill['sizes'].items():
            for k in FILL_CASES:
                w.writerow(['fill', k, N, f"{r['median_ms'][k]:.6g}", '', '', f"{r['speedup'].get(k, 1.0):.4g}", '',
                            f"{r['rel_err'].get(k, 0.0):.3g}" if k in r['rel_err'] else ''])
        if lat:
            for mode, s in lat['modes'].items():
                w.writerow(['latency', mode, s['sent'], f"{s['median_ms']:.6g}", f"{s['p99_ms']:.6g}",
                            f"{s['max_ms']:.6g}", '', s['drops'], ''])
                w.writerow(['inprocess', mode, 2000, f"{s['inproc_median_us'] / 1e3:.6g}",
                            f"{s['inproc_p99_us'] / 1e3:.6g}", '', '', '', ''])
    return md


def run(quick=False, out=None, latency=True, rate=1000.0, pin_cpus=True):
    """Both parts; writes out/feedforward.{md,csv} (default bench/out); returns (fill, latency or None,
    markdown)."""
    out = out or os.path.join(HERE, 'out')
    fill = fill_bench(quick)
    lat = latency_bench(1.0 if quick else 3.0, rate, 1 if quick else 3, pin_cpus) if latency else None
    return fill, lat, write(fill, lat, out)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('--quick', action='store_true', help='fewer rounds, 1 s latency runs')
    ap.add_argument('--no-latency', action='store_true', help='trajectory fill only (no ROS processes)')
    ap.add_argument('--rate', type=float, default=1000.0, help='latency run rate, Hz')
    ap.add_argument('--no-pin', action='store_true', help='do not pin driver and node to CPUs 0 and 1')
    ap.add_argument('--out', default=os.path.join(HERE, 'out'), help='output directory')
    args = ap.parse_args(argv)
    print(run(args.quick, args.out, not args.no_latency, args.rate, not args.no_pin)[2])
    return 0


if __name__ == '__main__':
    sys.exit(main())
