"""Stability map: where each method stops being accurate, found by scanning towards the trouble.

    python -m bench.stability [--quick] [--out DIR]

Five scans, each against an extended-precision reference (numpy.longdouble, bench/reference.py),
each reporting the boundary where a method fails by the stated criterion:

1. exp/log of SO(3) and SE(3) as theta -> 0 and theta -> pi: lie_dynamics.se3 against the
   textbook closed forms ("naive") and Modern Robotics. Fails: error > 1e-12 (exp: max entry
   error of the matrix, which has entries of size 1; log: relative error of the twist).
2. Error growth with chain length (2 to 200 joints), RNEA in float64 (every path) and float32.
   Fails: error > 1000 ulps of the dtype (2.2e-13 in float64, 1.2e-4 in float32).
3. Forward dynamics with an ill-conditioned mass matrix: by scale (the distal/proximal mass
   ratio of the arm from 1 to 1e-10 and on to 1e-300) and by geometry (two joints coaxial up to
   a tilt, a massless link between; tilt 0 is singular): Cholesky, ABA, explicit inverse,
   Pinocchio's ABA, on torques of a known moderate motion. Fails: relative error in qdd > 1e-6,
   or an exception (which is the right answer only where M is numerically singular).
4. Finite-difference step size against error (the V curve) for dtau/dq and dtau/dqd, with the
   analytic derivatives, Pinocchio and the complex step. Fails: relative error > 1e-6.
5. Energy drift over 10 s of free motion of the bundled arm without damping, for explicit
   Euler, semi-implicit Euler, RK4 and the symplectic Lie-group midpoint rule
   (lie_dynamics/integrators.py), at several steps dt. Fails: max |E(t) - E(0)| over the run
   > 1% of the largest kinetic energy of the motion.

Writes stability.{md,csv,json} and stability_*.png. The CSV has one row per measured point:
scan, method, x_name, x, error, status.
"""
import argparse
import json
import os
import time

import numpy as np

from bench import common
from bench.common import rel_err
from bench.reference import LD, Generic, exp6_ld, ld_cholesky_solve
from bench.stability_charts import RATIO, TILT, charts

TOL_EXPLOG = 1e-12
TOL_FD = 1e-6
TOL_DERIV = 1e-6
TOL_ENERGY = 1e-2
PI_LD = np.longdouble('3.14159265358979323846264338327950288')


def _ulps_tol(dtype):
    return 1e3 * float(np.finfo(dtype).eps)


# ------------------------------------------------------------------ 1. exp / log
def _unit_rows(x):
    return x / np.linalg.norm(x, axis=-1, keepdims=True)


def naive_exp3(w):
    """Rodrigues with the unit axis w/theta: R = I + sin t [u] + (1 - cos t)[u]^2."""
    from lie_dynamics.spatial import hat3
    t = np.linalg.norm(w, axis=-1)[..., None, None]
    K = hat3(w) / t
    return np.eye(3) + np.sin(t) * K + (1 - np.cos(t)) * K @ K


def naive_exp6(V):
    from lie_dynamics.spatial import hat3
    w, v = V[..., :3], V[..., 3:]
    t = np.linalg.norm(w, axis=-1)[..., None, None]
    K = hat3(w) / t
    T = np.zeros(V.shape[:-1] + (4, 4))
    T[..., :3, :3] = np.eye(3) + np.sin(t) * K + (1 - np.cos(t)) * K @ K
    G = np.eye(3) * t + (1 - np.cos(t)) * K + (t - np.sin(t)) * K @ K     # acts on v / theta
    T[..., :3, 3] = np.einsum('...ij,...j->...i', G, v / t[..., 0])
    T[..., 3, 3] = 1
    return T


def naive_log3(R):
    """theta = arccos((tr R - 1)/2), w = theta / (2 sin theta) vee(R - R^T)."""
    from lie_dynamics.spatial import vee3
    t = np.arccos((np.trace(R, axis1=-2, axis2=-1) - 1) / 2)
    return (t / (2 * np.sin(t)))[..., None] * vee3(R - np.swapaxes(R, -1, -2))


