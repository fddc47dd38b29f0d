"""External-torque observer and collision detection: accuracy against gain, detection delay against
threshold, and the node's cost per joint_states message with the observer beside without it.

    .venv/bin/python -m bench.observer [--quick] [--noise 0.2] [--out DIR]

Data: the bundled arm simulated at 1 kHz (lie_dynamics.sim.arm, semi-implicit Euler, URDF
damping) tracking the demo trajectory with feedforward + PD, pushed at its flange by a known
wrench (the demo's contact scenario, ground truth J^T F); the efforts are the simulator's motor
torques plus white noise of --noise N m (0: also reported). The observer runs on that recording
with the node's friction model (the URDF damping, as the simulator applies it).
  * gain sweep: RMS error against J^T F over the whole run (lag included) and once settled in the
    push (5 time constants after its start), the largest |estimate| in free motion (noise);
  * threshold sweep (gain GAIN, hold HOLD): detection delay (first flag after the push starts)
    and false alarms (flags rising in free motion);
  * cost: `DynamicsNode.on_joint_state` in-process (real rclpy publishers, no DDS transport)
    for the same states, interleaved rounds: observer off (the peer), on with `total` and with
    `gravity_removed` efforts (there the motor torque less g(q), as such a driver reports it);
    per-message medians and percentiles, and per-round ratios of the medians to the peer.
    Also the observer update alone against gravity(q) (the node's default law).
This is a benchmark, not a test: the times depend on the machine and its load; read the ratios.
Writes observer.md/.csv/.json, observer_gain.png and observer_threshold.png to --out.
"""
import argparse
import os
import sys
import time

import numpy as np

from bench.common import HERE, savefig, setup_matplotlib, time_interleaved, write_tables
from lie_dynamics import default_urdf_path, load_urdf
from lie_dynamics.algorithms.observer import MomentumObserver
from lie_dynamics.laws import clamp, effort_limits, feedforward_law, make_friction
from lie_dynamics.ros.features.contact import Debounce
from lie_dynamics.sim import contact_demo
from lie_dynamics.sim.arm import ArmSim
from lie_dynamics.sim.demo import AMPLITUDE, FREQUENCY, HOME, KD, KP
from lie_dynamics.sim.trajectory_source import desired_state

DT = 1e-3
GAINS = (5.0, 10.0, 20.0, 50.0, 100.0, 200.0, 500.0, 1000.0)
THRESHOLDS = (0.05, 0.1, 0.15, 0.25, 0.5, 1.0, 2.0, 3.0, 5.0, 8.0, 10.0, 12.0)
GAIN, HOLD = contact_demo.GAIN, contact_demo.HOLD
PUSH = (1.5, 0.5)   # start, length (s)
FLANGE = contact_demo.PUSHES[1]   # the demo's push on the flange, off the tool axis
LINK, WRENCH = FLANGE[0], contact_demo.wrench_of(FLANGE)
JOINTS = [f'joint{i}' for i in range(1, 8)]


def recording(seconds):
    """(model, friction, t, q, qd, motor, true): the contact scenario without ROS. Each sample is
    what sim_node publishes: the state, the motor torque of the step that led to it, its J^T F."""
    model = load_urdf(default_urdf_path())
    friction = make_friction(model.damping, None, 0.05)
    sim = ArmSim(model, DT, q0=HOME)
    sim.set_external(LINK, WRENCH, *PUSH)
    lim = effort_limits(model.effort_limits, 1.0)
    kp, kd = np.array(KP), np.array(KD)
    rows = []
    for _ in range(int(round(seconds / DT))):
        rows.append((sim.t, sim.q.copy(), sim.qd.copy(), sim.motor.copy(), sim.external_torque.copy()))
        des = desired_state(sim.t + DT, HOME, AMPLITUDE, FREQUENCY)
        sim.set_command(clamp(feedforward_law(model, sim.q, sim.qd, des, kp, kd, friction, False), lim)[0])
        sim.step()
    t, q, qd, motor, true = (np.array(c) for c in zip(*rows, strict=True))
    return model, friction, t, q, qd, motor, true


def windows(t, true, gain):
    """(push start, settled-push mask, free-motion mask), the push found in the truth itself."""
    pushed = np.flatnonzero(np.abs(true).max(axis=1) > 0)
    start, end = t[pushed[0]], t[pushed[-1]]
    during = (t >= start + 5.0 / gain) & (t <= end)
    free = (t < start) | (t > end + 5.0 / gain + HOLD)
    return start, during, free


