"""Fixed-step integrators for the arm's equations of motion M(q) qdd + C(q, qd) qd + g(q) = tau.

Every stepper has the signature step(model, q, qd, dt, tau=None, damping=None) -> (q, qd):
the applied torque tau - damping * qd is re-evaluated wherever the method needs a force.

* explicit_euler:       q += dt qd,  qd += dt qdd(q, qd)                  (order 1, energy grows)
* semi_implicit_euler:  qd += dt qdd(q, qd),  q += dt qd_new              (order 1; ArmSim's
  default, which arm.py steps inline to add an external wrench. Symplectic only for a constant
  M: with M(q) the energy drifts, in bench/stability.py's undamped free fall faster than with
  explicit Euler)
* rk4:                  classical Runge-Kutta on (q, qd)                   (order 4, not symplectic:
  a slow energy drift remains)
* lie_midpoint:         the implicit midpoint rule in canonical coordinates (q, p = M(q) qd) on
  the configuration group, see below                                    (order 2, symplectic)

Lie-group view. A fixed-base arm with revolute joints lives on the torus T^n = SO(2)^n
(prismatic joints add R factors): an abelian Lie group whose exponential map is angle addition.
Runge-Kutta-Munthe-Kaas methods on such a group need dexp^-1 = identity, so RKMK4 is exactly
rk4 on the angles; the geometric property worth having here is symplecticity. lie_midpoint
updates the configuration by the group exponential of the midpoint velocity,
q_{k+1} = q_k exp(dt qd_m) (= q_k + dt qd_m on T^n), and the momentum p = M(q) qd in the dual
of the Lie algebra by the midpoint force:
    q_m = (q_k + q_{k+1}) / 2,  p_m = (p_k + p_{k+1}) / 2,  qd_m = M(q_m)^-1 p_m,
    p_{k+1} = p_k + dt (1/2 qd_m^T dM/dq(q_m) qd_m - g(q_m) + tau - damping qd_m),
(the first term is C(q_m, qd_m)^T qd_m, since Mdot = C + C^T),
i.e. Hamilton's equations dp/dt = -dH/dq, H = 1/2 p^T M^-1 p + U, with the implicit midpoint
rule (the one-stage Gauss collocation method: symplectic and time-reversible). Its energy error
stays bounded, O(dt^2), over long times instead of drifting. The implicit equations are solved
by fixed-point iteration to rounding level (about 6 iterations at dt = 1 ms, 8 at 5 ms); it
raises RuntimeError when the iteration does not converge (step too large for the dynamics).
"""
import numpy as np


def _torque(model, tau, damping, qd):
    t = np.zeros(model.n) if tau is None else tau
    return t if damping is None else t - damping * qd


def _qdd(model, q, qd, tau, damping):
    return model.forward_dynamics(q, qd, _torque(model, tau, damping, qd))


def explicit_euler(model, q, qd, dt, tau=None, damping=None):
    qdd = _qdd(model, q, qd, tau, damping)
    return q + dt * qd, qd + dt * qdd


def semi_implicit_euler(model, q, qd, dt, tau=None, damping=None):
    qd = qd + dt * _qdd(model, q, qd, tau, damping)
    return q + dt * qd, qd


def rk4(model, q, qd, dt, tau=None, damping=None):
    def f(x, v):
        return v, _qdd(model, x, v, tau, damping)
    k1 = f(q, qd)
    k2 = f(q + 0.5 * dt * k1[0], qd + 0.5 * dt * k1[1])
    k3 = f(q + 0.5 * dt * k2[0], qd + 0.5 * dt * k2[1])
    k4 = f(q + dt * k3[0], qd + dt * k3[1])
    return (q + dt / 6 * (k1[0] + 2 * k2[0] + 2 * k3[0] + k4[0]),
            qd + dt / 6 * (k1[1] + 2 * k2[1] + 2 * k3[1] + k4[1]))


def lie_midpoint(model, q, qd, dt, tau=None, damping=None, tol=1e-14, max_iter=60):
    """Symplectic implicit midpoint on (q, p = M(q) qd); see the module docstring."""
    p = model.mass_matrix(q) @ qd
    t = np.zeros(model.n) if tau is None else tau
    qm, pm, vm = q + 0.5 * dt * qd, p, qd
    for _ in range(max_iter):
        M = model.mass_matrix(qm)
        vm = np.linalg.solve(M, pm)
        # 1/2 qd^T dM/dq_a qd = (C^T qd)_a (Mdot = C + C^T), and C = 1/2 dtau/dqd at qdd = 0:
        # one analytic-derivative call, about half the cost of forming dM/dq.
        C = 0.5 * model.inverse_dynamics_derivatives(qm, vm, np.zeros(model.n))[1]
        force = C.T @ vm - model.gravity(qm) + t
        if damping is not None:
            force = force - damping * vm
        qm_new = q + 0.5 * dt * vm
        pm_new = p + 0.5 * dt * force
        dq = np.max(np.abs(qm_new - qm))
        dp = np.max(np.abs(pm_new - pm)) / max(1.0, np.max(np.abs(pm_new)))
        qm, pm = qm_new, pm_new
        if not (np.all(np.isfinite(qm)) and np.all(np.isfinite(pm))):
            break
        if dq <= tol * max(1.0, np.max(np.abs(qm))) and dp <= tol:
            q1 = 2 * qm - q
            return q1, np.linalg.solve(model.mass_matrix(q1), 2 * pm - p)
    raise RuntimeError(f'lie_midpoint: the implicit step did not converge in {max_iter} iterations '
                       f'(dt = {dt} is too large for these dynamics)')


STEPPERS = {'explicit_euler': explicit_euler, 'semi_implicit_euler': semi_implicit_euler, 'rk4': rk4,
            'lie_midpoint': lie_midpoint}
