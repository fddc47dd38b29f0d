"""Contact isolation and the external wrench: random pushes on the bundled arm and two real robots
through the observer and the node's decision logic, offline; the node's callback cost with
isolation beside without it.

    .venv/bin/python -m bench.contact [--quick] [--pushes 150] [--out DIR]

Plant: the robot (lie_dynamics.sim.arm, the library's forward dynamics at 1 kHz, URDF damping)
held at a random state q0 within its joint limits by gravity compensation + PD; the efforts the
observer reads are the motor torques plus white noise of NOISE x each joint's threshold. The
thresholds are scaled with the effort limits (THRESHOLD_SCALE x limit). Each push: a random link
that a controlled joint moves, a random point within +-5 cm of its origin (link axes), a random
direction, a pure force of 1x to 5x its threshold equivalent force (the force at which the most
loaded joint reaches its threshold at q0), from t = 0.1 s for PUSH_S s. The observer and the
decisions are the node's own plain-Python parts (features/contact.py ContactMonitor,
features/contact_link.py ContactIsolation) with the default gain, hold time and rcond.
  * isolation: right (the link named at the end of the push is the pushed link's body link),
    ambiguous ('' at the end), wrong (any link other than that one named at any time of the
    push), missed (no collision flag), by multiple of the threshold force;
  * identification, links with 6 or more supporting joints: force error (% of |F|) of the wrench
    at the pushed body's link at the end of the push, and the distance of its line of action
    from the pushed point;
  * the tool frame: a force at the tool's origin plus a torque, the tool wrench's force and
    torque errors;
  * cost: DynamicsNode.on_joint_state in-process (real rclpy publishers, no DDS transport) on
    the bundled arm pushed at its flange, the collision flag up: isolation on against the same
    node with its isolation stubbed out (the peer), interleaved rounds, per-round ratios.
Writes contact.md/.csv/.json to --out.
"""
import argparse
import glob
import os
import sys
import time
import warnings

import numpy as np

from bench.common import HERE, write_tables
from lie_dynamics import default_urdf_path, load_urdf
from lie_dynamics.algorithms import contact_isolation as ci
from lie_dynamics.laws import make_friction
from lie_dynamics.ros.core.params import defaults
from lie_dynamics.ros.features.contact import ContactMonitor
from lie_dynamics.ros.features.contact_link import ContactIsolation, Published
from lie_dynamics.sim.arm import ArmSim

DT = 1e-3
THRESHOLD_SCALE = 0.03     # threshold_j = this x effort limit_j
NOISE = 0.05               # effort noise, x threshold_j
START, PUSH_S, AFTER_S = 0.1, 0.4, 0.1
KP, KD = 400.0, 40.0       # the hold, per unit of the mass matrix diagonal at q0
ERD = next(iter(glob.glob(os.path.join(sys.prefix, 'lib', 'python3*', 'site-packages', 'cmeel.prefix', 'share',
                                       'example-robot-data', 'robots'))), None)


def robots():
    """[(name, model, tool link)]: the bundled arm and, with example-robot-data, Panda (arm joints,
    fingers locked) and UR5."""
    out = [('arm7 (bundled)', load_urdf(default_urdf_path()), 'tool0')]
    if ERD is None:
        return out
    with warnings.catch_warnings():
        warnings.simplefilter('ignore')
        panda = load_urdf(os.path.join(ERD, 'panda_description', 'urdf', 'panda.urdf'),
                          joints=[f'panda_joint{i}' for i in range(1, 8)])
        panda.set_locked({'panda_finger_joint1': 0.03})
        ur5 = load_urdf(os.path.join(ERD, 'ur_description', 'urdf', 'ur5_robot.urdf'))
    return out + [('Panda (fingers locked)', panda, 'panda_hand_tcp'), ('UR5', ur5, 'tool0')]


def settings_for(model):
    s = defaults()
    s.update({'collision.threshold': (THRESHOLD_SCALE * model.effort_limits).tolist(),
              'friction.viscous': model.damping.tolist(), 'friction.coulomb': [0.0]})
    return s


def random_state(model, rng):
    lo, hi = model.position_lower, model.position_upper
    ok = np.isfinite(lo) & np.isfinite(hi) & (hi > lo)
    lo, hi = np.where(ok, lo, -np.pi), np.where(ok, hi, np.pi)
    mid, half = (lo + hi) / 2, 0.45 * (hi - lo)
    return mid + rng.uniform(-1, 1, model.n) * half


def body_link(model, link):
    """The link isolation names for a push on `link`: its body's, up through bodies no joint of their own moves."""
    t = ci.tree(model)
    b = model.link_frames[link][0]
    while model.parent[b] >= 0 and not t.own[b].any():
        b = model.parent[b]
    return model.body_link_names[b]


