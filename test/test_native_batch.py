"""Native batches across states (codegen/clanes.py), their threads, and `out` buffers."""
import concurrent.futures
import copy
import glob
import inspect
import math
import os
import sys
import time
import warnings

import numpy as np
import pytest

from lie_dynamics import load_urdf
from lie_dynamics.codegen import clanes, native, runtime
from lie_dynamics.codegen.traced import crba as t_crba
from lie_dynamics.codegen.traced import rnea as t_rnea
from oracle import Oracle

HERE = os.path.dirname(os.path.abspath(__file__))
ARM = os.path.join(HERE, '..', 'lie_dynamics', 'data', 'arm7.urdf')
ROOT = next(iter(glob.glob(os.path.join(sys.prefix, 'lib', 'python3*', 'site-packages', 'cmeel.prefix', 'share',
                                        'example-robot-data', 'robots'))), None)
ROBOTS = ['arm7', 'ur_description/urdf/ur5_robot.urdf', 'panda_description/urdf/panda.urdf']
PANDA_ARM = [f'panda_joint{k}' for k in range(1, 8)]
TOL = 1e-12

pytestmark = pytest.mark.skipif(native.module() is None, reason='no working C compiler')


def _xml(name):
    if name == 'arm7':
        path = ARM
    else:
        if ROOT is None:
            pytest.skip('example-robot-data is not installed')
        path = os.path.join(ROOT, name)
    with open(path, encoding='utf-8') as fh:
        return fh.read()


def _model(name):
    joints = PANDA_ARM if name.startswith('panda') else None
    with warnings.catch_warnings():
        warnings.simplefilter('ignore')   # vendor inertias are warned about
        return load_urdf(_xml(name), joints=joints), joints


def _states(model, N, seed):
    rng = np.random.default_rng(seed)
    return [np.ascontiguousarray(x) for x in rng.uniform(-2, 2, (3, N, model.n))]


def _rel(a, b):
    return float(np.max(np.abs(a - b)) / max(1.0, float(np.max(np.abs(b)))))


@pytest.mark.parametrize('name', ROBOTS)
def test_lanes_equal_the_one_state_kernel_and_pinocchio(name):
    """A batch runs blocks of LANES states through the vector form, the rest state by state:
    every state equals the one-state kernel to the bit, and Pinocchio to 1e-12."""
    model, joints = _model(name)
    lib = runtime.kernel(model, t_rnea.INVERSE_DYNAMICS).native()
    assert lib.lanes_address, 'a 7-joint arm gets the form across states'
    oracle = Oracle(_xml(name), joints=joints)
    for N in (clanes.LANES - 1, 4 * clanes.LANES + 3, 101):   # never a multiple of the width
        q, qd, qdd = _states(model, N, seed=N)
        batch = model.inverse_dynamics(q, qd, qdd)
        one = np.array([model.inverse_dynamics(q[i], qd[i], qdd[i]) for i in range(N)])
        assert np.array_equal(batch, one)
        ref = np.array([oracle.rnea(q[i], qd[i], qdd[i]) for i in range(N)])
        assert _rel(batch, ref) <= TOL
        g = model.gravity(q)
        assert np.array_equal(g, np.array([model.gravity(x) for x in q]))
        assert _rel(g, np.array([oracle.gravity(x) for x in q])) <= TOL


def test_sines_and_cosines_computed_together_equal_the_one_state_kernel():
    """The form across states takes the sin and cos of the joint angles computed by the batch,
    SC_CHUNK = 256 states at a time in groups (native_call.c sincos_grouped): angles over every
    range the C library branches on (|q| up to 7), a batch of several chunks and not a multiple of
    the width, every state equal to the one-state kernel to the bit, and a threaded batch too."""
    model, _ = _model('ur_description/urdf/ur5_robot.urdf')
    lib = runtime.kernel(model, t_rnea.INVERSE_DYNAMICS).native()
    assert lib.lanes_sincos == tuple(x for k in range(model.n) for x in (0, k)), 'every angle computed outside'
    rng = np.random.default_rng(12)
    N = 2 * 256 + clanes.LANES + 1
    q = rng.uniform(-7, 7, (N, model.n))
    q[:, 0] = rng.choice([0.0, 1e-9, np.pi / 2, np.pi, -3 * np.pi / 2], N) + rng.uniform(-0.2, 0.2, N)
    qd, qdd = rng.uniform(-2, 2, (2, N, model.n))
    one = np.array([model.inverse_dynamics(q[i], qd[i], qdd[i]) for i in range(N)])
    assert np.array_equal(model.inverse_dynamics(q, qd, qdd), one)
    assert np.array_equal(model.gravity(q), np.array([model.gravity(x) for x in q]))
    previous = native.set_threads(2, min_rows=64)
    try:
        assert np.array_equal(model.inverse_dynamics(q, qd, qdd), one)
    finally:
        native.set_threads(previous)


