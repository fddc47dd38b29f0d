"""Real vendor robots (example-robot-data): speed beside Pinocchio, and what folding buys.

The Panda controlled by its 7 arm joints keeps two locked finger joints. They are folded into
the hand's inertia (urdf.py), so the model should cost what the same arm with the fingers
fixed in the URDF costs. Both are timed here, each beside Pinocchio's model of the same
reduced robot (`buildReducedModel` with the fingers locked; the fixed-finger file as it is),
interleaved in the same run; ratios are our time / Pinocchio's.

--large adds robots of 12-32 joints (Solo12, Talos reduced, Baxter, PR2) and the Coriolis matrix, the
regressor and the frame Jacobian of the deepest body's link to every robot: issue 32's "every
family ≤ 1.0× Pinocchio" on those robots. Pinocchio's model there is its own of the same URDF (its
mimic joints are joints, PR2's continuous joints two coordinates), at a state of its own.

    python -m bench.robots [--quick] [--large]
"""
import argparse
import glob
import os
import sys
import warnings

import numpy as np

from bench import common

ROBOTS = ('panda_description/urdf/panda.urdf', 'ur_description/urdf/ur5_robot.urdf',
          'talos_data/robots/talos_left_arm.urdf', 'kinova_description/robots/kinova.urdf',
          'tiago_description/robots/tiago.urdf')
LARGE = ('solo_description/robots/solo12.urdf', 'talos_data/robots/talos_reduced.urdf',
         'baxter_description/urdf/baxter.urdf', 'pr2_description/urdf/pr2.urdf')
PANDA_ARM = [f'panda_joint{k}' for k in range(1, 8)]
FINGERS = ('panda_finger_joint1', 'panda_finger_joint2')


def robot_dir():
    found = glob.glob(os.path.join(sys.prefix, 'lib', 'python3*', 'site-packages', 'cmeel.prefix', 'share',
                                   'example-robot-data', 'robots'))
    if not found:
        raise RuntimeError('example-robot-data is not installed (pip install example-robot-data)')
    return found[0]


def fixed_fingers(xml):
    """The Panda file with its finger joints welded (what a user would otherwise edit by hand)."""
    for name in FINGERS:
        start = xml.index(f'<joint name="{name}"')
        head_end = xml.index('>', start)
        xml = xml[:start] + xml[start:head_end].replace('type="prismatic"', 'type="fixed"') + xml[head_end:]
    return xml


def _cases(quick, large=False):
    from lie_dynamics import load_urdf
    import pinocchio as pin

    root = robot_dir()
    out = []
    with open(os.path.join(root, ROBOTS[0]), encoding='utf-8') as fh:
        panda = fh.read()
    full = pin.buildModelFromXML(panda)
    locked = pin.buildReducedModel(full, [full.getJointId(j) for j in FINGERS], pin.neutral(full))
    out.append(('panda, fingers locked (folded)', load_urdf(panda, joints=PANDA_ARM), locked))
    out.append(('panda, fingers fixed in the URDF', load_urdf(fixed_fingers(panda)),
                pin.buildModelFromXML(fixed_fingers(panda))))
    for rel in ROBOTS[1:2 if quick else None]:
        with open(os.path.join(root, rel), encoding='utf-8') as fh:
            xml = fh.read()
        with warnings.catch_warnings():
            warnings.simplefilter('ignore')  # vendor files with odd inertias: warned about, not refused
            model = load_urdf(xml)
        pm = pin.buildModelFromXML(xml)
        if pm.nq != model.n:  # continuous joints or mimics: Pinocchio's coordinates differ
            continue
        out.append((rel.split('/')[0].replace('_description', '').replace('_data', ''), model, pm))
    for rel in LARGE if large else ():
        with open(os.path.join(root, rel), encoding='utf-8') as fh:
            xml = fh.read()
        with warnings.catch_warnings():
            warnings.simplefilter('ignore')
            model = load_urdf(xml)
        out.append((os.path.basename(rel)[:-5], model, pin.buildModelFromXML(xml)))
    return out


def _pin_state(pm, model, q, qd, qdd, tau):
    """Pinocchio's state: ours where its coordinates are ours (its rnea agrees), else a state of its
    own (random joint velocities integrated from its neutral configuration: other joint order,
    mimic joints, continuous joints)."""
    import pinocchio as pin
    pd = pm.createData()
    if pm.nq == model.n and pm.nv == model.n:
        ptau = pin.rnea(pm, pd, q, qd, qdd)
        if np.allclose(ptau, tau, atol=1e-9 * max(1, np.abs(ptau).max())):
            return q, qd, qdd, tau
    rng = np.random.default_rng(1)
    pq = pin.integrate(pm, pin.neutral(pm), rng.uniform(-0.5, 0.5, pm.nv))
    pv, pa = (rng.uniform(-1, 1, pm.nv) for _ in range(2))
    return pq, pv, pa, pin.rnea(pm, pd, pq, pv, pa)