def naive_log6(T):
    from lie_dynamics.spatial import hat3
    w = naive_log3(T[..., :3, :3])
    t = np.linalg.norm(w, axis=-1)[..., None, None]
    K = hat3(w) / t
    Ginv = np.eye(3) - t / 2 * K + (1 - t / 2 / np.tan(t / 2)) * K @ K   # v = theta G(theta)^-1 p
    return np.concatenate([w, np.einsum('...ij,...j->...i', Ginv, T[..., :3, 3])], axis=-1)


def _mr_fns():
    import modern_robotics as mr

    def loop(f):
        return lambda X: np.array([f(x) for x in X])
    return dict(
        exp3=loop(lambda w: mr.MatrixExp3(mr.VecToso3(w))),
        log3=loop(lambda R: mr.so3ToVec(mr.MatrixLog3(R))),
        exp6=loop(lambda V: mr.MatrixExp6(mr.VecTose3(V))),
        log6=loop(lambda T: mr.se3ToVec(mr.MatrixLog6(T))))


def scan_explog(quick):
    from lie_dynamics import spatial as se3
    impls = {'lie_dynamics': dict(exp3=se3.exp3, log3=se3.log3, exp6=se3.exp6, log6=se3.log6),
             'naive closed form': dict(exp3=naive_exp3, log3=naive_log3, exp6=naive_exp6, log6=naive_log6),
             'Modern Robotics': _mr_fns()}
    rng = np.random.default_rng(1)
    k = 3 if quick else 8
    u = _unit_rows(rng.normal(size=(k, 3))).astype(LD)
    v = _unit_rows(rng.normal(size=(k, 3))).astype(LD)
    dist = np.logspace(-16, 0, 17 if quick else 49)
    rows = []
    for where in ('0', 'pi'):
        ds = dist if where == '0' else dist[dist >= 1e-15]   # pi - 1e-16 is pi in float64
        for d in ds:
            theta = LD(d) if where == '0' else PI_LD - LD(d)
            w = theta * u
            T_ref = exp6_ld(w, v)
            R_ref = T_ref[..., :3, :3]
            Tin = T_ref.astype(float)       # what a caller would hold
            V_true = np.concatenate([w, v], axis=-1)
            w64 = w.astype(float)
            V64 = V_true.astype(float)
            for impl, f in impls.items():
                with np.errstate(all='ignore'):
                    errs = dict(
                        exp3=rel_err(f['exp3'](w64), R_ref),
                        exp6=rel_err(f['exp6'](V64), T_ref),
                        log3=rel_err(f['log3'](Tin[..., :3, :3]), w),
                        log6=rel_err(f['log6'](Tin), V_true))
                for fn, e in errs.items():
                    rows.append(dict(scan='explog', method=f'{impl} {fn}', x_name=f'distance to theta={where}',
                                     x=float(d), error=e, status='ok' if e <= TOL_EXPLOG else 'fail', where=where))
    # theta = 0 exactly: the series must return the identity and a zero twist
    at_zero = {}
    for impl, f in impls.items():
        with np.errstate(all='ignore'):
            R0, T0 = f['exp3'](np.zeros((1, 3))), f['exp6'](np.zeros((1, 6)))
            w0, V0 = f['log3'](np.eye(3)[None]), f['log6'](np.eye(4)[None])
        at_zero[impl] = bool(np.allclose(R0, np.eye(3), 0, 0) and np.allclose(T0, np.eye(4), 0, 0)
                             and np.all(w0 == 0) and np.all(V0 == 0))
    bounds = {}
    for where in ('0', 'pi'):
        for m in dict.fromkeys(r['method'] for r in rows):
            pts = [r for r in rows if r['method'] == m and r['where'] == where]
            bounds[f'{m} near {where}'] = common.boundary([r['x'] for r in pts], [r['error'] for r in pts], TOL_EXPLOG)
    worst = {f'{m} near {w}': max(r['error'] for r in rows if r['method'] == m and r['where'] == w)
             for m in dict.fromkeys(r['method'] for r in rows) for w in ('0', 'pi')}
    return dict(rows=rows, boundaries=bounds, exact_at_zero=at_zero, worst=worst, tol=TOL_EXPLOG)


