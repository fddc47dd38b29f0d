"""The algorithms as methods of a Model (Pinocchio's free functions, here `model.<algorithm>(...)`).

Each method hands its arguments to the algorithm's one public function (algorithms/), which
validates them once; a robot without movable joints gets empty results (`_jointless`).
"""
import functools
import inspect

import numpy as np

from ..algorithms import aba, aba_derivatives, crba, jacobian, lagrangian, regressor, rnea, rnea_derivatives
from ..codegen import runtime
from ..codegen.traced import crba as traced_crba
from ..codegen.traced import derivatives as traced_derivatives
from ..codegen.traced import rnea as traced_rnea

_jacobian_kernel = jacobian.kernel_of   # in the class body `jacobian` is the method


def _jointless(states, *shapes):
    """A robot without movable joints (a URDF that only welds links together) is a valid model:
    its calls check their state arguments and return empty results of the usual shapes.

    The wrapper is written with the method's own signature (no *args, **kwargs): a one-state
    call of a 6-joint arm then costs about 0.35 us less, a third of Pinocchio's rnea."""
    def wrap(method):
        params = list(inspect.signature(method).parameters.values())[1:]
        names = [p.name for p in params]
        heads = [p.name if p.default is p.empty else f'{p.name}=_d{i}' for i, p in enumerate(params)]
        ns = {f'_d{i}': p.default for i, p in enumerate(params)}
        ns.update(_method_=method, _empty_=functools.partial(_empty, states, shapes))
        src = (f'def {method.__name__}(self, {", ".join(heads)}):\n'
               f'    if self.n:\n        return _method_(self, {", ".join(names)})\n'
               f'    return _empty_(self, ({", ".join(states)},))\n')
        exec(compile(src, f'<lie_dynamics facade {method.__name__}>', 'exec'), ns)
        return functools.wraps(method)(ns[method.__name__])
    return wrap


def _empty(states, shapes, model, given):
    """The results of a jointless model: `given` the state arguments, checked first."""
    first = model.validate(states, given).arrays[0]
    lead = () if np.ndim(given[0]) == 1 else (first.shape[0],)
    out = tuple(np.zeros(lead + sh) for sh in shapes)
    return out if len(out) > 1 else out[0]


