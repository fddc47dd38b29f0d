"""A simulated fixed-base arm: forward dynamics integrated at a fixed step (no ROS here).

Per step of length dt (default: semi-implicit Euler):
    motor = clip(command, -effort_limit, effort_limit)       (what a drive reports as effort)
    tau   = motor - damping * qd - coulomb * tanh(qd / eps)   (laws.friction_torque; Coulomb off
                                                              by default)
    qdd   = forward_dynamics(q, qd, tau, wrenches)            (+ J^T F of an external wrench)
    qd   += dt * qdd ;  q += dt * qd
An external wrench F = (m, f) on a link, in the link frame, can act during a window of simulated
time (`set_external`): it is the ground truth for external-torque estimation, and
`external_torque` holds its joint torques J^T F of the last step.
Other integrators (integrators.py: explicit Euler, RK4, the symplectic Lie-group midpoint) are
selected with `integrator=`; they re-evaluate the damping torque wherever they need a force.
Semi-implicit Euler in (q, qd) is symplectic only for a constant mass matrix: with M(q) its energy
drifts, in a 10 s undamped free fall of the bundled arm even faster than explicit Euler's (RK4 or
the midpoint rule hold it; docs/benchmarks.md, bench/stability.py).
Joint position limits act as hard stops (position clamped, velocity into the stop zeroed).
Coulomb friction is off by default (coulomb=None); when given it is the model's smooth form
fc tanh(qd / eps), which has no stiction. URDF damping is on, and can be switched off
(damping=False) for energy checks. The armature is the model's (Model.armature): forward
dynamics includes it.
"""
import numpy as np

from ..laws import COULOMB_VELOCITY_EPSILON, friction_torque
from .integrators import STEPPERS


