"""Analytic inverse-dynamics derivatives against Pinocchio and central finite differences."""
import numpy as np
import pytest

from dyn_cases import CASES, case, oracle_stack, rel_err, states
from lie_dynamics.algorithms import rnea_derivatives


@pytest.mark.parametrize('name', CASES)
def test_rnea_derivatives_match_pinocchio(name):
    model, oracle = case(name)
    q, qd, qdd = states(model, seed=10)
    dq, dv = model.inverse_dynamics_derivatives(q, qd, qdd)
    ref = [np.array(r) for r in zip(*(oracle.rnea_derivatives(*s) for s in zip(q, qd, qdd, strict=True)), strict=True)]
    floor = 1e-4 * np.abs(model.mass_matrix(q)).max() * max(1.0, np.abs(qd).max())
    assert rel_err(dq, ref[0], floor) < 1e-8
    assert rel_err(dv, ref[1], floor) < 1e-8
    # the vectorised form (used above the kernel size cap) and the per-state kernel loop
    vq, vv = rnea_derivatives.inverse_dynamics_derivatives_vectorized(model, q, qd, qdd)
    assert rel_err(vq, ref[0], floor) < 1e-8 and rel_err(vv, ref[1], floor) < 1e-8
    sq, sv = model.inverse_dynamics_derivatives(q[:4], qd[:4], qdd[:4])
    assert rel_err(sq, ref[0][:4], floor) < 1e-8 and rel_err(sv, ref[1][:4], floor) < 1e-8
    # dtau/dqd = 2 C (Christoffel symbols are symmetric in their first two indices)
    assert rel_err(dv, 2 * model.coriolis_matrix(q, qd), floor) < 1e-10


@pytest.mark.parametrize('name', ['chain2', 'tree20_mimic', 'mixed_types', 'fixed_heavy', 'arm7'])
def test_rnea_derivatives_match_finite_differences(name):
    model, _ = case(name)
    q, qd, qdd = states(model, 5, seed=11)
    links = [ln for ln, (b, _) in model.link_frames.items() if b >= 0]
    rng = np.random.default_rng(2)
    w = {links[-1]: rng.normal(size=6), links[0]: rng.normal(size=(5, 6))}
    n = model.n
    # central differences are best near h = 1e-5 (2e-10, stability map); at 1e-6 their own
    # rounding error (eps |tau| / h) reaches 1e-7 here and the check would test the rounding
    # order of inverse_dynamics rather than the derivatives
    h = 1e-5

    def fd(fun):
        return np.stack([(fun(h * e) - fun(-h * e)) / (2 * h) for e in np.eye(n)], axis=-1)

    for wr in (None, w):
        dq, dv = model.inverse_dynamics_derivatives(q, qd, qdd, wr)
        assert rel_err(dq, fd(lambda d, wr=wr: model.inverse_dynamics(q + d, qd, qdd, wr)), 1e-3) < 1e-7
        assert rel_err(dv, fd(lambda d, wr=wr: model.inverse_dynamics(q, qd + d, qdd, wr)), 1e-3) < 1e-7
    one = model.inverse_dynamics_derivatives(q[1], qd[1], qdd[1])
    full = model.inverse_dynamics_derivatives(q, qd, qdd)
    assert one[0].shape == (n, n) and np.allclose(one[0], full[0][1], rtol=1e-12, atol=1e-12)


def test_derivatives_follow_gravity_and_payload():
    model, _ = case('arm7')
    from lie_dynamics import load_urdf
    from dyn_cases import ARM
    model = load_urdf(ARM, gravity=(1.0, -2.0, -9.0))
    model.set_payload('link7', 1.5, (0.0, 0.02, 0.1))
    q, qd, qdd = states(model, 3, seed=12)
    h = 1e-6
    dq, _ = model.inverse_dynamics_derivatives(q, qd, qdd)
    fd = np.stack([(model.inverse_dynamics(q + h * e, qd, qdd) - model.inverse_dynamics(q - h * e, qd, qdd)) / (2 * h)
                   for e in np.eye(7)], axis=-1)
    assert rel_err(dq, fd, 1e-3) < 1e-7


def test_derivative_error_paths():
    model, _ = case('chain7')
    z = np.zeros(7)
    with pytest.raises(ValueError, match=r'qdd must have shape \(7,\)'):
        model.inverse_dynamics_derivatives(z, z, np.zeros(2))
    with pytest.raises(ValueError, match="unknown link 'nope' in wrenches"):
        model.inverse_dynamics_derivatives(z, z, z, {'nope': np.zeros(6)})


