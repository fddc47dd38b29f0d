"""Frame Jacobians and J̇q̇ (algorithms/jacobian.py, codegen/traced/jacobian.py) against Pinocchio's
getFrameJacobian and getFrameClassicalAcceleration in its three reference frames, against finite
differences of link_pose, and the root-frame forward pass; every execution path; the error cases."""
import glob
import inspect
import os
import re
import sys
import warnings

import numpy as np
import pytest

from dyn_cases import ARM, rel_err, states
from lie_dynamics import load_urdf
from lie_dynamics.algorithms import jacobian as jac
from lie_dynamics.algorithms.kinematics import adjoints, spatial_motion, spatial_screws, world_poses
from lie_dynamics.codegen import native, runtime
from lie_dynamics.codegen.traced import jacobian as t_jac
from lie_dynamics.spatial import log3
from oracle import Oracle
from robots import named_urdf, random_urdf

FRAMES = ('world_aligned', 'local', 'world')
TOL = 1e-10
ERD = next(iter(glob.glob(os.path.join(sys.prefix, 'lib', 'python3*', 'site-packages', 'cmeel.prefix', 'share',
                                       'example-robot-data', 'robots'))), None)


def _read(path):
    with open(path, encoding='utf-8') as fh:
        return fh.read()


def _robot(name):
    """(xml, controlled joints or None, locked values or None, links to check)."""
    if name == 'arm7':
        return _read(ARM), None, None, ['link3', 'tool0', 'flange']
    if name == 'panda_mimic':       # panda_finger_joint2 mimics panda_finger_joint1
        return _read(os.path.join(ERD, 'panda_description', 'urdf', 'panda.urdf')), None, None, \
            ['panda_rightfinger', 'panda_hand_tcp', 'panda_link4']
    if name == 'panda_locked':      # arm joints only: the fingers are locked, their links folded
        return _read(os.path.join(ERD, 'panda_description', 'urdf', 'panda.urdf')), \
            [f'panda_joint{i}' for i in range(1, 8)], {'panda_finger_joint1': 0.03}, \
            ['panda_leftfinger', 'panda_rightfinger', 'panda_hand_tcp']
    if name == 'ur5':
        return _read(os.path.join(ERD, 'ur_description', 'urdf', 'ur5_robot.urdf')), None, None, \
            ['tool0', 'wrist_2_link']
    xml = named_urdf(name)
    if name == 'tree12':            # half the joints controlled, the rest locked at random values
        names = load_urdf(xml).joint_names
        rng = np.random.default_rng(12)
        ctrl = sorted(rng.choice(names, size=len(names) // 2, replace=False), key=names.index)
        locked = {n: float(rng.uniform(-1, 1)) for n in names if n not in ctrl}
        return xml, ctrl, locked, None
    return xml, None, None, None


def _case(name):
    xml, ctrl, locked, links = _robot(name)
    with warnings.catch_warnings():
        warnings.simplefilter('ignore')
        model = load_urdf(xml, joints=ctrl)
    if locked:
        model.set_locked(locked)
    oracle = Oracle(xml, joints=model.joint_names, locked=locked)
    if links is None:  # every link a movable body carries, the last few of the tree
        links = [ln for ln, (b, _) in model.link_frames.items() if b >= 0][-4:]
    return model, oracle, links


ROBOTS = ['arm7', 'panda_mimic', 'panda_locked', 'ur5', 'tree20_mimic', 'mixed_types', 'tree12', 'fixed_heavy']
needs_erd = pytest.mark.skipif(ERD is None, reason='example-robot-data is a test dependency')


@pytest.mark.parametrize('name', ROBOTS)
def test_jacobian_and_drift_match_pinocchio_in_every_frame(name):
    if name.startswith(('panda', 'ur5')) and ERD is None:
        pytest.skip('example-robot-data is not installed')
    model, oracle, links = _case(name)
    q, qd, qdd = states(model, N=6, seed=23)
    rng = np.random.default_rng(5)
    for link in links:
        for point in (None, rng.uniform(-0.2, 0.2, 3)):
            for frame in FRAMES:
                J = model.jacobian(q, link, frame, point)                       # batch
                a = model.jacobian_dot_times_qd(q, qd, link, frame, point)
                assert J.shape == (len(q), 6, model.n) and a.shape == (len(q), 6)
                J_ref = np.array([oracle.frame_jacobian(x, link, frame, point) for x in q])
                a_ref = np.array([oracle.frame_classical_acceleration(x, v, 0 * v, link, frame, point)
                                  for x, v in zip(q, qd)])
                assert rel_err(J, J_ref, 1.0) < TOL, (link, frame, point)
                assert rel_err(a, a_ref, 1.0) < TOL, (link, frame, point)
                # one state (the float kernel's fast path), and J qdd + drift = the classical acceleration
                assert rel_err(model.jacobian(q[0], link, frame, point)[None], J_ref[:1], 1.0) < TOL
                a0 = model.jacobian_dot_times_qd(q[0], qd[0], link, frame, point)
                full = oracle.frame_classical_acceleration(q[0], qd[0], qdd[0], link, frame, point)
                assert rel_err((J[0] @ qdd[0] + a0)[None], full[None], 1.0) < TOL


@needs_erd
def test_mimic_joint_adds_to_its_masters_column():
    model, oracle, _ = _case('panda_mimic')
    k = model.joint_names.index('panda_finger_joint1')
    assert 'panda_finger_joint2' in model.mimic_joints and k >= 0
    q = states(model, N=1, seed=3)[0][0]
    J = model.jacobian(q, 'panda_rightfinger', 'world_aligned')
    # the right finger moves only through the mimic joint: its finger column is the mimic's axis
    assert np.linalg.norm(J[:3, k]) == pytest.approx(1.0, abs=1e-12)
    assert np.allclose(J[3:, k], 0.0)
    assert np.allclose(model.jacobian(q, 'panda_leftfinger', 'world_aligned')[:3, k], -J[:3, k])


@needs_erd
def test_locked_values_reach_the_kernel_after_compilation():
    """Folded finger links follow set_locked (the link offset is a kernel input, never recompiled)."""
    xml, ctrl, _, _ = _robot('panda_locked')
    model = load_urdf(xml, joints=ctrl)
    q, qd, _ = states(model, N=3, seed=8)
    for value in (0.0, 0.04, 0.01):
        model.set_locked({'panda_finger_joint1': value})
        oracle = Oracle(xml, joints=ctrl, locked={'panda_finger_joint1': value})
        for frame in FRAMES:
            J = model.jacobian(q[0], 'panda_leftfinger', frame)
            assert rel_err(J[None], oracle.frame_jacobian(q[0], 'panda_leftfinger', frame)[None], 1.0) < TOL
            a = model.jacobian_dot_times_qd(q[1], qd[1], 'panda_leftfinger', frame)
            a_ref = oracle.frame_classical_acceleration(q[1], qd[1], 0 * qd[1], 'panda_leftfinger', frame)
            assert rel_err(a[None], a_ref[None], 1.0) < TOL


# ------------------------------------------------------------------ finite differences of link_pose
def _point_pose(model, q, link, point):
    T = model.link_pose(link, q)
    T[..., :3, 3] += T[..., :3, :3] @ point
    return T


@pytest.mark.parametrize('name', ['arm7', 'mixed_types', 'tree20_mimic'])
def test_jacobian_and_drift_against_finite_differences_of_link_pose(name):
    model, _, links = _case(name)
    q, qd, _ = states(model, N=4, seed=31)
    point = np.array([0.05, -0.1, 0.2])
    h, h2 = 1e-6, 1e-4
    for link in links:
        for x, v in zip(q, qd):
            Tp, Tm, T0 = (_point_pose(model, x + s * v, link, point) for s in (h, -h, 0.0))
            pdot = (Tp[:3, 3] - Tm[:3, 3]) / (2 * h)
            w = log3(Tp[:3, :3] @ Tm[:3, :3].T) / (2 * h)                 # world-axes angular velocity
            R = T0[:3, :3]
            vs = pdot + np.cross(T0[:3, 3], w)                              # velocity of the point at the origin
            expected = {'world_aligned': np.concatenate([pdot, w]), 'local': np.concatenate([R.T @ pdot, R.T @ w]),
                        'world': np.concatenate([vs, w])}
            for frame, fd in expected.items():
                Jv = model.jacobian(x, link, frame, point) @ v
                assert np.allclose(Jv, fd, rtol=0, atol=1e-8 * max(1, np.abs(fd).max())), frame
            # p̈ at q̈ = 0: second central difference of the point's position along q + t qd
            P = [_point_pose(model, x + s * v, link, point)[:3, 3] for s in (h2, 0.0, -h2)]
            pdd = (P[0] - 2 * P[1] + P[2]) / h2 ** 2
            a = model.jacobian_dot_times_qd(x, v, link, 'world_aligned', point)
            assert np.allclose(a[:3], pdd, rtol=0, atol=1e-6 * max(1, np.abs(pdd).max()))
            # the documented relations to d/dt (J q̇) along q + t qd, in every frame
            for frame in FRAMES:
                Jd = (model.jacobian(x + h * v, link, frame, point) - model.jacobian(x - h * v, link, frame, point)) @ v
                Jd /= 2 * h
                V = model.jacobian(x, link, frame, point) @ v
                extra = np.zeros(6)
                if frame != 'world_aligned':
                    extra[:3] = np.cross(V[3:], V[:3])
                a = model.jacobian_dot_times_qd(x, v, link, frame, point)
                assert np.allclose(a, Jd + extra, rtol=0, atol=1e-7 * max(1, np.abs(a).max())), frame


@pytest.mark.parametrize('name', ['arm7', 'tree20_mimic'])
def test_jacobian_times_qd_is_the_forward_pass_twist(name):
    """J_world q̇ = the root-frame twist of eq 18 (kinematics.spatial_motion), for the kernel path."""
    model, _, links = _case(name)
    q, qd, _ = states(model, N=5, seed=4)
    x = model.body_coordinates(q)
    A = spatial_screws(model, adjoints(world_poses(model, x))[0])
    V, _ = spatial_motion(model, A, qd @ model.E.T)
    for link in links:
        b = model.link_frames[link][0]
        J = jac.jacobian(model, q, link, 'world', mode='loop')
        assert rel_err(np.einsum('nij,nj->ni', J, qd), np.concatenate([V[:, b, 3:], V[:, b, :3]], axis=1), 1.0) < 1e-12


# ------------------------------------------------------------------ execution paths
@pytest.mark.parametrize('name', ['chain7', 'tree20_mimic', 'mixed_types', 'prismatic_only'])
def test_every_path_gives_the_same_result(name):
    model = load_urdf(named_urdf(name))
    N = runtime.THRESHOLDS['jacobian'].rows_from + 3
    q, qd, _ = states(model, N=N, seed=2)
    link = [ln for ln, (b, _) in model.link_frames.items() if b >= 0][-1]
    point = np.array([0.1, 0.0, -0.3])
    for frame in FRAMES:
        for fn, args in ((jac.jacobian, (q,)), (jac.jacobian_dot_times_qd, (q, qd))):
            ref = fn(model, *args, link, frame, point, mode='vectorized')
            for mode in ('loop', 'rows', None):
                assert rel_err(fn(model, *args, link, frame, point, mode=mode), ref, 1.0) < 1e-12, (frame, mode)
            small = fn(model, *(a[:3] for a in args), link, frame, point)
            one = fn(model, *(a[-1] for a in args), link, frame, point)
            assert rel_err(small, ref[:3], 1.0) < 1e-12 and rel_err(one[None], ref[-1:], 1.0) < 1e-12


def test_models_without_a_kernel_take_the_reference(monkeypatch):
    xml = named_urdf('chain7')
    monkeypatch.setitem(runtime.THRESHOLDS, 'jacobian', runtime.THRESHOLDS['jacobian']._replace(compile_max=2))
    model = load_urdf(xml)
    oracle = Oracle(xml, joints=model.joint_names)
    link = [ln for ln, (b, _) in model.link_frames.items() if b >= 0][-1]
    q, qd, _ = states(model, N=3, seed=9)
    assert jac.jacobian(model, q, link, mode='loop') is None      # no kernel for this model
    for frame in FRAMES:
        J = model.jacobian(q, link, frame)
        assert rel_err(J, np.array([oracle.frame_jacobian(x, link, frame) for x in q]), 1.0) < TOL
        a = model.jacobian_dot_times_qd(q[0], qd[0], link, frame)
        a_ref = oracle.frame_classical_acceleration(q[0], qd[0], 0 * qd[0], link, frame)
        assert rel_err(a[None], a_ref[None], 1.0) < TOL


def test_links_no_controlled_joint_moves_have_zero_jacobians():
    """The root link, and the links of a branch the model dropped (no controlled joint beneath)."""
    xml = named_urdf('tree12')
    full = load_urdf(xml)
    ctrl = full.joint_names[-2:]
    model = load_urdf(xml, joints=ctrl)
    oracle = Oracle(xml, joints=ctrl)
    still = [ln for ln, (b, _) in model.link_frames.items() if b < 0]
    assert len(still) >= 2 and any(b == -2 for b, _ in model.link_frames.values())
    q, qd, _ = states(model, N=2, seed=1)
    for link in still:
        for frame in FRAMES:
            J = model.jacobian(q, link, frame, point=[0.1, 0.2, 0.3])
            assert J.shape == (2, 6, model.n) and not J.any()
            assert not model.jacobian_dot_times_qd(q[0], qd[0], link, frame).any()
            assert np.abs(oracle.frame_jacobian(q[0], link, frame)).max() < 1e-15


@needs_erd
def test_links_moved_only_by_locked_joints_have_zero_jacobians():
    """Panda controlled by joints 3-7: links 1 and 2 are modelled bodies (ancestors of controlled
    joints) that only locked joints move; the kernels trace constant zeros for them."""
    xml = _read(os.path.join(ERD, 'panda_description', 'urdf', 'panda.urdf'))
    ctrl = [f'panda_joint{i}' for i in range(3, 8)]
    locked = {'panda_joint1': 0.4, 'panda_joint2': -0.3, 'panda_finger_joint1': 0.02}
    model = load_urdf(xml, joints=ctrl)
    model.set_locked(locked)
    oracle = Oracle(xml, joints=ctrl, locked=locked)
    q, qd, _ = states(model, N=40, seed=6)       # 40 states: the rows kernel
    for link in ('panda_link1', 'panda_link2', 'panda_link5'):
        assert model.link_frames[link][0] >= 0
        for frame in FRAMES:
            J, a = model.jacobian(q, link, frame), model.jacobian_dot_times_qd(q, qd, link, frame)
            J1 = model.jacobian(q[0], link, frame)
            assert rel_err(J, np.array([oracle.frame_jacobian(x, link, frame) for x in q]), 1.0) < TOL
            assert rel_err(J1[None], J[:1], 1.0) < 1e-14
            assert rel_err(a, np.array([oracle.frame_classical_acceleration(x, v, 0 * v, link, frame)
                                        for x, v in zip(q, qd)]), 1.0) < TOL
            if link != 'panda_link5':
                assert not J.any() and not J1.any() and not a.any()


def test_a_robot_without_movable_joints():
    model = load_urdf('<robot name="r"><link name="a"/><link name="b"/><joint name="j" type="fixed">'
                      '<parent link="a"/><child link="b"/></joint></robot>')
    assert model.jacobian(np.zeros(0), 'b').shape == (6, 0)
    assert model.jacobian_dot_times_qd(np.zeros((3, 0)), np.zeros((3, 0)), 'b', 'local').shape == (3, 6)


# ------------------------------------------------------------------ errors
def test_bad_arguments_are_refused_with_a_reason():
    model = load_urdf(ARM)
    q = np.zeros(model.n)
    with pytest.raises(ValueError, match=r"unknown link 'tool1'; did you mean 'tool0'"):
        model.jacobian(q, 'tool1')
    with pytest.raises(ValueError, match=r"unknown link 'zzz'"):
        model.jacobian(q, 'zzz')
    with pytest.raises(ValueError, match=r"unknown link 3"):
        model.jacobian(q, 3)
    with pytest.raises(ValueError, match=r"unknown frame 'global': use one of 'world_aligned', 'local', 'world'"):
        model.jacobian(q, 'tool0', 'global')
    with pytest.raises(ValueError, match=r'point must have shape \(3,\)'):
        model.jacobian(q, 'tool0', point=[0.1, 0.2])
    with pytest.raises(ValueError, match='point contains non-finite values'):
        model.jacobian_dot_times_qd(q, q, 'tool0', point=[0.1, np.nan, 0.2])
    with pytest.raises(ValueError, match=r'q must have shape \(7,\) or \(N, 7\)'):
        model.jacobian(np.zeros(6), 'tool0')
    with pytest.raises(ValueError, match='qd has 1 states, expected 2'):
        model.jacobian_dot_times_qd(np.zeros((2, 7)), q, 'tool0')
    with pytest.raises(ValueError, match='q contains non-finite values'):
        model.jacobian(np.full(7, np.inf), 'tool0')
    with pytest.raises(ValueError, match='mode must be one of'):
        jac.jacobian(model, q, 'tool0', mode='fast')


def test_eqs_13_to_15_as_corrected_in_the_architecture_notes():
    """f^-1 ḟ for f = M e^{[B_1] x_1} e^{[B_2] x_2} e^{[B_3] x_3}: eq 13 with e^{-B x} B e^{+B x} in every
    term, and eqs 14-15 with A_i = M B_i M^-1, equal a central difference; the summary's eq 13 term
    e^{-B_n x_n} B_{n-1} e^{-B_n x_n} does not."""
    from lie_dynamics.spatial import Ad, exp6, hat6, inv, vee6
    rng = np.random.default_rng(13)
    B = [np.concatenate([w / np.linalg.norm(w), rng.normal(size=3)]) for w in rng.normal(size=(3, 3))]
    M = exp6(rng.normal(size=6))
    x, xd, h = rng.normal(size=3), rng.normal(size=3), 1e-6

    def f(x):
        return M @ exp6(B[0] * x[0]) @ exp6(B[1] * x[1]) @ exp6(B[2] * x[2])
    fd = vee6(inv(f(x)) @ (f(x + h * xd) - f(x - h * xd)) / (2 * h))

    def e(S, t):
        return exp6(S * t)

    def eq13(S, sign):
        return vee6(hat6(S[2]) * xd[2] + e(S[2], -x[2]) @ hat6(S[1]) @ e(S[2], sign * x[2]) * xd[1]
                    + e(S[2], -x[2]) @ e(S[1], -x[1]) @ hat6(S[0]) @ e(S[1], x[1]) @ e(S[2], x[2]) * xd[0])
    A = [Ad(M) @ b for b in B]
    assert np.allclose(eq13(B, 1.0), fd, atol=1e-8)
    assert np.allclose(Ad(inv(M)) @ eq13(A, 1.0), fd, atol=1e-8)     # eqs 14-15
    assert not np.allclose(eq13(B, -1.0), fd, atol=1e-3)


def test_native_kernels_above_the_python_cap():
    """THRESHOLDS['jacobian'] native_max: a chain deeper than compile_max keeps native Jacobians
    (no Python kernel: the vectorised reference is the comparison), equal to it and Pinocchio."""
    if native.module() is None:
        pytest.skip('no working C compiler')
    xml = random_urdf(71, 70, fixed_links=False)
    model = load_urdf(xml)
    t = runtime.THRESHOLDS['jacobian']
    assert t.compile_max < model.nb <= runtime.native_max(t)
    oracle = Oracle(xml, joints=model.joint_names)
    b = int(np.argmax(model.depth))
    link = next(ln for ln, (bb, _) in model.link_frames.items() if bb == b)
    q, qd, _ = states(model, N=2, seed=3)
    for frame in ('world_aligned', 'local'):
        J, a = model.jacobian(q, link, frame), model.jacobian_dot_times_qd(q, qd, link, frame)
        for kind in ('jacobian', 'jacobian_dot'):
            assert runtime.native(model, t_jac.spec(kind, frame, b)) is not None
        assert rel_err(J, jac.jacobian(model, q, link, frame, mode='vectorized'), 1.0) < 1e-12
        assert rel_err(a, jac.jacobian_dot_times_qd(model, q, qd, link, frame, mode='vectorized'), 1.0) < 1e-12
        for i in range(len(q)):
            assert rel_err(J[i], oracle.frame_jacobian(q[i], link, frame), 1.0) < 1e-10
            a_ref = oracle.frame_classical_acceleration(q[i], qd[i], 0 * qd[i], link, frame)
            assert rel_err(a[i][None], a_ref[None], 1.0) < 1e-10


# ------------------------------------------------------------------ the methods' C call (dispatch.native_keyed)
def _count_python_path(monkeypatch):
    """Counts the calls that reach the algorithm's Python function (the methods' slow path)."""
    calls = []
    for name in ('jacobian', 'jacobian_dot_times_qd'):
        fn = getattr(jac, name)
        monkeypatch.setattr(jac, name, lambda *a, _fn=fn, **k: calls.append(1) or _fn(*a, **k))
    return calls


@pytest.mark.parametrize('xml', [_read(ARM), named_urdf('tree20_mimic'), random_urdf(32, 32, tree=True)],
                         ids=['arm7', 'tree20_mimic', 'tree32'])
def test_methods_call_the_kernel_from_c_bit_for_bit(xml, monkeypatch):
    """model.jacobian(q, link[, frame]) and model.jacobian_dot_times_qd(q, qd, link[, frame]) run
    the link frame's kernel from C, positional or keyword, never reaching the Python function;
    their results equal that function's (the previous path) to the bit."""
    if native.module() is None:
        pytest.skip('no working C compiler')
    with warnings.catch_warnings():
        warnings.simplefilter('ignore')
        model = load_urdf(xml)
    oracle = Oracle(xml, joints=model.joint_names)
    links = [ln for ln, (b, _) in model.link_frames.items() if b >= 0][-3:]
    q, qd, _ = states(model, N=4, seed=31)
    expected = {(link, frame, i): (jac.jacobian(model, q[i], link, frame),
                                   jac.jacobian_dot_times_qd(model, q[i], qd[i], link, frame))
                for link in links for frame in FRAMES for i in range(len(q))}
    for link in links:
        for frame in FRAMES:
            model.jacobian(q[0], link, frame), model.jacobian_dot_times_qd(q[0], qd[0], link, frame)   # resolved
    calls = _count_python_path(monkeypatch)
    for (link, frame, i), (J, a) in expected.items():
        got = [model.jacobian(q[i], link, frame), model.jacobian(q[i], link, frame=frame),
               model.jacobian_dot_times_qd(q[i], qd[i], link, frame),
               model.jacobian_dot_times_qd(q[i], qd[i], link=link, frame=frame)]
        if frame == 'world_aligned':
            got += [model.jacobian(q[i], link), model.jacobian_dot_times_qd(q[i], qd[i], link)]
        for r in got:
            ref = J if r.ndim == 2 else a
            assert r.shape == ref.shape and np.array_equal(r, ref), (link, frame, i)
    assert not calls   # every call above ran from C
    assert type(inspect.getattr_static(model, 'jacobian')).__name__ == 'Method'
    for link in links[-1:]:
        assert rel_err(model.jacobian(q[1], link, 'local')[None], oracle.frame_jacobian(q[1], link, 'local')[None],
                       1.0) < TOL
        a_ref = oracle.frame_classical_acceleration(q[1], qd[1], 0 * qd[1], link, 'world')
        assert rel_err(model.jacobian_dot_times_qd(q[1], qd[1], link, 'world')[None], a_ref[None], 1.0) < TOL


def test_methods_fall_back_to_the_validating_path(monkeypatch):
    """What the C call cannot take runs the Python function: other dtypes, strides and batches
    give the same results, bad states and unknown links or frames the same ValueErrors, each time;
    a setter, another model and runtime.clear are followed."""
    model = load_urdf(ARM)
    other = load_urdf(ARM)
    q, qd, _ = states(model, N=3, seed=32)
    link = 'tool0'
    J0, a0 = model.jacobian(q[0], link), model.jacobian_dot_times_qd(q[0], qd[0], link, 'local')
    calls = _count_python_path(monkeypatch)
    J_batch = model.jacobian(q, link)
    assert np.array_equal(J_batch[0], J0) and calls
    calls.clear()
    assert np.array_equal(model.jacobian(q[0].tolist(), link), J0) and calls
    strided = np.empty((model.n, 2))
    strided[:, 0] = q[0]
    assert np.array_equal(model.jacobian(strided[:, 0], link), J0)
    assert np.array_equal(model.jacobian(np.zeros(7, dtype=int), link), model.jacobian(np.zeros(7), link))
    assert np.array_equal(model.jacobian_dot_times_qd(q[0], qd[0].astype(np.float32).astype(float), link, 'local'),
                          model.jacobian_dot_times_qd(q[0], qd[0].astype(np.float32), link, 'local'))
    assert np.array_equal(model.jacobian_dot_times_qd(q[0], qd[0], link, 'local'), a0)
    J_point = model.jacobian(q[0], link, point=(0.0, 0.0, 0.0))
    assert rel_err(J_point[None], J0[None], 1.0) < 1e-12
    for _ in range(2):   # a failing key is not remembered as a kernel
        with pytest.raises(ValueError, match=r"unknown link 'tool1'; did you mean 'tool0'"):
            model.jacobian(q[0], 'tool1')
        with pytest.raises(ValueError, match=r'unknown link 3'):
            model.jacobian(q[0], 3)
        with pytest.raises(ValueError, match=r"unknown frame 'global'"):
            model.jacobian_dot_times_qd(q[0], qd[0], link, frame='global')
        with pytest.raises(ValueError, match=r'q must have shape \(7,\) or \(N, 7\)'):
            model.jacobian(q[0, :6], link)
        with pytest.raises(ValueError, match='q contains non-finite values'):
            model.jacobian(np.full(7, np.nan), link)
        with pytest.raises(ValueError, match='qd contains non-finite values'):
            model.jacobian_dot_times_qd(q[0], np.full(7, np.inf), link)
        bad = np.array(['a'] * 7)   # the same error as the Python function's, whatever it says
        with pytest.raises(ValueError) as direct:
            jac.jacobian(model, bad, link)
        with pytest.raises(ValueError, match=f'^{re.escape(str(direct.value))}$'):
            model.jacobian(bad, link)
        with pytest.raises(TypeError):
            model.jacobian(q[0], link, 'local', None, 1)
    part = load_urdf(ARM, joints=model.joint_names[1:])
    for value in (0.0, 0.3):   # a setter: the kernel's parameters change, the C call follows
        part.set_locked({'joint1': value})
        oracle = Oracle(_read(ARM), joints=part.joint_names, locked={'joint1': value})
        assert rel_err(part.jacobian(q[0, 1:], link)[None],
                       oracle.frame_jacobian(q[0, 1:], link, 'world_aligned')[None], 1.0) < TOL
    assert np.array_equal(other.jacobian(q[0], link), J0)   # another model in turn
    runtime.clear()
    assert np.array_equal(other.jacobian(q[0], link), J0)


def test_tree_kernels_write_only_the_path_columns(monkeypatch):
    """On a 64-body tree, the Jacobian kernel of a deep and of a shallow link computes only the
    columns of the joints that move it (Trace.scatter), zeros elsewhere; a chain's tip has no
    scatter. One state (from C) and a batch equal the Python kernel to the bit and Pinocchio to
    1e-12 in every frame; bad states leave the fast path for the validating one."""
    xml = random_urdf(64, 64, tree=True, fixed_links=False)
    model = load_urdf(xml)
    assert model.nb == 64
    oracle = Oracle(xml, joints=model.joint_names)
    fr = runtime.frames(model)
    deep = int(np.argmax(model.depth))
    shallow = next(b for b in range(model.nb) if model.depth[b] == min(model.depth) and model.ancestors[b].sum() == 1)
    assert model.depth[deep] >= 4 * model.depth[shallow]
    q, qd, _ = states(model, N=5, seed=64)
    for b in (deep, shallow):
        link = next(ln for ln, (bb, _) in model.link_frames.items() if bb == b)
        moved = np.flatnonzero(model.ancestors[b] @ np.abs(model.E))   # columns of the path's joints
        assert 0 < len(moved) < model.n
        idx, size = t_jac.build(fr, 'jacobian', 'world_aligned', b).scatter
        assert size == 6 * model.n and sorted(idx) == sorted(r * model.n + k for r in range(6) for k in moved)
        for frame in FRAMES:
            J = model.jacobian(q, link, frame)                     # a batch
            J0 = model.jacobian(q[0], link, frame)                 # one state, the C method
            assert np.array_equal(J0, J[0])
            J_loop = jac.jacobian(model, q, link, frame, mode='loop')
            assert J_loop is not None and np.array_equal(J, J_loop)
            off = np.setdiff1d(np.arange(model.n), moved)
            assert not J[:, :, off].any()
            J_ref = np.array([oracle.frame_jacobian(x, link, frame) for x in q])
            assert rel_err(J, J_ref, 1.0) < 1e-12, (b, frame)
            a = model.jacobian_dot_times_qd(q, qd, link, frame)
            a_ref = np.array([oracle.frame_classical_acceleration(x, v, 0 * v, link, frame) for x, v in zip(q, qd)])
            assert rel_err(a, a_ref, 1.0) < 1e-12, (b, frame)
        calls = _count_python_path(monkeypatch)
        if b == deep:   # a NaN the result depends on: the path's first joint's (the shallow link's
            for bad in (q[0].copy(), q.copy()):   # own joint does not move its frame's Jacobian)
                bad[..., moved[0]] = np.nan
                with pytest.raises(ValueError, match='q contains non-finite values'):
                    model.jacobian(bad, link)
        with pytest.raises(ValueError, match=rf'q must have shape \({model.n},\) or \(N, {model.n}\)'):
            model.jacobian(q[0, :-1], link)
        strided = np.repeat(q[0], 2)[::2]
        assert np.array_equal(model.jacobian(strided, link), model.jacobian(q[0], link))
        if native.module() is not None:   # these ran the Python function, the plain call from C did not
            assert len(calls) == (4 if b == deep else 2)
        monkeypatch.undo()
    chain = load_urdf(random_urdf(7, 20, fixed_links=False))
    tip = int(np.argmax(chain.depth))
    assert t_jac.build(runtime.frames(chain), 'jacobian', 'world_aligned', tip).scatter is None
