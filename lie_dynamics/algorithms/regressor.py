"""Inertial-parameter regressor: tau = Y(q, qd, qdd) pi, linear in the inertial parameters.

The paper notes (after eq 32) that each link's inertia has exactly 10 independent
parameters. Per body, about its own frame and in Pinocchio's order (docs/architecture.md),

    pi_i = (m, m c_x, m c_y, m c_z, I_xx, I_xy, I_yy, I_xz, I_yz, I_zz),
    J_i  = [[I, [h]], [-[h], m 1]],  h = m c,  I = I_c - m [c]^2 (inertia about the frame origin).

The body-frame Newton-Euler wrench of the RNEA (codegen/traced/rnea.py),
F = J Vdot - ad_V^T J V, is linear in pi_i:
with V = (w, v) and Vdot = (alpha, a) in body frame (gravity included as Vdot_0 = (0, -g)),

    F = K(V, Vdot) pi_i,   K = [[0,         -[a + w x v],    L(alpha) + [w] L(w)],
                                [a + w x v,  [alpha] + [w]^2, 0                 ]],

where L(u) is the 3x6 matrix with I u = L(u) (I_xx, I_xy, I_yy, I_xz, I_yz, I_zz). The
joint torques are tau_k = sum_{k <= i} (Ad_{T_i^-1} A_k)^T F_i, and Ad_{T_i^-1} A_k is
block (i, k) of G S in the factorisation M = S^T G^T J G S (eq 39): the regressor is

    Y[k, block i] = (G S)_{ik}^T K_i          (k <= i; zero otherwise),


Two evaluations: vectorised numpy over bodies and states (`regressor_vectorized`), and
generated straight-line code (codegen/traced/regressor.py, `regressor_kernel`), used where
codegen.runtime.route says it is faster (sized in (body, ancestor) pairs).
"""
import numpy as np

from ..codegen import runtime
from ..codegen.traced import regressor as traced
from ..model.inertia import inertia_to_parameters, parameter_consistency, parameters_to_inertia
from ..spatial import ad, cross, hat3, transpose
from .common import body_constants, chunks, kinematic_state

# L(u): I u = L(u) iota, iota = (xx, xy, yy, xz, yz, zz); entry (row, col) <- u[idx]
_L_ROW = np.array([0, 0, 0, 1, 1, 1, 2, 2, 2])
_L_COL = np.array([0, 1, 3, 1, 2, 4, 3, 4, 5])
_L_IDX = np.array([0, 1, 2, 0, 1, 2, 0, 1, 2])


def physical_consistency(pi):
    """Per body: (ok, reason) for parameters (nb, 10): the one consistency check
    (inertia.violations) applied to the inertia about each body's CoM."""
    return parameter_consistency(pi)


def inertial_parameters(model):
    """Current parameters (nb * 10,) of the model (payloads included), body order of model.body_joint_names."""
    return inertia_to_parameters(model.J).reshape(-1)


def with_inertial_parameters(model, pi, check=True):
    """A copy of `model` whose bodies have the inertial parameters `pi` ((nb*10,) or (nb, 10)).

    `pi` is the total per body (payloads included): the copy carries it as its link
    inertias and has no separate payloads. check: raise ValueError for physically
    inconsistent parameters (negative mass, invalid inertia about the CoM); identified
    parameters often are, and check=False accepts them (the dynamics stay defined,
    though the mass matrix may then not be positive definite).
    """
    p = np.asarray(pi, dtype=float)
    if p.size != 10 * model.nb or p.ndim not in (1, 2):
        raise ValueError(f'inertial parameters must have shape ({10 * model.nb},) or ({model.nb}, 10) '
                         f'for the {model.nb} bodies, got {p.shape}')
    p = p.reshape(model.nb, 10)
    if not np.all(np.isfinite(p)):
        raise ValueError('inertial parameters contain non-finite values')
    if check:
        bad = [reason for ok, reason in physical_consistency(p) if not ok]
        if bad:
            raise ValueError('inertial parameters are not physically consistent: ' + '; '.join(bad)
                             + ' (pass check=False to accept them)')
    return model.with_body_inertias(parameters_to_inertia(p))