def estimates(model, friction, t, q, qd, tau, gains):
    """{gain: (N, n) estimates}; M, C, g once for the recording, then the recursion per gain."""
    p, beta = MomentumObserver(model, gains[0], friction).momentum_terms(q, qd, tau)
    out = {}
    for k in gains:
        obs = MomentumObserver(model, k, friction)
        out[k] = np.array([obs.advance(t[i], p[i], beta[i]) for i in range(len(t))])
    return out


def gain_sweep(rec, noise, seed=0):
    model, friction, t, q, qd, motor, true = rec
    rows = []
    for sigma in sorted({0.0, noise}):
        tau = motor + np.random.default_rng(seed).normal(0.0, sigma, motor.shape) if sigma else motor
        for k, r in estimates(model, friction, t, q, qd, tau, GAINS).items():
            _, during, free = windows(t, true, k)
            err = r - true
            rows.append({'noise_nm': sigma, 'gain': k, 'time_constant_ms': 1e3 / k,
                         'rms_error': float(np.sqrt(np.mean(err[t > 0.1] ** 2))),
                         # nan when 5 time constants outlast the push
                         'settled_rms_error': float(np.sqrt(np.mean(err[during] ** 2))) if during.any() else np.nan,
                         'free_max': float(np.abs(r[free & (t > 0.1)]).max()),
                         'free_rms': float(np.sqrt(np.mean(r[free & (t > 0.1)] ** 2)))})
    return rows


def threshold_sweep(rec, noise, seed=0):
    model, friction, t, q, qd, motor, true = rec
    tau = motor + np.random.default_rng(seed).normal(0.0, noise, motor.shape) if noise else motor
    r = estimates(model, friction, t, q, qd, tau, (GAIN,))[GAIN]
    start, _, free = windows(t, true, GAIN)
    a = np.abs(r).max(axis=1)
    rows = []
    for thr in THRESHOLDS:
        d = Debounce(HOLD)
        flags = np.array([d.update(bool(x > thr), ti) and d.state for x, ti in zip(a, t, strict=True)])
        rising = np.flatnonzero(flags)   # update() is True on a change: with `and state`, the rising edges
        after = rising[t[rising] >= start]
        rows.append({'threshold_nm': thr, 'noise_nm': noise, 'gain': GAIN, 'hold_ms': 1e3 * HOLD,
                     'true_max_nm': float(np.abs(true).max()),
                     'detection_delay_ms': float(1e3 * (t[after[0]] - start)) if len(after) else float('nan'),
                     'false_alarms': int(np.count_nonzero(free[rising]))})
    return rows


def _messages(rec, n, convention='total'):
    """The recording's first n samples as joint_states messages, efforts under `convention`
    (gravity_removed: the motor torque less g(q), as such a driver reports it)."""
    from sensor_msgs.msg import JointState
    model, _, t, q, qd, motor, _ = rec
    msgs = []
    for i in range(min(n, len(t))):
        effort = motor[i] - model.gravity(q[i]) if convention == 'gravity_removed' else motor[i]
        m = JointState(name=JOINTS, position=q[i].tolist(), velocity=qd[i].tolist(), effort=effort.tolist())
        ns = 1_000_000_000 + int(round(t[i] * 1e9))
        m.header.stamp.sec, m.header.stamp.nanosec = ns // 1_000_000_000, ns % 1_000_000_000
        msgs.append(m)
    return msgs


# The cases of node_cost (bench.probes.observer_node too): parameters beyond bench_node's
CASES = {'observer off (peer)': {'observer.enabled': False}, 'observer, total': {},
         'observer, gravity_removed': {'measured_effort': 'gravity_removed'}}


def bench_node(model, ctx, name, extra):
    """A DynamicsNode on the bundled arm with the recording's friction (the simulator's damping),
    parameters `extra` beyond that, in rclpy context ctx."""
    from rclpy.parameter import Parameter

    from lie_dynamics.ros.node import DynamicsNode
    params = {'urdf_path': default_urdf_path(), 'friction.viscous': model.damping.tolist(),
              'friction.coulomb': [0.0], 'stale_timeout': 60.0, **extra}
    return DynamicsNode(name, context=ctx, parameter_overrides=[Parameter(p, value=v) for p, v in params.items()])


