"""Contact isolation and the external wrench (algorithms/contact_isolation.py) on residuals made
from known wrenches through Pinocchio's frame Jacobians (computeFrameJacobian, LOCAL): chains,
trees, mimic and locked joints, a real robot; rank-deficient links; two contacts; settling."""
import glob
import os
import sys
import warnings

import numpy as np
import pinocchio as pin
import pytest

from dyn_cases import ARM, states
from lie_dynamics import load_urdf
from lie_dynamics.algorithms import contact_isolation as ci
from oracle import Oracle
from robots import named_urdf

ERD = next(iter(glob.glob(os.path.join(sys.prefix, 'lib', 'python3*', 'site-packages', 'cmeel.prefix', 'share',
                                       'example-robot-data', 'robots'))), None)
needs_erd = pytest.mark.skipif(ERD is None, reason='example-robot-data is a test dependency')


def _read(path):
    with open(path, encoding='utf-8') as fh:
        return fh.read()


def _panda():
    return _read(os.path.join(ERD, 'panda_description', 'urdf', 'panda.urdf'))


def _robot(name):
    """(model, oracle): the model with its controlled and locked joints, Pinocchio beside it."""
    ctrl = locked = None
    if name == 'arm7':
        xml = _read(ARM)
    elif name == 'panda_mimic':     # panda_finger_joint2 mimics panda_finger_joint1 (two branches)
        xml = _panda()
    elif name == 'panda_locked':    # arm joints only: the fingers locked (folded into the hand)
        xml, ctrl, locked = _panda(), [f'panda_joint{i}' for i in range(1, 8)], {'panda_finger_joint1': 0.03}
    elif name == 'ur5':
        xml = _read(os.path.join(ERD, 'ur_description', 'urdf', 'ur5_robot.urdf'))
    else:
        xml = named_urdf(name)
        if name == 'tree12':        # half the joints controlled, the rest locked at random values
            names = load_urdf(xml).joint_names
            rng = np.random.default_rng(12)
            ctrl = sorted(rng.choice(names, size=len(names) // 2, replace=False), key=names.index)
            locked = {n: float(rng.uniform(-1, 1)) for n in names if n not in ctrl}
    with warnings.catch_warnings():
        warnings.simplefilter('ignore')
        model = load_urdf(xml, joints=ctrl)
    if locked:
        model.set_locked(locked)
    return model, Oracle(xml, joints=model.joint_names, locked=locked)


def pin_jacobian(oracle, q, link):
    """Pinocchio's LOCAL frame Jacobian of a link, (6, n) in our columns (rows v, w)."""
    fid = oracle.model.getFrameId(link, pin.FrameType.BODY)
    J = pin.computeFrameJacobian(oracle.model, oracle.data, oracle.pin_q(q), fid, pin.LOCAL)
    return J @ oracle.E


def scaled(J):
    """(D J, D): the Jacobian with its translation rows divided by the lever L, the RMS distance of
    the origin from the revolute joints' axes (|v_j| / |w_j|), D = diag(1/L x 3, 1 x 3): the
    unknowns (L f, m) of the wrench fit."""
    w = np.linalg.norm(J[3:], axis=0)
    d = np.linalg.norm(J[:3, w > 1e-12], axis=0) / w[w > 1e-12]
    L = np.sqrt(np.mean(d * d)) if d.size and np.any(d > 0) else 1.0
    D = np.array([1 / L] * 3 + [1.0] * 3)
    return D[:, None] * J, D


def residual(oracle, q, pushes):
    """r = sum J_k^T F_k for {link: wrench (f, m) at its origin in its axes}."""
    return sum(pin_jacobian(oracle, q, link).T @ np.asarray(F, dtype=float) for link, F in pushes.items())


def _expected_support(model):
    """Per body, the controlled joints that move it: a walk to the root (independent of the tree
    matrices the module uses)."""
    out = []
    for b in range(model.nb):
        s, a = np.zeros(model.n, dtype=bool), b
        while a >= 0:
            s |= model.E[a] != 0
            a = model.parent[a]
        out.append(s)
    return np.array(out)


def _rigid_root(model, support, b):
    """The body whose link names a contact on body b: up while no controlled joint (nor a mimic of
    one) moves the body's own joint (a locked joint)."""
    while model.parent[b] >= 0 and not (model.E[b] != 0).any():
        b = model.parent[b]
    return b


ROBOTS = ['arm7', 'tree12', 'tree20_mimic', 'mimic', 'mixed_types', 'fixed_heavy', 'panda_mimic', 'panda_locked',
          'ur5']


@pytest.mark.parametrize('name', ROBOTS)
def test_a_push_on_each_link_is_isolated_and_its_wrench_recovered(name):
    if name.startswith(('panda', 'ur5')) and ERD is None:
        pytest.skip('example-robot-data is not installed')
    model, oracle = _robot(name)
    support = _expected_support(model)
    rng = np.random.default_rng(33)
    q = states(model, N=1, seed=34)[0][0]
    checked = isolated = 0
    for link, (b, _) in model.link_frames.items():
        if b < 0:
            continue
        # the supporting joints are Pinocchio's nonzero columns
        Jp = pin_jacobian(oracle, q, link)
        assert np.array_equal(ci.supporting_joints(model, link), np.abs(Jp).sum(axis=0) > 1e-12), link
        if not support[b].any():
            continue
        F = rng.normal(size=6) * np.array([20, 20, 20, 2, 2, 2])
        r = Jp.T @ F
        th = np.full(model.n, 1e-6 * np.abs(r).max())
        res = ci.isolate(model, q, r, th)
        checked += 1
        named = model.body_link_names[_rigid_root(model, support, b)]
        if model.mimic_joints and res.status == 'ambiguous':   # other links move with these joints alike
            assert named in res.candidates and res.link == '' and res.wrench is None, (link, res)
            continue
        assert res.status == 'isolated' and res.link == named, (link, res)
        isolated += 1
        # the wrench at the named link explains r; with 6 independent joints it is F itself
        w = res.wrench
        Jn = pin_jacobian(oracle, q, named)
        assert np.allclose(Jn.T @ w.wrench, r, atol=1e-9 * np.abs(r).max()), link
        sv = np.linalg.svd(scaled(Jn)[0], compute_uv=False)
        assert w.rank == int((sv >= ci.RCOND * sv[0]).sum())
        assert w.sigma_min == pytest.approx(sv[w.rank - 1], rel=1e-9)
        if w.rank == 6 and link == named:
            assert np.allclose(w.wrench, F, rtol=1e-8, atol=1e-8 * np.abs(F).max()), link
    assert checked >= 3 and isolated >= 1


def test_line_of_action_of_a_pure_force():
    model, oracle = _robot('arm7')
    q = states(model, N=1, seed=2)[0][0]
    rng = np.random.default_rng(4)
    for link in ('link6', 'link7'):
        p, f = rng.uniform(-0.1, 0.1, 3), rng.normal(size=3) * 30
        F = np.concatenate([f, np.cross(p, f)])            # the force f at p: the wrench at the origin
        res = ci.isolate(model, q, residual(oracle, q, {link: F}), 1e-6)
        assert res.link == link and res.wrench.rank == 6
        point, direction, pitch = ci.line_of_action(res.wrench.wrench)
        assert np.allclose(direction, f / np.linalg.norm(f), atol=1e-9)
        assert abs(pitch) < 1e-9
        assert np.linalg.norm(np.cross(p - point, direction)) < 1e-9    # p lies on the line
        assert abs(point @ direction) < 1e-9                            # the point closest to the origin
    assert ci.line_of_action(np.array([0, 0, 0, 1.0, 2.0, 3.0])) is None   # a pure torque has no line


def test_rank_deficient_links_solve_the_visible_components():
    model, oracle = _robot('arm7')
    rng = np.random.default_rng(6)
    q = states(model, N=1, seed=7)[0][0]
    for link, rank in (('link1', 1), ('link2', 2), ('link3', 3), ('link5', 5)):
        F = rng.normal(size=6) * 10
        J = pin_jacobian(oracle, q, link)
        res = ci.isolate(model, q, J.T @ F, 1e-6)
        w = res.wrench
        assert res.link == link and w.rank == rank
        # the visible part of F: in (L f, m) its projection on the row space of J (the minimum-norm solution)
        Js, D = scaled(J)
        U, s, _ = np.linalg.svd(Js)
        visible = D * (U[:, :rank] @ (U[:, :rank].T @ (F / D)))
        assert np.allclose(w.wrench, visible, atol=1e-9 * np.abs(F).max())
        assert w.sigma_min == pytest.approx(s[rank - 1], rel=1e-9)
        assert np.abs(w.misfit).max() < 1e-9 * np.abs(F).max()
    # rcond decides what is solved for: between the two smallest singular values, one is dropped
    J = model.jacobian(q, 'link7', 'local')
    s = np.linalg.svd(scaled(J)[0], compute_uv=False)
    r = J.T @ rng.normal(size=6)
    w = ci.link_wrench(model, q, r, 'link7', rcond=np.sqrt(s[4] * s[5]) / s[0])
    assert w.rank == 5 and w.sigma_min == pytest.approx(s[4], rel=1e-9)
    assert np.abs(w.misfit).max() > 1e-6 and np.abs(w.unexplained).max() < 1e-9   # dropped, not unexplainable
    assert ci.link_wrench(model, q, r, 'link7').rank == 6
    assert ci.link_wrench(model, q, r, 'link7', rcond=0.999).rank == 1


def test_the_rank_of_the_wrench_fit_does_not_depend_on_the_unit_of_length():
    """The same fit in millimetres (J's translation rows and the torques x 1000): the same rank and
    sigma_min, the force alike and the torque x 1000, at random states and near a singularity
    (the wrist: joints 5 and 7 aligned). Unscaled, the singular values for force and torque differ
    by the lever, so the rank depended on the unit."""
    model, oracle = _robot('arm7')
    rng = np.random.default_rng(21)
    qs = list(states(model, N=6, seed=22)[0]) + [np.array([0.2, -0.6, 0.1, 2.0, 0.3, 1e-4, 0.8])]
    for q in qs:
        for link in ('link3', 'link5', 'link6', 'link7', 'tool0'):
            J = pin_jacobian(oracle, q, link)
            F = rng.normal(size=6) * np.array([20, 20, 20, 2, 2, 2])
            r = J.T @ F
            Jmm = J * np.array([1e3] * 3 + [1.0] * 3)[:, None]
            m, mm = ci.solve_wrench(J, r), ci.solve_wrench(Jmm, 1e3 * r)
            assert m.rank == mm.rank and mm.sigma_min == pytest.approx(m.sigma_min, rel=1e-9), (link, q)
            np.testing.assert_allclose(mm.wrench, m.wrench * np.array([1.0] * 3 + [1e3] * 3), rtol=1e-7,
                                       atol=1e-9 * np.abs(m.wrench).max() * 1e3)
            assert ci.lever(Jmm) == pytest.approx(1e3 * ci.lever(J), rel=1e-12)
    # what the scaling recovers: at this state (a push of the contact benchmark) link6's J^T has,
    # unscaled, a singular value under rcond x the largest (a component of F was dropped, 0 by
    # design); scaled it has not, and the wrench comes back whole
    q = np.array([1.065, -0.022, 1.328, 1.749, -1.662, 2.659, 0.391])
    J = pin_jacobian(oracle, q, 'link6')
    s = np.linalg.svd(J, compute_uv=False)
    assert s[-1] < ci.RCOND * s[0]
    F = np.array([10.0, -20.0, 5.0, 0.5, -1.0, 2.0])
    w = ci.link_wrench(model, q, J.T @ F, 'link6')
    assert w.rank == 6 and w.sigma_min > 1.2 * ci.RCOND * np.linalg.svd(scaled(J)[0], compute_uv=False)[0]
    np.testing.assert_allclose(w.wrench, F, rtol=1e-8, atol=1e-8 * np.abs(F).max())


def test_two_contacts_are_ambiguous_never_guessed():
    # on a tree: joints over threshold on two branches
    model, oracle = _robot('tree12')
    support = _expected_support(model)
    q = states(model, N=1, seed=8)[0][0]
    bodies = [b for b in range(model.nb) if support[b].any()]
    pair = next((a, b) for a in bodies for b in bodies
                if not model.ancestors[a, b] and not model.ancestors[b, a]
                and not (support[a] & support[b]).any())
    rng = np.random.default_rng(9)
    r = residual(oracle, q, {model.body_link_names[b]: rng.normal(size=6) * 20 for b in pair})
    res = ci.isolate(model, q, r, 1e-6 * np.abs(r).max())
    assert res.status == 'ambiguous' and res.link == '' and res.wrench is None and 'branch' in res.reason
    # on a 7-joint chain: two contacts that no single wrench on the outer link explains
    model, oracle = _robot('arm7')
    for seed in range(5):
        q = states(model, N=1, seed=seed)[0][0]
        rng = np.random.default_rng(seed)
        r = residual(oracle, q, {'link3': rng.normal(size=6) * 20, 'link7': rng.normal(size=6) * 20})
        # thresholds under what no wrench on link7 can give (the part of r outside the range of J7^T)
        J = pin_jacobian(oracle, q, 'link7')
        U = np.linalg.svd(J.T, full_matrices=False)[0]
        th = min(0.5 * np.abs(r - U @ (U.T @ r)).max(), 0.5 * np.abs(r).min())
        assert th > 1e-3
        one = ci.isolate(model, q, residual(oracle, q, {'link7': rng.normal(size=6) * 20}), th)
        assert one.status == 'isolated' and one.link == 'link7'
        res = ci.isolate(model, q, r, th)
        assert res.status == 'ambiguous' and res.candidates == ('link7',) and 'two contacts' in res.reason, res
    # a joint beyond link4 under its threshold but above the tolerance: the contact is further out
    q = states(model, N=1, seed=1)[0][0]
    r = residual(oracle, q, {'link4': np.array([10.0, -5, 3, 1, 0.5, -1])})
    th = np.array([0.01] * 4 + [1.0] * 3)
    assert ci.isolate(model, q, r, th).link == 'link4'
    r[5] = 0.7
    assert ci.isolate(model, q, r, th).link == 'link6'   # a wrench on link6 (rank 6) gives exactly this r
    r[5] = 0.5 * ci.TOLERANCE   # within the tolerance, and not the next joint out: quiet
    assert ci.isolate(model, q, r, th).link == 'link4'
    r[5] = 0.0
    r[4] = 0.2 * ci.TOLERANCE   # the next joint out, within DOUBT x the tolerance: quiet
    assert ci.isolate(model, q, r, th).link == 'link4'
    r[4] = 0.5 * ci.TOLERANCE   # under the tolerance, over DOUBT x it: a contact on link5 may load it so
    res = ci.isolate(model, q, r, th)
    assert res.status == 'ambiguous' and res.candidates == ('link4', 'link5'), res
    assert "joint 'joint5'" in res.reason and 'near its tolerance' in res.reason
    assert ci.isolate(model, q, np.zeros(7), 1.0).status == 'none'


@needs_erd
def test_mimic_fingers_and_locked_fingers():
    model, oracle = _robot('panda_mimic')
    q = states(model, N=1, seed=3)[0][0]
    F = np.array([30.0, 10, 5, 0.1, 0.2, 0.3])
    r = residual(oracle, q, {'panda_leftfinger': F})
    res = ci.isolate(model, q, r, 1e-3)   # the fingers' Jacobians differ: one of them explains r
    assert res.status == 'isolated' and res.link == 'panda_leftfinger'
    assert np.allclose(pin_jacobian(oracle, q, res.link).T @ res.wrench.wrench, r, atol=1e-9)
    # locked fingers are folded into the hand: a push on a finger is a push on the hand's body
    model, oracle = _robot('panda_locked')
    q = states(model, N=1, seed=3)[0][0]
    r = residual(oracle, q, {'panda_leftfinger': F})
    res = ci.isolate(model, q, r, 1e-3)
    assert res.status == 'isolated' and res.link == model.body_link_names[model.link_frames['panda_leftfinger'][0]]
    assert np.allclose(pin_jacobian(oracle, q, res.link).T @ res.wrench.wrench, r, atol=1e-9)


@needs_erd
def test_tool_wrench_at_a_frame_on_a_real_robot():
    model, oracle = _robot('ur5')
    q = states(model, N=1, seed=5)[0][0]
    F = np.array([12.0, -4, 20, 0.5, -1, 0.2])
    est = ci.link_wrench(model, q, residual(oracle, q, {'tool0': F}), 'tool0', rcond=1e-6)
    assert est.rank == 6 and np.allclose(est.wrench, F, atol=1e-9)


def test_settling_waits_for_the_first_order_rise():
    K, dt = 50.0, 0.001
    s = ci.Settling(1.0 / K)
    tau = np.array([30.0, -12.0, 4.0])
    th = np.full(3, 2.0)
    settled_at = None
    for k in range(400):
        t = k * dt
        r = (1 - np.exp(-K * t)) * tau
        if s.update(t, r, th) and settled_at is None:
            settled_at = t
        if settled_at is not None:
            assert s.update(t + 1e-6, r, th)   # and it stays settled
    # after about 3.6 time constants: the residual within 3 % of tau
    assert 3.0 / K < settled_at < 4.5 / K
    s.reset()
    assert not s.update(0.0, tau, th)          # no history: not settled
    with pytest.raises(ValueError, match='settling'):
        ci.Settling(0.0)


def test_bad_arguments_are_refused():
    model, _ = _robot('arm7')
    q = np.zeros(7)
    with pytest.raises(ValueError, match='r must be 7 finite'):
        ci.isolate(model, q, np.full(7, np.nan), 1.0)
    with pytest.raises(ValueError, match='threshold'):
        ci.isolate(model, q, np.zeros(7), [1.0, 2.0])
    with pytest.raises(ValueError, match='threshold'):
        ci.isolate(model, q, np.zeros(7), 0.0)
    for bad in (0.0, -1.0, float('nan'), float('inf'), 1.0):
        with pytest.raises(ValueError, match='rcond'):
            ci.link_wrench(model, q, np.zeros(7), 'link7', rcond=bad)
    with pytest.raises(ValueError, match="did you mean 'link7'"):
        ci.check_moving_link(model, 'lnk7')
    with pytest.raises(ValueError, match='fixed to the root'):
        ci.check_moving_link(model, 'base_link')
    ci.check_moving_link(model, 'tool0')


def test_a_contact_further_out_that_its_own_joints_do_not_feel_is_not_guessed():
    model, oracle = _robot('arm7')
    q = np.array([0.2, -0.6, 0.1, 2.0, 0.3, 1.6, 0.8])   # link6's wrench fully seen here (rank 6)
    assert ci.link_wrench(model, q, np.zeros(7), 'link6').rank == 6
    # a force through the axis of joint 7 on link7: joint 7 feels nothing, r is that of a wrench on link6
    T7 = model.link_pose('link7', q)
    f = np.array([3.0, -20.0, 6.0])
    F7 = np.concatenate([f, np.cross(np.array([0.0, 0.0, 0.05]), f)])       # at (0, 0, 5 cm): on the z axis
    J7 = pin_jacobian(oracle, q, 'link7')
    assert np.allclose(T7[:3, 2] @ model.jacobian(q, 'link7', 'world_aligned')[3:, 6], 1.0)   # joint 7 turns about z
    r = J7.T @ F7
    assert abs(r[6]) < 1e-9
    # link6's wrench is fully seen: its pure force's line passes through joint 7's axis near link7,
    # so a push on link7 fits as well: ambiguous, never link6
    res = ci.isolate(model, q, r, 1e-3)
    assert res.status == 'ambiguous' and res.candidates == ('link6', 'link7') and 'through the axis' in res.reason
    res = ci.isolate(model, q, r, 1e-3, strict=True)
    assert res.status == 'ambiguous' and res.candidates == ('link6', 'link7')
    # off the axis, joint 7 feels it: isolated, the wrench fully seen
    F7 = np.concatenate([f, np.cross(np.array([0.04, 0.0, 0.05]), f)])
    for strict in (False, True):
        res = ci.isolate(model, q, J7.T @ F7, 1e-3, strict=strict)
        assert res.status == 'isolated' and res.link == 'link7'
    # a link with fewer than 6 supporting joints: named, but strict says a point contact further out fits too
    F3 = np.array([10.0, -20.0, 5.0, 0.5, -1.0, 2.0])
    r = pin_jacobian(oracle, q, 'link3').T @ F3
    assert ci.isolate(model, q, r, 1e-3).link == 'link3'
    res = ci.isolate(model, q, r, 1e-3, strict=True)
    assert res.status == 'ambiguous' and res.candidates[:2] == ('link3', 'link4'), res
    # strict still names a link whose wrench no point contact further out gives (a torque as well)
    r6 = pin_jacobian(oracle, q, 'link6').T @ np.array([10.0, -20.0, 5.0, 0.5, -1.0, 2.0])
    res = ci.isolate(model, q, r6, 1e-3, strict=True)
    assert res.status == 'isolated' and res.link == 'link6'


def test_a_joint_near_its_tolerance_is_ambiguous_and_the_measured_noise_resolves_it():
    """A push on link7 whose line passes near joint 7's axis: joint 7 feels 2 % of its threshold.
    Within the fixed tolerance (5 %) but over DOUBT x it: ambiguous between link6 and link7, never
    link6; with the residual's measured noise low (tol_j = NOISE_SIGMAS x noise_j), joint 7 is
    felt and link7 named with its wrench; with high noise the fixed tolerance stands."""
    model, oracle = _robot('arm7')
    q = np.array([0.2, -0.6, 0.1, 2.0, 0.3, 1.6, 0.8])
    th = np.array([2.6] * 4 + [0.36] * 3)
    J7 = pin_jacobian(oracle, q, 'link7')
    f = np.array([3.0, -20.0, 6.0])
    F7 = np.concatenate([f, np.cross([0.0, 0.0, 0.05], f)])   # through joint 7's axis (z): joint 7 quiet
    F7[5] += 0.02 * th[6]                                       # plus a torque about it: 2 % of its threshold
    r = J7.T @ F7
    assert abs(r[6]) == pytest.approx(0.02 * th[6], rel=1e-9)
    res = ci.isolate(model, q, r, th)
    assert res.status == 'ambiguous' and res.candidates == ('link6', 'link7') and res.link == '', res
    assert "joint 'joint7'" in res.reason
    quiet = 0.001 * th                                          # tol: max(6 x 0.1 %, floor 1 %) of th
    np.testing.assert_allclose(ci.tolerances(th, ci.TOLERANCE, quiet), ci.NOISE_FLOOR * ci.TOLERANCE * th)
    res = ci.isolate(model, q, r, th, noise=quiet)
    assert res.status == 'isolated' and res.link == 'link7'
    np.testing.assert_allclose(res.wrench.wrench, F7, rtol=1e-8, atol=1e-8 * np.abs(F7).max())
    loud = 0.01 * th                                            # 6 sigma over the fixed tolerance: capped
    np.testing.assert_allclose(ci.tolerances(th, ci.TOLERANCE, loud), ci.TOLERANCE * th)
    assert ci.isolate(model, q, r, th, noise=loud).status == 'ambiguous'
    # a joint well under DOUBT x its tolerance is quiet, but link6's wrench (rank 6) is a force whose
    # line passes near joint 7's axis on link7: ambiguous, never link6
    F7[5] -= 0.015 * th[6]
    res = ci.isolate(model, q, J7.T @ F7, th)
    assert res.status == 'ambiguous' and res.candidates == ('link6', 'link7'), res
    for bad in (np.full(6, 0.1), np.full(7, -0.1), np.full(7, np.nan)):
        with pytest.raises(ValueError, match='noise must be 7 finite values'):
            ci.isolate(model, q, r, th, noise=bad)


@needs_erd
def test_a_push_through_the_next_axis_is_ambiguous_where_the_line_is_fully_seen():
    """Panda (fingers locked): link6 has 6 supporting joints, so its wrench fixes the line of a pure
    force. A push on link7 whose line crosses joint 7's axis loads joint 7 with nothing and gives
    exactly the r of a wrench on link6: isolation says ambiguous, never link6. Pushes on link6
    itself (random points within 5 cm of its origin, random directions) are still named link6, and
    pushes on link7 off its axis link7. Residuals through Pinocchio's frame Jacobians."""
    model, oracle = _robot('panda_locked')
    th = 0.03 * model.effort_limits
    rng = np.random.default_rng(61)
    named = {'on axis': [], 'link6': [], 'link7': []}
    # the states where link6's wrench is fully seen (a few random ones are near a singularity:
    # rank 5 at the default rcond, and the line is not fixed)
    full = [q for q in states(model, N=16, seed=62)[0]
            if ci.link_wrench(model, q, np.zeros(7), 'panda_link6').rank == 6]
    assert len(full) >= 12
    for q in full[:12]:
        T7 = model.link_pose('panda_link7', q)
        z7 = T7[:3, 2]   # joint 7 turns link7 about its z axis (checked below)
        assert np.allclose(model.jacobian(q, 'panda_link7', 'world_aligned')[3:, 6], z7)
        J6, J7 = pin_jacobian(oracle, q, 'panda_link6'), pin_jacobian(oracle, q, 'panda_link7')
        for kind in named:
            u = rng.normal(size=3)
            u /= np.linalg.norm(u)
            p = rng.uniform(-0.05, 0.05, 3)
            if kind == 'on axis':
                p[:2] = 0.0   # on joint 7's axis, in link7's axes
            J = J6 if kind == 'link6' else J7
            f = rng.uniform(2.0, 5.0) / (np.abs(J[:3].T @ u) / th).max() * u   # 2x-5x the threshold force
            r = J.T @ np.concatenate([f, np.cross(p, f)])
            if kind == 'on axis':
                assert abs(r[6]) < 1e-9 * np.abs(r).max()
            res = ci.isolate(model, q, r, th)
            named[kind].append(res.link)
            if kind == 'on axis':
                assert res.link in ('', 'panda_link7') and res.link != 'panda_link6', res
                assert res.status == 'isolated' or 'through the axis' in res.reason
    assert named['on axis'] == [''] * 12
    assert named['link6'] == ['panda_link6'] * 12
    assert named['link7'] == ['panda_link7'] * 12


def test_a_mean_over_the_arms_yield_is_explained_with_q_from_and_two_contacts_still_are_not():
    """The node decides on the mean r of a settled stretch while the arm yields to the push (a few
    hundredths of a radian): no single J7^T gives that mean within the tolerance, and a 7-joint
    link would be ambiguous ('two contacts?'). With q_from (where the mean began) step 3 allows
    the change of J7^T w over that motion: link7. Two contacts (link3 and link7) stay ambiguous."""
    model, oracle = _robot('arm7')
    th = 0.03 * model.effort_limits
    q_b = np.array([0.2, -0.6, 0.1, 2.0, 0.3, 1.6, 0.8])
    q_a = q_b + np.array([0.03, -0.025, 0.02, 0.03, -0.03, 0.025, -0.02])
    path = [q_a + (q_b - q_a) * (1 - np.exp(-5 * s)) / (1 - np.exp(-5)) for s in np.linspace(0, 1, 40)]
    F = np.array([30.0, -40.0, 25.0, 1.5, -2.0, 1.0])
    r = np.mean([pin_jacobian(oracle, q, 'link7').T @ F for q in path], axis=0)
    assert np.abs(r / th).max() > 2
    quiet = np.zeros(7)   # exact efforts: the tolerance's floor, 1 % of the thresholds
    res = ci.isolate(model, q_b, r, th, noise=quiet)
    assert res.status == 'ambiguous' and 'two contacts' in res.reason, res
    res = ci.isolate(model, q_b, r, th, noise=quiet, q_from=q_a)
    assert res.status == 'isolated' and res.link == 'link7', res
    F3 = np.array([20.0, 10.0, -30.0, 2.0, 1.0, -1.0])
    r2 = r + np.mean([pin_jacobian(oracle, q, 'link3').T @ F3 for q in path], axis=0)
    res = ci.isolate(model, q_b, r2, th, noise=quiet, q_from=q_a)
    assert res.status == 'ambiguous' and 'two contacts' in res.reason, res
    with pytest.raises(ValueError, match='q_from must be 7 finite'):
        ci.isolate(model, q_b, r, th, q_from=np.zeros(6))


def test_a_weak_push_through_its_own_joints_axis_is_ambiguous_with_the_weak_tier():
    """A push on link4 whose line crosses joint 4's axis loads joint 4 with nothing: its r is that of
    a wrench on link3 (3 supporting joints, the line free). The default rule alone (strict_below 0)
    names link3 (wrong); with strict_below above the residual's largest |r_j| / th_j (the default,
    STRICT_BELOW) the strict rule decides: ambiguous. A strong push (above strict_below) is decided
    as without the tier."""
    model, oracle = _robot('arm7')
    q = np.array([0.2, -0.6, 0.1, 2.0, 0.3, 1.6, 0.8])
    th = np.array([2.6] * 4 + [0.36] * 3)
    J4 = pin_jacobian(oracle, q, 'link4')
    v, w = J4[:3, 3], J4[3:, 3]                 # joint 4's column in link4's axes
    p = np.cross(w, v) / (w @ w) + 0.03 * w / np.linalg.norm(w)   # a point on its axis, 3 cm along it
    f = np.array([1.0, 1.0, 0.0])                # joints 1-3 all well over their tolerances
    r1 = J4.T @ np.concatenate([f, np.cross(p, f)])
    assert abs(r1[3]) < 1e-12 * np.abs(r1).max()
    for multiple, tiered in ((1.5, True), (3.0, False)):
        r = multiple / np.max(np.abs(r1) / th) * r1    # the largest |r_j| / th_j is `multiple`
        off = ci.isolate(model, q, r, th, strict_below=0.0)
        assert off.status == 'isolated' and off.link == 'link3', off
        on = ci.isolate(model, q, r, th)
        assert ci.isolate(model, q, r, th, strict_below=ci.STRICT_BELOW)[:5] == on[:5]
        if tiered:   # the strict rule's answer, named candidates and reason
            assert on[:5] == ci.isolate(model, q, r, th, strict=True)[:5]
            assert on.status == 'ambiguous' and on.candidates[:2] == ('link3', 'link4') and on.link == '', on
        else:        # a strong push: the default rule, as without the tier
            assert on.status == 'isolated' and on.link == 'link3'
    # a strong push on link4 off its axis is still named link4 with the tier on
    F4 = np.concatenate([f, np.cross(p + np.array([0.05, 0.04, 0.0]), f)])
    r = J4.T @ F4
    r *= 3.0 / np.max(np.abs(r) / th)
    assert ci.isolate(model, q, r, th, strict_below=ci.STRICT_BELOW).link == 'link4'
    for bad in (-1.0, float('nan'), float('inf')):
        with pytest.raises(ValueError, match='strict_below must be finite and >= 0'):
            ci.isolate(model, q, r, th, strict_below=bad)


def _skeleton_points(model, q, b, radius, rng, count):
    """`count` random points within `radius` of body b's skeleton: the segments from its link's
    origin to the origins of the links fixed to it and of its child bodies (from link poses)."""
    T = model.link_pose(model.body_link_names[b], q)
    ends = [model.link_pose(name, q)[:3, 3] for name, (c, _) in model.link_frames.items()
            if c == b and name != model.body_link_names[b]]
    ends += [model.link_pose(model.body_link_names[c], q)[:3, 3] for c in np.flatnonzero(model.parent == b)]
    o = T[:3, 3]
    seg = np.array([o] + ends)[rng.integers(len(ends) + 1, size=count)]
    u = rng.normal(size=(count, 3))
    u *= (radius * rng.uniform(size=count) ** (1 / 3) / np.linalg.norm(u, axis=1))[:, None]
    return o + rng.uniform(size=count)[:, None] * (seg - o) + u


@needs_erd
@pytest.mark.parametrize('name', ['arm7', 'ur5', 'panda_locked'])
def test_the_point_force_search_finds_every_fit_a_dense_sampling_finds(name):
    """The strict rule's search (_point_forces) against brute force: for pushes made through
    Pinocchio's WORLD Jacobians, every body on which one of 3000 random points within the radius of
    its skeleton gives r within tol (the best force at that point in least squares, weighted by
    1 / tol) is found, and each point the search returns does so: within the radius of the
    skeleton (to the line's nearest point) and within tol on every joint."""
    model, oracle = _robot(name)
    rng = np.random.default_rng(7)
    th = 0.03 * model.effort_limits
    tol = ci.tolerances(th)
    t = ci.tree(model)
    moving = [b for b in range(model.nb) if t.support[b].any()]
    checked = found = 0
    for _ in range(12):
        lo, hi = model.position_lower, model.position_upper
        q = np.where(np.isfinite(lo) & np.isfinite(hi), 0.5 * (lo + hi) + rng.uniform(-0.45, 0.45, model.n) * (hi - lo),
                     rng.uniform(-np.pi, np.pi, model.n))
        oracle_q = oracle.pin_q(q)
        pin.computeJointJacobians(oracle.model, oracle.data, oracle_q)
        pin.updateFramePlacements(oracle.model, oracle.data)

        def world(b):   # (n, 3) linear and angular rows: a force f at p gives V f + W (p x f)
            fid = oracle.model.getFrameId(model.body_link_names[b], pin.FrameType.BODY)
            J = pin.getFrameJacobian(oracle.model, oracle.data, fid, pin.WORLD) @ oracle.E
            return J[:3].T, J[3:].T
        b = moving[rng.integers(len(moving))]
        V, W = world(b)
        p = _skeleton_points(model, q, b, 1.2 * ci.RADIUS, rng, 1)[0]
        f = rng.normal(size=3)
        r = V @ f + W @ np.cross(p, f)
        r *= rng.uniform(1.0, 3.0) / np.max(np.abs(r) / th)
        r += rng.normal(size=model.n) * 0.02 * th
        felt = np.abs(r) > tol
        bodies = [c for c in moving if t.support[c][felt].all()]
        got = ci._point_forces(model, q, r, tol, bodies, ci.RADIUS)
        for c in bodies:
            V, W = world(c)
            pts = _skeleton_points(model, q, c, ci.RADIUS, rng, 3000)
            A = (V[None] + np.cross(W[None], pts[:, None, :])) / tol[None, :, None]   # (P, n, 3)
            G = np.einsum('pji,pjk->pik', A, A) + 1e-12 * np.eye(3)
            fits = np.linalg.solve(G, np.einsum('pji,j->pi', A, r / tol)[..., None])[..., 0]
            worst = np.abs(np.einsum('pji,pi->pj', A, fits) - r / tol).max(axis=1)
            checked += 1
            if worst.min() <= 1.0:
                found += 1
                assert c in got, (name, model.body_link_names[c], worst.min())
            if c in got:   # the search's own answer holds up
                x = got[c]
                a = (V + np.cross(W, x)) / tol[:, None]
                fx = np.linalg.lstsq(a, r / tol, rcond=None)[0]
                assert np.abs(a @ fx - r / tol).max() <= 1.0 + 1e-9
                d = fx / np.linalg.norm(fx)
                near = _skeleton_points(model, q, c, 0.0, rng, 2000)   # the skeleton itself, densely
                off = (near - x) - np.outer((near - x) @ d, d)
                assert np.linalg.norm(off, axis=1).min() <= ci.RADIUS * (1 + 1e-6) + 5e-3
    assert checked >= 20 and 0 < found < checked, (checked, found)


def test_within_is_the_one_settling_test():
    """|r - ref| <= tolerance x max(|scale|, th) on every joint; the scale is the caller's side
    (Settling: the newer r; the node's drift test: the mean); a NaN never passes."""
    th = np.array([1.0, 1.0])
    assert ci.within(np.array([10.0, 0.0]), np.array([10.4, 0.04]), np.array([10.0, 0.0]), th)
    assert not ci.within(np.array([10.0, 0.0]), np.array([10.6, 0.0]), np.array([10.0, 0.0]), th)
    # the same pair passes with the larger side as the scale only
    r, ref = np.array([20.0]), np.array([21.5])
    assert ci.within(r, ref, ref, th[:1], tolerance=0.07) and not ci.within(r, ref, r, th[:1], tolerance=0.07)
    assert not ci.within(np.array([np.nan]), np.array([0.0]), np.array([0.0]), th[:1])
