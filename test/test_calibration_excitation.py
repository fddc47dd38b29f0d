"""The optimised excitation (lie_dynamics.calibration.excitation) and its console script."""
import glob
import os
import subprocess
import sys

import numpy as np
import pytest

from dyn_cases import ARM, ROOT
from lie_dynamics import load_urdf
from lie_dynamics.algorithms.identification import excitation_trajectory
from lie_dynamics.calibration import excitation as ex
from lie_dynamics.trajectory import read_csv

_ERD = glob.glob(os.path.join(sys.prefix, 'lib', 'python3*', 'site-packages', 'cmeel.prefix', 'share',
                              'example-robot-data', 'robots', 'ur_description', 'urdf', 'ur5_robot.urdf'))
UR5 = _ERD[0] if _ERD else None


@pytest.fixture(scope='module')
def arm():
    return load_urdf(ARM)


@pytest.fixture(scope='module')
def optimized(arm):
    # 100 L-BFGS-B iterations on a 60-sample grid (the defaults are 2,500 and 300) keep the test near
    # 20 s on a loaded machine
    return excitation_trajectory(arm, duration=10.0, rate=100.0, optimize=True, seed=0, iterations=100, samples=60)


def test_within_its_limits_on_the_sampled_trajectory_and_at_rest_at_both_ends(arm, optimized):
    t, q, qd, qdd = optimized
    assert t[0] == 0.0 and t[-1] == pytest.approx(10.0) and q.shape == (len(t), arm.n)
    home = 0.5 * (arm.position_lower + arm.position_upper)
    for k in (0, -1):
        assert np.allclose(q[k], home, atol=1e-12) and np.allclose(qd[k], 0, atol=1e-12)
        assert np.allclose(qdd[k], 0, atol=1e-12)
    span = arm.position_upper - arm.position_lower
    assert np.all(q >= arm.position_lower + 0.1 * span - 1e-12) and np.all(q <= arm.position_upper - 0.1 * span + 1e-12)
    assert np.all(np.abs(qd) <= 0.8 * arm.velocity_limits + 1e-12)
    assert np.all(np.abs(qdd) <= 5.0 + 1e-12)
    assert np.all(np.abs(arm.inverse_dynamics(q, qd, qdd)) <= 0.8 * arm.effort_limits + 1e-9)
    # the samples are one trajectory: qd and qdd are the derivatives of q
    assert np.allclose(np.gradient(q, t, axis=0)[2:-2], qd[2:-2], atol=2e-3)
    assert np.allclose(np.gradient(qd, t, axis=0)[2:-2], qdd[2:-2], atol=2e-2)
    assert np.ptp(q, axis=0).min() > 0.1   # every joint moves


def test_better_conditioned_than_the_random_excitation(arm, optimized):
    _, q, qd, qdd = optimized
    _, qr, qdr, qddr = excitation_trajectory(arm, duration=10.0, rate=100.0, seed=0)
    # measured: 9.05 (numpy 2.4; 9.44 with central differences in qd and qdd, 12.0 with position amplitudes as
    # the coefficients) against 20.1 here; less with the defaults (bench/calibration_excitation.py). The issue's
    # target, 1/5 of the random excitation held to the same limits, is reached on this arm at 10, 20 and 60 s with
    # the defaults (docs/benchmarks.md, "Excitation: condition number")
    assert ex.condition_number(arm, q, qd, qdd) < 0.65 * ex.condition_number(arm, qr, qdr, qddr)