# ------------------------------------------------------------------ 2. chain length
def scan_chain_length(quick):
    from lie_dynamics import load_urdf
    from lie_dynamics.algorithms import rnea
    sizes = (2, 10, 30) if quick else (2, 5, 10, 20, 50, 100, 150, 200)
    S = 3 if quick else 8
    rows = []
    for n in sizes:
        xml = common.robot_urdf(n, seed=1000 + n)
        model = load_urdf(xml)
        pin, pm, pd = common.pinocchio_model(xml, model)
        q, qd, qdd = common.random_states(model, S, seed=n)
        ref = Generic(model, LD).inverse_dynamics(q, qd, qdd)
        big = 64   # a batch large enough for the generated row kernels
        outs = {
            'lie_dynamics single state': np.array([model.inverse_dynamics(q[i], qd[i], qdd[i]) for i in range(S)]),
            'lie_dynamics batched': model.inverse_dynamics(*(np.resize(a, (big, n)) for a in (q, qd, qdd)))[:S],
            'lie_dynamics vectorised path': rnea.inverse_dynamics_vectorized(model, q, qd, qdd),
            'Pinocchio': np.array([pin.rnea(pm, pd, q[i], qd[i], qdd[i]) for i in range(S)]),
            'bench RNEA float64': Generic(model, np.float64).inverse_dynamics(q, qd, qdd),
            'bench RNEA float32': Generic(model, np.float32).inverse_dynamics(
                q.astype(np.float32), qd.astype(np.float32), qdd.astype(np.float32)),
        }
        for m, o in outs.items():
            dt = np.float32 if o.dtype == np.float32 else np.float64
            e = float(np.max(rel_err(o, ref, axis=1)))
            rows.append(dict(scan='chain_length', method=m, x_name='joints', x=n, error=e,
                             status='ok' if e <= _ulps_tol(dt) else 'fail', dtype=np.dtype(dt).name))
    fits, first_fail = {}, {}
    for m in dict.fromkeys(r['method'] for r in rows):
        pts = [r for r in rows if r['method'] == m]
        xs, es = np.array([r['x'] for r in pts], float), np.array([r['error'] for r in pts])
        sel = xs >= 5
        fits[m] = float(np.polyfit(np.log(xs[sel]), np.log(es[sel]), 1)[0]) if sel.sum() >= 2 else float('nan')
        bad = [r['x'] for r in pts if r['status'] != 'ok']
        first_fail[m] = min(bad) if bad else None
    return dict(rows=rows, growth_exponent=fits, first_failing_n=first_fail,
                tol=dict(float64=_ulps_tol(np.float64), float32=_ulps_tol(np.float32)))


# ------------------------------------------------------------------ 3. ill-conditioned forward dynamics
def _fd_case(xml, S, x_name, x, rows, meta):
    import warnings

    from lie_dynamics import InertiaWarning, load_urdf
    with warnings.catch_warnings():
        warnings.simplefilter('ignore', InertiaWarning)  # ill-conditioned on purpose
        model = load_urdf(xml)
    pin, pm, pd = common.pinocchio_model(xml, model)
    q, qd, qdd0 = common.random_states(model, S, seed=3)
    tau = model.inverse_dynamics(q, qd, qdd0)   # torques of a known, moderate motion
    G = Generic(model, LD)
    with np.errstate(all='ignore'):
        ref = G.forward_dynamics(q, qd, tau)                                    # longdouble ABA
        ref_chol = ld_cholesky_solve(G.mass_matrix(q), tau.astype(LD) - G.coriolis_term(q, qd) - G.gravity(q))
    M = model.mass_matrix(q)
    ev = np.linalg.eigvalsh(M)
    meta.append(dict(x_name=x_name, x=x, cond=float(np.max(ev[:, -1] / np.maximum(np.abs(ev[:, 0]), 1e-300))),
                     reference_spread=float(np.max(rel_err(ref_chol, ref, axis=1)))))

    def explicit_inverse():
        h = model.inverse_dynamics(q, qd, np.zeros_like(q))
        return np.einsum('nij,nj->ni', np.linalg.inv(M), tau - h)
    cands = {'Cholesky': lambda: model.forward_dynamics(q, qd, tau),
             'ABA O(n)': lambda: model.forward_dynamics(q, qd, tau, method='aba'),
             'explicit inverse M^-1': explicit_inverse,
             'Pinocchio ABA': lambda: np.array([pin.aba(pm, pd, q[i], qd[i], tau[i]) for i in range(S)])}
    for m, f in cands.items():
        try:
            with np.errstate(all='ignore'):
                e = float(np.max(rel_err(f(), ref, axis=1)))
            status = 'ok' if e <= TOL_FD else 'fail'
        except (ValueError, np.linalg.LinAlgError) as exc:
            e, status = float('nan'), f'raised {type(exc).__name__}'
        rows.append(dict(scan='forward_dynamics', method=m, x_name=x_name, x=x, error=e, status=status))


