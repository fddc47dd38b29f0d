"""External joint torques from measured motor torques: the generalized-momentum observer.

With p = M(q) qd and the property Mdot = C + C^T of the Christoffel-form C (the C of
`Model.coriolis_matrix`, for which Mdot - 2C is skew: lagrangian.py, eqs 40-42), the equations
of motion M qdd + C qd + g = tau + tau_ext give

    pdot = tau + tau_ext + C(q, qd)^T qd - g(q),

so the residual (De Luca & Mattone 2003)

    r(t) = K_O [ p(t) - p(0) - integral_0^t (tau + C^T qd - g + r) ds ]

obeys rdot = K_O (tau_ext - r): a first-order low-pass of the true external torque, per joint
with time constant 1 / K_O, that needs no acceleration. tau is the torque the motors put on
the joints: the measured motor torque minus the friction the model knows (`friction`, the same
b qd + fc tanh(qd / eps) the node compensates), so modelled friction is not reported as contact.

Sign convention: tau_ext is the generalized force the environment applies to the joints, in the
same sense as tau (a push that would accelerate joint k positively is a positive tau_ext[k]);
a wrench F on a link gives tau_ext = J^T F.

Discretisation: the integral is a trapezoid over the samples, the r inside it taken at both
ends (implicit in the newest r, solved per joint), so a constant tau_ext is followed with the
trapezoid's response r_k = a r_{k-1} + (1 - a) tau_ext, a = (1 - K dt / 2) / (1 + K dt / 2).
p and C^T qd come from `generalized_momentum`: one O(n) recursive pass (a generated kernel,
codegen/traced/rnea.py: trace_momentum) for the C of the Christoffel form (eqs 40-42), the one
with Mdot - 2C skew; its reference is M(q) qd and C^T qd from those matrices.

A streaming sample (MomentumObserver.update) is one call of the traced step
(codegen/traced/observer.py: these terms, g(q), the friction and the trapezoid together, in C
where a compiler works); momentum_terms and advance are its numpy reference, on the same state.
"""
import math

import numpy as np

from . import crba, rnea, rnea_derivatives
from ..codegen import runtime
from ..codegen.traced import observer as observer_kernel
from ..codegen.traced import rnea as traced
from ..laws import friction_torque
from ..model.joint_names import broadcast_joints
from ..validation import finite

_STEP = observer_kernel.OBSERVER_STEP


def generalized_momentum(model, q, qd):
    """(p, C^T qd) with p = M(q) qd and C the Christoffel-form Coriolis matrix (eqs 40-42), for
    one state (n,) or a batch (N, n): the generated kernel (trace_momentum) where the model
    has one, else the matrices; empty for a robot without movable joints, as every algorithm.
    Raises ValueError naming a bad argument."""
    n = model.n
    # the fast path: the result, or None (a jointless model has no kernel: runtime.call checks)
    out = runtime.fast(model, traced.MOMENTUM)(q, qd) if n else None
    if out is None:
        out = runtime.call(model, _MOMENTUM, (q, qd))
    return out[..., :n], out[..., n:]


def _momentum(model, arrays):
    """(N, 2n): p then C^T qd, on validated (N, n) arrays."""
    if not model.n:   # no movable joints: no kernel, nothing to compute (as Model's _jointless)
        return np.zeros((len(arrays[0]), 0))
    out = runtime.run(model, traced.MOMENTUM, arrays)
    if out is None:
        q, qd = arrays
        p = np.einsum('...ij,...j->...i', crba.mass_matrix_validated(model, q), qd)
        c = np.einsum('...ji,...j->...i', rnea_derivatives.coriolis_matrix_validated(model, arrays), qd)
        out = np.concatenate([p, c], axis=1)
    return out


_MOMENTUM = runtime.Entry(('q', 'qd'), None, _momentum)


def _gains(gain, n):
    k = broadcast_joints(gain, n)   # a copy: made read-only below, the caller's array is not
    if k is None or not np.all(np.isfinite(k)) or np.any(k <= 0):
        raise ValueError(f'observer gain must be one positive number or {n} positive numbers (1/s), got {gain!r}')
    return k


