"""Trajectory effort fill: batched inverse dynamics per point, derived derivatives, validation."""
import os
import subprocess
import sys

import numpy as np
import pytest

from lie_dynamics import load_urdf
from lie_dynamics.trajectory import fill_trajectory_efforts, read_csv, write_csv
from oracle import Oracle

ARM = os.path.join(os.path.dirname(__file__), '..', 'config', 'arm7.urdf')


@pytest.fixture(scope='module')
def arm():
    with open(ARM) as fh:
        xml = fh.read()
    model = load_urdf(xml)
    return model, Oracle(xml, joints=model.joint_names)


def _smooth(model, N, T=2.0):
    t = np.linspace(0, T, N)
    w = 2 * np.pi / T * np.arange(1, model.n + 1) / 3
    q = 0.4 * np.sin(np.outer(t, w))
    qd = 0.4 * np.cos(np.outer(t, w)) * w
    qdd = -0.4 * np.sin(np.outer(t, w)) * w ** 2
    return t, q, qd, qdd


def test_fill_matches_pinocchio_per_point_in_shuffled_joint_order(arm):
    model, oracle = arm
    t, q, qd, qdd = _smooth(model, 300)
    perm = np.random.default_rng(0).permutation(model.n)
    names = [model.joint_names[i] for i in perm] + ['gripper_finger']  # extra joints are ignored
    pad = np.zeros((len(t), 1))
    traj = {'joint_names': names, 'time_from_start': t, 'positions': np.hstack([q[:, perm], pad]),
            'velocities': np.hstack([qd[:, perm], pad]), 'accelerations': np.hstack([qdd[:, perm], pad])}
    out = fill_trajectory_efforts(model, traj)
    ref = np.array([oracle.rnea(*s) for s in zip(q, qd, qdd)])
    assert np.max(np.abs(out['efforts'] - ref)) < 1e-9 * max(1.0, np.max(np.abs(ref)))


def test_missing_accelerations_and_velocities_are_derived_second_order(arm):
    model, oracle = arm
    errs = []
    for N in (101, 201, 401):
        t, q, qd, qdd = _smooth(model, N)
        out = fill_trajectory_efforts(model, {'time_from_start': t, 'positions': q, 'velocities': qd})
        errs.append(np.max(np.abs(out['accelerations'][1:-1] - qdd[1:-1])))
        ref = np.array([oracle.rnea(*s) for s in zip(q, qd, out['accelerations'])])
        np.testing.assert_allclose(out['efforts'], ref, atol=1e-9)
    # halving the step divides the interior error by ~4
    assert errs[1] < errs[0] / 3 and errs[2] < errs[1] / 3
    t, q, qd, qdd = _smooth(model, 401)
    out = fill_trajectory_efforts(model, {'time_from_start': t, 'positions': q})
    assert np.max(np.abs(out['velocities'] - qd)) < 1e-3 * np.max(np.abs(qd))


def test_non_uniform_times(arm):
    model, _ = arm
    t = np.sort(np.random.default_rng(1).uniform(0, 1, 200))
    q = np.outer(t ** 2, np.ones(model.n))  # qdd = 2 exactly, qd = 2t
    out = fill_trajectory_efforts(model, {'time_from_start': t, 'positions': q,
                                          'velocities': np.outer(2 * t, np.ones(model.n))})
    np.testing.assert_allclose(out['accelerations'], 2.0, atol=1e-8)


def test_single_point_and_friction(arm):
    model, _ = arm
    out = fill_trajectory_efforts(model, {'positions': np.zeros((1, model.n))})
    np.testing.assert_allclose(out['efforts'][0], model.gravity(np.zeros(model.n)), atol=1e-12)
    qd = np.full((1, model.n), 0.5)
    f = fill_trajectory_efforts(model, {'positions': np.zeros((1, model.n)), 'velocities': qd,
                                        'accelerations': np.zeros((1, model.n))}, friction=True)
    nf = fill_trajectory_efforts(model, {'positions': np.zeros((1, model.n)), 'velocities': qd,
                                         'accelerations': np.zeros((1, model.n))})
    np.testing.assert_allclose(f['efforts'] - nf['efforts'], (model.damping * 0.5 + model.friction)[None])


@pytest.mark.parametrize('mutate, msg', [
    (lambda d: d.update(joint_names=['joint1'] * 7), r'joint_names has duplicates'),
    (lambda d: d.update(joint_names=[f'j{i}' for i in range(7)]), r'lacks controlled joints'),
    (lambda d: d.update(positions=np.zeros((5, 6))), r'positions must have shape \(points, 7\)'),
    (lambda d: d.update(velocities=np.zeros((4, 7))), r'velocities has 4 points, positions have 5'),
    (lambda d: d['positions'].__setitem__((2, 3), np.nan), r"non-finite value at point 2, joint 'joint4'"),
    (lambda d: d.update(time_from_start=np.array([0, 1, 1, 2, 3.0])), r'times must increase strictly \(point 2'),
    (lambda d: d.update(time_from_start=np.array([0, 1, 2.0])), r'time_from_start has 3 entries'),
    (lambda d: d.pop('time_from_start'), r'needs time_from_start'),
    (lambda d: d.update(positions=np.zeros((0, 7)), time_from_start=np.zeros(0)), r'no points'),
])
def test_bad_trajectories_are_rejected(arm, mutate, msg):
    model, _ = arm
    d = {'time_from_start': np.arange(5.0), 'positions': np.zeros((5, 7))}
    mutate(d)
    with pytest.raises(ValueError, match=msg):
        fill_trajectory_efforts(model, d)


def test_csv_round_trip_and_cli(arm, tmp_path):
    model, _ = arm
    t, q, qd, qdd = _smooth(model, 50)
    src = tmp_path / 'in.csv'
    write_csv(src, {'time_from_start': t}, {'positions': q, 'velocities': qd, 'accelerations': qdd,
                                           'efforts': np.zeros_like(q)}, model.joint_names)
    traj = read_csv(src)
    np.testing.assert_allclose(traj['positions'], q)
    out = tmp_path / 'out.csv'
    root = os.path.join(os.path.dirname(__file__), '..')
    r = subprocess.run([sys.executable, '-m', 'lie_dynamics.trajectory', ARM, str(src), '-o', str(out)],
                       cwd=root, capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    back = read_csv(out)
    header = open(out).readline().strip().split(',')
    eff = np.loadtxt(out, delimiter=',', skiprows=1)[:, [header.index(f'eff.{j}') for j in model.joint_names]]
    np.testing.assert_allclose(eff, model.inverse_dynamics(q, qd, back['accelerations']), atol=1e-9)
    bad = tmp_path / 'bad.csv'
    bad.write_text('time,pos.joint1\n0,abc\n')
    with pytest.raises(ValueError, match='non-numeric'):
        read_csv(bad)