@pytest.mark.parametrize('name', ['arm7', 'mimic', 'mixed_types', 'fixed_heavy'])
def test_generated_kernel_paths(name):
    """Float loop and numpy-rows forms of the generated kernel, with and without wrenches."""
    model, oracle = case(name)
    q, qd, qdd = states(model, 30, seed=15)
    ref = [np.array(r) for r in zip(*(oracle.rnea_derivatives(*s) for s in zip(q, qd, qdd, strict=True)), strict=True)]
    floor = 1e-4 * np.abs(model.mass_matrix(q)).max() * max(1.0, np.abs(qd).max())
    links = [ln for ln, (b, _) in model.link_frames.items() if b >= 0]
    w = {links[-1]: np.random.default_rng(3).normal(size=(30, 6))}
    vec = rnea_derivatives.inverse_dynamics_derivatives_vectorized(model, q, qd, qdd, w)
    for mode in ('loop', 'rows'):
        dq, dv = rnea_derivatives.inverse_dynamics_derivatives_kernel(model, q, qd, qdd, None, mode)
        assert rel_err(dq, ref[0], floor) < 1e-8 and rel_err(dv, ref[1], floor) < 1e-8
        wq, wv = rnea_derivatives.inverse_dynamics_derivatives_kernel(model, q, qd, qdd, w, mode)
        assert rel_err(wq, vec[0], floor) < 1e-10 and rel_err(wv, vec[1], floor) < 1e-10