class MomentumObserver:
    """Streaming estimate of the external joint torques (module docstring).

    gain: K_O, 1/s, one value or one per joint. friction: None, or (viscous, coulomb, eps) as
    `laws.Friction` / `laws.make_friction` give it: subtracted from the measured torque. Both
    are fixed at construction (`gain` is read-only): other ones need another observer.

    One sample is one call of the generated step kernel where the model has one
    (codegen/traced/observer.py: the momentum terms, the friction and the trapezoid in one
    pass, natively compiled where a C compiler works); `momentum_terms` and `advance` are its
    reference, with the same state.
    """

    def __init__(self, model, gain, friction=None):
        self.model = model
        self.gain = _gains(gain, model.n)
        self.gain.flags.writeable = False   # the step kernel holds a copy (its settings)
        self.friction = friction
        # no step kernel without movable joints: update runs the reference, which returns zeros
        self._settings = _step_settings(self.gain, friction, model.n) if model.n else None
        n = model.n   # where the step kernel's outputs are: next state, estimate, p and beta
        self._parts = (slice(0, 3 * n + 1), slice(3 * n + 1, 4 * n + 1), 4 * n + 1)
        self._kernel = (None, -1)   # (runtime.fast's step kernel, the model version it is for)
        self.reset()

    def reset(self):
        """Forget the history: the next update starts a new integral (estimate 0)."""
        n = self.model.n
        self._t = None
        # p(0), the integral, beta + r of the last sample, then the step's dt (the kernel's Z)
        self._state = np.zeros(3 * n + 1)
        self.estimate = np.zeros(n)

    @property
    def last_time(self):
        """Time of the last accepted sample (None before the first, and after reset)."""
        return self._t

    @property
    def state(self):
        """A copy of the integration state: p(0), the integral and beta + r of the last sample (3 n values)."""
        return self._state[:3 * self.model.n].copy()

    def momentum_terms(self, q, qd, tau_measured):
        """(p, beta) with p = M(q) qd and beta = tau + C^T qd - g, for one state (n,) or a batch."""
        m, n = self.model, self.model.n
        q, qd, tau = (np.asarray(x, dtype=float) for x in (q, qd, tau_measured))
        pc = g = None
        if n and q.shape == qd.shape == tau.shape == (n,) and np.count_nonzero(np.isfinite(tau)) == n:
            # a node's hot path is one state: the fast paths check q and qd themselves
            pc = runtime.fast(m, traced.MOMENTUM)(q, qd)
            if pc is not None:
                g = runtime.fast(m, traced.GRAVITY)(q)
        if g is None:   # validated once; then the functions that take validated arrays
            (q, qd, tau), single = m.validate(('q', 'qd', 'tau_measured'), (q, qd, tau))
            pc = _momentum(m, [q, qd])
            g = rnea.gravity_validated(m, [q]) if n else np.zeros_like(q)
            if single:   # qd too: the friction below is per state
                pc, g, tau, qd = pc[0], g[0], tau[0], qd[0]
        p, ctqd = pc[..., :n], pc[..., n:]
        beta = tau + ctqd - g
        if self.friction is not None:
            beta = beta - friction_torque(qd, *self.friction)
        return p, beta

    def advance(self, t, p, beta):
        """One sample from its momentum terms (momentum_terms); returns the estimate r."""
        t = float(t)
        if not np.isfinite(t):
            raise ValueError(f'observer time must be finite, got {t}')
        n, z = self.model.n, self._state
        if self._t is None:
            self._t = t
            z[:n], z[n:2 * n], z[2 * n:3 * n] = p, 0.0, beta
            self.estimate = np.zeros(n)
            return self.estimate
        dt = t - self._t
        if not dt > 0:
            raise ValueError(f'observer times must increase: {t} after {self._t}')
        half = 0.5 * dt * self.gain
        # I_k = I_{k-1} + dt/2 (beta_{k-1} + r_{k-1} + beta_k + r_k), r_k = K (p_k - p_0 - I_k)
        partial = z[n:2 * n] + 0.5 * dt * (z[2 * n:3 * n] + beta)
        r = self.gain * (p - z[:n] - partial) / (1.0 + half)
        z[n:2 * n] = partial + 0.5 * dt * r
        z[2 * n:3 * n] = beta + r
        self._t, self.estimate = t, r
        return r

    def step(self, t, q, qd, tau_measured):
        """One sample through the generated step kernel: the estimate (as update), or None when
        the kernel declines (no kernel for this model, arguments other than finite (n,)
        float64 arrays, a time that is not finite or does not increase, a non-finite result),
        and then nothing has changed: update validates, names the problem or runs the reference."""
        settings = self._settings
        if settings is None:
            return None
        t = float(t)
        last = self._t
        if last is None:
            if not finite(t):
                return None
            dt = 0.0
        else:
            dt = t - last
            if not 0.0 < dt < math.inf:
                return None
        z = self._state
        z[-1] = dt
        kernel, version = self._kernel
        if version != self.model.version:   # runtime.fast's cache rule, without its lookup per sample
            kernel = runtime.fast(self.model, _STEP)
            self._kernel = (kernel, self.model.version)
        out = kernel(q, qd, tau_measured, z, settings)   # None: not finite, or declined
        if out is None:
            self._kernel = (None, -1)   # a kernel still being built declines: ask again next time
            return None
        state, estimate, first = self._parts
        self._state = out[state]   # the next state: where the next call reads it
        if last is None:   # the first sample starts the integral: p(0), beta
            n = self.model.n
            self._state[:n], self._state[n:2 * n], self._state[2 * n:3 * n] = out[first:first + n], 0.0, out[first + n:]
            r = np.zeros(n)
        else:
            r = out[estimate]
        self._t = t
        self.estimate = r
        return r

    def update(self, t, q, qd, tau_measured):
        """Feed one sample (time t in s, measured q, qd and motor torque); returns the estimate
        of tau_ext (n,). The first sample starts the integral and returns zeros."""
        r = self.step(t, q, qd, tau_measured)
        if r is not None:
            return r
        if np.ndim(q) != 1:
            raise ValueError(f'update takes one state: q must have shape ({self.model.n},), got {np.shape(q)}')
        return self.advance(t, *self.momentum_terms(q, qd, tau_measured))


