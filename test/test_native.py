"""The native backend (codegen/native.py): C kernels equal to the Python kernels and Pinocchio, on
every kernel family; run-time parameters without recompiling; the switch and the fallback; the
disk cache (corrupted files, concurrent compilers); the GIL released in batches; out= buffers;
the frame Jacobians and J̇q̇ (X, the link frame and point, given per state)."""
import os
import subprocess
import sys
import textwrap
import threading
import time

import numpy as np
import pytest

from lie_dynamics.algorithms import jacobian as jac
from lie_dynamics.codegen import native, runtime
from lie_dynamics.codegen.traced import aba as t_aba
from lie_dynamics.codegen.traced import cholesky as t_chol
from lie_dynamics.codegen.traced import crba as t_crba
from lie_dynamics.codegen.traced import derivatives as t_der
from lie_dynamics.codegen.traced import jacobian as t_jac
from lie_dynamics.codegen.traced import regressor as t_reg
from lie_dynamics.codegen.traced import rnea as t_rnea
from dyn_cases import case_urdf as _xml, quiet_load as _load, rel_max as _rel
from oracle import Oracle

HERE = os.path.dirname(os.path.abspath(__file__))
ARM = os.path.join(HERE, '..', 'lie_dynamics', 'data', 'arm7.urdf')
REAL = ['ur_description/urdf/ur5_robot.urdf', 'talos_data/robots/talos_left_arm.urdf']
TOL = 1e-12
SPECS = [t_rnea.INVERSE_DYNAMICS, t_rnea.GRAVITY, t_rnea.MOMENTUM, t_crba.MASS_MATRIX, t_chol.FORWARD_DYNAMICS,
         t_aba.ABA, t_aba.ABA_RIGID, t_der.INVERSE_DYNAMICS_DERIVATIVES, t_der.CORIOLIS,
         t_der.FORWARD_DYNAMICS_DERIVATIVES, t_reg.REGRESSOR]

pytestmark = pytest.mark.skipif(native.module() is None, reason='no working C compiler')


def _states(model, N, seed=0):
    rng = np.random.default_rng(seed)
    return [np.ascontiguousarray(x) for x in rng.uniform(-2, 2, (3, N, model.n))]


def _python_outputs(model, spec, arrays):
    """The Python float kernel's outputs (N, n_out) for the same per-state arrays."""
    vals = runtime.evaluate(model, spec, arrays, 'loop')
    scatter = runtime.kernel(model, spec).scatter
    if scatter is None:
        return vals
    idx, size = scatter
    full = np.zeros((len(vals), size))
    full[:, idx] = vals
    return full


@pytest.mark.parametrize('name', ['arm7', 'mixed_types', 'mimic'] + REAL)
def test_every_family_equals_the_python_kernels(name):
    model = _load(_xml(name))
    q, qd, qdd = _states(model, 6)
    for spec in SPECS:
        nk = runtime.native(model, spec)
        if spec in (t_aba.ABA, t_aba.ABA_RIGID) and not t_aba.supports(model):
            assert nk is None
            continue
        if nk is None:   # only a kernel above the size cap of the C compiler stays Python
            t = spec.build(runtime.frames(model))
            assert len(t.graph.live(t.outputs)[1]) > runtime.THRESHOLDS['native_nodes'], spec.name
            continue
        k = runtime.kernel(model, spec).n_state
        args = [q, qd, qdd][:k]
        ref = _python_outputs(model, spec, args)
        batch = nk(*args)
        assert batch is not None, spec.name
        batch = batch.reshape(len(q), -1)
        assert _rel(batch, ref[:, :batch.shape[1]]) <= TOL, spec.name
        for i in (0, 5):
            one = nk(*[a[i] for a in args])
            assert _rel(one.reshape(-1), ref[i, :batch.shape[1]]) <= TOL, spec.name