def simulate(model, settings, q0, link, wrench_mf, rng, tool=''):
    """Run one push; returns a dict of what the node's logic published and the last sample."""
    s = dict(settings, **{'contact.wrench_frame': tool})
    th = np.asarray(s['collision.threshold'])
    friction = make_friction(model.damping, None, s['friction.coulomb_velocity_epsilon'])
    mon, iso = ContactMonitor(), ContactIsolation()
    mon.sync(s, model, friction, model.joint_names)
    iso.sync(s, model)
    sim = ArmSim(model, DT, q0=q0, limits=False)   # no stops: their impulses would be contact too
    sim.set_external(link, wrench_mf, START, PUSH_S)
    diag = np.diag(model.mass_matrix(q0))
    kp, kd = KP * diag, KD * diag
    idx = np.arange(model.n)
    named, flagged, last = set(), False, None
    for _ in range(int(round((START + PUSH_S + AFTER_S) / DT))):
        t = sim.t
        motor = sim.motor + rng.normal(0.0, NOISE, model.n) * th
        out = mon.on_state(idx, sim.q, sim.qd, motor, stamp=1_000_000_000 + int(round(t * 1e9)))
        if out is not None:
            pub = iso.update(mon.last_stamp, sim.q, out[0], out[1], mon.threshold)
            in_push = START <= t < START + PUSH_S
            if in_push:
                flagged |= out[1]
                if pub.link:
                    named.add(pub.link)
                last = (sim.q.copy(), out[0].copy(), iso.isolation, pub.tool)
        sim.set_command(model.gravity(sim.q) + kp * (q0 - sim.q) - kd * sim.qd)
        sim.step()
    return {'named': named, 'flagged': flagged, 'last': last}


def push_isolation(name, model, n_push, rng):
    settings = settings_for(model)
    th = np.asarray(settings['collision.threshold'])
    links = [ln for ln, (b, _) in model.link_frames.items() if b >= 0 and ci.supporting_joints(model, ln).any()]
    rows = []
    for _ in range(n_push):
        q0 = random_state(model, rng)
        link = links[rng.integers(len(links))]
        p = rng.uniform(-0.05, 0.05, 3)
        u = rng.normal(size=3)
        u /= np.linalg.norm(u)
        J = model.jacobian(q0, link, 'local', point=p)
        per_newton = np.abs(J[:3].T @ u) / th
        if per_newton.max() <= 0:
            continue
        mult = rng.uniform(1.0, 5.0)
        f = mult / per_newton.max() * u
        res = simulate(model, settings, q0, link, np.concatenate([np.cross(p, f), f]), rng)
        expected = body_link(model, link)
        q, r, final, _ = res['last']
        row = {'robot': name, 'link': link, 'expected': expected, 'multiple': mult, 'force_n': float(np.linalg.norm(f)),
               'supporting': int(ci.supporting_joints(model, expected).sum()), 'flagged': res['flagged'],
               'final': '' if final is None else final.link, 'status': 'none' if final is None else final.status,
               'wrong': any(x != expected for x in res['named'])}
        # identification at the pushed body's link, the last sample of the push
        est = ci.link_wrench(model, q, r, expected)
        T = np.linalg.inv(model.link_pose(expected, q)) @ model.link_pose(link, q)
        f_k = T[:3, :3] @ f
        p_k = T[:3, :3] @ p + T[:3, 3]
        row['rank'] = est.rank
        row['force_error'] = float(np.linalg.norm(est.wrench[:3] - f_k) / np.linalg.norm(f))
        line = ci.line_of_action(est.wrench)
        row['line_distance_m'] = float(np.linalg.norm(np.cross(p_k - line[0], line[1]))) if line else float('nan')
        rows.append(row)
    return rows


def tool_pushes(name, model, tool, n_push, rng):
    settings = settings_for(model)
    th = np.asarray(settings['collision.threshold'])
    rows = []
    for _ in range(n_push):
        q0 = random_state(model, rng)
        u = rng.normal(size=3)
        u /= np.linalg.norm(u)
        J = model.jacobian(q0, tool, 'local')
        f = rng.uniform(1.0, 5.0) / (np.abs(J[:3].T @ u) / th).max() * u
        m = rng.normal(size=3) * 0.05 * np.linalg.norm(f)     # a torque as a 5 cm lever would give
        res = simulate(model, settings, q0, tool, np.concatenate([m, f]), rng, tool=tool)
        q, r, _, w = res['last']
        sv = np.linalg.svd(J, compute_uv=False)
        rows.append({'robot': name, 'tool': tool, 'rank': ci.link_wrench(model, q, r, tool).rank,
                     'sigma_ratio': float(sv[-1] / sv[0]),
                     'force_error': float(np.linalg.norm(w[:3] - f) / np.linalg.norm(f)),
                     'torque_error': float(np.linalg.norm(w[3:] - m) / np.linalg.norm(m))})
    return rows


