"""Feedforward efforts for whole trajectories: one batched inverse-dynamics call.

`fill_trajectory_efforts(model, traj)` takes a trajectory as arrays (the shape of a
trajectory_msgs/JointTrajectory: times, joint names, positions, optional velocities and
accelerations), validates it, derives what is missing and returns the efforts
tau_k = ID(q_k, qd_k, qdd_k) for every point at once (the batch is vectorised: no
Python loop over points).

Missing derivatives: velocities from positions, and accelerations from velocities, by
np.gradient over the (possibly non-uniform) times: second-order central differences
inside, second-order one-sided differences at the two ends (first order when the
trajectory has only two points). A single point without accelerations gets zero.

CSV form (offline use): a header `time, pos.<joint>..., [vel.<joint>...], [acc.<joint>...]`;
`python -m lie_dynamics.trajectory robot.urdf traj.csv -o out.csv` adds `eff.<joint>` columns.
"""
import csv
import sys

import numpy as np

from .cli import CliParser, run_cli
from .laws import COULOMB_VELOCITY_EPSILON, friction_torque
from .model.joint_names import joint_columns


def derivative(y, t):
    """dy/dt along axis 0 at the (possibly non-uniform) times t: the missing-derivative rule of
    this module's docstring (zeros for one point)."""
    if len(t) == 1:
        return np.zeros_like(y)
    return np.gradient(y, t, axis=0, edge_order=2 if len(t) > 2 else 1)


def fill_trajectory_efforts(model, traj, friction=False, eps=COULOMB_VELOCITY_EPSILON, with_gravity=True):
    """Efforts (N, n) in the model's joint order for a trajectory given as arrays.

    traj: mapping with 'positions' (N, k) and, optionally, 'time_from_start' (N,)
    (needed to derive missing derivatives), 'velocities' (N, k), 'accelerations' (N, k)
    and 'joint_names' (k names; default: the model's joint order). Joints the model
    does not control are ignored; every controlled joint must be present.
    friction: also add the friction compensation b*qd + fc*tanh(qd/eps) with the URDF's
    <dynamics damping> (b) and <dynamics friction> (fc): the smooth Coulomb term the
    dynamics node streams (lie_dynamics.laws.friction_torque), not sign(qd).
    eps: velocity scale of that Coulomb term, rad/s (m/s for prismatic joints), > 0; the
    default 0.05 is the node's friction.coulomb_velocity_epsilon default. Used only with
    friction=True.
    with_gravity=False leaves g(q) out of the efforts (a robot that adds it itself).
    Returns a dict with 'efforts', 'positions', 'velocities', 'accelerations' (model order).
    Raises ValueError naming the problem for any malformed trajectory.
    """
    if friction and not (np.isfinite(eps) and eps > 0):
        raise ValueError(f'eps must be finite and > 0, got {eps}')
    names = list(traj.get('joint_names') or model.joint_names)
    mapped = joint_columns(names, model.joint_names)
    if mapped.duplicates:
        raise ValueError(f'trajectory joint_names has duplicates: {names}')
    if mapped.missing:
        raise ValueError(f'trajectory lacks controlled joints {mapped.missing}')
    cols = mapped.columns

    def field(key, required):
        if traj.get(key) is None or (np.size(traj.get(key)) == 0 and not required):
            if required:
                raise ValueError(f'trajectory has no {key}')
            return None
        a = np.asarray(traj[key], dtype=float)
        if a.ndim == 1 and len(names) == 1:
            a = a[:, None]
        if a.ndim != 2 or a.shape[1] != len(names):
            raise ValueError(f'trajectory {key} must have shape (points, {len(names)}), got {a.shape}')
        if not np.all(np.isfinite(a)):
            bad = np.argwhere(~np.isfinite(a))[0]
            raise ValueError(f'trajectory {key} has a non-finite value at point {bad[0]}, joint {names[bad[1]]!r}')
        return a[:, cols]

    q = field('positions', True)
    N = q.shape[0]
    if N == 0:
        raise ValueError('trajectory has no points')
    qd = field('velocities', False)
    qdd = field('accelerations', False)
    for key, a in (('velocities', qd), ('accelerations', qdd)):
        if a is not None and a.shape[0] != N:
            raise ValueError(f'trajectory {key} has {a.shape[0]} points, positions have {N}')
    t = traj.get('time_from_start')
    if t is not None:
        t = np.asarray(t, dtype=float).reshape(-1)
        if t.shape[0] != N:
            raise ValueError(f'trajectory time_from_start has {t.shape[0]} entries, positions have {N} points')
        if not np.all(np.isfinite(t)):
            raise ValueError('trajectory time_from_start has non-finite values')
        if N > 1 and np.any(np.diff(t) <= 0):
            k = int(np.argmax(np.diff(t) <= 0))
            raise ValueError(f'trajectory times must increase strictly (point {k + 1}: {t[k + 1]} after {t[k]})')
    if (qd is None or qdd is None) and t is None and N > 1:
        raise ValueError('trajectory needs time_from_start to derive missing velocities/accelerations')
    if qd is None:
        qd = derivative(q, t) if N > 1 else np.zeros_like(q)
    if qdd is None:
        qdd = derivative(qd, t) if N > 1 else np.zeros_like(q)
    tau = model.inverse_dynamics(q, qd, qdd, with_gravity=with_gravity)
    if friction:
        tau = tau + friction_torque(qd, model.damping, model.friction, eps)
    return {'efforts': tau, 'positions': q, 'velocities': qd, 'accelerations': qdd}


KINDS = {'pos.': 'positions', 'vel.': 'velocities', 'acc.': 'accelerations'}