def test_kernels_cut_into_parts_equal_the_python_kernels_bit_for_bit(tmp_path, monkeypatch):
    """Kernels above THRESHOLDS['native_part'] nodes are cut into functions that pass values
    through the slots of one array, compiled as translation units in parallel and linked
    (crender.py, native.py): their results are the Python float kernel's to the bit. The
    arm at the default cut (its derivative kernels are cut), and a tree of every joint type
    cut into parts of 40 nodes (hundreds of functions, slots reused across many parts; the
    regressor's outputs scattered)."""
    monkeypatch.setenv('LIE_DYNAMICS_CACHE_DIR', str(tmp_path / 'cache'))
    specs = {'arm7': SPECS, 'mixed_types': [t_rnea.INVERSE_DYNAMICS, t_chol.FORWARD_DYNAMICS,
                                            t_der.INVERSE_DYNAMICS_DERIVATIVES, t_reg.REGRESSOR]}
    for name, part in (('arm7', runtime.THRESHOLDS['native_part']), ('mixed_types', 40)):
        monkeypatch.setitem(runtime.THRESHOLDS, 'native_part', part)
        runtime.clear()
        model = _load(_xml(name))
        q, qd, qdd = _states(model, 5, seed=9)
        cut = []
        for spec in specs[name]:
            nk = runtime.native(model, spec)
            assert nk is not None, spec.name
            trace = spec.build(runtime.frames(model))
            if len(trace.graph.live(trace.outputs)[1]) > 2 * part:
                cut.append(spec.name)
            args = [q, qd, qdd][:runtime.kernel(model, spec).n_state]
            ref = _python_outputs(model, spec, args)
            got = nk(*args).reshape(len(q), -1)
            assert np.array_equal(got, ref[:, :got.shape[1]]), spec.name
            assert np.array_equal(nk(*[a[3] for a in args]).reshape(-1), got[3]), spec.name
        assert 'inverse_dynamics_derivatives' in cut, name
    runtime.clear()


@pytest.mark.parametrize('name', ['arm7', 'mixed_types'] + REAL)
def test_native_against_pinocchio(name):
    xml = _xml(name)
    model = _load(xml)
    oracle = Oracle(xml, joints=model.joint_names)
    q, qd, qdd = _states(model, 4, seed=1)
    tau = model.inverse_dynamics(q, qd, qdd)
    g, M = model.gravity(q), model.mass_matrix(q)
    fd, fd_aba = model.forward_dynamics(q, qd, qdd), model.forward_dynamics(q, qd, qdd, method='aba')
    dq, dv = model.inverse_dynamics_derivatives(q, qd, qdd)
    C = model.coriolis_matrix(q, qd, method='recursive')
    Minv = model.forward_dynamics_derivatives(q, qd, qdd)[2]
    Y = model.regressor(q, qd, qdd)
    pi = model.inertial_parameters()
    for i in range(len(q)):
        single = model.inverse_dynamics(q[i], qd[i], qdd[i])
        ref = oracle.rnea(q[i], qd[i], qdd[i])
        assert _rel(single, ref) <= TOL and _rel(tau[i], ref) <= TOL
        assert _rel(model.gravity(q[i]), oracle.gravity(q[i])) <= TOL and _rel(g[i], oracle.gravity(q[i])) <= TOL
        Mr = oracle.crba(q[i])
        assert _rel(model.mass_matrix(q[i]), Mr) <= TOL and _rel(M[i], Mr) <= TOL
        a = oracle.aba(q[i], qd[i], qdd[i])
        assert _rel(fd[i], a) <= 1e-10 and _rel(fd_aba[i], a) <= 1e-10   # M^-1: its conditioning
        assert _rel(model.forward_dynamics(q[i], qd[i], qdd[i]), a) <= 1e-10
        rdq, rdv = oracle.rnea_derivatives(q[i], qd[i], qdd[i])
        assert _rel(dq[i], rdq) <= TOL and _rel(dv[i], rdv) <= TOL
        assert _rel(C[i], 0.5 * rdv) <= TOL or name == 'mixed_types'   # 1/2 dtau/dqd
        assert _rel(Minv[i], np.linalg.inv(Mr)) <= 1e-10
        assert _rel(Y[i] @ pi, ref) <= TOL


