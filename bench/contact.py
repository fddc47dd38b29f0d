"""Contact isolation and the external wrench: random pushes on the bundled arm and two real robots
through the observer and the node's decision logic, offline; the node's callback cost with
isolation beside without it.

    .venv/bin/python -m bench.contact [--quick] [--pushes 150] [--strict-below 0] [--out DIR]

Plant: the robot (lie_dynamics.sim.arm, the library's forward dynamics at 1 kHz, URDF damping)
held at a random state q0 within its joint limits by gravity compensation + PD (HOLD_KP, a damping
matrix that damps every mode of M(q0) critically: hold_gains); the efforts the observer reads are
the motor torques (before the first step the hold's, g(q0)), exact and with white noise of NOISE x
each joint's threshold. The arm runs free for START s first: the node measures the residual's noise. The
thresholds are scaled with the effort limits (THRESHOLD_SCALE x limit). Each push: a random link
that a controlled joint moves, a random point within +-5 cm of its origin (link axes), a random
direction, a pure force of 1x to 5x its threshold equivalent force (the force at which the most
loaded joint reaches its threshold at q0), from t = 0.1 s for PUSH_S s. The observer and the
decisions are the node's own plain-Python parts (features/contact.py ContactMonitor,
features/contact_link.py ContactIsolation) with the default gain, hold time and rcond.
  * isolation, default and strict (contact.strict_isolation), from one run of the observer:
    right (the link named at the end of the push is the pushed link's body link), ambiguous
    ('' at the end, the flag up), wrong (any link other than that one named at any time of the
    push), by multiple of the threshold force;
  * identification, links with 6 or more supporting joints: force error (% of |F|) of the wrench
    at the pushed body's link at the end of the push (from ContactIsolation.residual: the mean
    over the settled stretch), and the distance of its line of action
    from the pushed point;
  * the tool frame: a force at the tool's origin plus a torque, the tool wrench's force and
    torque errors;
  * cost: DynamicsNode.on_joint_state in-process (real rclpy publishers, no DDS transport) on
    the bundled arm, in free motion (flag down) and pushed at its tool (flag up, isolated):
    isolation on, and with the tool wrench, against the same node with its isolation stubbed
    out (the peer), interleaved rounds, per-round ratios.
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
from lie_dynamics.ros.core.settings import Settings
from lie_dynamics.ros.features.contact import ContactMonitor
from lie_dynamics.ros.features.contact_link import ContactIsolation, Published
from lie_dynamics.sim.arm import ArmSim

DT = 1e-3
THRESHOLD_SCALE = 0.03     # threshold_j = this x effort limit_j
NOISE = 0.05               # effort noise, x threshold_j
START, PUSH_S, AFTER_S = 0.5, 0.4, 0.1   # free 0.5 s first: the node measures the residual's noise
MODES = ('default', 'strict')   # contact.strict_isolation false, true
STRICT_BELOW = ci.STRICT_BELOW   # contact.strict_below of both modes: the node's default (--strict-below 0: off)
HOLD_KP = 3.0              # the hold's stiffness, N m/rad per N m of effort limit (critically damped)
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
    return Settings({'collision.threshold': (THRESHOLD_SCALE * model.effort_limits).tolist(),
                     'contact.strict_below': STRICT_BELOW,
                     'friction.viscous': model.damping.tolist(), 'friction.coulomb': [0.0]})


def random_state(model, rng):
    lo, hi = model.position_lower, model.position_upper
    ok = np.isfinite(lo) & np.isfinite(hi) & (hi > lo)
    lo, hi = np.where(ok, lo, -np.pi), np.where(ok, hi, np.pi)
    mid, half = (lo + hi) / 2, 0.45 * (hi - lo)
    return mid + rng.uniform(-1, 1, model.n) * half


def hold_gains(model, q0):
    """(kp (n,), Kd (n, n)) of the hold: kp = HOLD_KP x effort limit, Kd critically damping every mode
    of M(q0) under kp (2 M^1/2 (M^-1/2 Kp M^-1/2)^1/2 M^1/2). A diagonal kd from M's diagonal
    left coupled modes (parallel axes) with dt x eig(M^-1 Kd) above 2 in some states: the
    explicit damping of the 1 ms step went unstable, the arm swung and the drives saturated."""
    kp = HOLD_KP * model.effort_limits
    w, V = np.linalg.eigh(model.mass_matrix(q0))
    half = (V * np.sqrt(w)) @ V.T
    inv_half = (V / np.sqrt(w)) @ V.T
    w2, V2 = np.linalg.eigh(inv_half @ (kp[:, None] * inv_half))
    return kp, 2.0 * half @ ((V2 * np.sqrt(np.maximum(w2, 0.0))) @ V2.T) @ half


def body_link(model, link):
    """The link isolation names for a push on `link`: its body's, up through bodies no joint of their own moves."""
    t = ci.tree(model)
    b = model.link_frames[link][0]
    while model.parent[b] >= 0 and not t.own[b].any():
        b = model.parent[b]
    return model.body_link_names[b]