def _K(Vb, Ab):
    """Per-body 6x10 maps K(V, Vdot) with J Vdot - ad_V^T J V = K pi, for (N, nb, 6) inputs."""
    w, v = Vb[..., :3], Vb[..., 3:]
    al, a = Ab[..., :3], Ab[..., 3:]
    shape = Vb.shape[:-1]
    W = hat3(w)
    Alpha = hat3(al)
    acc = a + cross(w, v)
    Acc = hat3(acc)
    Lw = np.zeros(shape + (3, 6))
    La = np.zeros(shape + (3, 6))
    Lw[..., _L_ROW, _L_COL] = w[..., _L_IDX]
    La[..., _L_ROW, _L_COL] = al[..., _L_IDX]
    K = np.zeros(shape + (6, 10))
    K[..., 3:, 0] = acc
    K[..., :3, 1:4] = -Acc
    K[..., 3:, 1:4] = Alpha + W @ W
    K[..., :3, 4:] = La + W @ Lw
    return K


def _regressor(model, x, xd, xdd, a0):
    Adinv, AdinvT, A = kinematic_state(model, x)
    anc = model.ancestors
    N, nb = x.shape
    Axd = A * xd[..., None]
    V = anc @ Axd
    acc = anc @ (A * xdd[..., None] + (ad(V) @ Axd[..., None])[..., 0]) + a0
    VV = Adinv @ np.stack([V, acc], axis=-1)                 # to body frames
    K = _K(VV[..., 0], VV[..., 1])                           # (N, nb, 6, 10)
    GS = (Adinv @ transpose(A)[:, None]) * anc[None, :, None, :]  # (N, i, 6, k)
    Y = transpose(GS) @ K                                        # (N, i, k, 10)
    return np.swapaxes(Y, 1, 2).reshape(N, nb, nb * 10)      # (N, k, 10 i)


def regressor(model, q, qd, qdd):
    """Y(q, qd, qdd) with inverse_dynamics(q, qd, qdd) = Y @ inertial_parameters() + armature * qdd
    (the rigid-body parameters only; Model.armature is not among them).

    Shape (n, 10 nb) or (N, n, 10 nb); columns are 10 per body in model.body_joint_names
    order, parameters as PARAMETER_NAMES (Pinocchio's computeJointTorqueRegressor layout).
    Gravity (as set on the model) is included.
    """
    Y = runtime.fast(model, traced.REGRESSOR)(q, qd, qdd)   # the fast path: the result, or None
    return runtime.call(model, _REGRESSOR, (q, qd, qdd)) if Y is None else Y


def regressor_validated(model, arrays):
    """regressor on validated (N, n) arrays [q, qd, qdd] (Model.validate) -> (N, n, 10 nb): the
    kernel, else the vectorised form. For callers that validated their arguments already."""
    q, qd, qdd = arrays
    Y = _kernel(model, q, qd, qdd)
    return _vectorized(model, q, qd, qdd) if Y is None else Y


_REGRESSOR = runtime.Entry(('q', 'qd', 'qdd'), None, regressor_validated)


def regressor_vectorized(model, q, qd, qdd):
    """regressor() by the vectorised form (numpy over bodies and states), any model."""
    (q, qd, qdd), single = model.validate(('q', 'qd', 'qdd'), (q, qd, qdd))
    Y = _vectorized(model, q, qd, qdd)
    return Y[0] if single else Y


def _vectorized(model, q, qd, qdd):
    """Vectorised path on validated (N, n) arrays -> (N, n, 10 nb)."""
    c = body_constants(model)
    x = model.body_coordinates(q)
    E = model.E
    xd, xdd = qd @ E.T, qdd @ E.T
    N, nb = x.shape
    out = np.empty((N, nb, 10 * nb))
    for sl in chunks(N, 100 * nb + 30 * nb * nb):
        out[sl] = _regressor(model, x[sl], xd[sl], xdd[sl], model.base_acceleration)
    if not c['identity']:
        out = E.T @ out    # a batched matmul: several times faster than the equivalent einsum
    return out


def regressor_kernel(model, q, qd, qdd, mode=None):
    """regressor() from the generated Python kernel: mode 'loop' (Python floats, state by
    state), 'rows' (numpy rows over the states) or None (as route decides; then also None
    where the vectorised form is faster). None when the model has no kernel (screws that are
    not plain URDF joints, or more (body, ancestor) pairs than THRESHOLDS allows)."""
    (q, qd, qdd), single = model.validate(('q', 'qd', 'qdd'), (q, qd, qdd))
    Y = _kernel(model, q, qd, qdd, mode, native_first=False)
    return Y if Y is None or not single else Y[0]


def _kernel(model, q, qd, qdd, mode=None, native_first=True):
    """The kernels on validated (N, n) arrays -> (N, n, 10 nb), or None (see regressor_kernel)."""
    Y = runtime.run(model, traced.REGRESSOR, [q, qd, qdd], mode, native_first)
    return None if Y is None else Y.reshape(len(q), model.n, 10 * model.nb)