@pytest.mark.parametrize('name', ['arm7'] + REAL)
def test_jacobians_against_the_python_kernels_and_pinocchio(name):
    xml = _xml(name)
    model = _load(xml)
    oracle = Oracle(xml, joints=model.joint_names)
    q, qd, _ = _states(model, 5, seed=7)
    links = [ln for ln, (b, _) in model.link_frames.items() if b >= 0][-2:]
    for link in links:
        b = model.link_frames[link][0]
        for point in (None, [0.05, -0.1, 0.2]):
            for frame in t_jac.FRAMES:
                for kind, fn, args in (('jacobian', model.jacobian, (q,)),
                                       ('jacobian_dot', model.jacobian_dot_times_qd, (q, qd))):
                    assert runtime.native(model, t_jac.spec(kind, frame, b)) is not None, (kind, frame)
                    py = getattr(jac, 'jacobian' if kind == 'jacobian' else 'jacobian_dot_times_qd')(
                        model, *args, link, frame, point, mode='loop')
                    batch = fn(*args, link, frame, point)
                    assert _rel(batch, py) <= TOL, (link, frame, kind)
                    for i in (0, 4):
                        one = fn(*(a[i] for a in args), link, frame, point)
                        assert one.shape == py[i].shape and _rel(one, py[i]) <= TOL
                        if kind == 'jacobian':
                            ref = oracle.frame_jacobian(q[i], link, frame, point)
                        else:
                            ref = oracle.frame_classical_acceleration(q[i], qd[i], 0 * qd[i], link, frame, point)
                        assert _rel(one, ref) <= TOL and _rel(batch[i], ref) <= TOL, (link, frame, kind)


def test_jacobians_compile_to_c_and_fall_back(tmp_path, monkeypatch):
    """A fresh cache: the first calls compile the six kernels of a link (three frames, J and J̇q̇);
    with the native backend off, the same results from the Python kernels."""
    monkeypatch.setenv('LIE_DYNAMICS_CACHE_DIR', str(tmp_path / 'cache'))
    runtime.clear()
    model = _load(_xml('arm7'))
    q, qd, _ = _states(model, 3, seed=8)
    before = native.compile_count()
    got = [(model.jacobian(q[0], 'tool0', f), model.jacobian_dot_times_qd(q, qd, 'tool0', f, [0.1, 0.0, 0.0]))
           for f in t_jac.FRAMES]
    assert native.compile_count() == before + 6
    monkeypatch.setenv('LIE_DYNAMICS_NATIVE', '0')
    off = _load(_xml('arm7'))
    b = off.link_frames['tool0'][0]
    assert runtime.native(off, t_jac.spec('jacobian', 'local', b)) is None
    for f, (J, a) in zip(t_jac.FRAMES, got, strict=True):
        assert _rel(off.jacobian(q[0], 'tool0', f), J) <= TOL
        assert _rel(off.jacobian_dot_times_qd(q, qd, 'tool0', f, [0.1, 0.0, 0.0]), a) <= TOL
    with pytest.raises(ValueError, match='unknown link'):
        model.jacobian(q[0], 'no_such_link')
    monkeypatch.delenv('LIE_DYNAMICS_NATIVE')
    for bad, match in ((q[0][:-1], 'q must have shape'), (np.full(model.n, np.nan), 'non-finite')):
        with pytest.raises(ValueError, match=match):
            model.jacobian(bad, 'tool0')
    with pytest.raises(ValueError, match='qd has 1 states'):
        model.jacobian_dot_times_qd(q, qd[0], 'tool0')
    with pytest.raises(ValueError, match='point must have shape'):
        model.jacobian(q, 'tool0', point=[0.0, 1.0])
    runtime.clear()


def test_parameters_change_without_recompiling():
    xml = _xml('arm7')
    model = _load(xml)
    q, qd, qdd = _states(model, 50, seed=2)
    model.inverse_dynamics(q, qd, qdd)
    model.gravity(q[0])
    model.forward_dynamics(q, qd, qdd)
    before = native.compile_count()
    link = [nm for nm, (b, _) in model.link_frames.items() if b >= 0][-1]
    model.set_payload(link, 1.5, [0.05, 0.0, 0.1], [0.01, 0.0, 0.0, 0.02, 0.0, 0.03])
    model.set_gravity([0.5, -1.0, -9.0])
    for s in (slice(None), 0):
        args = [x[s].reshape(-1, model.n) for x in (q, qd, qdd)]
        ref = runtime.evaluate(model, t_rnea.INVERSE_DYNAMICS, args, 'loop')
        assert _rel(model.inverse_dynamics(q[s], qd[s], qdd[s]).reshape(-1, model.n), ref) <= TOL
        ref = runtime.evaluate(model, t_rnea.GRAVITY, args[:1], 'loop')
        assert _rel(model.gravity(q[s]).reshape(-1, model.n), ref) <= TOL
        ref = runtime.evaluate(model, t_chol.FORWARD_DYNAMICS, args, 'loop')[:, :model.n]
        assert _rel(model.forward_dynamics(q[s], qd[s], qdd[s]).reshape(-1, model.n), ref) <= TOL
    assert native.compile_count() == before
    part = _load(xml, joints=model.joint_names[::2])
    qq = _states(part, 20, seed=3)
    part.inverse_dynamics(*qq)
    compiled = native.compile_count()
    part.set_locked({j: 0.2 + 0.1 * k for k, j in enumerate(part.locked_joint_names)})
    oracle = Oracle(xml, joints=part.joint_names, locked=part.locked_values)
    for i in range(3):
        assert _rel(part.inverse_dynamics(qq[0][i], qq[1][i], qq[2][i]),
                    oracle.rnea(qq[0][i], qq[1][i], qq[2][i])) <= TOL
    assert native.compile_count() == compiled