def test_the_objectives_gradient_is_its_derivative(arm):
    # the closed-form gradient (singular values from the Gram matrix, the regressor contracted at perturbed
    # states, exact unit differences in qd and qdd, the effort penalty through tau = Y pi + armature qdd)
    # against central differences of the value, inside the limits and beyond them (every penalty active)
    from lie_dynamics.calibration import regressor as creg
    n, H, duration = arm.n, 6, 10.0
    series = ex._Series(np.arange(40) * (duration / 40), 2 * np.pi / duration * np.arange(1, H + 1))
    home = 0.5 * (arm.position_lower + arm.position_upper)
    limits = ex._limits(arm, home, 0.1, 0.8, 5.0, 0.8, np.arange(n))[:5]
    columns, bases = creg.structural_base(arm).base_columns, ex._derivative_bases(series, n)
    rng = np.random.default_rng(3)
    for scale, power in ((0.05, None), (0.05, 4.0), (0.5, 16.0)):
        x, d = rng.normal(size=(2, n * 2 * (H - 1)))
        x *= scale

        def value(x, gradient=False, power=power):
            return ex._objective(arm, home, *series(x, n), columns, 0.05, limits, 1e3, bases if gradient else None,
                                 np.ones(x.size), power=power)
        assert value(x, True)[0] == pytest.approx(value(x)[0], rel=1e-9)   # the kernels may route the two apart
        numeric = (value(x + 1e-6 * d)[0] - value(x - 1e-6 * d)[0]) / 2e-6
        assert value(x, True)[1] @ d == pytest.approx(numeric, rel=1e-5)


def test_a_start_on_a_limit_does_not_stall_the_optimiser(arm):
    # seed 1's random start, scaled right to the limits, sat on a penalty's kink: L-BFGS-B's line search
    # failed within a few iterations and the result was 4.7x worse than the random excitation (0.56x once
    # the start sits inside the limits and a failed line search restarts the optimiser's memory; 0.48x with
    # velocity amplitudes as the coefficients; 0.54x with the gradient's exact qd, qdd differences)
    _, q, qd, qdd = excitation_trajectory(arm, duration=10.0, rate=100.0, optimize=True, seed=1, iterations=100,
                                          samples=60)
    _, qr, qdr, qddr = excitation_trajectory(arm, duration=10.0, rate=100.0, seed=0)
    assert ex.condition_number(arm, q, qd, qdd) < 0.65 * ex.condition_number(arm, qr, qdr, qddr)


def test_the_target_on_the_ur5_at_60_s():
    # the target: <= 1/5 of the condition number of the random excitation at the same duration and
    # limits (shrunk into them: bench/calibration_excitation.py's 'random in limits'), every limit met on
    # the samples; 60 s sampled at 20 Hz and 120 iterations to stay quick (the bench: 0.106 at 100 Hz and
    # the default 2,500)
    if UR5 is None:
        pytest.skip('example-robot-data is not installed')
    from bench.calibration_excitation import excess, within_limits
    model = load_urdf(UR5)
    _, q, qd, qdd = excitation_trajectory(model, duration=60.0, rate=20.0, optimize=True, seed=0, iterations=120)
    _, qr, qdr, qddr = excitation_trajectory(model, duration=60.0, rate=20.0, seed=0)
    random = within_limits(model, qr, qdr, qddr)
    assert excess(model, q, qd, qdd) <= 0 and excess(model, *random) <= 0
    # measured 0.124 (numpy 2.4; 0.126 on the former 150-sample grid and central differences in qd and qdd,
    # 0.148-0.151 with position amplitudes as the coefficients): the optimiser's path
    # depends on the numpy build's last bits (an earlier gate at 60 iterations measured 0.67 and 0.73), hence
    # the margin
    assert ex.condition_number(model, q, qd, qdd) <= 0.2 * ex.condition_number(model, *random)