def scan_forward_dynamics(quick):
    """Two kinds of ill-conditioning: by scale (the arm's masses graded down the chain) and by
    geometry (two nearly coaxial joints with a massless link between, common.near_coaxial_urdf)."""
    ratios = ([1.0, 1e-4, 1e-8, 1e-10, 1e-12, 1e-16] if quick else
              list(10.0 ** -np.arange(0, 10.5, 0.5)) + [1e-11, 1e-12, 1e-13, 1e-14, 1e-16, 1e-20, 1e-50, 1e-300])
    tilts = [1e-1, 1e-3, 1e-5, 1e-6, 0.0] if quick else list(10.0 ** -np.arange(1, 8.25, 0.25)) + [0.0]
    S = 3 if quick else 8
    base = common.arm_xml()
    rows, meta = [], []
    for r in ratios:
        _fd_case(common.scale_chain_masses(base, r), S, RATIO, r, rows, meta)
    for t in tilts:
        _fd_case(common.near_coaxial_urdf(t), S, TILT, t, rows, meta)
    bounds = {}
    for xn in (RATIO, TILT):
        for m in dict.fromkeys(r['method'] for r in rows):
            pts = [r for r in rows if r['method'] == m and r['x_name'] == xn]
            bad = [r['x'] for r in pts if r['status'] != 'ok']
            raised = [r['x'] for r in pts if r['status'].startswith('raised')]
            returned = [r['error'] for r in pts if not r['status'].startswith('raised')]
            bounds[f'{xn}/{m}'] = dict(
                first_failing=max(bad) if bad else None, raises_from=max(raised) if raised else None,
                inaccurate_without_raising=sorted((r['x'] for r in pts if r['status'] == 'fail'), reverse=True),
                worst_returned_error=max(returned) if returned else None)
    return dict(rows=rows, conditioning=meta, boundaries=bounds, tol=TOL_FD)