def test_out_buffers():
    model = _load(_xml('arm7'))
    n = model.n
    q, qd, qdd = _states(model, 5, seed=4)
    cases = [(model.inverse_dynamics, (q, qd, qdd), (n,)), (model.gravity, (q,), (n,)),
             (model.mass_matrix, (q,), (n, n)), (model.forward_dynamics, (q, qd, qdd), (n,))]
    for fn, args, shape in cases:
        for single in (True, False):
            a = [x[0] for x in args] if single else list(args)
            want = fn(*a)
            buf = np.full(shape if single else (len(q),) + shape, np.nan)
            got = fn(*a, out=buf)
            assert got is buf and _rel(buf, want) <= TOL
            lists = [x.tolist() for x in a]                       # the validating path
            buf2 = np.full(buf.shape, np.nan)
            assert fn(*lists, out=buf2) is buf2 and _rel(buf2, want) <= TOL
            for bad in (np.empty(buf.shape, np.float32), np.empty(buf.shape[:-1] + (n + 1,)), buf.tolist()):
                with pytest.raises(ValueError, match='out must be'):
                    fn(*a, out=bad)
    if model.n:
        with pytest.raises(ValueError, match='qd'):
            bad = qd[0].copy()
            bad[1] = np.nan
            model.inverse_dynamics(q[0], bad, qdd[0])


def test_gil_is_released_in_batches():
    model = _load(_xml('arm7'))
    nk = runtime.native(model, t_rnea.INVERSE_DYNAMICS)
    Q = np.random.default_rng(5).uniform(-1, 1, (100_000, model.n))
    nk(Q[:10], Q[:10], Q[:10])
    stamps, stop = [], threading.Event()

    def ticker():
        while not stop.is_set():
            time.sleep(0.0005)           # releases the GIL; recording needs it again
            stamps.append(time.perf_counter())
    th = threading.Thread(target=ticker)
    th.start()
    try:
        time.sleep(0.01)
        t0 = time.perf_counter()
        out = nk(Q, Q, Q)
        t1 = time.perf_counter()
    finally:
        stop.set()
        th.join()
    inside = [s for s in stamps if t0 < s < t1]
    # holding the GIL, at most the stamp of one forced switch could fall inside
    assert out is not None and len(inside) >= 5, (len(inside), t1 - t0)


# ---------------------------------------------------------------- switch, fallback, cache (subprocesses)
PROBE = textwrap.dedent('''
    import warnings, numpy as np
    warnings.simplefilter('always')
    from lie_dynamics import load_urdf
    from lie_dynamics.codegen import native, runtime
    from lie_dynamics.codegen.traced import rnea
    m = load_urdf({path!r})
    q = np.linspace(-1, 1, m.n)
    with warnings.catch_warnings(record=True) as w:
        warnings.simplefilter('always')
        tau = m.inverse_dynamics(q, q, q)
        tau2 = m.gravity(q)
    print(repr(tau.tolist()), native.compile_count(), runtime.native(m, rnea.INVERSE_DYNAMICS) is not None,
          sum(issubclass(x.category, RuntimeWarning) for x in w))
    for x in w:
        print('WARNING', x.message)
''')


def _probe(env_extra, tmp_path, path=ARM, check=True):
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([os.path.join(HERE, '..'), os.environ.get('PYTHONPATH', '')]))
    env['LIE_DYNAMICS_CACHE_DIR'] = str(tmp_path / 'cache')
    env.update(env_extra)
    r = subprocess.run([sys.executable, '-c', PROBE.format(path=path)], env=env, capture_output=True, text=True,
                       timeout=300)
    if check:
        assert r.returncode == 0, r.stderr
    return r


def _reference_tau():
    model = _load(_xml('arm7'))
    q = np.linspace(-1, 1, model.n)
    return np.array(runtime.evaluate(model, t_rnea.INVERSE_DYNAMICS, [q[None]] * 3, 'loop')[0])