def _step_settings(gain, friction, n):
    """The step kernel's settings (K, b, fc, eps) as one float64 array, or None when they are
    not finite numbers or eps is 0 (the reference then runs and reports). A term that is off is a
    coefficient of 0 (and eps 1 without a Coulomb term)."""
    b, fc, eps = (None, None, 1.0) if friction is None else friction
    try:
        with np.errstate(all='ignore'):
            o = np.concatenate([gain, np.zeros(n) + (0.0 if b is None else np.asarray(b, dtype=float)),
                                np.zeros(n) + (0.0 if fc is None else np.asarray(fc, dtype=float)),
                                [float(eps) if fc is not None else 1.0]])
    except (ValueError, TypeError):
        return None
    return o if o.shape == (3 * n + 1,) and np.all(np.isfinite(o)) and o[-1] != 0 else None


def estimate_external_torques(model, t, q, qd, tau_measured, gain, friction=None):
    """The observer over a whole recording: t (N,) increasing, q, qd, tau_measured (N, n);
    returns the estimates (N, n). M, C and g are evaluated in one batched call each."""
    obs = MomentumObserver(model, gain, friction)
    t = np.asarray(t, dtype=float)
    q = model.check_batch('q', q)
    if t.shape != (q.shape[0],):
        raise ValueError(f't must have shape ({q.shape[0]},) like the states, got {t.shape}')
    p, beta = obs.momentum_terms(q, qd, tau_measured)
    out = np.empty_like(p)
    for k in range(len(t)):
        out[k] = obs.advance(t[k], p[k], beta[k])
    return out
