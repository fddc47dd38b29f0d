"""One step of the generalized-momentum observer, traced (algorithms/observer.py).

One call per sample does the whole step: p = M qd and C^T qd (trace_momentum), g(q)
(trace_gravity), the motor torque less the modelled friction
b qd + fc tanh(qd / eps) (laws.friction_torque), beta = tau + C^T qd - g, and the trapezoid
of the module docstring of algorithms/observer.py with the newest r implicit:

    P_k = I_{k-1} + dt/2 (c_{k-1} + beta_k),       c = beta + r (the previous sample's sum)
    r_k = K (p_k - p_0 - P_k) / (1 + K dt / 2),    I_k = P_k + dt/2 r_k,    c_k = beta_k + r_k

Per-state arguments: Q, QD, TAU (the motor torque, model order), Z = (p_0, I, c, dt) (the
observer's state, 3n + 1) and O = (K, b, fc, eps) (its settings, 3n + 1: they belong to
the observer, not to the model, so they are not bound with the model's parameters). Outputs, 6n + 1: the next
state (p_0, I_k, c_k, a slot for the next dt), so that the next call reads it where this one
wrote it, then r_k, p_k, beta_k (p and beta start the integral at the first sample).
"""
from ...laws import friction_torque
from ..kernel import Trace
from ..runtime import Spec
from ..tracer import Graph
from .rnea import joint_torques, subtree_inputs, trace_gravity, trace_momentum, trig, with_armature


def build_observer_step(fr):
    """k(Q, QD, TAU, Z, O, P, S, A0, E0, AR) -> (p_0, I, c, 0, r, p, beta) tuple (module docstring); P the
    inertias (trace_momentum), S the subtree parameters (trace_gravity), AR the armature (in p only)."""
    n = fr.n
    g = Graph()
    co = fr.trace_coordinates(g, rates=1)
    cs = trig(fr, g, co['x'])
    # g(q) first, its inputs made in build_gravity's order: the same sums in the same order,
    # so the same bits as Model.gravity (a motor torque of exactly g(q) at rest gives beta = 0)
    sarg, sub = subtree_inputs(g, fr.nb, 'S', 's')
    a0arg, ga = fr.trace_gravity(g)
    grav = joint_torques(fr, trace_gravity(fr, cs, co['x'], sub, ga))
    parg, params = fr.trace_params(g)
    lists = {'TAU': [f'mt{j}' for j in range(n)],
             'Z': [f'zp{j}' for j in range(n)] + [f'zi{j}' for j in range(n)] + [f'zc{j}' for j in range(n)]
             + ['zdt'],
             'O': [f'ok{j}' for j in range(n)] + [f'ob{j}' for j in range(n)] + [f'oc{j}' for j in range(n)]
             + ['oeps']}
    sym = {k: [g.input(nm) for nm in v] for k, v in lists.items()}
    tau, z, o = sym['TAU'], sym['Z'], sym['O']
    p0, integral, carry, dt = z[:n], z[n:2 * n], z[2 * n:3 * n], z[3 * n]
    gain, visc, coul, eps = o[:n], o[n:2 * n], o[2 * n:3 * n], o[3 * n]
    p_b, c_b = trace_momentum(fr, cs, co['x'], co['xd'], params)
    ararg, arm = fr.trace_armature(g)
    qd = [g.input(nm) for nm in co['args'][1][1]]
    p, ctqd = with_armature(joint_torques(fr, p_b), arm, qd), joint_torques(fr, c_b)
    half = 0.5 * dt
    r, i_k, c_k, beta = [], [], [], []
    for j in range(n):
        # the one friction law, traced (qd / eps becomes qd * (1 / eps): one reciprocal, shared)
        b = tau[j] + ctqd[j] - grav[j] - friction_torque(qd[j], visc[j], coul[j], eps)
        partial = integral[j] + half * (carry[j] + b)
        rj = gain[j] * (p[j] - p0[j] - partial) * g.inv(1.0 + half * gain[j])
        r.append(rj)
        i_k.append(partial + half * rj)
        c_k.append(b + rj)
        beta.append(b)
    args = co['args'] + [(k, v) for k, v in lists.items()] + [parg, sarg, a0arg, co['offset_args'], ararg]
    return Trace(g, 'observer_step_kernel', args, list(p0) + i_k + c_k + [0.0] + r + p + beta)


# Single states only (the step is sequential); `inverse_dynamics` sets its size limits. Its result
# (6n + 1 outputs: the next state, the estimate, p, beta) is accepted when finite (rtol 0 and no
# pivots: spec.accepts), by the float kernel as by the C one, so its fast path is runtime.fast alone.
OBSERVER_STEP = Spec('observer_step', build_observer_step, ('inertia', 'subtree', 'gravity', 'offsets', 'armature'),
                     'inverse_dynamics', result=lambda model: ((6 * model.n + 1,), 0.0))