def read_csv(path):
    """Trajectory arrays from a CSV with columns time, pos.<j>, [vel.<j>], [acc.<j>].

    eff.<j> columns (what `write_csv` adds) are accepted, so an output can be read back; when
    every joint has one they come back as 'efforts' (measured efforts for calibration;
    fill_trajectory_efforts does not use them). Raises ValueError naming the file, line and
    column of the first problem.
    """
    try:
        with open(path, newline='', encoding='utf-8-sig') as fh:  # -sig: spreadsheets write a BOM
            rows = list(csv.reader(fh))
    except csv.Error as exc:  # e.g. a NUL byte: not a text CSV
        raise ValueError(f'{path}: not a readable CSV ({exc})') from None
    if not rows:
        raise ValueError(f'{path}: empty CSV')
    header, body = [h.strip() for h in rows[0]], rows[1:]
    # The header first: a file without the pos.<joint> convention fails on its first column,
    # whatever its numbers.
    for i, h in enumerate(header):
        if h != 'time' and not (h[:4] in ('pos.', 'vel.', 'acc.', 'eff.') and len(h) > 4):
            hint = f' (a position column is named pos.{h})' if h and '.' not in h and h.lower() != 'time' else ''
            raise ValueError(f'{path}: column {i + 1} ({h!r}) is not time, pos.<joint>, vel.<joint>, '
                             f'acc.<joint> or eff.<joint>{hint}')
        if header.index(h) != i:
            raise ValueError(f'{path}: column {h!r} appears twice')
    if 'time' not in header:
        raise ValueError(f"{path}: no 'time' column")
    joints = [h[4:] for h in header if h.startswith('pos.')]
    if not joints:
        raise ValueError(f"{path}: no 'pos.<joint>' columns")
    for h in header:
        if h[:4] in ('vel.', 'acc.') and h[4:] not in joints:
            raise ValueError(f'{path}: column {h!r} has no pos.{h[4:]} column')
    values = []
    for line, r in enumerate(body, start=2):
        if not any(x.strip() for x in r):
            continue
        if len(r) != len(header):
            raise ValueError(f'{path}: line {line} has {len(r)} values, the header has {len(header)} columns')
        row = []
        for name, x in zip(header, r):
            try:
                row.append(float(x))
            except ValueError:
                raise ValueError(f'{path}: line {line}: non-numeric value {x!r} in column {name!r}') from None
        values.append(row)
    data = np.array(values, dtype=float).reshape(-1, len(header))
    out = {'joint_names': joints, 'time_from_start': data[:, header.index('time')]}
    for prefix, key in KINDS.items():
        idx = [header.index(prefix + j) for j in joints if prefix + j in header]
        if idx and len(idx) != len(joints):
            missing = [prefix + j for j in joints if prefix + j not in header]
            raise ValueError(f'{path}: {prefix}<joint> columns must cover every joint or none; missing {missing}')
        if idx:
            out[key] = data[:, idx]
    if all('eff.' + j in header for j in joints):
        out['efforts'] = data[:, [header.index('eff.' + j) for j in joints]]
    return out


def write_csv(path, traj, result, joint_names):
    header = ['time'] + [f'{p}.{j}' for p in ('pos', 'vel', 'acc', 'eff') for j in joint_names]
    t = traj.get('time_from_start')
    t = np.zeros(len(result['efforts'])) if t is None else np.asarray(t, dtype=float)
    table = np.column_stack([t, result['positions'], result['velocities'], result['accelerations'],
                             result['efforts']])
    with open(path, 'w', newline='') as fh:
        w = csv.writer(fh)
        w.writerow(header)
        w.writerows(table.tolist())


CSV_FORMAT = """\
input CSV: a header row, then one row per trajectory point
  time, pos.<joint>..., [vel.<joint>...], [acc.<joint>...]
  time in s, strictly increasing; positions in rad (m for prismatic joints). Every joint
  that has a pos.<joint> column is controlled; the URDF's other movable joints are held at
  0. vel.* and acc.* are optional (all joints or none); what is missing is derived from the
  positions by finite differences. Columns may come in any order.
example (two joints, velocities given, accelerations derived):
  time,pos.joint1,pos.joint2,vel.joint1,vel.joint2
  0.00,0.0,0.50,0.0,0.0
  0.01,0.001,0.50,0.2,0.0
output CSV: time, pos.<joint>, vel.<joint>, acc.<joint>, eff.<joint> (N m, or N for prismatic
  joints), in the same joint order.
usage example:
  python -m lie_dynamics.trajectory config/arm7.urdf traj.csv -o traj_eff.csv
"""


def main(argv=None):
    """fill_trajectory: add inverse-dynamics efforts to a trajectory CSV."""
    ap = CliParser('lie_dynamics.trajectory', description='Fill a trajectory CSV with inverse-dynamics efforts.',
                   epilog=CSV_FORMAT)
    ap.add_argument('urdf', help='robot description (URDF file)')
    ap.add_argument('csv', help='input trajectory (format below)')
    ap.add_argument('-o', '--output', required=True, help='output CSV (input columns + eff.<joint>)')
    ap.add_argument('--friction', action='store_true',
                    help='add URDF damping and Coulomb friction (smooth: fc*tanh(qd/0.05), as the node)')
    return run_cli(ap, _fill, argv)


def _fill(args):
    from .model.urdf import load_urdf

    traj = read_csv(args.csv)
    model = load_urdf(args.urdf, joints=traj['joint_names'])
    try:
        result = fill_trajectory_efforts(model, traj, friction=args.friction)
    except ValueError as exc:
        raise ValueError(f'{args.csv}: {exc}') from None
    write_csv(args.output, traj, result, model.joint_names)
    print(f'{len(result["efforts"])} points -> {args.output}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