def test_sincos_grouped_is_the_c_librarys_sin_and_cos():
    """The grouped order (native_call.c sincos_grouped, exposed as sincos_batch for the probe)
    changes no value: each equals math.sin and math.cos, over every range they branch on."""
    x = np.random.default_rng(13).uniform(-9, 9, 3 * 256 * 7 + 5)
    x[:40] = [0.0, -0.0, 1e-300, 5e-9, np.pi / 2, np.pi, 2 * np.pi, 0.855469, 2.426265, 1e5] * 4
    for grouped in (True, False):
        s, c = native.module().sincos_batch(x, grouped)
        assert np.array_equal(s, [math.sin(v) for v in x]) and np.array_equal(c, [math.cos(v) for v in x])


def test_threads_give_identical_results():
    model, _ = _model('arm7')
    q, qd, qdd = _states(model, 2 * 1000 + 7, seed=3)
    previous = native.set_threads(1)
    try:
        one = model.inverse_dynamics(q, qd, qdd)
        m_one = model.mass_matrix(q)
        for n in (2, 3):
            native.set_threads(n, min_rows=64)   # cut even this batch
            assert np.array_equal(model.inverse_dynamics(q, qd, qdd), one)
            assert np.array_equal(model.mass_matrix(q), m_one)
            out = np.full_like(one, np.nan)
            assert model.inverse_dynamics(q, qd, qdd, out=out) is out and np.array_equal(out, one)
    finally:
        native.set_threads(previous)
    with pytest.raises(ValueError, match='threads'):
        native.set_threads(0)


def test_kept_helpers_serve_batches_in_turn_at_once_and_in_a_forked_child():
    """The helpers a threaded batch starts are kept (native_call.c run_pooled): batches back to
    back, after the helpers went to sleep, from several Python threads at once (one holds the
    helpers, the others start their own threads) and in a forked child (which has none of its
    parent's threads) all equal the one-thread batch, bit for bit."""
    model, _ = _model('arm7')
    q, qd, qdd = _states(model, 1500, seed=4)
    previous = native.set_threads(1)
    try:
        one = model.inverse_dynamics(q, qd, qdd)
        native.set_threads(2, min_rows=64)
        for k in range(20):
            assert np.array_equal(model.inverse_dynamics(q, qd, qdd), one)
            if k % 5 == 4:
                time.sleep(0.002)   # past the helpers' spin: they sleep, and are woken
        native.set_threads(3, min_rows=64)   # one more helper joins the kept one
        with concurrent.futures.ThreadPoolExecutor(4) as pool:
            got = list(pool.map(lambda _: [model.inverse_dynamics(q, qd, qdd) for _ in range(10)], range(4)))
        assert all(np.array_equal(r, one) for rs in got for r in rs)
        with warnings.catch_warnings():
            warnings.simplefilter('ignore', DeprecationWarning)   # fork() with threads running
            pid = os.fork()
        if pid == 0:   # the child: exit 0 only with the same results
            code = 1
            try:
                code = 0 if all(np.array_equal(model.inverse_dynamics(q, qd, qdd), one) for _ in range(3)) else 3
            finally:
                os._exit(code)
        _, status = os.waitpid(pid, 0)
        assert os.waitstatus_to_exitcode(status) == 0
    finally:
        native.set_threads(previous)