def summary(rows):
    out = []
    for name in dict.fromkeys(r['robot'] for r in rows):
        for label, sel in (('1-2x', lambda r: r['multiple'] < 2), ('2-5x', lambda r: r['multiple'] >= 2),
                           ('all', lambda r: True)):
            rs = [r for r in rows if r['robot'] == name and sel(r)]
            if not rs:
                continue
            n = len(rs)
            out.append({'robot': name, 'threshold_multiple': label, 'pushes': n,
                        'flagged_pct': 100 * sum(r['flagged'] for r in rs) / n,
                        'right_pct': 100 * sum(r['final'] == r['expected'] for r in rs) / n,
                        'ambiguous_pct': 100 * sum(r['final'] == '' and r['flagged'] for r in rs) / n,
                        'wrong_pct': 100 * sum(r['wrong'] for r in rs) / n,
                        'wrong_supporting_lt6': sum(r['wrong'] and r['supporting'] < 6 for r in rs)})
    return out


def identification(rows):
    out = []
    for name in dict.fromkeys(r['robot'] for r in rows):
        rs = [r for r in rows if r['robot'] == name and r['supporting'] >= 6]
        if not rs:
            continue
        fe = np.array([r['force_error'] for r in rs]) * 100
        ld = np.array([r['line_distance_m'] for r in rs]) * 100
        full = [r for r in rs if r['rank'] == 6]
        out.append({'robot': name, 'pushes': len(rs), 'rank6_pct': 100 * len(full) / len(rs),
                    'force_error_median_pct': float(np.median(fe)), 'force_error_p95_pct': float(np.percentile(fe, 95)),
                    'force_error_le5_pct': float(100 * np.mean(fe <= 5)),
                    'line_median_cm': float(np.nanmedian(ld)), 'line_p95_cm': float(np.nanpercentile(ld, 95)),
                    'line_le1cm_pct': float(100 * np.mean(ld <= 1))})
    return out


def tool_summary(rows):
    out = []
    for name in dict.fromkeys(r['robot'] for r in rows):
        rs = [r for r in rows if r['robot'] == name]
        fe = np.array([r['force_error'] for r in rs]) * 100
        te = np.array([r['torque_error'] for r in rs]) * 100
        out.append({'robot': name, 'tool': rs[0]['tool'], 'pushes': len(rs),
                    'rank6_pct': 100 * np.mean([r['rank'] == 6 for r in rs]),
                    'force_error_median_pct': float(np.median(fe)), 'force_error_p95_pct': float(np.percentile(fe, 95)),
                    'torque_error_median_pct': float(np.median(te)),
                    'torque_error_p95_pct': float(np.percentile(te, 95)),
                    'wrench_le2_pct': float(100 * np.mean((fe <= 2) & (te <= 2)))})
    return out


