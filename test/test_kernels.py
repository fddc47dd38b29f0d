"""Generated RNEA kernels (codegen/traced/rnea.py): every execution path gives the same torques.

Paths: float kernel (one state, small batches), numpy-rows kernel (chunks, tails shorter than
a chunk), the vectorised reference (models the kernels do not cover), and their parameter
caches (payload, gravity, locked values). Pinocchio agreement itself is in test_rnea.py.
"""
import copy
import pickle
import threading

import numpy as np
import pytest

from lie_dynamics.codegen import runtime
from lie_dynamics.codegen.traced import rnea as traced_rnea
from lie_dynamics import load_urdf
from lie_dynamics.algorithms import rnea
from robots import named_urdf

CASES = ['chain7', 'tree20_mimic', 'mixed_types', 'prismatic_only', 'mimic']


def _rel(a, b):
    return np.max(np.abs(a - b)) / max(1.0, np.max(np.abs(b)))


def _states(model, N, seed=0):
    rng = np.random.default_rng(seed)
    return rng.uniform(-3, 3, (3, N, model.n))


@pytest.mark.parametrize('case', CASES)
def test_float_rows_and_reference_paths_agree(case):
    model = load_urdf(named_urdf(case))
    assert runtime.kernel(model, traced_rnea.INVERSE_DYNAMICS) is not None
    N = 5 + runtime.THRESHOLDS['rows_chunk']  # one full chunk of the rows kernel plus a short tail
    q, qd, qdd = _states(model, N)
    batch = model.inverse_dynamics(q, qd, qdd)                       # rows kernel
    small = model.inverse_dynamics(q[:7], qd[:7], qdd[:7])           # float kernel in a loop
    single = np.array([model.inverse_dynamics(q[i], qd[i], qdd[i]) for i in (0, N - 1)])
    ref = rnea.inverse_dynamics_vectorized(model, q, qd, qdd)
    assert _rel(batch, ref) < 1e-12 and _rel(small, ref[:7]) < 1e-12
    assert _rel(single, ref[[0, N - 1]]) < 1e-12
    g = model.gravity(q)
    g_ref = rnea.gravity_vectorized(model, q)
    assert _rel(g, g_ref) < 1e-12
    assert _rel(np.array([model.gravity(q[0]), model.gravity(q[-1])]), g_ref[[0, -1]]) < 1e-12
    assert _rel(model.gravity(q[:3]), g_ref[:3]) < 1e-12
    cor = model.coriolis_term(q, qd)
    cor_ref = rnea.inverse_dynamics_vectorized(model, q, qd, 0 * qdd, with_gravity=False)
    assert _rel(cor, cor_ref) < 1e-12
    assert _rel(model.coriolis_term(q[0], qd[0]), cor_ref[0]) < 1e-12


def test_parameter_changes_reach_the_kernels():
    xml = named_urdf('tree12')
    model = load_urdf(xml)
    q, qd, qdd = _states(model, 100)
    model.inverse_dynamics(q, qd, qdd)  # compile, cache parameters
    link = [name for name, (b, _) in model.link_frames.items() if b >= 0][-1]
    model.set_payload(link, 2.0, [0.1, 0.0, -0.2], [0.02, 0.0, 0.0, 0.03, 0.0, 0.04])
    model.set_gravity([1.0, -2.0, -9.0])
    for qs in ((q, qd, qdd), (q[0], qd[0], qdd[0])):
        assert _rel(model.inverse_dynamics(*qs), rnea.inverse_dynamics_vectorized(model, *qs)) < 1e-12
        assert _rel(model.gravity(qs[0]), rnea.gravity_vectorized(model, qs[0])) < 1e-12
    # locked joints: values change after compilation
    ctrl = model.joint_names[::2]
    part = load_urdf(xml, joints=ctrl)
    qq = _states(part, 40)
    part.inverse_dynamics(*qq)
    part.set_locked({j: 0.3 + 0.1 * k for k, j in enumerate(part.locked_joint_names)})
    assert _rel(part.inverse_dynamics(*qq), rnea.inverse_dynamics_vectorized(part, *qq)) < 1e-12
    assert _rel(part.gravity(qq[0]), rnea.gravity_vectorized(part, qq[0])) < 1e-12


def test_wrenches_on_every_path():
    model = load_urdf(named_urdf('mixed_types'))
    links = [name for name, (b, _) in model.link_frames.items() if b >= 0]
    rng = np.random.default_rng(3)
    for N in (1, 10, 300):
        q, qd, qdd = _states(model, N)
        W = {links[0]: rng.normal(size=6), links[-1]: rng.normal(size=(N, 6))}
        ref = rnea.inverse_dynamics_vectorized(model, q, qd, qdd, W)
        assert _rel(model.inverse_dynamics(q, qd, qdd, W), ref) < 1e-12
    W1 = {links[-1]: rng.normal(size=6)}
    ref = rnea.inverse_dynamics_vectorized(model, q[0], qd[0], qdd[0], W1)
    assert _rel(model.inverse_dynamics(q[0], qd[0], qdd[0], W1), ref) < 1e-12