def pushable_links(model):
    """The links a push may hit: those of bodies that some controlled joint moves."""
    return [ln for ln, (b, _) in model.link_frames.items() if b >= 0 and ci.supporting_joints(model, ln).any()]


def draw_push(model, links, th, rng):
    """One random push, drawn in this order from rng: the held state q0, the link, the point p
    (link axes, within 5 cm of its origin), the direction and the multiple of the threshold's
    equivalent force. Returns (q0, link, p, f, multiple), or None for a direction no joint feels."""
    q0 = random_state(model, rng)
    link = links[rng.integers(len(links))]
    p = rng.uniform(-0.05, 0.05, 3)
    u = rng.normal(size=3)
    u /= np.linalg.norm(u)
    J = model.jacobian(q0, link, 'local', point=p)
    per_newton = np.abs(J[:3].T @ u) / th
    if per_newton.max() <= 0:
        return None
    mult = rng.uniform(1.0, 5.0)
    return q0, link, p, mult / per_newton.max() * u, mult


def run_push(model, settings, q0, link, wrench_mf, rng, noise, isos, seconds, on_sample):
    """The plant holding q0 while wrench_mf pushes `link` from START for PUSH_S, the observer
    (the node's ContactMonitor under `settings`) and each isolation of `isos` (adopted already)
    fed every sample, for `seconds`. on_sample(t, sim, out, pubs): each observer sample, out the
    monitor's (estimate, flag), pubs {key: the isolation's Published}."""
    th = np.asarray(settings.collision.threshold)
    mon = ContactMonitor()
    mon.adopt(settings, model, make_friction(model.damping, None, settings.friction.coulomb_velocity_epsilon),
              model.joint_names)
    sim = ArmSim(model, DT, q0=q0, limits=False)   # no stops: their impulses would be contact too
    sim.motor = model.gravity(q0)   # the drive's effort before the first step: the hold (not 0, a jolt)
    sim.set_external(link, wrench_mf, START, PUSH_S)
    kp, kd = hold_gains(model, q0)
    for _ in range(int(round(seconds / DT))):
        t = sim.t
        motor = sim.motor + rng.normal(0.0, noise, model.n) * th
        out = mon.on_state(sim.q, sim.qd, motor, stamp=1_000_000_000 + int(round(t * 1e9)))
        if out is not None:
            on_sample(t, sim, out, {m: iso.update(mon.last_stamp, sim.q, out[0], out[1], mon.threshold)
                                    for m, iso in isos.items()})
        sim.set_command(model.gravity(sim.q) + kp * (q0 - sim.q) - kd @ sim.qd)
        sim.step()


def simulate(model, settings, q0, link, wrench_mf, rng, noise, tool=''):
    """Run one push: for each isolation mode (default, strict) the links named during the push and
    the decision at its end; whether the flag rose; the last sample of the push (q, r, tool wrench)."""
    s = settings.replace({'contact.wrench_frame': tool})
    isos = {}
    for mode in MODES:
        isos[mode] = ContactIsolation()
        isos[mode].adopt(s.replace({'contact.strict_isolation': mode == 'strict',
                                    'contact.wrench_frame': tool if mode == 'default' else ''}), model)
    res = {'named': {m: set() for m in MODES}, 'flagged': False, 'last': None}

    def sample(t, sim, out, pubs):
        if START <= t < START + PUSH_S:
            res['flagged'] |= out[1]
            for m, pub in pubs.items():
                if pub.link:
                    res['named'][m].add(pub.link)
            res['last'] = (sim.q.copy(), isos['default'].residual.copy(), {m: iso.isolation for m, iso in isos.items()},
                           pubs['default'].tool)
    run_push(model, s, q0, link, wrench_mf, rng, noise, isos, START + PUSH_S + AFTER_S, sample)
    return res