# ------------------------------------------------------------------ 4. finite-difference step
def scan_fd_step(quick):
    from bench.accuracy import finite_differences
    from lie_dynamics import load_urdf
    xml = common.arm_xml()
    model = load_urdf(xml)
    pin, pm, pd = common.pinocchio_model(xml, model)
    S = 2 if quick else 4
    q, qd, qdd = common.random_states(model, S, seed=4)
    dq, dv = Generic(model, np.clongdouble).derivatives(q, qd, qdd)
    ref = np.stack([dq, dv], axis=1)
    c128 = Generic(model, np.complex128)
    hs = np.logspace(-16, -1, 11 if quick else 31)
    rows = []

    def err(fn):
        return float(np.max(rel_err(np.array([fn(i) for i in range(S)]).reshape(S, -1), ref.reshape(S, -1), axis=1)))
    for h in hs:
        for m, central in (('forward differences', False), ('central differences', True)):
            e = err(lambda i: finite_differences(model, q[i], qd[i], qdd[i], central=central, h=h))
            rows.append(dict(scan='fd_step', method=m, x_name='step h', x=float(h), error=e,
                             status='ok' if e <= TOL_DERIV else 'fail'))
        e = err(lambda i: np.stack([d[0] for d in c128.derivatives(q[i], qd[i], qdd[i], h=h)]))
        rows.append(dict(scan='fd_step', method='complex step (bench RNEA)', x_name='step h', x=float(h), error=e,
                         status='ok' if e <= TOL_DERIV else 'fail'))
    const = {'analytic': lambda i: np.stack(model.inverse_dynamics_derivatives(q[i], qd[i], qdd[i])),
             'Pinocchio': lambda i: np.stack([a.copy() for a in
                                              pin.computeRNEADerivatives(pm, pd, q[i], qd[i], qdd[i])[:2]])}
    flat = {m: err(f) for m, f in const.items()}
    best = {}
    for m in dict.fromkeys(r['method'] for r in rows):
        pts = [r for r in rows if r['method'] == m]
        i = int(np.argmin([r['error'] for r in pts]))
        ok = [r['x'] for r in pts if r['status'] == 'ok']
        best[m] = dict(best_h=pts[i]['x'], best_error=pts[i]['error'],
                       usable_h=(min(ok), max(ok)) if ok else None)
    return dict(rows=rows, flat=flat, best=best, tol=TOL_DERIV)


# ------------------------------------------------------------------ 5. energy drift
def scan_energy(quick):
    from lie_dynamics import load_urdf
    from lie_dynamics.sim.demo import HOME
    from lie_dynamics.sim.arm import ArmSim
    model = load_urdf(common.arm_xml())
    duration = 0.5 if quick else 10.0
    dts = (5e-3, 2e-2) if quick else (2.5e-4, 5e-4, 1e-3, 2e-3, 5e-3, 1e-2, 2e-2, 5e-2)
    integrators = ('explicit_euler', 'semi_implicit_euler', 'rk4', 'lie_midpoint')
    costly = {'rk4': 1e-3, 'lie_midpoint': 1e-3}   # smallest dt run for the expensive ones (time budget)
    q0, qd0 = np.array(HOME), np.linspace(-1.0, 1.0, model.n)
    rows, traces, cost = [], {}, {}
    for dt in dts:
        steps = int(round(duration / dt))
        every = max(1, int(round(0.01 / dt)))
        for name in integrators:
            if dt < costly.get(name, 0.0) and not quick:
                continue
            sim = ArmSim(model, dt=dt, q0=q0, qd0=qd0, damping=False, limits=False, integrator=name)
            E0 = sim.energy()
            t, dE, ke = [0.0], [0.0], [model.kinetic_energy(sim.q, sim.qd)]
            status = 'ok'
            t0 = time.perf_counter()
            try:
                with np.errstate(all='ignore'):
                    for k in range(0, steps, every):
                        sim.step(min(every, steps - k))
                        if not (np.all(np.isfinite(sim.q)) and np.all(np.isfinite(sim.qd))):
                            raise ValueError('state is not finite')
                        t.append(sim.t)
                        dE.append(sim.energy() - E0)
                        ke.append(model.kinetic_energy(sim.q, sim.qd))
            except (ValueError, RuntimeError, np.linalg.LinAlgError) as exc:
                status = f'diverged at t = {sim.t:.2f} s ({type(exc).__name__})'
            cost[(name, dt)] = (time.perf_counter() - t0) / max(1, round(sim.t / dt))
            traces[(name, dt)] = (np.array(t), np.array(dE), np.array(ke))
            rows.append(dict(scan='energy', method=name, x_name='dt', x=dt, drift=float(np.max(np.abs(dE))),
                             status=status, us_per_step=cost[(name, dt)] * 1e6))
    # energy scale: the largest kinetic energy of the motion (RK4 at its smallest dt)
    ref_dt = min(dt for (n, dt) in traces if n == 'rk4')
    scale = float(np.max(traces[('rk4', ref_dt)][2]))
    for r in rows:
        r['error'] = r['drift'] / scale if r['status'] == 'ok' else float('inf')
        if r['status'] == 'ok' and r['error'] > TOL_ENERGY:
            r['status'] = 'fail'
    bounds = {}
    for name in integrators:
        ok = [r['x'] for r in rows if r['method'] == name and r['status'] == 'ok']
        bad = [r['x'] for r in rows if r['method'] == name and r['status'] != 'ok']
        bounds[name] = dict(largest_ok_dt=max(ok) if ok else None, smallest_failing_dt=min(bad) if bad else None)
    tr = {f'{n} dt={dt:g}': dict(t=v[0].tolist(), rel_dE=(v[1] / scale).tolist()) for (n, dt), v in traces.items()
          if dt == ref_dt}
    return dict(rows=rows, boundaries=bounds, energy_scale_J=scale, duration=duration, traces=tr, trace_dt=ref_dt,
                tol=TOL_ENERGY,
                q0=q0.tolist(), qd0=qd0.tolist())