class Algorithms:
    """The algorithm methods of `model.Model` (a mixin: the data and setters live there)."""

    @runtime.native_first(traced_rnea.INVERSE_DYNAMICS, 3)   # (q, qd, qdd[, out=]) straight from C
    @_jointless(('q', 'qd', 'qdd'), (0,))
    def inverse_dynamics(self, q, qd, qdd, wrenches=None, with_gravity=True, out=None):
        """tau = M(q) qdd + C(q, qd) qd + g(q) - J^T F_ext: the Lie-group RNEA (paper eqs 16-21).

        wrenches: optional {link: (m, f)} external wrench acting on the link, expressed in
        the link frame. with_gravity=False leaves g(q) out. Single state (n,) or batch (N, n).
        out: optional float64 array of the result's shape, written and returned (no allocation).
        """
        return rnea.inverse_dynamics(self, q, qd, qdd, wrenches, with_gravity, out)

    @runtime.native_first(traced_rnea.GRAVITY, 1)
    @_jointless(('q',), (0,))
    def gravity(self, q, out=None):
        """Gravity compensation torques g(q) (RNEA with V = 0, Vdot_0 = (0, -g)); out: as inverse_dynamics."""
        return rnea.gravity(self, q, out)

    @runtime.native_first(traced_rnea.CORIOLIS_TERM, 2)   # (q, qd[, out=]) straight from C
    @_jointless(('q', 'qd'), (0,))
    def coriolis_term(self, q, qd, out=None):
        """C(q, qd) qd = inverse_dynamics(q, qd, 0) without gravity (its own kernel: the RNEA
        at qdd = 0, g = 0); out: as inverse_dynamics."""
        return rnea.coriolis_term(self, q, qd, out)

    @runtime.native_keyed(functools.partial(_jacobian_kernel, 'jacobian'), 1)   # (q, link[, frame]) from C
    def jacobian(self, q, link, frame='world_aligned', point=None):
        """6 x n Jacobian of `link`'s frame, or of `point` fixed in it (in the link frame, m): maps q̇
        (columns in q's order) to the frame's velocity. (6, n) for q (n,), (N, 6, n) for (N, n).
        Rows LINEAR THEN ANGULAR (vx vy vz wx wy wz), as Pinocchio and geometry_msgs/Twist; the
        paper's twists are (w, v). frame, as Pinocchio's getFrameJacobian: 'world_aligned'
        (LOCAL_WORLD_ALIGNED: ṗ and w in root axes), 'local' (LOCAL: the same in the frame's own
        axes) or 'world' (WORLD: the spatial twist, linear part at the root origin; `point` changes
        nothing). Paper eqs 13-15. Mimic joints add to their master's column; locked joints add
        nothing. A link that no controlled joint moves gets all zeros. Unknown link or frame, bad
        point: ValueError. Details: algorithms/jacobian.py."""
        return jacobian.jacobian(self, q, link, frame, point)

    @runtime.native_keyed(functools.partial(_jacobian_kernel, 'jacobian_dot'), 2)
    def jacobian_dot_times_qd(self, q, qd, link, frame='world_aligned', point=None):
        """J̇q̇ for `jacobian(q, link, frame, point)`: (6,) or (N, 6), rows linear then angular. Equal
        to Pinocchio's getFrameClassicalAcceleration at q̈ = 0, so J q̈ + J̇q̇ is the classical
        acceleration: in 'world_aligned' (p̈, ẇ) in root axes (exactly J̇q̇), in 'local' the same in
        the frame's axes, in 'world' that of the body-fixed point at the root origin (the last two
        are J̇q̇ plus (w x v, 0) of the frame's twist). Details: algorithms/jacobian.py."""
        return jacobian.jacobian_dot_times_qd(self, q, qd, link, frame, point)

    # --- Lagrangian dynamics, forward dynamics, derivatives, regressor (lagrangian.py, crba.py, aba.py, ...)
    @runtime.native_first(traced_crba.MASS_MATRIX, 1)   # (q[, out=]) straight from C
    @_jointless(('q',), (0, 0))
    def mass_matrix(self, q, method='crba', out=None):
        """M(q), (n, n) or (N, n, n). method: 'crba' (composite rigid body, O(n^2); a generated
        kernel for small models, the fastest) or 'closed_form' (S^T G^T J G S, paper eq 39, O(n^3)).
        out: as inverse_dynamics."""
        if method == 'closed_form':
            M = lagrangian.mass_matrix(self, q)
            return runtime.deliver(M, runtime.check_out(out, M.shape))
        if method == 'crba':
            return crba.mass_matrix(self, q, out)
        raise ValueError(f"unknown mass matrix method {method!r}: use 'closed_form' or 'crba'")

    @_jointless(('q',), (0, 0, 0))
    def christoffel(self, q):
        """Christoffel symbols of the first kind Gamma[i, j, k] (paper eq 40), (n, n, n) or (N, n, n, n)."""
        return lagrangian.christoffel(self, q)

    @_jointless(('q', 'qd'), (0, 0))
    def coriolis_matrix(self, q, qd, method='christoffel'):
        """C(q, qd) from the Christoffel symbols: C qd = coriolis_term(q, qd), Mdot - 2C skew.

        method: 'christoffel' (eqs 40-42 from dM/dq, O(n^3)) or 'recursive' (the same matrix as
        1/2 dtau/dqd of the differentiated RNEA, O(n^2); a generated kernel for small models,
        several times faster)."""
        if method == 'christoffel':
            return lagrangian.coriolis_matrix(self, q, qd)
        if method == 'recursive':
            return rnea_derivatives.coriolis_matrix(self, q, qd)
        raise ValueError(f"unknown Coriolis matrix method {method!r}: use 'christoffel' or 'recursive'")

    @_jointless(('q',), (0, 0, 0))
    def mass_matrix_derivatives(self, q):
        """dM/dq: D[..., a, :, :] = dM/dq_a (Proposition 1 applied to eq 39)."""
        return lagrangian.mass_matrix_derivatives(self, q)

    @_jointless(('q',), (0,))
    def gravity_potential(self, q):
        """g(q) = dU/dq from the potential energy (paper eqs 43-45); equals gravity(q)."""
        return lagrangian.gravity(self, q)

    @_jointless(('q',), ())
    def potential_energy(self, q):
        """U(q) = -sum_i m_i g . c_i (paper eq 43)."""
        return lagrangian.potential_energy(self, q)

    @_jointless(('q', 'qd'), ())
    def kinetic_energy(self, q, qd):
        """1/2 qd^T M(q) qd (M with the armature: the rotors' energy included)."""
        return lagrangian.kinetic_energy(self, q, qd)

    @runtime.native_first(aba.forward_dynamics_spec, 3)   # (q, qd, tau[, out=]) straight from C
    @_jointless(('q', 'qd', 'tau'), (0,))
    def forward_dynamics(self, q, qd, tau, wrenches=None, method='cholesky', out=None):
        """qdd with inverse_dynamics(q, qd, qdd, wrenches) = tau; method 'cholesky' or 'aba' (O(n)).
        out: as inverse_dynamics."""
        return aba.forward_dynamics(self, q, qd, tau, wrenches, method, out)

    @runtime.native_first(traced_derivatives.INVERSE_DYNAMICS_DERIVATIVES, 3, split=2)   # from C
    @_jointless(('q', 'qd', 'qdd'), (0, 0), (0, 0))
    def inverse_dynamics_derivatives(self, q, qd, qdd, wrenches=None):
        """(dtau/dq, dtau/dqd), analytic (rnea_derivatives.py)."""
        return rnea_derivatives.inverse_dynamics_derivatives(self, q, qd, qdd, wrenches)

    @runtime.native_first(traced_derivatives.FORWARD_DYNAMICS_DERIVATIVES, 3, split=3)   # from C
    @_jointless(('q', 'qd', 'tau'), (0, 0), (0, 0), (0, 0))
    def forward_dynamics_derivatives(self, q, qd, tau, wrenches=None):
        """(dqdd/dq, dqdd/dqd, dqdd/dtau = M^-1) at qdd = forward_dynamics(q, qd, tau)."""
        return aba_derivatives.forward_dynamics_derivatives(self, q, qd, tau, wrenches)

    @_jointless(('q', 'qd', 'qdd'), (0, 0))
    def regressor(self, q, qd, qdd):
        """Y with inverse_dynamics(q, qd, qdd) = Y @ inertial_parameters() + armature * qdd, (n, 10 nb)
        or (N, n, 10 nb): the rigid-body parameters only (the armature is not among them)."""
        return regressor.regressor(self, q, qd, qdd)

    def inertial_parameters(self):
        """(10 nb,) parameters (m, m c, I_xx, I_xy, I_yy, I_xz, I_yz, I_zz) per body, about the body frame."""
        return regressor.inertial_parameters(self)

    def with_inertial_parameters(self, pi, check=True):
        """Copy of this model with the given inertial parameters (payloads folded in)."""
        return regressor.with_inertial_parameters(self, pi, check)

    def with_calibration(self, calibration):
        """Copy with a calibration (a CalibrationResult or a calibration.yaml path) applied:
        lie_dynamics.calibration.result.with_calibration."""
        from ..calibration.result import with_calibration
        return with_calibration(self, calibration)