def _parse(r):
    first = r.stdout.splitlines()[0]
    lst, rest = first.split(']')
    count, on, warned = rest.split()
    return np.array(eval(lst + ']')), int(count), on == 'True', int(warned)   # noqa: S307 (our own output)


def test_switch_off(tmp_path):
    tau, count, on, warned = _parse(_probe({'LIE_DYNAMICS_NATIVE': '0'}, tmp_path))
    assert not on and count == 0 and warned == 0
    assert _rel(tau, _reference_tau()) <= TOL
    assert not (tmp_path / 'cache').exists()


def test_failing_compiler_under_auto_and_require(tmp_path):
    r = _probe({'LIE_DYNAMICS_NATIVE': 'auto', 'CC': '/bin/false'}, tmp_path)
    tau, _, on, warned = _parse(r)
    assert not on and warned == 1 and '/bin/false' in r.stdout
    assert _rel(tau, _reference_tau()) <= TOL
    r = _probe({'LIE_DYNAMICS_NATIVE': 'require', 'CC': '/bin/false'}, tmp_path, check=False)
    assert r.returncode != 0 and 'NativeUnavailable' in r.stderr and '/bin/false' in r.stderr
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([os.path.join(HERE, '..'), os.environ.get('PYTHONPATH', '')]),
               LIE_DYNAMICS_CACHE_DIR=str(tmp_path / 'cache'), LIE_DYNAMICS_NATIVE='require', CC='/bin/false')
    again = textwrap.dedent(f'''
        import numpy as np
        from lie_dynamics import load_urdf
        from lie_dynamics.codegen import native
        m = load_urdf({ARM!r})
        for _ in range(2):   # every call raises, not only the first
            try:
                m.gravity(np.zeros(m.n))
            except native.NativeUnavailable as e:
                print('raised', '/bin/false' in str(e))
    ''')
    r = subprocess.run([sys.executable, '-c', again], env=env, capture_output=True, text=True, timeout=300)
    assert r.stdout.split() == ['raised', 'True', 'raised', 'True'], r.stderr
    r = _probe({'LIE_DYNAMICS_NATIVE': 'require', 'CC': 'no-such-compiler-here'}, tmp_path, check=False)
    assert r.returncode != 0 and 'no-such-compiler-here' in r.stderr