def test_joints_home_and_infeasible_limits(arm):
    home = np.array([0.0, 0.3, 0.0, 1.5, 0.0, 1.6, 0.0])
    t, q, qd, qdd = ex.optimized_excitation(arm, duration=4.0, rate=50.0, home=home, joints=['joint2', 'joint4'],
                                            iterations=2)
    assert np.allclose(q[:, [0, 2, 4, 5, 6]], home[[0, 2, 4, 5, 6]]) and np.ptp(q[:, 1]) > 0
    assert np.allclose(q[0], home) and np.allclose(q[-1], home)
    with pytest.raises(ValueError, match=r"position limit of joint 'joint4': home 0 is outside"):
        ex.optimized_excitation(arm, home=np.zeros(7), iterations=1)
    with pytest.raises(ValueError, match=r"effort limit of joint 'joint2': gravity alone at home needs"):
        ex.optimized_excitation(arm, home=[0, 1.2, 0, 1.5, 0, 1.6, 0], effort_fraction=0.1, iterations=1)
    # bounds that leave no motion: the error names the binding limit and its joint (a fraction common to all
    # joints binds them nearly alike, and which binds first follows the last bits of the start: one joint moves)
    with pytest.raises(ValueError, match=r"no exciting motion: the acceleration bound of joint 'joint7' binds"):
        ex.optimized_excitation(arm, duration=4.0, rate=20.0, acceleration=[5, 5, 5, 5, 5, 5, 1e-8], iterations=1)
    with pytest.raises(ValueError, match=r"no exciting motion: the velocity limit of joint 'joint3' binds"):
        ex.optimized_excitation(arm, duration=4.0, rate=20.0, velocity_fraction=1e-7, joints=['joint3'], iterations=1)
    with pytest.raises(ValueError, match=r"no exciting motion: the position limit of joint 'joint2' binds"):
        ex.optimized_excitation(arm, duration=4.0, rate=20.0, margin=0.4999999, joints=['joint2'], iterations=1)
    with pytest.raises(ValueError, match='velocity_fraction must be in'):
        ex.optimized_excitation(arm, velocity_fraction=0.0)
    with pytest.raises(ValueError, match='acceleration bound must be > 0'):
        ex.optimized_excitation(arm, acceleration=0.0)
    with pytest.raises(ValueError, match=r"unknown joints \['joint9'\]"):
        ex.optimized_excitation(arm, joints=['joint9'])
    with pytest.raises(ValueError, match=r"options \['home'\] need optimize=True"):
        excitation_trajectory(arm, home=home)


def _run(args, tmp_path):
    script = ("import sys; sys.argv[0] = 'excitation_trajectory'; "
              'from lie_dynamics.calibration.excitation import main; sys.exit(main())')
    return subprocess.run([sys.executable, '-c', script] + args, cwd=tmp_path, capture_output=True, text=True,
                          timeout=300, env=dict(os.environ, PYTHONPATH=ROOT))


def test_console_script_writes_the_csv_fill_trajectory_reads(tmp_path):
    r = _run([ARM, '-o', 'exc.csv', '--joints', 'joint1,joint3', '--duration', '3', '--rate', '50',
              '--home', '0,0,0,1.5,0,1.6,0', '--iterations', '100'], tmp_path)
    assert r.returncode == 0, r.stderr
    assert 'exc.csv: 151 samples over 3 s' in r.stdout
    traj = read_csv(str(tmp_path / 'exc.csv'))
    assert traj['joint_names'] == [f'joint{i}' for i in range(1, 8)]
    assert len(traj['time_from_start']) == 151 and traj['positions'].shape == (151, 7)
    assert np.allclose(traj['positions'][:, 1], 0.0) and np.ptp(traj['positions'][:, 0]) > 0
    assert np.allclose(traj['velocities'][[0, -1]], 0.0, atol=1e-12)
    bad = _run([ARM, '-o', 'x.csv', '--home', '0,0,0'], tmp_path)
    assert bad.returncode == 2 and bad.stderr.count('\n') == 1
    assert bad.stderr.startswith('excitation_trajectory: error: --home has 3 values for the 7 joints')
    bad = _run([ARM, '-o', 'x.csv', '--home', '0,0,0,0,0,0,0'], tmp_path)
    assert bad.returncode == 2 and "position limit of joint 'joint4'" in bad.stderr and bad.stderr.count('\n') == 1
    bad = _run([ARM, '-o', 'x.csv', '--iterations', '0'], tmp_path)
    assert bad.returncode == 2 and '--iterations: must be an integer >= 1' in bad.stderr
    assert not (tmp_path / 'x.csv').exists()