def test_a_failing_state_in_a_threaded_batch_falls_back_to_the_checked_path():
    """A non-finite input in one thread's part: the kernel declines, the full path names it."""
    model, _ = _model('arm7')
    q, qd, qdd = _states(model, 600, seed=5)
    qd[555, 2] = np.inf
    previous = native.set_threads(2, min_rows=64)
    try:
        with pytest.raises(ValueError, match='qd'):
            model.inverse_dynamics(q, qd, qdd)
    finally:
        native.set_threads(previous)


@pytest.mark.parametrize('single', [True, False])
def test_out_good_and_bad_buffers(single):
    model, _ = _model('arm7')
    n = model.n
    q, qd, qdd = _states(model, 9, seed=6)
    if single:
        q, qd, qdd = q[0], qd[0], qdd[0]
    want = model.inverse_dynamics(q, qd, qdd)
    shape = want.shape
    good = np.full(shape, np.nan)
    assert model.inverse_dynamics(q, qd, qdd, out=good) is good and np.array_equal(good, want)
    strided = np.full(shape[:-1] + (2 * n,), np.nan)[..., ::2]   # not contiguous: written all the same
    assert model.inverse_dynamics(q, qd, qdd, out=strided) is strided and np.array_equal(strided, want)
    for alias in ('q', 'qd', 'qdd'):   # out may be an input: the inputs are read before it is written
        args = {'q': q.copy(), 'qd': qd.copy(), 'qdd': qdd.copy()}
        got = model.inverse_dynamics(**args, out=args[alias])
        assert got is args[alias] and np.array_equal(got, want)
    if not single:   # out overlapping an input shifted by a row: computed first, then written
        buf = np.concatenate([q, np.zeros((1, n))])
        shifted = buf[1:]
        got = model.inverse_dynamics(buf[:-1], qd, qdd, out=shifted)
        assert got is shifted and np.array_equal(got, want)
        mbuf = np.zeros((len(q) * n + 1, n))
        mbuf[:len(q)] = q
        assert np.allclose(model.mass_matrix(mbuf[:len(q)], out=mbuf[:len(q) * n].reshape(len(q), n, n)),
                           model.mass_matrix(q), rtol=0, atol=1e-12)
    readonly = np.empty(shape)
    readonly.flags.writeable = False
    bad = [np.empty(shape, np.float32), np.empty(shape[:-1] + (n + 1,)), np.empty((2,) + shape), readonly,
           want.tolist()]
    for b in bad:
        with pytest.raises(ValueError, match='^out must be a writeable float64 array'):
            model.inverse_dynamics(q, qd, qdd, out=b)
        with pytest.raises(ValueError, match='^out must be'):
            model.gravity(q, out=b)
    with pytest.raises(ValueError, match='^out must be'):
        model.mass_matrix(q, out=np.empty(shape))



def test_methods_run_the_kernel_from_c_and_follow_each_model():
    """model.inverse_dynamics and model.gravity are C methods (dispatch.native_first): they
    follow a model's setters, several models in turn, use_native and the runtime's clear."""
    model, _ = _model('arm7')
    other = copy.deepcopy(model)
    q, qd, qdd = (x[0] for x in _states(model, 1, seed=8))
    tau = model.inverse_dynamics(q, qd, qdd)
    assert type(inspect.getattr_static(model, 'inverse_dynamics')).__name__ == 'Method'
    assert 'RNEA' in type(model).inverse_dynamics.__doc__
    oracle = Oracle(_xml('arm7'))
    other.set_gravity([0.0, 0.0, -3.0])
    other_oracle = Oracle(_xml('arm7'), gravity=(0.0, 0.0, -3.0))
    for _ in range(2):   # in turn: each call finds its own model's kernel
        assert _rel(model.inverse_dynamics(q, qd, qdd), oracle.rnea(q, qd, qdd)) <= TOL
        assert _rel(other.inverse_dynamics(q, qd, qdd), other_oracle.rnea(q, qd, qdd)) <= TOL
        assert _rel(other.gravity(q), other_oracle.gravity(q)) <= TOL
    other.set_gravity(model.gravity_vector)   # a setter bumps the version
    assert np.array_equal(other.inverse_dynamics(q, qd, qdd), tau)
    runtime.use_native(other, False)
    assert _rel(other.inverse_dynamics(q, qd, qdd), tau) <= TOL
    assert runtime.native(other, t_rnea.INVERSE_DYNAMICS) is None
    runtime.clear()
    assert np.array_equal(model.inverse_dynamics(q, qd, qdd), tau)
    with pytest.raises(ValueError, match='qdd'):
        model.inverse_dynamics(q, qd, qdd[:-1])
    with pytest.raises(ValueError, match='q'):
        model.gravity(np.full_like(q, np.nan))