# ------------------------------------------------------------------ driver and reports
SCANS = {'explog': scan_explog, 'chain_length': scan_chain_length, 'forward_dynamics': scan_forward_dynamics,
         'fd_step': scan_fd_step, 'energy': scan_energy}


def run(quick=False, out=None, scans=None):
    res = {}
    for name, fn in SCANS.items():
        if scans and name not in scans:
            continue
        t0 = time.perf_counter()
        res[name] = fn(quick)
        res[name]['seconds'] = time.perf_counter() - t0
    res['meta'] = dict(quick=quick, reference='numpy.longdouble, eps %.2g' % np.finfo(LD).eps)
    if out:
        write(res, out)
    return res


def _fmt(x):
    return '—' if x is None else f'{x:.0e}' if isinstance(x, float) else str(x)


def _range(b):
    return 'none on the grid' if b is None else f'{b[0]:.0e} … {b[1]:.0e}' if b[0] != b[1] else f'{b[0]:.0e}'


def markdown(res):
    L = ['# Stability map', '',
         'Reference: ' + res['meta']['reference'] + '. Boundaries are found on the scan grids.', '']
    e = res['explog']
    L += [f"## exp / log (fails: error > {e['tol']:.0e})", '',
          '| method | worst error near 0 | failing distance to 0 | worst error near π | failing distance to π |',
          '|---|---:|---:|---:|---:|']
    for m in dict.fromkeys(r['method'] for r in e['rows']):
        L.append(f"| {m} | {e['worst'][m + ' near 0']:.1e} | {_range(e['boundaries'][m + ' near 0'])} | "
                 f"{e['worst'][m + ' near pi']:.1e} | {_range(e['boundaries'][m + ' near pi'])} |")
    L += ['', 'Exact at θ = 0 (identity / zero twist, no NaN): ' +
          ', '.join(f'{k}: {"yes" if v else "no"}' for k, v in e['exact_at_zero'].items()), '']
    c = res['chain_length']
    sizes = sorted({r['x'] for r in c['rows']})
    L += [f"## RNEA error against chain length (fails: > 1000 ulps: float64 {c['tol']['float64']:.1e}, "
          f"float32 {c['tol']['float32']:.1e})", '',
          '| method | ' + ' | '.join(f'n={n}' for n in sizes) + ' | growth exponent | first failing n |',
          '|---|' + '---:|' * (len(sizes) + 2)]
    for m in dict.fromkeys(r['method'] for r in c['rows']):
        by = {r['x']: r['error'] for r in c['rows'] if r['method'] == m}
        L.append(f'| {m} | ' + ' | '.join(f'{by[n]:.1e}' for n in sizes) +
                 f" | {c['growth_exponent'][m]:.2f} | {_fmt(c['first_failing_n'][m])} |")
    f = res['forward_dynamics']
    methods = list(dict.fromkeys(r['method'] for r in f['rows']))
    for xn, what in ((RATIO, 'the distal/proximal mass ratio of the arm (ill-conditioned by scale)'),
                     (TILT, 'the tilt between two joint axes with a massless link between '
                            '(ill-conditioned by geometry)')):
        xs = sorted({r['x'] for r in f['rows'] if r['x_name'] == xn}, reverse=True)
        L += ['', f"## Forward dynamics against {what}; fails: error > {f['tol']:.0e} or raises", '',
              f'| {xn} | cond(M) | longdouble ABA vs Cholesky | ' + ' | '.join(methods) + ' |',
              '|---:|---:|---:|' + '---:|' * len(methods)]
        for x in xs:
            mt = next(m for m in f['conditioning'] if m['x'] == x and m['x_name'] == xn)
            cells = ['raises' if r['status'].startswith('raised') else f"{r['error']:.1e}"
                     for r in f['rows'] if r['x'] == x and r['x_name'] == xn]
            L.append(f"| {x:.0e} | {mt['cond']:.1e} | {mt['reference_spread']:.1e} | " + ' | '.join(cells) + ' |')
        L += ['', '| method | first failing | raises from | inaccurate without raising at | worst error returned |',
              '|---|---:|---:|---|---:|']
        for m in methods:
            b = f['boundaries'][f'{xn}/{m}']
            L.append(f"| {m} | {_fmt(b['first_failing'])} | {_fmt(b['raises_from'])} | "
                     f"{', '.join(f'{x:.0e}' for x in b['inaccurate_without_raising']) or '—'} | "
                     f"{_fmt(b['worst_returned_error'])} |")
    d = res['fd_step']
    L += ['', f"## Derivatives: step size against error (fails: > {d['tol']:.0e})", '',
          '| method | best h | error at best h | usable h (error <= tol) |', '|---|---:|---:|---|']
    for m, b in d['best'].items():
        L.append(f"| {m} | {b['best_h']:.0e} | {b['best_error']:.1e} | {_range(b['usable_h'])} |")
    for m, v in d['flat'].items():
        L.append(f'| {m} (no step) | — | {v:.1e} | — |')
    en = res['energy']
    dts = sorted({r['x'] for r in en['rows']})
    L += ['', f"## Energy drift, {en['duration']:g} s free motion of the arm, no damping "
              f"(max |ΔE| / max kinetic energy = {en['energy_scale_J']:.3g} J; fails: > {en['tol']:.0%})", '',
          '| integrator | ' + ' | '.join(f'dt={x:g}' for x in dts) + ' | µs/step (its smallest dt) | largest good dt |',
          '|---|' + '---:|' * (len(dts) + 2)]
    for m in en['boundaries']:
        by = {r['x']: r for r in en['rows'] if r['method'] == m}
        cells = [('—' if x not in by else 'diverged' if by[x]['status'].startswith('diverged')
                  else f"{by[x]['error']:.1e}") for x in dts]
        L.append(f'| {m} | ' + ' | '.join(cells) + f" | {by[min(by)]['us_per_step']:.0f} | "
                 f"{_fmt(en['boundaries'][m]['largest_ok_dt'])} |")
    L += ['', 'Scan times: ' + ', '.join(f"{k} {res[k]['seconds']:.1f} s" for k in SCANS)]
    return '\n'.join(L) + '\n'


def _json_safe(x):
    if isinstance(x, dict):
        return {str(k): _json_safe(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_json_safe(v) for v in x]
    if isinstance(x, float) and not np.isfinite(x):
        return str(x)
    if isinstance(x, (np.floating, np.integer)):
        return _json_safe(x.item())
    return x


def write(res, out):
    common.write_tables(out, 'stability', markdown(res), _json_safe(res), (r for k in SCANS for r in res[k]['rows']),
                        ['scan', 'method', 'x_name', 'x', 'error', 'status'])
    return charts(res, out)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('--quick', action='store_true')
    ap.add_argument('--out', default=os.path.join(common.HERE, 'out'))
    ap.add_argument('--scans', help=f'comma-separated subset of {list(SCANS)} (prints only, writes nothing)')
    args = ap.parse_args(argv)
    if args.scans:
        res = run(args.quick, None, args.scans.split(','))
        print(json.dumps(_json_safe({k: {kk: vv for kk, vv in v.items() if kk not in ('rows', 'traces')}
                                     for k, v in res.items() if k != 'meta'}), indent=1))
        return 0
    print(markdown(run(args.quick, args.out)))
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