def node_cost(rec, rounds, per_round):
    """Per-message times (us) of the node's joint_states callback, observer off / total / gravity_removed."""
    import rclpy
    model = rec[0]
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    cases = CASES
    nodes = {}
    try:
        for k, (name, extra) in enumerate(cases.items()):
            nodes[name] = bench_node(model, ctx, f'observer_bench_{k}', extra)
        msgs = {name: _messages(rec, rounds * per_round, extra.get('measured_effort', 'total'))
                for name, extra in cases.items()}
        times = {name: [] for name in cases}
        for r in range(rounds):
            for name, node in nodes.items():   # interleaved: a slow phase of the machine hits all alike
                out = []
                for m in msgs[name][r * per_round:(r + 1) * per_round]:
                    t0 = time.perf_counter()
                    node.on_joint_state(m)
                    out.append(time.perf_counter() - t0)
                times[name].append(np.array(out[10:]) * 1e6)   # the first ones of a round warm caches
        published = {name: node.contact_monitor.samples for name, node in nodes.items()}
    finally:
        for node in nodes.values():
            node.destroy_node()
        rclpy.shutdown(context=ctx)
    peer = 'observer off (peer)'
    rows = []
    for name, per in times.items():
        allt = np.concatenate(per)
        ratios = [np.median(a) / np.median(b) for a, b in zip(per, times[peer], strict=True)]
        rows.append({'case': name, 'messages': int(allt.size), 'observer_samples': published[name],
                     'median_us': float(np.median(allt)), 'p90_us': float(np.percentile(allt, 90)),
                     'p99_us': float(np.percentile(allt, 99)), 'max_us': float(allt.max()),
                     'ratio_median': float(np.median(ratios)), 'ratio_min': float(np.min(ratios)),
                     'ratio_max': float(np.max(ratios))})
    return rows


def update_cost(rec, rounds):
    """The observer update alone and its kernels, per call, as ratios to gravity(q) in the same rounds."""
    model, friction, t, q, qd, motor, _ = rec
    i = len(t) // 2
    qi, qdi, ti = q[i], qd[i], motor[i]
    obs = MomentumObserver(model, GAIN, friction)
    clock = [0.0]

    def update():
        clock[0] += DT
        obs.update(clock[0], qi, qdi, ti)
    fns = {'gravity g(q) (peer)': lambda: model.gravity(qi), 'mass matrix M(q)': lambda: model.mass_matrix(qi),
           'Coriolis C(q, qd), recursive': lambda: model.coriolis_matrix(qi, qdi, method='recursive'),
           'observer update': update}
    res = time_interleaved(fns, rounds, 0.02)
    peer = res['gravity g(q) (peer)']
    return [{'call': k, 'median_us': float(np.median(v) * 1e6), 'ratio_median': float(np.median(v / peer)),
             'ratio_min': float(np.min(v / peer)), 'ratio_max': float(np.max(v / peer))} for k, v in res.items()]


def charts(gains, thresholds, out):
    plt = setup_matplotlib()
    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    for sigma in sorted({r['noise_nm'] for r in gains}):
        rs = [r for r in gains if r['noise_nm'] == sigma]
        k = [r['gain'] for r in rs]
        label = f'effort noise {sigma:g} N m'
        ax.loglog(k, [r['rms_error'] for r in rs], 'o-', label=f'RMS error, whole run ({label})')
        ax.loglog(k, [r['free_max'] for r in rs], 's--', label=f'max |estimate|, free motion ({label})')
    ax.set_xlabel('observer gain K (1/s)')
    ax.set_ylabel('N m')
    ax.set_title(f'external-torque estimate against J^T F (bundled arm, {np.linalg.norm(WRENCH[3:]):.3g} N push)',
                 fontsize=9)
    ax.grid(alpha=0.3, which='both')
    ax.legend(fontsize=7)
    fig.tight_layout()
    savefig(fig, os.path.join(out, 'observer_gain.png'))
    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    thr = [r['threshold_nm'] for r in thresholds]
    ax.plot(thr, [r['detection_delay_ms'] for r in thresholds], 'o-', label='detection delay')
    for r in thresholds:
        if r['false_alarms']:
            ax.annotate(f"{r['false_alarms']} false", (r['threshold_nm'], r['detection_delay_ms']), fontsize=7,
                        color='red', xytext=(3, 6), textcoords='offset points')
    ax.set_xlabel('collision.threshold (N m, every joint)')
    ax.set_ylabel('ms after the push starts')
    ax.set_title(f"gain {GAIN:g}/s, hold {1e3 * HOLD:g} ms, effort noise {thresholds[0]['noise_nm']:g} N m; "
                 f"largest |J^T F| {thresholds[0]['true_max_nm']:.1f} N m", fontsize=9)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    savefig(fig, os.path.join(out, 'observer_threshold.png'))