def test_lanes_of_a_kernel_with_scattered_outputs(tmp_path, monkeypatch):
    """The mass matrix (outputs scattered into n x n) rendered across states when asked for."""
    monkeypatch.setenv('LIE_DYNAMICS_CACHE_DIR', str(tmp_path / 'cache'))
    monkeypatch.setattr(clanes, 'FAMILIES', clanes.FAMILIES + ('mass_matrix',))
    runtime.clear()
    try:
        model, _ = _model('arm7')
        assert runtime.kernel(model, t_crba.MASS_MATRIX).native().lanes_address
        q, _, _ = _states(model, 2 * clanes.LANES + 1, seed=9)
        assert np.array_equal(model.mass_matrix(q), np.array([model.mass_matrix(x) for x in q]))
        assert _rel(model.mass_matrix(q), np.array([Oracle(_xml('arm7')).crba(x) for x in q])) <= TOL
    finally:
        runtime.clear()


@pytest.mark.parametrize('name', ['arm7', 'tree30'])
def test_mass_matrix_forward_dynamics_and_derivatives_run_from_c(name):
    """M, forward dynamics and both derivative families are C methods too (dispatch.native_first;
    forward dynamics by the model's own kernel, the looped ABA from 24 bodies; the derivatives as
    the tuple of (n, n) views the Python method cuts): equal to the Python path to the bit and
    to Pinocchio; out= where the method has it, its bad buffers and the derivatives' lack of it
    still answered by the Python method."""
    if name == 'arm7':
        xml = _xml('arm7')
    else:
        from robots import random_urdf
        xml = random_urdf(30, 30, tree=True)
    model = load_urdf(xml)
    oracle = Oracle(xml)
    n = model.n
    q, qd, x = _states(model, 4, seed=11)
    for s in (0, slice(None)):
        a, b, c = q[s], qd[s], x[s]
        M = model.mass_matrix(a)
        assert np.array_equal(M, model.mass_matrix(a, 'crba'))
        qdd = model.forward_dynamics(a, b, c)
        assert np.array_equal(qdd, model.forward_dynamics(a, b, c, None))
        d = model.inverse_dynamics_derivatives(a, b, c)
        f = model.forward_dynamics_derivatives(a, b, c)
        assert type(d) is tuple and len(d) == 2 and type(f) is tuple and len(f) == 3
        for got, want in zip(d + f, model.inverse_dynamics_derivatives(a, b, c, None)
                             + model.forward_dynamics_derivatives(a, b, c, None), strict=True):
            assert got.shape == np.shape(a)[:-1] + (n, n) and got.flags.writeable and np.array_equal(got, want)
    for method in ('mass_matrix', 'forward_dynamics', 'inverse_dynamics_derivatives', 'forward_dynamics_derivatives'):
        assert type(inspect.getattr_static(model, method)).__name__ == 'Method', method   # installed by now
    for i in range(len(q)):   # against Pinocchio, state by state (the batch equals them above)
        M = model.mass_matrix(q[i])
        assert _rel(M, oracle.crba(q[i])) <= TOL
        assert _rel(model.forward_dynamics(q[i], qd[i], x[i]), oracle.aba(q[i], qd[i], x[i])) <= 1e-10
        dq, dv = model.inverse_dynamics_derivatives(q[i], qd[i], x[i])
        pq, pv = oracle.rnea_derivatives(q[i], qd[i], x[i])
        assert _rel(dq, pq) <= TOL and _rel(dv, pv) <= TOL
        assert _rel(model.forward_dynamics_derivatives(q[i], qd[i], x[i])[2] @ M, np.eye(n)) <= 1e-10
    good = np.full((n, n), np.nan)
    assert model.mass_matrix(q[0], out=good) is good and np.array_equal(good, model.mass_matrix(q[0]))
    good = np.full(n, np.nan)
    assert model.forward_dynamics(q[0], qd[0], x[0], out=good) is good
    assert np.array_equal(good, model.forward_dynamics(q[0], qd[0], x[0]))
    with pytest.raises(ValueError, match='^out must be'):
        model.forward_dynamics(q[0], qd[0], x[0], out=np.empty(n, np.float32))
    with pytest.raises(TypeError, match='out'):
        model.inverse_dynamics_derivatives(q[0], qd[0], x[0], out=np.empty((2, n, n)))
    with pytest.raises(ValueError, match='tau'):
        model.forward_dynamics_derivatives(q[0], qd[0], x[0][:-1])
    with pytest.raises(ValueError, match='q'):
        model.mass_matrix(np.full(n, np.nan))