def node_cost(rounds, per_round):
    """Per-message times (us) of the node's joint_states callback on a push at the flange (flag
    up), isolation on and stubbed out; interleaved rounds, per-round ratios of the medians."""
    import rclpy
    from rclpy.parameter import Parameter
    from sensor_msgs.msg import JointState

    from lie_dynamics.ros.node import DynamicsNode
    model = load_urdf(default_urdf_path())
    rng = np.random.default_rng(3)
    q0 = np.array([0.0, -0.6, 0.0, 2.0, 0.0, 1.6, 0.8])
    s = settings_for(model)
    sim = ArmSim(model, DT, q0=q0)
    sim.set_external('tool0', np.array([0.3, -0.5, 0.2, 20.0, -15.0, 10.0]), 0.05, 10.0)
    diag = np.diag(model.mass_matrix(q0))
    msgs = []
    th = np.asarray(s['collision.threshold'])
    for k in range(rounds * per_round + 100):
        m = JointState(name=model.joint_names, position=sim.q.tolist(), velocity=sim.qd.tolist(),
                       effort=(sim.motor + rng.normal(0, NOISE, model.n) * th).tolist())
        ns = 1_000_000_000 + k * 1_000_000
        m.header.stamp.sec, m.header.stamp.nanosec = divmod(ns, 1_000_000_000)
        msgs.append(m)
        sim.set_command(model.gravity(sim.q) + KP * diag * (q0 - sim.q) - KD * diag * sim.qd)
        sim.step()
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    cases = ('isolation stubbed (peer)', 'isolation on', 'isolation on + tool wrench')
    nodes = {}
    try:
        for k, name in enumerate(cases):
            params = {'urdf_path': default_urdf_path(), 'friction.viscous': model.damping.tolist(),
                      'friction.coulomb': [0.0], 'stale_timeout': 60.0,
                      'collision.threshold': s['collision.threshold'],
                      'contact.wrench_frame': 'tool0' if 'tool' in name else ''}
            nodes[name] = DynamicsNode(f'contact_bench_{k}', context=ctx,
                                       parameter_overrides=[Parameter(p, value=v) for p, v in params.items()])
        feature = nodes[cases[0]].features.get('contact')
        feature.isolation.update = lambda *a: Published(None, None, None)   # the peer: the observer only
        for node in nodes.values():     # the first 100 states: the push rises, the flag goes up, isolation settles
            for m in msgs[:100]:
                node.on_joint_state(m)
        times = {name: [] for name in cases}
        for r in range(rounds):
            batch = msgs[100 + r * per_round:100 + (r + 1) * per_round]
            for name in cases[r % 3:] + cases[:r % 3]:
                out = []
                for m in batch:
                    t0 = time.perf_counter()
                    nodes[name].on_joint_state(m)
                    out.append(time.perf_counter() - t0)
                times[name].append(np.array(out) * 1e6)
        state = {name: (node.contact_monitor.collision, node.features.get('contact').isolation.link)
                 for name, node in nodes.items()}
    finally:
        for node in nodes.values():
            node.destroy_node()
        rclpy.shutdown(context=ctx)
    peer = cases[0]
    rows = []
    for name, per in times.items():
        allt = np.concatenate(per)
        ratios = [np.median(a) / np.median(b) for a, b in zip(per, times[peer], strict=True)]
        rows.append({'case': name, 'collision': state[name][0], 'link': state[name][1], 'messages': int(allt.size),
                     'median_us': float(np.median(allt)), 'p90_us': float(np.percentile(allt, 90)),
                     'p99_us': float(np.percentile(allt, 99)), 'ratio_median': float(np.median(ratios)),
                     'ratio_min': float(np.min(ratios)), 'ratio_max': float(np.max(ratios))})
    return rows


def _table(rows, cols):
    head = '| ' + ' | '.join(cols) + ' |\n|' + '---|' * len(cols) + '\n'
    def fmt(v):
        return f'{v:.3g}' if isinstance(v, float) else str(v)
    return head + ''.join('| ' + ' | '.join(fmt(r[c]) for c in cols) + ' |\n' for r in rows)


def run(quick=False, out=None, pushes=None, seed=0):
    rng = np.random.default_rng(seed)
    n = pushes or (12 if quick else 150)
    rows, tools = [], []
    for name, model, tool in robots():
        rows += push_isolation(name, model, n, rng)
        tools += tool_pushes(name, model, tool, max(4, n // 5), rng)
    iso, ident, tool = summary(rows), identification(rows), tool_summary(tools)
    cost = node_cost(rounds=4 if quick else 20, per_round=50 if quick else 200)
    md = ('# Contact isolation and the external wrench\n\n'
          f'Pushes per robot: {n}; thresholds {THRESHOLD_SCALE} x effort limits; effort noise {NOISE} x threshold; '
          f'seed {seed}.\n\n## Isolation\n\n'
          + _table(iso, list(iso[0])) + '\n## Identification (links with 6 or more supporting joints)\n\n'
          + (_table(ident, list(ident[0])) if ident else 'none\n') + '\n## Tool frame\n\n'
          + _table(tool, list(tool[0])) + '\n## Callback cost (bundled arm, flag up)\n\n' + _table(cost, list(cost[0])))
    if out:
        os.makedirs(out, exist_ok=True)
        write_tables(out, 'contact', md, {'isolation': iso, 'identification': ident, 'tool': tool, 'cost': cost,
                                          'pushes': rows}, rows=rows)
    print(md)
    return iso, ident, tool, cost


def main(argv=None):
    ap = argparse.ArgumentParser(prog='python -m bench.contact', description=__doc__.split('\n')[0])
    ap.add_argument('--quick', action='store_true')
    ap.add_argument('--pushes', type=int, default=None, help='pushes per robot (default 150, quick 12)')
    ap.add_argument('--out', default=os.path.join(HERE, 'out'))
    args = ap.parse_args(argv)
    run(args.quick, args.out, args.pushes)


if __name__ == '__main__':
    main()