def markdown(gains, thresholds, cost, update):
    lines = ['# External-torque observer', '',
             f'Bundled arm, 1 kHz, feedforward + PD tracking, {np.linalg.norm(WRENCH[3:]):.3g} N on the flange for '
             f'{PUSH[1]:g} s (truth J^T F); efforts = motor torque + white noise.', '',
             '## Estimate error against gain', '',
             '| noise (N m) | gain (1/s) | 1/K (ms) | RMS error, whole run | RMS error, settled push | '
             'free-motion max | free-motion RMS |', '|---' * 7 + '|']
    lines += [f"| {r['noise_nm']:g} | {r['gain']:g} | {r['time_constant_ms']:.1f} | {r['rms_error']:.3g} | "
              f"{r['settled_rms_error']:.3g} | {r['free_max']:.3g} | {r['free_rms']:.3g} |" for r in gains]
    lines += ['', f'## Detection delay against threshold (gain {GAIN:g}/s, hold {1e3 * HOLD:g} ms)', '',
              '| threshold (N m) | detection delay (ms) | false alarms in free motion |', '|---' * 3 + '|']
    lines += [f"| {r['threshold_nm']:g} | {r['detection_delay_ms']:.1f} | {r['false_alarms']} |" for r in thresholds]
    lines += ['', '## Cost per joint_states message in the node (in-process callback, interleaved rounds)', '',
              '| case | messages | median µs | p90 µs | p99 µs | max µs | ratio to peer (median of rounds) | '
              'range over rounds |', '|---' * 8 + '|']
    lines += [f"| {r['case']} | {r['messages']} | {r['median_us']:.1f} | {r['p90_us']:.1f} | {r['p99_us']:.1f} | "
              f"{r['max_us']:.0f} | {r['ratio_median']:.2f} | {r['ratio_min']:.2f}-{r['ratio_max']:.2f} |"
              for r in cost]
    lines += ['', '## The observer update alone (single state, ratio to gravity(q) in the same rounds)', '',
              '| call | median µs | ratio to g(q) | range over rounds |', '|---' * 4 + '|']
    lines += [f"| {r['call']} | {r['median_us']:.1f} | {r['ratio_median']:.1f} | "
              f"{r['ratio_min']:.1f}-{r['ratio_max']:.1f} |" for r in update]
    return '\n'.join(lines) + '\n'


def run(quick=False, out=None, noise=0.2):
    out = out or os.path.join(HERE, 'out')
    os.makedirs(out, exist_ok=True)
    rec = recording(2.5 if quick else 4.0)
    gains, thresholds = gain_sweep(rec, noise), threshold_sweep(rec, noise)
    cost = node_cost(rec, 2 if quick else 8, 200 if quick else 400)
    update = update_cost(rec, 3 if quick else 15)
    md = markdown(gains, thresholds, cost, update)
    rows = ([dict(part='gain', **r) for r in gains] + [dict(part='threshold', **r) for r in thresholds]
            + [dict(part='node_cost', **r) for r in cost] + [dict(part='update_cost', **r) for r in update])
    fields = sorted({k for r in rows for k in r}, key=lambda k: (k != 'part', k))
    write_tables(out, 'observer', md, {'gain': gains, 'threshold': thresholds, 'node_cost': cost,
                                       'update_cost': update}, rows, fields)
    charts(gains, thresholds, out)
    print(md)
    return md


def main(argv=None):
    ap = argparse.ArgumentParser(prog='python -m bench.observer', description=__doc__.split('\n')[0])
    ap.add_argument('--quick', action='store_true', help='shorter recording, fewer rounds')
    ap.add_argument('--noise', type=float, default=0.2, help='effort noise, N m (white, per sample)')
    ap.add_argument('--out', default=os.path.join(HERE, 'out'), help='output directory (default bench/out)')
    args = ap.parse_args(argv)
    run(args.quick, args.out, args.noise)
    return 0


if __name__ == '__main__':
    sys.exit(main())
