"""Scaling: time per call against the number of joints, chains and trees, with fitted slopes.

    python -m bench.scaling [--quick] [--out DIR]

Random revolute robots (bench/common.py: robot_urdf) of 2 to 200 joints, as serial chains
(depth n) and binary trees (depth log2 n), single state unless marked batched. The slope is
a least-squares fit of log(time) against log(n) over the larger half of the sizes, where
fixed per-call costs no longer dominate: ~1 for O(n), ~2 for O(n^2). The library switches
implementation with size (generated kernels up to a size, vectorised numpy above), which
shows as kinks. Kernel compile times (once per robot structure) are listed, not timed in.
Each family is also given as a ratio to its Pinocchio counterpart (RATIOS; medians of per-round
ratios, same process). Writes scaling.{md,csv,json,png} and scaling_ratio.png.
"""
import os
import time

import numpy as np

from bench import common

SIZES = (2, 4, 6, 8, 16, 32, 64, 100, 200)
SIZES_QUICK = (2, 8)   # the smoke test: two sizes give the slope; every family compiles per size
ALGOS = ('RNEA', 'RNEA batched (per state)', 'gravity', 'M CRBA', 'M closed form', 'C Christoffel',
         'FD Cholesky', 'FD ABA', 'ID derivatives', 'C recursive', 'FD derivatives', 'regressor',
         'Jacobian', 'J̇q̇',
         'Pinocchio rnea', 'Pinocchio crba', 'Pinocchio aba', 'Pinocchio derivatives', 'Pinocchio gravity',
         'Pinocchio coriolis', 'Pinocchio aba derivatives', 'Pinocchio regressor', 'Pinocchio Jacobian',
         'Pinocchio J̇q̇')
# each family of ours against Pinocchio's counterpart (the ratio chart)
RATIOS = {'RNEA': 'Pinocchio rnea', 'gravity': 'Pinocchio gravity', 'M CRBA': 'Pinocchio crba',
          'FD Cholesky': 'Pinocchio aba', 'FD ABA': 'Pinocchio aba', 'ID derivatives': 'Pinocchio derivatives',
          'C recursive': 'Pinocchio coriolis', 'FD derivatives': 'Pinocchio aba derivatives',
          'regressor': 'Pinocchio regressor', 'Jacobian': 'Pinocchio Jacobian', 'J̇q̇': 'Pinocchio J̇q̇'}
NB = 256
# Pinocchio's counterparts share the colour of ours (dashed)
COLORS = dict(zip(ALGOS[:14], ('C0', 'C1', 'C2', 'C3', 'C4', 'C5', 'C6', 'C7', 'C8', 'C9', 'navy', 'k', 'olive',
                               'teal')))
COLORS.update({'Pinocchio rnea': 'C0', 'Pinocchio crba': 'C3', 'Pinocchio aba': 'C7', 'Pinocchio derivatives': 'C8',
               'Pinocchio gravity': 'C2', 'Pinocchio coriolis': 'C9', 'Pinocchio aba derivatives': 'navy',
               'Pinocchio regressor': 'k', 'Pinocchio Jacobian': 'olive', 'Pinocchio J̇q̇': 'teal'})


