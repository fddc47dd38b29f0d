"""SE(3) toolkit: round trips, adversarial angles, Pinocchio agreement, Lie identities."""
import numpy as np
import pinocchio as pin
import pytest

from lie_dynamics import spatial as se3

ANGLES = [0.0, 1e-12, 1e-8, 1e-4, 1e-2, 0.5, 1.0, 2.0, np.pi - 1e-2, np.pi - 1e-6, np.pi - 1e-9, np.pi]


def _axes(rng, k):
    a = rng.normal(size=(k, 3))
    a = np.vstack([a, np.eye(3), -np.eye(3), [[1, 1, 0], [0, -1, 1]]])
    return a / np.linalg.norm(a, axis=1, keepdims=True)


def _rot_close(R1, R2, tol):
    assert np.max(np.abs(R1 - R2)) < tol


@pytest.mark.parametrize('theta', ANGLES)
def test_exp3_log3_round_trip_and_pinocchio(theta):
    rng = np.random.default_rng(1)
    for u in _axes(rng, 20):
        w = theta * u
        R = se3.exp3(w)
        _rot_close(R, pin.exp3(w), 4e-16 * 8)
        assert np.max(np.abs(R @ R.T - np.eye(3))) < 1e-15 * 4
        w2 = se3.log3(R)
        # at theta = pi both w and -w are valid logs
        if theta > np.pi - 1e-7:
            assert min(np.linalg.norm(w2 - w), np.linalg.norm(w2 + w)) < 1e-8 * max(1.0, theta)
        else:
            assert np.linalg.norm(w2 - w) <= 1e-14 * max(1.0, theta) + 1e-15 * theta
        _rot_close(se3.exp3(w2), R, 1e-14)
        if theta < np.pi - 1e-3:
            # Pinocchio's log3 loses digits near pi (theta / sin theta); ours is checked by the round trip.
            np.testing.assert_allclose(w2, pin.log3(R), atol=1e-14 if theta < 2 else 1e-12)


@pytest.mark.parametrize('theta', ANGLES)
def test_exp6_log6_round_trip_and_pinocchio(theta):
    rng = np.random.default_rng(2)
    for u in _axes(rng, 10):
        V = np.concatenate([theta * u, rng.normal(size=3)])
        T = se3.exp6(V)
        Tp = pin.exp6(pin.Motion(V[3:], V[:3])).homogeneous  # pinocchio: (linear, angular)
        np.testing.assert_allclose(T, Tp, atol=1e-14)
        V2 = se3.log6(T)
        np.testing.assert_allclose(se3.exp6(V2), T, atol=1e-13)
        if theta < np.pi - 1e-3:
            np.testing.assert_allclose(V2, V, atol=1e-13)
            lp = pin.log6(pin.SE3(T[:3, :3], T[:3, 3]))
            np.testing.assert_allclose(V2, np.concatenate([lp.angular, lp.linear]), atol=1e-13)


def test_small_angle_accuracy_beats_closed_form():
    """At theta = 1e-12 the series keep full relative precision of the rotation vector."""
    w = np.array([1e-12, -2e-12, 0.5e-12])
    np.testing.assert_allclose(se3.log3(se3.exp3(w)), w, rtol=1e-14)
    V = np.array([1e-12, 0, 0, 1.0, 2.0, 3.0])
    np.testing.assert_allclose(se3.log6(se3.exp6(V)), V, rtol=1e-14, atol=1e-26)


def test_near_pi_log_is_accurate():
    for eps in (1e-6, 1e-9, 1e-12):
        u = np.array([2.0, -1.0, 0.5]) / np.linalg.norm([2.0, -1.0, 0.5])
        w = (np.pi - eps) * u
        np.testing.assert_allclose(se3.log3(se3.exp3(w)), w, atol=1e-14 * np.pi / 1e-2 * 1e-1 + 4e-15)


def test_batched_matches_single():
    rng = np.random.default_rng(3)
    V = rng.normal(size=(50, 6)) * 2
    T = se3.exp6(V)
    for i in range(50):
        np.testing.assert_array_equal(T[i], se3.exp6(V[i]))
    np.testing.assert_allclose(se3.log6(T), np.array([se3.log6(t) for t in T]), atol=0)


def test_adjoint_identities():
    rng = np.random.default_rng(4)
    for _ in range(50):
        T1, T2 = se3.exp6(rng.normal(size=6)), se3.exp6(rng.normal(size=6))
        V, W = rng.normal(size=6), rng.normal(size=6)
        np.testing.assert_allclose(se3.Ad(T1 @ T2), se3.Ad(T1) @ se3.Ad(T2), atol=1e-12)
        np.testing.assert_allclose(se3.Ad(se3.inv(T1)), np.linalg.inv(se3.Ad(T1)), atol=1e-12)
        np.testing.assert_allclose(se3.Ad_inv(T1), se3.Ad(se3.inv(T1)), atol=1e-14)
        np.testing.assert_allclose(se3.ad(V) @ W, -se3.ad(W) @ V, atol=1e-14)
        np.testing.assert_allclose(se3.bracket(V, W), se3.ad(V) @ W, atol=1e-14)
        np.testing.assert_allclose(se3.Ad(T1) @ se3.ad(V) @ se3.Ad(se3.inv(T1)), se3.ad(se3.Ad(T1) @ V),
                                   atol=1e-12)
        # Ad_T [V] T^-1 = [Ad_T V] (definition of Ad, paper section 3.1.1)
        np.testing.assert_allclose(T1 @ se3.hat6(V) @ se3.inv(T1), se3.hat6(se3.Ad(T1) @ V), atol=1e-12)
        # [V, W] as matrices: [V][W] - [W][V]
        np.testing.assert_allclose(se3.hat6(V) @ se3.hat6(W) - se3.hat6(W) @ se3.hat6(V),
                                   se3.hat6(se3.ad(V) @ W), atol=1e-12)
        # dual operators: <Ad*_T F, V> = <F, Ad_T V>
        F = rng.normal(size=6)
        assert abs((se3.Ad_star(T1) @ F) @ V - F @ (se3.Ad(T1) @ V)) < 1e-12
        assert abs((se3.ad_star(V) @ F) @ W - F @ (se3.ad(V) @ W)) < 1e-12
        # Pinocchio's action matrix is in (linear, angular) order
        P = np.block([[np.zeros((3, 3)), np.eye(3)], [np.eye(3), np.zeros((3, 3))]])
        np.testing.assert_allclose(se3.Ad(T1), P @ pin.SE3(T1[:3, :3], T1[:3, 3]).action @ P, atol=1e-14)


def test_spatial_inertia_matches_pinocchio():
    rng = np.random.default_rng(5)
    for _ in range(20):
        m, c = rng.uniform(0.1, 5), rng.normal(size=3)
        A = rng.normal(size=(3, 3))
        Ic = A @ A.T
        J = se3.spatial_inertia(m, c, Ic)
        P = np.block([[np.zeros((3, 3)), np.eye(3)], [np.eye(3), np.zeros((3, 3))]])
        np.testing.assert_allclose(J, P @ pin.Inertia(m, c, Ic).matrix() @ P, atol=1e-12)


def test_rpy_matches_pinocchio():
    rng = np.random.default_rng(6)
    for rpy in rng.uniform(-np.pi, np.pi, size=(20, 3)):
        np.testing.assert_allclose(se3.rpy_to_matrix(rpy), pin.rpy.rpyToMatrix(*rpy), atol=1e-15)