def push_isolation(name, model, n_push, rng, noise):
    settings = settings_for(model)
    th = np.asarray(settings.collision.threshold)
    links = pushable_links(model)
    rows = []
    for _ in range(n_push):
        drawn = draw_push(model, links, th, rng)
        if drawn is None:
            continue
        q0, link, p, f, mult = drawn
        res = simulate(model, settings, q0, link, np.concatenate([np.cross(p, f), f]), rng, noise)
        expected = body_link(model, link)
        q, r, final, _ = res['last']
        row = {'robot': name, 'noise': noise, 'link': link, 'expected': expected, 'multiple': mult,
               'force_n': float(np.linalg.norm(f)), 'supporting': int(ci.supporting_joints(model, expected).sum()),
               'flagged': res['flagged']}
        for m in MODES:
            iso = final[m]
            row[f'{m}_final'] = '' if iso is None else iso.link
            row[f'{m}_wrong'] = any(x != expected for x in res['named'][m])
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


def tool_pushes(name, model, tool, n_push, rng, noise):
    settings = settings_for(model)
    th = np.asarray(settings.collision.threshold)
    rows = []
    for _ in range(n_push):
        q0 = random_state(model, rng)
        u = rng.normal(size=3)
        u /= np.linalg.norm(u)
        J = model.jacobian(q0, tool, 'local')
        f = rng.uniform(1.0, 5.0) / (np.abs(J[:3].T @ u) / th).max() * u
        m = rng.normal(size=3) * 0.05 * np.linalg.norm(f)     # a torque as a 5 cm lever would give
        res = simulate(model, settings, q0, tool, np.concatenate([m, f]), rng, noise, tool=tool)
        q, r, _, w = res['last']
        est = ci.link_wrench(model, q, r, tool)
        rows.append({'robot': name, 'noise': noise, 'tool': tool, 'rank': est.rank,
                     'sigma_min': est.sigma_min,
                     'force_error': float(np.linalg.norm(w[:3] - f) / np.linalg.norm(f)),
                     'torque_error': float(np.linalg.norm(w[3:] - m) / np.linalg.norm(m))})
    return rows


def _groups(rows):
    return list(dict.fromkeys((r['robot'], r['noise']) for r in rows))


def summary(rows):
    out = []
    for name, noise in _groups(rows):
        for label, sel in (('1-2x', lambda r: r['multiple'] < 2), ('2-5x', lambda r: r['multiple'] >= 2)):
            rs = [r for r in rows if (r['robot'], r['noise']) == (name, noise) and sel(r)]
            if not rs:
                continue
            n = len(rs)
            row = {'robot': name, 'noise': noise, 'threshold_multiple': label, 'pushes': n,
                   'flagged_pct': 100 * sum(r['flagged'] for r in rs) / n}
            for m in MODES:
                row[f'{m}_right_pct'] = 100 * sum(r[f'{m}_final'] == r['expected'] for r in rs) / n
                row[f'{m}_ambiguous_pct'] = 100 * sum(r[f'{m}_final'] == '' and r['flagged'] for r in rs) / n
                row[f'{m}_wrong_pct'] = 100 * sum(r[f'{m}_wrong'] for r in rs) / n
            out.append(row)
    return out


def identification(rows):
    out = []
    for name, noise in _groups(rows):
        rs = [r for r in rows if (r['robot'], r['noise']) == (name, noise) and r['supporting'] >= 6]
        if not rs:
            continue
        fe = np.array([r['force_error'] for r in rs]) * 100
        ld = np.array([r['line_distance_m'] for r in rs]) * 100
        out.append({'robot': name, 'noise': noise, 'pushes': len(rs),
                    'rank6_pct': 100 * np.mean([r['rank'] == 6 for r in rs]),
                    'force_error_median_pct': float(np.median(fe)), 'force_error_p95_pct': float(np.percentile(fe, 95)),
                    'force_error_le5_pct': float(100 * np.mean(fe <= 5)),
                    'line_median_cm': float(np.nanmedian(ld)), 'line_p95_cm': float(np.nanpercentile(ld, 95)),
                    'line_le1cm_pct': float(100 * np.mean(ld <= 1))})
    return out