@pytest.mark.parametrize('name', ['tree12', 'mixed_types'])
def test_kernel_frame_choice_does_not_change_results(name):
    """The kernel works in the frame of one body (the first by default): any body gives the same
    derivatives, with and without wrenches (covariance of the formulas)."""
    import math
    from lie_dynamics.codegen import runtime
    from lie_dynamics.codegen.kernel import Kernel
    from lie_dynamics.codegen.traced import derivatives as traced
    model, oracle = case(name)
    q, qd, qdd = states(model, 3, seed=17)
    fr = runtime.frames(model)
    P, A0, E0 = runtime.params(model, traced.INVERSE_DYNAMICS_DERIVATIVES)
    fx = np.random.default_rng(4).normal(size=(fr.nb * 6)).tolist()
    ref = [np.array(r) for r in zip(*(oracle.rnea_derivatives(*s) for s in zip(q, qd, qdd, strict=True)), strict=True)]
    floor = 1e-4 * np.abs(model.mass_matrix(q)).max() * max(1.0, np.abs(qd).max())
    n = model.n
    centres = sorted({0, fr.nb // 2, fr.nb - 1})
    with_wrench = []
    for centre in centres:
        fn = Kernel.of(traced.build_inverse_dynamics_derivatives(fr, False, center=centre)).function
        fw = Kernel.of(traced.build_inverse_dynamics_derivatives(fr, True, center=centre)).function
        out = np.array([fn(a.tolist(), b.tolist(), c.tolist(), P, A0, E0, sin=math.sin, cos=math.cos)
                        for a, b, c in zip(q, qd, qdd, strict=True)]).reshape(-1, 2, n, n)
        assert rel_err(out[:, 0], ref[0], floor) < 1e-8 and rel_err(out[:, 1], ref[1], floor) < 1e-8
        with_wrench.append(np.array(fw(q[0].tolist(), qd[0].tolist(), qdd[0].tolist(), fx, P, A0, E0,
                                       sin=math.sin, cos=math.cos)))
    for w in with_wrench[1:]:
        assert rel_err(w, with_wrench[0], floor) < 1e-10


def test_derivatives_with_locked_joints():
    from lie_dynamics import load_urdf
    from oracle import Oracle
    from robots import random_urdf
    xml = random_urdf(22, 8, tree=True)
    ctrl = load_urdf(xml).joint_names[1::2]
    model = load_urdf(xml, joints=ctrl)
    locked = {nm: -0.4 + 0.25 * k for k, nm in enumerate(model.locked_joint_names)}
    model.set_locked(locked)
    oracle = Oracle(xml, joints=ctrl, locked=locked)
    q, qd, qdd = states(model, 6, seed=16)
    ref = [np.array(r) for r in zip(*(oracle.rnea_derivatives(*s) for s in zip(q, qd, qdd, strict=True)), strict=True)]
    floor = 1e-4 * np.abs(model.mass_matrix(q)).max() * max(1.0, np.abs(qd).max())
    for mode in ('loop', 'rows'):
        dq, dv = rnea_derivatives.inverse_dynamics_derivatives_kernel(model, q, qd, qdd, None, mode)
        assert rel_err(dq, ref[0], floor) < 1e-8 and rel_err(dv, ref[1], floor) < 1e-8
    dq, dv = rnea_derivatives.inverse_dynamics_derivatives_vectorized(model, q, qd, qdd)
    assert rel_err(dq, ref[0], floor) < 1e-8 and rel_err(dv, ref[1], floor) < 1e-8
    one = model.inverse_dynamics_derivatives(q[0], qd[0], qdd[0])
    assert rel_err(one[0][None], ref[0][:1], floor) < 1e-8
    assert rel_err(model.mass_matrix(q), oracle_stack(oracle.crba, q)) < 1e-10
    # changing the locked values changes the kernel's runtime offsets, not its code
    model.set_locked({nm: v + 0.5 for nm, v in locked.items()})
    oracle2 = Oracle(xml, joints=ctrl, locked={nm: v + 0.5 for nm, v in locked.items()})
    assert rel_err(model.inverse_dynamics_derivatives(q[0], qd[0], qdd[0])[0][None],
                   oracle2.rnea_derivatives(q[0], qd[0], qdd[0])[0][None], floor) < 1e-8
    assert rel_err(model.mass_matrix(q[0])[None], oracle2.crba(q[0])[None]) < 1e-10


def test_codegen_tracer_folds_and_matches_float_evaluation():
    """The tracer behind the generated kernels: folding, cancellation, float and row evaluation."""
    import math

    from lie_dynamics.codegen import algebra, runtime, tracer
    from lie_dynamics.codegen.kernel import Kernel, Trace
    g = tracer.Graph()
    x, y = g.input('x'), g.input('y')
    assert (x - x) == 0.0 and 0.0 * x == 0.0 and (x + 0.0).terms == x.terms and (x - 2.0 * x).terms == (-x).terms
    z = algebra.cross((x, y, 1.0), (y, x, 0.0))          # (-x, y, x^2 - y^2)

    def direct(a, b):
        return (-a, b, a * a - b * b, math.sin(a) * b + 2.0 / (a * a + 1.0), math.sqrt(b * b + 1.0))

    outs = list(z) + [g.sin(x) * y + 2.0 * g.inv(x * x + 1.0), g.sqrt(y * y + 1.0)]
    k = Kernel.of(Trace(g, 'k', [('A', ['x', 'y'])], outs))
    assert k.roles == ('state',) and k.widths == (2,) and k.n_out == 5
    for a, b in [(0.3, -1.2), (2.0, 0.5)]:
        assert np.allclose(k.function([a, b], sin=math.sin, cos=math.cos, sqrt=math.sqrt), direct(a, b), rtol=1e-15)
    rows = runtime.run_rows(k, [np.array([[0.3, -1.2], [2.0, 0.5]])])
    assert np.allclose(rows, [direct(0.3, -1.2), direct(2.0, 0.5)], rtol=1e-15)


def test_codegen_rows_rendering_registers_and_parameters():
    """The numpy-rows rendering: parameter-only values as floats, every row operation in place
    into a reused register that is never one of its own operands, chunks with a short last one."""
    import math

    from lie_dynamics.codegen import render, runtime, tracer
    from lie_dynamics.codegen.kernel import Kernel, Trace
    g = tracer.Graph()
    a, b = g.input('a'), g.input('b')            # per state
    p, k = g.input('p'), g.input('k')            # parameters
    s = a
    for i in range(30):                          # a long chain: registers must be reused
        s = g.cos(s * p + b) * (1.5 + 0.1 * i) - a * k
    pk = p * k + 2.0                             # parameters only
    outs = [s, pk * a - 3.0 * b, g.inv(pk), g.sqrt(a * a + k * k), -(a - 2.0 * b) + pk]
    kern = Kernel.of(Trace(g, 'k', [('X', ['a', 'b']), render.Params('P', ['p', 'k'])], outs))
    assert kern.roles == ('state', 'param') and kern.n_state == 1
    assert kern.nreg < 10 and 'u' in kern.rows_source      # registers reused; a hoisted parameter value
    for line in kern.rows_source.splitlines():
        if 'out=' in line:                       # the target is not read by the same ufunc
            target = line.split('out=')[1].rstrip(')')
            assert target not in line.split('(', 1)[1].split('out=')[0]
    X = np.random.default_rng(0).uniform(-1, 1, (11, 2))
    P = [0.7, -1.3]
    ref = np.array([kern.function(list(x), P, sin=math.sin, cos=math.cos, sqrt=math.sqrt) for x in X])
    for chunk in (None, 4):
        assert np.allclose(runtime.run_rows(kern, [X, P], chunk=chunk), ref, rtol=1e-14, atol=1e-14)