@pytest.mark.parametrize('name', ['arm7', 'tree30'])
def test_coriolis_term_runs_its_own_kernel_from_c(name):
    """C(q, qd) qd has its own kernel (the traced RNEA at qdd = 0 without gravity) behind a C
    method: equal to inverse dynamics at qdd = 0 without gravity (to rounding: the zeros are
    folded), its batch rows to its single states to the bit, and to Pinocchio's C(q, qd) qd;
    out= good and bad; a bad state still refused by name."""
    xml = _xml('arm7') if name == 'arm7' else __import__('robots').random_urdf(30, 30, tree=True)
    model = load_urdf(xml)
    oracle = Oracle(xml)
    n = model.n
    q, qd, _ = _states(model, 4, seed=12)
    zeros = np.zeros_like(qd)
    got = model.coriolis_term(q, qd)
    assert _rel(got, model.inverse_dynamics(q, qd, zeros, with_gravity=False)) <= 1e-15
    assert type(inspect.getattr_static(model, 'coriolis_term')).__name__ == 'Method'
    for i in range(len(q)):
        one = model.coriolis_term(q[i], qd[i])
        assert np.array_equal(one, got[i])
        assert _rel(one, oracle.coriolis_matrix(q[i], qd[i]) @ qd[i]) <= TOL
    good = np.full(n, np.nan)
    assert model.coriolis_term(q[0], qd[0], out=good) is good and np.array_equal(good, got[0])
    with pytest.raises(ValueError, match='^out must be'):
        model.coriolis_term(q[0], qd[0], out=np.empty(n + 1))
    with pytest.raises(ValueError, match='qd'):
        model.coriolis_term(q[0], np.full(n, np.inf))


def test_methods_hold_several_models():
    """A C method holds the kernels of up to four models (native_method.c HELD): models called in
    turn each get their own kernel, a setter on one of them is seen, a fifth model and a model
    that is gone take an entry without confusing the others."""
    import gc
    base, _ = _model('arm7')
    q, qd, qdd = (x[0] for x in _states(base, 1, seed=12))
    gravities = [(0.0, 0.0, -9.81 + k) for k in range(6)]
    models = []
    for g in gravities:
        m = copy.deepcopy(base)
        m.set_gravity(list(g))
        models.append(m)
    oracles = [Oracle(_xml('arm7'), gravity=g) for g in gravities]
    link = base.body_link_names[-1]
    for _ in range(3):
        for m, o in zip(models, oracles, strict=True):   # six models in turn: more than are held
            assert _rel(m.gravity(q), o.gravity(q)) <= TOL
            assert _rel(m.forward_dynamics(q, qd, qdd), o.aba(q, qd, qdd)) <= 1e-10
            assert _rel(m.jacobian(q, link), o.frame_jacobian(q, link, 'world_aligned')) <= TOL
        for m, o in zip(models[:2], oracles[:2], strict=True):   # two in turn, both held
            assert _rel(m.inverse_dynamics(q, qd, qdd), o.rnea(q, qd, qdd)) <= TOL
    models[1].set_gravity(list(gravities[0]))   # a setter on a held model: its version changes
    assert np.array_equal(models[1].gravity(q), models[0].gravity(q))
    del models[2:]
    gc.collect()   # held models gone: their entries are taken again
    fresh = copy.deepcopy(base)
    assert _rel(fresh.gravity(q), oracles[0].gravity(q)) <= TOL
    assert _rel(models[0].gravity(q), oracles[0].gravity(q)) <= TOL