def test_cache_reuse_and_corrupted_files(tmp_path):
    ref = _reference_tau()
    tau, count, on, _ = _parse(_probe({}, tmp_path))
    assert on and count >= 2 and _rel(tau, ref) <= TOL     # the call module and the kernels
    tau, count, on, _ = _parse(_probe({}, tmp_path))
    assert on and count == 0 and _rel(tau, ref) <= TOL     # all from the cache
    libs = sorted((tmp_path / 'cache').glob('*.so'), key=lambda p: p.stat().st_size)
    assert len(libs) >= 3 and not list((tmp_path / 'cache').glob('build-*'))
    victim = libs[-1]
    data = victim.read_bytes()
    victim.write_bytes(data[:len(data) // 2])              # truncated
    tau, count, on, _ = _parse(_probe({}, tmp_path))
    assert on and count == 1 and _rel(tau, ref) <= TOL
    victim.write_bytes(libs[0].read_bytes())               # a foreign (valid) library under its name
    tau, count, on, _ = _parse(_probe({}, tmp_path))
    assert on and count == 1 and _rel(tau, ref) <= TOL


def test_read_only_cache_compiles_in_a_temporary_folder(tmp_path):
    blocker = tmp_path / 'cache'
    blocker.write_text('not a folder')                     # the cache cannot be created
    tau, count, on, _ = _parse(_probe({}, tmp_path))
    assert on and count >= 2 and _rel(tau, _reference_tau()) <= TOL


def test_two_processes_compiling_at_once(tmp_path):
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([os.path.join(HERE, '..'), os.environ.get('PYTHONPATH', '')]),
               LIE_DYNAMICS_CACHE_DIR=str(tmp_path / 'cache'))
    procs = [subprocess.Popen([sys.executable, '-c', PROBE.format(path=ARM)], env=env, stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE, text=True) for _ in range(2)]
    ref = _reference_tau()
    for p in procs:
        out, err = p.communicate(timeout=300)
        assert p.returncode == 0, err
        tau, _, on, warned = _parse(subprocess.CompletedProcess([], 0, out, err))
        assert on and warned == 0 and _rel(tau, ref) <= TOL
    assert not list((tmp_path / 'cache').glob('build-*'))


def test_cache_eviction_removes_the_least_recently_used(tmp_path):
    """evict: above the bound, the oldest libraries go until 3/4 of it remain, never a kept one;
    abandoned build folders go, other files stay."""
    now = 1e9
    paths = []
    for i in range(5):
        p = tmp_path / f'k{i}.so'
        p.write_bytes(b'x' * 1000)
        os.utime(p, (now - 100 + i, now - 100 + i))   # k0 the least recently used
        paths.append(p)
    (tmp_path / 'notes.txt').write_bytes(b'y' * 10000)
    old, new = tmp_path / 'build-old', tmp_path / 'build-new'
    old.mkdir()
    new.mkdir()
    os.utime(old, (now - 2 * native.STALE_BUILD_S, now - 2 * native.STALE_BUILD_S))
    os.utime(new, (now - 10, now - 10))
    assert native.evict(tmp_path, 6000, now=now) == [str(old)]          # 5000 bytes: under the bound
    removed = native.evict(tmp_path, 3000, keep=(paths[0],), now=now)
    assert removed == [str(paths[1]), str(paths[2]), str(paths[3])]       # 5000 -> 2000 <= 2250
    assert sorted(p.name for p in tmp_path.iterdir()) == ['build-new', 'k0.so', 'k4.so', 'notes.txt']


def test_cache_bound_from_the_environment(tmp_path, monkeypatch):
    """LIE_DYNAMICS_CACHE_MAX_MB bounds the folder after every compile: with a bound below one
    library only the newest stays, and the results are unchanged; a cache hit counts as a use."""
    for bad in ('not a number', '0', '-5', 'nan', 'inf', ''):   # unusable: the default bound
        monkeypatch.setenv('LIE_DYNAMICS_CACHE_MAX_MB', bad)
        assert native.cache_max_bytes() == int(native.CACHE_MAX_MB * 2 ** 20), bad
    monkeypatch.setenv('LIE_DYNAMICS_CACHE_MAX_MB', '1.5')
    assert native.cache_max_bytes() == int(1.5 * 2 ** 20)
    ref = _reference_tau()
    tau, count, on, _ = _parse(_probe({'LIE_DYNAMICS_CACHE_MAX_MB': '0.0001'}, tmp_path))
    assert on and count >= 2 and _rel(tau, ref) <= TOL
    libs = list((tmp_path / 'cache').glob('*.so'))
    assert len(libs) == 1
    os.utime(libs[0], (1e9, 1e9))
    _parse(_probe({}, tmp_path))                       # default bound: nothing evicted, the survivor used
    assert libs[0].exists() and libs[0].stat().st_mtime > 1e9 + 1


def test_set_jobs_bounds_the_compiler_processes_of_a_cut_kernel(tmp_path, monkeypatch):
    """A kernel cut into parts compiles as one object per usable core, or at most set_jobs(n)
    (the node's build process leaves a core to the control path): counted through a $CC that
    logs each compiler run. Invalid counts are refused."""
    log = tmp_path / 'cc.log'
    cc = tmp_path / 'cc'
    cc.write_text(f'#!/bin/sh\necho "$@" >> {log}\nexec {" ".join(native.compiler())} "$@"\n')
    cc.chmod(0o755)
    monkeypatch.setenv('CC', str(cc))
    monkeypatch.setitem(runtime.THRESHOLDS, 'native_part', 40)
    model = _load(_xml('arm7'))
    try:
        for k, jobs in enumerate((1, None)):
            monkeypatch.setenv('LIE_DYNAMICS_CACHE_DIR', str(tmp_path / f'cache{k}'))
            native.set_jobs(jobs)
            runtime.clear()
            log.write_text('')
            assert runtime.native(model, t_rnea.INVERSE_DYNAMICS) is not None
            runs = log.read_text().splitlines()
            objects = [ln for ln in runs if ' -c ' in f' {ln} ']
            if jobs == 1 or native.usable_cores() == 1:
                assert len(runs) == 1 and not objects, runs   # one process, no separate link
            else:
                assert 2 <= len(objects) <= native.usable_cores() and len(runs) == len(objects) + 1, runs
    finally:
        native.set_jobs(None)
        runtime.clear()
    for bad in (0, -1, 1.5, '2'):
        with pytest.raises(ValueError, match='compiler jobs'):
            native.set_jobs(bad)