def _fns(model, xml, rng):
    pin, pm, pd = common.pinocchio_model(xml, model)
    n = model.n
    q, qd, qdd = rng.uniform(-1, 1, (3, n))
    tau = model.inverse_dynamics(q, qd, qdd)
    Q, Qd, Qdd = rng.uniform(-1, 1, (3, NB, n))
    deep = int(np.argmax(model.depth))   # the Jacobians: the deepest body's link, 'world_aligned'
    link = next(nm for nm, (b, _) in model.link_frames.items() if b == deep)
    fid, ref, zero = pm.getFrameId(link), pin.ReferenceFrame.LOCAL_WORLD_ALIGNED, np.zeros(n)

    def pin_drift():
        pin.forwardKinematics(pm, pd, q, qd, zero)
        return pin.getFrameClassicalAcceleration(pm, pd, fid, ref).vector
    return {
        'RNEA': (lambda: model.inverse_dynamics(q, qd, qdd), 1),
        'RNEA batched (per state)': (lambda: model.inverse_dynamics(Q, Qd, Qdd), NB),
        'gravity': (lambda: model.gravity(q), 1),
        'M CRBA': (lambda: model.mass_matrix(q), 1),
        'M closed form': (lambda: model.mass_matrix(q, 'closed_form'), 1),
        'C Christoffel': (lambda: model.coriolis_matrix(q, qd), 1),
        'FD Cholesky': (lambda: model.forward_dynamics(q, qd, tau), 1),
        'FD ABA': (lambda: model.forward_dynamics(q, qd, tau, method='aba'), 1),
        'ID derivatives': (lambda: model.inverse_dynamics_derivatives(q, qd, qdd), 1),
        'C recursive': (lambda: model.coriolis_matrix(q, qd, method='recursive'), 1),
        'FD derivatives': (lambda: model.forward_dynamics_derivatives(q, qd, tau), 1),
        'regressor': (lambda: model.regressor(q, qd, qdd), 1),
        'Jacobian': (lambda: model.jacobian(q, link), 1),
        'J̇q̇': (lambda: model.jacobian_dot_times_qd(q, qd, link), 1),
        'Pinocchio rnea': (lambda: pin.rnea(pm, pd, q, qd, qdd), 1),
        'Pinocchio crba': (lambda: pin.crba(pm, pd, q), 1),
        'Pinocchio aba': (lambda: pin.aba(pm, pd, q, qd, tau), 1),
        'Pinocchio derivatives': (lambda: pin.computeRNEADerivatives(pm, pd, q, qd, qdd), 1),
        'Pinocchio gravity': (lambda: pin.computeGeneralizedGravity(pm, pd, q), 1),
        'Pinocchio coriolis': (lambda: pin.computeCoriolisMatrix(pm, pd, q, qd), 1),
        'Pinocchio aba derivatives': (lambda: pin.computeABADerivatives(pm, pd, q, qd, tau), 1),
        'Pinocchio regressor': (lambda: pin.computeJointTorqueRegressor(pm, pd, q, qd, qdd), 1),
        'Pinocchio Jacobian': (lambda: pin.computeFrameJacobian(pm, pd, q, fid, ref), 1),
        'Pinocchio J̇q̇': (pin_drift, 1),
    }