def tool_summary(rows):
    out = []
    for name, noise in _groups(rows):
        rs = [r for r in rows if (r['robot'], r['noise']) == (name, noise)]
        fe = np.array([r['force_error'] for r in rs]) * 100
        te = np.array([r['torque_error'] for r in rs]) * 100
        out.append({'robot': name, 'noise': noise, 'tool': rs[0]['tool'], 'pushes': len(rs),
                    'rank6_pct': 100 * np.mean([r['rank'] == 6 for r in rs]),
                    'force_error_median_pct': float(np.median(fe)), 'force_error_p95_pct': float(np.percentile(fe, 95)),
                    'torque_error_median_pct': float(np.median(te)),
                    'torque_error_p95_pct': float(np.percentile(te, 95)),
                    'wrench_le2_pct': float(100 * np.mean((fe <= 2) & (te <= 2)))})
    return out


def cost_messages(model, n, push):
    """n joint_states messages of the bundled arm held at HOME-like q0, pushed from 50 ms at the tool
    (push 'tool'), or on link4 through joint 4's axis at 1.5x threshold (push 'weak': the weak tier's
    strict decisions, ambiguous, decided anew as the mean grows), or never (None: free motion, the
    flag stays down)."""
    from sensor_msgs.msg import JointState
    rng = np.random.default_rng(3)
    q0 = np.array([0.0, -0.6, 0.0, 2.0, 0.0, 1.6, 0.8])
    th = np.asarray(settings_for(model).collision.threshold)
    sim = ArmSim(model, DT, q0=q0)
    sim.motor = model.gravity(q0)
    if push == 'tool':
        f = np.array([12.0, -20.0, 8.0])    # at (4, 3, 2) cm in tool0: isolated at link7 (test_node_contact_link.py)
        sim.set_external('tool0', np.concatenate([np.cross([0.04, 0.03, 0.02], f), f]), 0.05, 100.0)
    elif push == 'weak':   # bench.probes.isolation_decision's push, at q0
        J4 = model.jacobian(q0, 'link4', 'local')
        v, w = J4[:3, 3], J4[3:, 3]
        p = np.cross(w, v) / (w @ w) + 0.03 * w / np.linalg.norm(w)   # on joint 4's axis
        f = np.array([1.0, 1.0, 0.0])
        f *= 1.5 / np.max(np.abs(J4.T @ np.concatenate([f, np.cross(p, f)])) / th)
        sim.set_external('link4', np.concatenate([np.cross(p, f), f]), 0.05, 100.0)
    kp, kd = hold_gains(model, q0)
    msgs = []
    for k in range(n):
        m = JointState(name=model.joint_names, position=sim.q.tolist(), velocity=sim.qd.tolist(),
                       effort=(sim.motor + rng.normal(0, NOISE, model.n) * th).tolist())
        m.header.stamp.sec, m.header.stamp.nanosec = divmod(1_000_000_000 + k * 1_000_000, 1_000_000_000)
        msgs.append(m)
        sim.set_command(model.gravity(sim.q) + kp * (q0 - sim.q) - kd @ sim.qd)
        sim.step()
    return msgs