def test_input_forms_and_shapes():
    model = load_urdf(named_urdf('chain7'))
    q, qd, qdd = _states(model, 3)
    tau = model.inverse_dynamics(q[0], qd[0], qdd[0])
    assert tau.shape == (model.n,)
    assert np.array_equal(model.inverse_dynamics(q[0].tolist(), qd[0], tuple(qdd[0])), tau)  # generic path
    ints = np.arange(model.n)
    assert np.array_equal(model.gravity(ints), model.gravity(ints.astype(float)))
    assert model.inverse_dynamics(q[:1], qd[:1], qdd[:1]).shape == (1, model.n)
    assert model.inverse_dynamics(q[0], qd[:1], qdd[:1]).shape == (model.n,)  # (n,) mixed with (1, n)
    empty = np.zeros((0, model.n))
    assert model.inverse_dynamics(empty, empty, empty).shape == (0, model.n)
    assert model.gravity(empty).shape == (0, model.n)
    bad = q[0].copy()
    bad[2] = np.nan
    with pytest.raises(ValueError, match='non-finite'):
        model.inverse_dynamics(bad, qd[0], qdd[0])
    with pytest.raises(ValueError, match='non-finite'):
        model.gravity(bad)
    big = np.full(model.n, 1e308)  # finite but its sum overflows: must still be accepted
    assert model.gravity(big).shape == (model.n,)


def test_unsupported_screws_use_the_reference_path():
    original = load_urdf(named_urdf('chain7'))
    q, qd, qdd = _states(original, 2)
    expected = original.inverse_dynamics(q, qd, qdd)
    model = copy.deepcopy(original)
    model.S = model.S * 1.5  # not a unit axis: the kernels' closed forms do not apply
    assert runtime.kernel(model, traced_rnea.INVERSE_DYNAMICS) is None
    got = model.inverse_dynamics(q, qd, qdd)
    ref = rnea.inverse_dynamics_vectorized(model, q, qd, qdd)
    assert np.array_equal(got, ref) and not np.allclose(got, expected)


def test_pickle_copy_and_threads():
    model = load_urdf(named_urdf('tree12'))
    q, qd, qdd = _states(model, 600)
    expected = model.inverse_dynamics(q, qd, qdd)
    for other in (pickle.loads(pickle.dumps(model)), copy.deepcopy(model)):
        assert np.array_equal(other.inverse_dynamics(q, qd, qdd), expected)
    results = [None] * 4

    def work(k):  # concurrent batches must not share the rows kernel's registers
        results[k] = [model.inverse_dynamics(q, qd, qdd) for _ in range(3)]

    threads = [threading.Thread(target=work, args=(k,)) for k in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert all(np.array_equal(r, expected) for rs in results for r in rs)


def test_a_deferring_thread_builds_no_kernel_and_takes_the_reference(tmp_path, monkeypatch):
    """runtime.deferred (the node's control path): a kernel not built yet is not built in that
    thread; the call takes the reference, the build is requested, and `build` (another thread's
    work) makes later calls use the kernel."""
    from lie_dynamics.codegen import kernel
    from robots import random_urdf
    monkeypatch.setenv('LIE_DYNAMICS_CACHE_DIR', str(tmp_path))   # nothing compiled yet
    model = load_urdf(random_urdf(90817, 6))   # a structure no other test uses
    q, qd, qdd = _states(model, 1, seed=3)[:, 0]
    asked, builds = {}, kernel.builds()
    with runtime.deferred(lambda m, spec: asked.setdefault(spec.name, (m, spec))):
        g = model.gravity(q)
        tau = model.inverse_dynamics(q, qd, qdd)
    assert kernel.builds() == builds
    assert {traced_rnea.GRAVITY.name, traced_rnea.INVERSE_DYNAMICS.name} <= set(asked)
    assert all(m is model for m, _ in asked.values())
    for m, spec in asked.values():
        runtime.build(m, spec)
    assert kernel.builds() > builds
    again = []
    with runtime.deferred(lambda m, spec: again.append(spec.name)):
        g2 = model.gravity(q)
        tau2 = model.inverse_dynamics(q, qd, qdd)
    assert again == []   # built: the kernels answer
    assert _rel(g2, g) < 1e-12 and _rel(tau2, tau) < 1e-12
    assert _rel(g, rnea.gravity_vectorized(model, q)) < 1e-12   # the reference answered
    assert _rel(tau, rnea.inverse_dynamics_vectorized(model, q, qd, qdd)) < 1e-12