def run(quick=False, out=None, seed=0):
    from lie_dynamics import load_urdf
    sizes = SIZES_QUICK if quick else SIZES
    fit_from = sizes[len(sizes) // 2]
    rounds = 3 if quick else 9
    target = 0.0005 if quick else 0.003
    rows, compile_s, fns = [], [], {}
    for kind in ('chain', 'tree'):
        for n in sizes:
            xml = common.robot_urdf(n, tree=kind == 'tree', seed=seed + n)
            model = load_urdf(xml)
            f_n = _fns(model, xml, np.random.default_rng(seed + n))
            t0 = time.perf_counter()
            for f, _ in f_n.values():   # first calls compile the generated kernels
                f()
            compile_s.append(dict(kind=kind, n=n, seconds=time.perf_counter() - t0))
            fns.update({(kind, n, k): v for k, v in f_n.items()})
    # one interleaved set over all sizes: a busy phase of the shared machine then hits every size
    # in that round, and the median over rounds drops it (timing size by size bent the slopes)
    secs = common.time_interleaved({k: f for k, (f, _) in fns.items()}, rounds, target)
    for (kind, n, k), (_, per) in fns.items():
        peer = RATIOS.get(k)
        ratio = float(np.median(secs[(kind, n, k)] / secs[(kind, n, peer)])) if peer else None
        rows.append(dict(kind=kind, n=n, algorithm=k, us=float(np.median(secs[(kind, n, k)]) / per * 1e6),
                         ratio=ratio))
    slopes = {}
    for kind in ('chain', 'tree'):
        for a in ALGOS:
            pts = [(r['n'], r['us']) for r in rows if r['kind'] == kind and r['algorithm'] == a]
            slopes[f'{kind}/{a}'] = common.slope(*zip(*pts), fit_from=fit_from)
    res = dict(rows=rows, slopes=slopes, fit_from=fit_from, sizes=list(sizes), compile_s=compile_s,
               meta=dict(quick=quick, rounds=rounds, batch=NB))
    if out:
        write(res, out)
    return res


def markdown(res):
    sizes = res['sizes']
    by = {(r['kind'], r['n'], r['algorithm']): r['us'] for r in res['rows']}
    L = ['# Scaling with the number of joints', '',
         f"µs per call, single state (batched: per state of a {res['meta']['batch']}-state call), median of "
         f"{res['meta']['rounds']} interleaved rounds. Slope: log-log fit for n >= {res['fit_from']}.", '']
    for kind in ('chain', 'tree'):
        L += [f'## {kind}s', '', '| algorithm | ' + ' | '.join(f'n={n}' for n in sizes) + ' | slope |',
              '|---|' + '---:|' * (len(sizes) + 1)]
        for a in ALGOS:
            L.append(f'| {a} | ' + ' | '.join(f'{by[(kind, n, a)]:.3g}' for n in sizes) +
                     f" | {res['slopes'][f'{kind}/{a}']:.2f} |")
        L.append('')
    ratio = {(r['kind'], r['n'], r['algorithm']): r.get('ratio') for r in res['rows']}
    for kind in ('chain', 'tree'):
        L += [f'## {kind}s: ours / Pinocchio (median of per-round ratios)', '',
              '| algorithm | ' + ' | '.join(f'n={n}' for n in sizes) + ' |', '|---|' + '---:|' * len(sizes)]
        L += [f'| {a} / {p} | ' + ' | '.join(f'{ratio[(kind, n, a)]:.2f}' for n in sizes) + ' |'
              for a, p in RATIOS.items()]
        L.append('')
    L.append('First-call time (kernel compilation, all algorithms): ' +
             ', '.join(f"{c['kind']} n={c['n']}: {c['seconds']:.2f} s" for c in res['compile_s']))
    return '\n'.join(L) + '\n'


def chart(res, path):
    plt = common.setup_matplotlib()
    fig, axes = plt.subplots(1, 2, figsize=(14, 5.5), sharey=True)
    for ax, kind in zip(axes, ('chain', 'tree')):
        for a in ALGOS:
            pts = sorted((r['n'], r['us']) for r in res['rows'] if r['kind'] == kind and r['algorithm'] == a)
            ls = '--' if a.startswith('Pinocchio') else '-'
            ax.loglog(*zip(*pts), ls, marker='o', ms=3, color=COLORS[a],
                      label=f"{a} ({res['slopes'][f'{kind}/{a}']:.2f})")
        ax.set_xlabel('joints n')
        ax.set_title(f"{kind}s ({'depth n' if kind == 'chain' else 'binary tree, depth log2 n'}); "
                     f"slope fitted for n >= {res['fit_from']}", fontsize=10)
        ax.grid(True, which='both', alpha=0.3)
        ax.legend(fontsize=7, ncol=2)
    axes[0].set_ylabel('µs per call (median)')
    fig.tight_layout()
    common.savefig(fig, path)


def ratio_chart(res, path):
    plt = common.setup_matplotlib()
    fig, axes = plt.subplots(1, 2, figsize=(14, 5.5), sharey=True)
    for ax, kind in zip(axes, ('chain', 'tree')):
        for a, p in RATIOS.items():
            pts = sorted((r['n'], r['ratio']) for r in res['rows'] if r['kind'] == kind and r['algorithm'] == a)
            ax.loglog(*zip(*pts), '-', marker='o', ms=3, color=COLORS[a], label=f'{a} / {p}')
        ax.axhline(1.0, color='grey', lw=1)
        ax.set_xlabel('joints n')
        ax.set_title(f"{kind}s: time per call / Pinocchio's, one state", fontsize=10)
        ax.grid(True, which='both', alpha=0.3)
        ax.legend(fontsize=7, ncol=2)
    axes[0].set_ylabel('ours / Pinocchio (median of per-round ratios)')
    fig.tight_layout()
    common.savefig(fig, path)


def write(res, out):
    rows = [dict(r, slope=res['slopes'][f"{r['kind']}/{r['algorithm']}"]) for r in res['rows']]
    common.write_tables(out, 'scaling', markdown(res), res, rows, ['kind', 'n', 'algorithm', 'us', 'ratio', 'slope'])
    chart(res, os.path.join(out, 'scaling.png'))
    ratio_chart(res, os.path.join(out, 'scaling_ratio.png'))


def main(argv=None):
    return common.section_main(argv, __doc__, run, markdown)


if __name__ == '__main__':
    raise SystemExit(main())