def node_cost(rounds, per_round):
    """Per-message times (us) of the node's joint_states callback, flag down (free) and up (a push
    at the tool, isolated at link7; a weak push on link4 through joint 4's axis, ambiguous by the
    weak tier's strict decisions, from the first message on: those decisions are in the rounds):
    isolation on, on with the tool wrench, and stubbed out (the peer); interleaved rounds,
    per-round ratios of the medians."""
    import rclpy
    from rclpy.parameter import Parameter

    from lie_dynamics.ros.node import DynamicsNode
    model = load_urdf(default_urdf_path())
    s = settings_for(model)
    cases = ('isolation stubbed (peer)', 'isolation on', 'isolation on + tool wrench')
    rows = []
    for flag, push in (('down', None), ('up', 'tool'), ('up, weak', 'weak')):
        msgs = cost_messages(model, rounds * per_round + 100, push)
        ctx = rclpy.Context()
        rclpy.init(context=ctx)
        nodes = {}
        try:
            for k, name in enumerate(cases):
                params = {'urdf_path': default_urdf_path(), 'friction.viscous': model.damping.tolist(),
                          'friction.coulomb': [0.0], 'stale_timeout': 60.0,
                          'collision.threshold': list(s.collision.threshold),
                          'contact.wrench_frame': 'tool0' if 'tool' in name else ''}
                nodes[name] = DynamicsNode(f'contact_bench_{k}', context=ctx,
                                           parameter_overrides=[Parameter(p, value=v) for p, v in params.items()])
            feature = nodes[cases[0]].features.get('contact')
            feature.isolation.update = lambda *a: Published(None, None, None)   # the peer: the observer only
            warm = 0 if push == 'weak' else 100
            for node in nodes.values():   # the first 100 states: the push rises, the flag rises, isolation decides
                for m in msgs[:warm]:
                    node.on_joint_state(m)
            times = {name: [] for name in cases}
            for r in range(rounds):
                batch = msgs[warm + r * per_round:warm + (r + 1) * per_round]
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
        for name, per in times.items():
            allt = np.concatenate(per)
            ratios = [np.median(a) / np.median(b) for a, b in zip(per, times[peer], strict=True)]
            rows.append({'flag': flag, 'case': name, 'collision': state[name][0], 'link': state[name][1],
                         'messages': int(allt.size), 'mean_us': float(np.mean(allt)),
                         'median_us': float(np.median(allt)),
                         'p90_us': float(np.percentile(allt, 90)), 'p99_us': float(np.percentile(allt, 99)),
                         'ratio_median': float(np.median(ratios)), 'ratio_min': float(np.min(ratios)),
                         'ratio_max': float(np.max(ratios))})
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
        for noise in (0.0, NOISE):
            rows += push_isolation(name, model, n, rng, noise)
            tools += tool_pushes(name, model, tool, max(4, n // 5), rng, noise)
    iso, ident, tool = summary(rows), identification(rows), tool_summary(tools)
    cost = node_cost(rounds=4 if quick else 20, per_round=50 if quick else 200)
    md = ('# Contact isolation and the external wrench\n\n'
          f'Pushes per robot and noise level: {n}; thresholds {THRESHOLD_SCALE} x effort limits; effort noise 0 and '
          f'{NOISE} x threshold; seed {seed}; contact.strict_below {STRICT_BELOW:g}.\n\n## Isolation\n\n'
          + _table(iso, list(iso[0])) + '\n## Identification (links with 6 or more supporting joints)\n\n'
          + (_table(ident, list(ident[0])) if ident else 'none\n') + '\n## Tool frame\n\n'
          + _table(tool, list(tool[0])) + '\n## Callback cost (bundled arm)\n\n' + _table(cost, list(cost[0])))
    if out:
        os.makedirs(out, exist_ok=True)
        write_tables(out, 'contact', md, {'isolation': iso, 'identification': ident, 'tool': tool, 'cost': cost,
                                          'pushes': rows, 'tool_pushes': tools}, rows=rows)
    print(md)
    return iso, ident, tool, cost


def main(argv=None):
    global STRICT_BELOW
    ap = argparse.ArgumentParser(prog='python -m bench.contact', description=__doc__.split('\n')[0])
    ap.add_argument('--quick', action='store_true')
    ap.add_argument('--pushes', type=int, default=None, help='pushes per robot (default 150, quick 12)')
    ap.add_argument('--strict-below', type=float, default=STRICT_BELOW,
                    help='contact.strict_below (default %(default)g, the node\'s: the weak tier, '
                         'never wrong in docs/benchmarks.md)')
    ap.add_argument('--out', default=os.path.join(HERE, 'out'))
    args = ap.parse_args(argv)
    STRICT_BELOW = args.strict_below
    run(args.quick, args.out, args.pushes)


if __name__ == '__main__':
    main()