class ArmSim:
    """State (q, qd, t) of a model integrated under held effort commands."""

    def __init__(self, model, dt=1e-3, q0=None, qd0=None, damping=True, limits=True,
                 integrator='semi_implicit_euler', coulomb=None, eps=COULOMB_VELOCITY_EPSILON):
        if not (np.isfinite(dt) and dt > 0):
            raise ValueError(f'dt must be a positive number, got {dt}')
        if integrator not in STEPPERS:
            raise ValueError(f'unknown integrator {integrator!r}: use one of {sorted(STEPPERS)}')
        self.integrator = integrator
        self.model = model
        self.dt = float(dt)
        self.q = np.zeros(model.n) if q0 is None else np.array(q0, dtype=float).reshape(model.n)
        self.qd = np.zeros(model.n) if qd0 is None else np.array(qd0, dtype=float).reshape(model.n)
        self.t = 0.0
        self.damping = model.damping.copy() if damping else np.zeros(model.n)
        if coulomb is not None:
            coulomb = np.broadcast_to(np.asarray(coulomb, dtype=float), (model.n,)).copy()
            if not (np.all(np.isfinite(coulomb)) and np.all(coulomb >= 0) and np.isfinite(eps) and eps > 0):
                raise ValueError(f'Coulomb friction must be finite and >= 0 with eps > 0, got {coulomb}, {eps}')
            if integrator != 'semi_implicit_euler':
                raise ValueError('Coulomb friction is simulated by the semi_implicit_euler integrator only')
        self.coulomb, self.eps = coulomb, float(eps)
        self.limits = limits
        self.command = np.zeros(model.n)
        self.last_qdd = np.zeros(model.n)
        self.applied = np.zeros(model.n)   # motor - friction of the last step
        self.motor = np.zeros(model.n)     # the clipped command of the last step
        self.external_torque = np.zeros(model.n)
        self._external = None              # (link, wrench (6,), start, stop)

    def set_external(self, link=None, wrench=None, start=0.0, duration=np.inf):
        """Apply `wrench` (m, f) to `link`, in the link frame, while start <= t < start + duration
        (simulated seconds); link None removes it. Only the default integrator applies it."""
        if link is None:
            self._external = None
            return
        if link not in self.model.link_frames:
            raise ValueError(f"unknown link '{link}' for the external wrench")
        w = np.asarray(wrench, dtype=float)
        if w.shape != (6,) or not np.all(np.isfinite(w)):
            raise ValueError(f'external wrench must be 6 finite numbers (m, f), got {wrench!r}')
        if not (np.isfinite(start) and duration >= 0):
            raise ValueError(f'external wrench window must be finite and non-negative, got {start}, {duration}')
        if self.integrator != 'semi_implicit_euler':
            raise ValueError('external wrenches are applied by the semi_implicit_euler integrator only')
        self._external = (link, w, float(start), float(start) + float(duration))

    def _wrenches(self):
        e = self._external
        if e is None or not (e[2] <= self.t + 1e-12 < e[3]):
            return None
        return {e[0]: e[1]}

    def set_command(self, tau):
        """Hold a new effort command (like ros2_control's JointGroupEffortController)."""
        tau = np.asarray(tau, dtype=float)
        if tau.shape != (self.model.n,):
            raise ValueError(f'command must have {self.model.n} values, got {tau.shape}')
        if not np.all(np.isfinite(tau)):
            raise ValueError('command contains non-finite values')
        self.command = tau.copy()

    def step(self, n=1):
        m = self.model
        lim = m.effort_limits
        for _ in range(n):
            motor = np.clip(self.command, -lim, lim)
            tau = motor - friction_torque(self.qd, self.damping, self.coulomb, self.eps)
            wrenches = self._wrenches()
            zero = np.zeros(m.n)
            # J^T F: what the wrench adds to the joint torques (inverse dynamics is linear in F)
            self.external_torque = (zero if wrenches is None else
                                    m.inverse_dynamics(self.q, self.qd, zero) -
                                    m.inverse_dynamics(self.q, self.qd, zero, wrenches))
            if self.integrator == 'semi_implicit_euler':
                qdd = m.forward_dynamics(self.q, self.qd, tau, wrenches)
                self.qd = self.qd + self.dt * qdd
                self.q = self.q + self.dt * self.qd
            else:
                qd0 = self.qd
                self.q, self.qd = STEPPERS[self.integrator](m, self.q, self.qd, self.dt,
                                                            np.clip(self.command, -lim, lim), self.damping)
                qdd = (self.qd - qd0) / self.dt   # mean acceleration over the step
            if self.limits:
                lo, hi = m.position_lower, m.position_upper
                below, above = self.q < lo, self.q > hi
                if below.any() or above.any():
                    self.q = np.clip(self.q, lo, hi)
                    self.qd = np.where((below & (self.qd < 0)) | (above & (self.qd > 0)), 0.0, self.qd)
            self.t += self.dt
            self.last_qdd = qdd
            self.applied = tau
            self.motor = motor
        return self.q

    def energy(self):
        """Kinetic + potential energy of the current state."""
        return self.model.kinetic_energy(self.q, self.qd) + self.model.potential_energy(self.q)

    @property
    def held_torque(self):
        """The clipped held command: the motor torque the next step applies at the current state."""
        return np.clip(self.command, -self.model.effort_limits, self.model.effort_limits)


class EffortSensor:
    """What a drive's effort sensor reports: true effort + offset + Gaussian noise (std `noise`).
    offset, noise: one value or one per joint. The noise comes from its own generator seeded with
    `seed` (a fixed default: runs repeat)."""

    def __init__(self, n, offset=0.0, noise=0.0, seed=0):
        self.offset = np.broadcast_to(np.asarray(offset, dtype=float), (n,)).copy()
        self.noise = np.broadcast_to(np.asarray(noise, dtype=float), (n,)).copy()
        if not (np.all(np.isfinite(self.offset)) and np.all(np.isfinite(self.noise)) and np.all(self.noise >= 0)):
            raise ValueError(f'effort offsets must be finite and noise finite and >= 0, got {offset}, {noise}')
        self.rng = np.random.default_rng(int(seed))

    def read(self, effort):
        """One reading of the true effort (n,)."""
        e = np.asarray(effort, dtype=float) + self.offset
        return e + self.rng.standard_normal(len(e)) * self.noise if np.any(self.noise) else e