def run(quick=False, out=None, rounds=None, large=False):
    import pinocchio as pin

    rounds = rounds or (3 if quick else 15)
    target = 0.002 if quick else 0.02
    rows = []
    for label, model, pm in _cases(quick, large):
        pm.gravity.linear = model.gravity_vector
        pd = pm.createData()
        q, qd, qdd = common.random_states(model, 1, seed=1)
        q, qd, qdd = q[0], qd[0], qdd[0]
        tau = model.inverse_dynamics(q, qd, qdd)
        pq, pv, pa, ptau = _pin_state(pm, model, q, qd, qdd, tau)
        assert large or pq is q, f'{label}: Pinocchio disagrees with inverse_dynamics'
        py = common.python_kernels(model)
        calls = {
            'inverse dynamics': (lambda m: m.inverse_dynamics(q, qd, qdd), lambda: pin.rnea(pm, pd, pq, pv, pa)),
            'gravity': (lambda m: m.gravity(q), lambda: pin.computeGeneralizedGravity(pm, pd, pq)),
            'mass matrix': (lambda m: m.mass_matrix(q), lambda: pin.crba(pm, pd, pq)),
            'forward dynamics': (lambda m: m.forward_dynamics(q, qd, tau), lambda: pin.aba(pm, pd, pq, pv, ptau)),
            'ID derivatives': (lambda m: m.inverse_dynamics_derivatives(q, qd, qdd),
                               lambda: pin.computeRNEADerivatives(pm, pd, pq, pv, pa)),
            'FD derivatives': (lambda m: m.forward_dynamics_derivatives(q, qd, tau),
                               lambda: pin.computeABADerivatives(pm, pd, pq, pv, ptau)),
        }
        if large:
            link = model.body_link_names[int(np.argmax(model.depth))]   # the deepest body's
            fid = pm.getFrameId(link)
            calls.update({
                'Coriolis matrix': (lambda m: m.coriolis_matrix(q, qd, method='recursive'),
                                    lambda: pin.computeCoriolisMatrix(pm, pd, pq, pv)),
                'regressor': (lambda m: m.regressor(q, qd, qdd),
                              lambda: pin.computeJointTorqueRegressor(pm, pd, pq, pv, pa)),
                'Jacobian': (lambda m: m.jacobian(q, link),
                             lambda: pin.computeFrameJacobian(pm, pd, pq, fid, pin.LOCAL_WORLD_ALIGNED)),
            })
        for op, (ours, peer) in calls.items():
            t = common.time_interleaved({'ours': lambda f=ours: f(model), 'python': lambda f=ours: f(py),
                                         'pin': peer}, rounds, target)
            ratio, ratio_py = t['ours'] / t['pin'], t['python'] / t['pin']
            rows.append(dict(robot=label, n=model.n, bodies=model.nb, op=op, ours_us=float(np.median(t['ours'])) * 1e6,
                             pin_us=float(np.median(t['pin'])) * 1e6, ratio_median=float(np.median(ratio)),
                             ratio_p10=float(np.percentile(ratio, 10)), ratio_p90=float(np.percentile(ratio, 90)),
                             python_us=float(np.median(t['python'])) * 1e6,
                             python_ratio=float(np.median(ratio_py))))
    md = markdown(rows)
    print(md)
    if out:
        common.write_tables(out, 'robots', md, dict(rows=rows), rows)
        plot(rows, os.path.join(out, 'robots.png'))
    return rows


def markdown(rows):
    lines = ['# Real robots (example-robot-data): time / Pinocchio, one state', '',
             'Medians of interleaved rounds; ratio = our time / Pinocchio\'s in the same round (p10-p90). '
             'ours: the native C kernels where a C compiler works; Python kernels: the same model with the '
             'native backend off.', '',
             '| robot | n | bodies | call | ratio (p10-p90) | ours (µs) | Pinocchio (µs) | Python kernels (µs) '
             '| Python kernels / Pinocchio |',
             '|---|---|---|---|---|---|---|---|---|']
    for r in rows:
        lines.append(f"| {r['robot']} | {r['n']} | {r['bodies']} | {r['op']} | {r['ratio_median']:.2f} "
                     f"({r['ratio_p10']:.2f}-{r['ratio_p90']:.2f}) | {r['ours_us']:.2f} | {r['pin_us']:.2f} "
                     f"| {r['python_us']:.1f} | {r['python_ratio']:.1f} |")
    return '\n'.join(lines) + '\n'


def plot(rows, path):
    plt = common.setup_matplotlib()
    robots = list(dict.fromkeys(r['robot'] for r in rows))
    ops = list(dict.fromkeys(r['op'] for r in rows))
    fig, ax = plt.subplots(figsize=(9, 4))
    width = 0.8 / len(robots)
    for k, rb in enumerate(robots):
        vals = [next((r['ratio_median'] for r in rows if r['robot'] == rb and r['op'] == op), np.nan) for op in ops]
        ax.bar(np.arange(len(ops)) + k * width, vals, width, label=rb)
    ax.set_xticks(np.arange(len(ops)) + 0.4 - width / 2, ops)
    ax.set_ylabel('time / Pinocchio (one state)')
    ax.set_title('Real robots: the locked-finger Panda costs what the fixed-finger Panda costs')
    ax.legend(fontsize=7)
    fig.tight_layout()
    common.savefig(fig, path)


def main(argv=None):
    ap = argparse.ArgumentParser(prog='python -m bench.robots', description=__doc__.split('\n')[0])
    ap.add_argument('--quick', action='store_true')
    ap.add_argument('--out', default=os.path.join(os.path.dirname(os.path.abspath(__file__)), 'out'))
    ap.add_argument('--large', action='store_true', help='also robots of 12-32 joints and three more families')
    args = ap.parse_args(argv)
    run(quick=args.quick, out=args.out, large=args.large)


if __name__ == '__main__':
    main()
