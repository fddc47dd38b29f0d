"""Speed against accuracy: every method we have, its time per evaluation and its error.

    python -m bench.accuracy [--quick] [--out DIR]

For the bundled arm and a random 30-joint chain (12 joints with --quick), on the same random
states: time per evaluation (median of interleaved rounds; batched methods per state, from
one call on a batch) and error = max over states of max|out - ref| / max|ref| against the
same quantity evaluated in numpy.longdouble (bench/reference.py: the RNEA of eqs 16-21, M by
columns, forward dynamics by a longdouble ABA, derivatives by a longdouble complex step).
Pinocchio and Modern Robotics run on the same states; ratios are to the Pinocchio
counterpart, medians of per-round ratios.

Writes accuracy.{md,csv,json} and accuracy_<robot>.png.
"""
import argparse
import os

import numpy as np

from bench import common
from bench.common import rel_err
from bench.reference import LD, Generic

OPS = ('inverse dynamics', 'gravity', 'mass matrix', 'Coriolis term C(q, qd) qd', 'forward dynamics',
       'derivatives dtau/dq, dtau/dqd')
IMPL_STYLE = {'lie_dynamics': ('o', 'C0'), 'lie_dynamics_python': ('v', 'C4'), 'bench': ('s', 'C2'),
              'pinocchio': ('D', 'C3'), 'modern_robotics': ('^', 'C1')}


def _batch(a, N):
    reps = -(-N // len(a))
    return np.tile(a, (reps, 1))[:N]


def _pin_sym(M):
    return np.triu(M) + np.triu(M, 1).T


def methods(model, xml, q, qd, qdd, tau, NB, S_mr):
    """{op: [(method, impl, mode, outputs(), timed callable, states per call)]}."""
    import modern_robotics as mr
    from lie_dynamics.algorithms import rnea
    pin, pm, pd = common.pinocchio_model(xml, model)
    S, n = q.shape
    qb, qdb, qddb, taub = (_batch(a, NB) for a in (q, qd, qdd, tau))
    g = model.gravity_vector
    try:
        Ml, Gl, Sl = common.modern_robotics_lists(model)
    except ValueError:
        Ml = None
    f32, f64, c128 = Generic(model, np.float32), Generic(model, np.float64), Generic(model, np.complex128)
    qb32, qdb32, qddb32 = (a.astype(np.float32) for a in (qb, qdb, qddb))
    zero = np.zeros(n)
    out = {op: [] for op in OPS}
    py = common.python_kernels(model)   # 'lie_dynamics' rows: the native kernels where a C compiler works

    def add(op, method, impl, mode, outputs, timed, per=1):
        out[op].append((method, impl, mode, outputs, timed, per))

    def each(f, k=S):
        return lambda: np.array([f(i) for i in range(k)])

    def first(f, k=S):
        return lambda: f()[:k]

    # inverse dynamics
    op = OPS[0]
    add(op, 'lie_dynamics', 'lie_dynamics', 'single', each(lambda i: model.inverse_dynamics(q[i], qd[i], qdd[i])),
        lambda: model.inverse_dynamics(q[0], qd[0], qdd[0]))
    add(op, 'lie_dynamics batched', 'lie_dynamics', 'batched', first(lambda: model.inverse_dynamics(qb, qdb, qddb)),
        lambda: model.inverse_dynamics(qb, qdb, qddb), NB)

    add(op, 'Python kernels', 'lie_dynamics_python', 'single',
        each(lambda i: py.inverse_dynamics(q[i], qd[i], qdd[i])), lambda: py.inverse_dynamics(q[0], qd[0], qdd[0]))
    add(op, 'Python kernels batched', 'lie_dynamics_python', 'batched',
        first(lambda: py.inverse_dynamics(qb, qdb, qddb)), lambda: py.inverse_dynamics(qb, qdb, qddb), NB)

    def vect(i):
        return rnea.inverse_dynamics_vectorized(model, q[i], qd[i], qdd[i])
    add(op, 'lie_dynamics vectorised path', 'lie_dynamics', 'single', each(vect), lambda: vect(0))
    add(op, 'bench RNEA float64', 'bench', 'batched', first(lambda: f64.inverse_dynamics(qb, qdb, qddb)),
        lambda: f64.inverse_dynamics(qb, qdb, qddb), NB)
    add(op, 'bench RNEA float32', 'bench', 'batched', first(lambda: f32.inverse_dynamics(qb32, qdb32, qddb32)),
        lambda: f32.inverse_dynamics(qb32, qdb32, qddb32), NB)
    add(op, 'Pinocchio', 'pinocchio', 'single', each(lambda i: pin.rnea(pm, pd, q[i], qd[i], qdd[i]).copy()),
        lambda: pin.rnea(pm, pd, q[0], qd[0], qdd[0]))
    if Ml is not None:
        add(op, 'Modern Robotics', 'modern_robotics', 'single',
            each(lambda i: mr.InverseDynamics(q[i], qd[i], qdd[i], g, np.zeros(6), Ml, Gl, Sl), S_mr),
            lambda: mr.InverseDynamics(q[0], qd[0], qdd[0], g, np.zeros(6), Ml, Gl, Sl))

    op = OPS[1]
    add(op, 'lie_dynamics', 'lie_dynamics', 'single', each(lambda i: model.gravity(q[i])), lambda: model.gravity(q[0]))
    add(op, 'lie_dynamics batched', 'lie_dynamics', 'batched', first(lambda: model.gravity(qb)),
        lambda: model.gravity(qb), NB)
    add(op, 'Python kernels', 'lie_dynamics_python', 'single', each(lambda i: py.gravity(q[i])),
        lambda: py.gravity(q[0]))
    add(op, 'potential gradient (eqs 43-45)', 'lie_dynamics', 'single', each(lambda i: model.gravity_potential(q[i])),
        lambda: model.gravity_potential(q[0]))
    add(op, 'Pinocchio', 'pinocchio', 'single', each(lambda i: pin.computeGeneralizedGravity(pm, pd, q[i]).copy()),
        lambda: pin.computeGeneralizedGravity(pm, pd, q[0]))
    if Ml is not None:
        add(op, 'Modern Robotics', 'modern_robotics', 'single',
            each(lambda i: mr.GravityForces(q[i], g, Ml, Gl, Sl), S_mr),
            lambda: mr.GravityForces(q[0], g, Ml, Gl, Sl))

    op = OPS[2]
    add(op, 'CRBA (recursive)', 'lie_dynamics', 'single', each(lambda i: model.mass_matrix(q[i])),
        lambda: model.mass_matrix(q[0]))
    add(op, 'CRBA batched', 'lie_dynamics', 'batched', first(lambda: model.mass_matrix(qb)),
        lambda: model.mass_matrix(qb), NB)
    add(op, 'CRBA, Python kernels', 'lie_dynamics_python', 'single', each(lambda i: py.mass_matrix(q[i])),
        lambda: py.mass_matrix(q[0]))
    add(op, 'closed form (eq 39)', 'lie_dynamics', 'single', each(lambda i: model.mass_matrix(q[i], 'closed_form')),
        lambda: model.mass_matrix(q[0], 'closed_form'))
    add(op, 'closed form batched', 'lie_dynamics', 'batched', first(lambda: model.mass_matrix(qb, 'closed_form')),
        lambda: model.mass_matrix(qb, 'closed_form'), NB)
    add(op, 'Pinocchio', 'pinocchio', 'single', each(lambda i: _pin_sym(pin.crba(pm, pd, q[i]))),
        lambda: pin.crba(pm, pd, q[0]))
    if Ml is not None:
        add(op, 'Modern Robotics', 'modern_robotics', 'single', each(lambda i: mr.MassMatrix(q[i], Ml, Gl, Sl), S_mr),
            lambda: mr.MassMatrix(q[0], Ml, Gl, Sl))

    op = OPS[3]
    add(op, 'C via Christoffel, times qd', 'lie_dynamics', 'single',
        each(lambda i: model.coriolis_matrix(q[i], qd[i]) @ qd[i]), lambda: model.coriolis_matrix(q[0], qd[0]) @ qd[0])
    add(op, 'C via Christoffel batched', 'lie_dynamics', 'batched',
        first(lambda: np.einsum('nij,nj->ni', model.coriolis_matrix(qb, qdb), qdb)),
        lambda: np.einsum('nij,nj->ni', model.coriolis_matrix(qb, qdb), qdb), NB)
    add(op, 'C qd via RNEA', 'lie_dynamics', 'single', each(lambda i: model.coriolis_term(q[i], qd[i])),
        lambda: model.coriolis_term(q[0], qd[0]))
    add(op, 'C qd via RNEA batched', 'lie_dynamics', 'batched', first(lambda: model.coriolis_term(qb, qdb)),
        lambda: model.coriolis_term(qb, qdb), NB)
    add(op, 'Pinocchio', 'pinocchio', 'single', each(lambda i: pin.computeCoriolisMatrix(pm, pd, q[i], qd[i]) @ qd[i]),
        lambda: pin.computeCoriolisMatrix(pm, pd, q[0], qd[0]) @ qd[0])
    if Ml is not None:
        add(op, 'Modern Robotics', 'modern_robotics', 'single',
            each(lambda i: mr.VelQuadraticForces(q[i], qd[i], Ml, Gl, Sl), S_mr),
            lambda: mr.VelQuadraticForces(q[0], qd[0], Ml, Gl, Sl))

    op = OPS[4]
    add(op, 'Cholesky', 'lie_dynamics', 'single', each(lambda i: model.forward_dynamics(q[i], qd[i], tau[i])),
        lambda: model.forward_dynamics(q[0], qd[0], tau[0]))
    add(op, 'Cholesky batched', 'lie_dynamics', 'batched', first(lambda: model.forward_dynamics(qb, qdb, taub)),
        lambda: model.forward_dynamics(qb, qdb, taub), NB)
    add(op, 'ABA O(n)', 'lie_dynamics', 'single',
        each(lambda i: model.forward_dynamics(q[i], qd[i], tau[i], method='aba')),
        lambda: model.forward_dynamics(q[0], qd[0], tau[0], method='aba'))
    add(op, 'ABA O(n) batched', 'lie_dynamics', 'batched',
        first(lambda: model.forward_dynamics(qb, qdb, taub, method='aba')),
        lambda: model.forward_dynamics(qb, qdb, taub, method='aba'), NB)

    add(op, 'Cholesky, Python kernels', 'lie_dynamics_python', 'single',
        each(lambda i: py.forward_dynamics(q[i], qd[i], tau[i])), lambda: py.forward_dynamics(q[0], qd[0], tau[0]))

    def explicit_inverse(i):
        return np.linalg.inv(model.mass_matrix(q[i])) @ (tau[i] - model.inverse_dynamics(q[i], qd[i], zero))
    add(op, 'explicit inverse M^-1', 'lie_dynamics', 'single', each(explicit_inverse), lambda: explicit_inverse(0))
    add(op, 'Pinocchio ABA', 'pinocchio', 'single', each(lambda i: pin.aba(pm, pd, q[i], qd[i], tau[i]).copy()),
        lambda: pin.aba(pm, pd, q[0], qd[0], tau[0]))
    if Ml is not None:
        add(op, 'Modern Robotics', 'modern_robotics', 'single',
            each(lambda i: mr.ForwardDynamics(q[i], qd[i], tau[i], g, np.zeros(6), Ml, Gl, Sl), S_mr),
            lambda: mr.ForwardDynamics(q[0], qd[0], tau[0], g, np.zeros(6), Ml, Gl, Sl))

    op = OPS[5]
    add(op, 'analytic', 'lie_dynamics', 'single',
        each(lambda i: np.stack(model.inverse_dynamics_derivatives(q[i], qd[i], qdd[i]))),
        lambda: model.inverse_dynamics_derivatives(q[0], qd[0], qdd[0]))
    add(op, 'analytic batched', 'lie_dynamics', 'batched',
        first(lambda: np.stack(model.inverse_dynamics_derivatives(qb, qdb, qddb), axis=1)),
        lambda: model.inverse_dynamics_derivatives(qb, qdb, qddb), NB)
    add(op, 'analytic, Python kernels', 'lie_dynamics_python', 'single',
        each(lambda i: np.stack(py.inverse_dynamics_derivatives(q[i], qd[i], qdd[i]))),
        lambda: py.inverse_dynamics_derivatives(q[0], qd[0], qdd[0]))
    add(op, 'forward differences', 'lie_dynamics', 'single',
        each(lambda i: finite_differences(model, q[i], qd[i], qdd[i])),
        lambda: finite_differences(model, q[0], qd[0], qdd[0]))
    add(op, 'central differences', 'lie_dynamics', 'single',
        each(lambda i: finite_differences(model, q[i], qd[i], qdd[i], central=True)),
        lambda: finite_differences(model, q[0], qd[0], qdd[0], central=True))
    add(op, 'complex step (bench RNEA)', 'bench', 'single',
        each(lambda i: np.stack([d[0] for d in c128.derivatives(q[i], qd[i], qdd[i])])),
        lambda: c128.derivatives(q[0], qd[0], qdd[0]))
    add(op, 'Pinocchio', 'pinocchio', 'single',
        each(lambda i: np.stack([a.copy() for a in pin.computeRNEADerivatives(pm, pd, q[i], qd[i], qdd[i])[:2]])),
        lambda: pin.computeRNEADerivatives(pm, pd, q[0], qd[0], qdd[0]))
    return out


def finite_differences(model, q, qd, qdd, central=False, h=None):
    """(dtau/dq, dtau/dqd) stacked (2, n, n) by one batched inverse-dynamics call.

    Default steps: sqrt(eps) (forward) and eps^(1/3) (central), scaled by max(1, |x|): the
    textbook balance of truncation against rounding.
    """
    n = len(q)
    if h is None:
        h = common.EPS64 ** (1 / 3 if central else 1 / 2)
    hq = h * np.maximum(1.0, np.abs(q))
    hv = h * np.maximum(1.0, np.abs(qd))
    Q = np.tile(q, (4 * n + 1, 1))
    V = np.tile(qd, (4 * n + 1, 1))
    idx = np.arange(n)
    Q[1 + idx, idx] += hq
    Q[1 + n + idx, idx] -= hq
    V[1 + 2 * n + idx, idx] += hv
    V[1 + 3 * n + idx, idx] -= hv
    sq = (Q[1 + idx, idx] - q, q - Q[1 + n + idx, idx])   # the steps actually taken, (x + h) - x
    sv = (V[1 + 2 * n + idx, idx] - qd, qd - V[1 + 3 * n + idx, idx])
    with np.errstate(divide='ignore', invalid='ignore'):   # a step below rounding is 0: NaN, reported as such
        if central:
            tau = model.inverse_dynamics(Q[1:], V[1:], np.tile(qdd, (4 * n, 1)))
            dq = (tau[:n] - tau[n:2 * n]) / (sq[0] + sq[1])[:, None]
            dv = (tau[2 * n:3 * n] - tau[3 * n:]) / (sv[0] + sv[1])[:, None]
        else:
            sel = np.r_[0, 1 + idx, 1 + 2 * n + idx]
            tau = model.inverse_dynamics(Q[sel], V[sel], np.tile(qdd, (2 * n + 1, 1)))
            dq = (tau[1:n + 1] - tau[0]) / sq[0][:, None]
            dv = (tau[n + 1:] - tau[0]) / sv[0][:, None]
    return np.stack([dq.T, dv.T])


def references(model, q, qd, qdd, tau):
    """Longdouble references of every op (see the module docstring)."""
    G = Generic(model, LD)
    dq, dv = Generic(model, np.clongdouble).derivatives(q, qd, qdd)
    return {OPS[0]: G.inverse_dynamics(q, qd, qdd), OPS[1]: G.gravity(q), OPS[2]: G.mass_matrix(q),
            OPS[3]: G.coriolis_term(q, qd), OPS[4]: G.forward_dynamics(q, qd, tau),
            OPS[5]: np.stack([dq, dv], axis=1)}


def run_robot(name, xml, quick, rounds, target, seed=0):
    from lie_dynamics import load_urdf
    model = load_urdf(xml)
    S = 4 if quick else 16
    S_mr = 2 if quick else 4
    NB = 256 if quick else 1000
    q, qd, qdd = common.random_states(model, S, seed)
    tau = model.inverse_dynamics(q, qd, qdd)
    refs = references(model, q, qd, qdd, tau)
    rows = []
    for op, cands in methods(model, xml, q, qd, qdd, tau, NB, S_mr).items():
        errs = {}
        for method, _impl, _mode, outputs, _, _ in cands:
            with np.errstate(all='ignore'):
                o = np.asarray(outputs())
            ref = refs[op][:len(o)]
            e = rel_err(o.reshape(len(o), -1), ref.reshape(len(o), -1), axis=1)
            errs[method] = e
        fns = {c[0]: c[4] for c in cands}
        secs = common.time_interleaved(fns, rounds, target)
        pin_key = next(c[0] for c in cands if c[1] == 'pinocchio')
        for method, impl, mode, _, _, per in cands:
            t = secs[method] / per
            rows.append(dict(robot=name, dof=model.n, op=op, method=method, impl=impl, mode=mode,
                             us=float(np.median(t) * 1e6),
                             ratio_to_pinocchio=float(np.median(t / secs[pin_key])),
                             err_max=float(np.max(errs[method])), err_median=float(np.median(errs[method])),
                             states=int(len(errs[method]))))
    return rows


def run(quick=False, out=None, seed=0):
    import pinocchio as pin
    n_chain = 12 if quick else 30
    rounds = 3 if quick else 9
    target = 0.002 if quick else 0.01
    rows = []
    robots = [('arm7', common.arm_xml()), (f'chain{n_chain}', common.robot_urdf(n_chain, seed=n_chain))]
    for name, xml in robots:
        rows += run_robot(name, xml, quick, rounds, target, seed)
    res = dict(rows=rows, meta=dict(quick=quick, rounds=rounds, numpy=np.__version__, pinocchio=pin.__version__,
                                    cpu_count=os.cpu_count(), reference='numpy.longdouble (80-bit) evaluation, '
                                    'eps %.2g' % np.finfo(LD).eps))
    if out:
        write(res, out)
    return res


# ------------------------------------------------------------------ reports
def markdown(res):
    L = ['# Speed against accuracy', '',
         'Error: max over states of max|out - ref| / max|ref|, ref = the same quantity in numpy.longdouble '
         '(bench/common.py). Time: median of %d interleaved rounds, per state; ratio = median of per-round '
         'ratios to the Pinocchio counterpart (same run).' % res['meta']['rounds'], '']
    for robot in dict.fromkeys(r['robot'] for r in res['rows']):
        rows = [r for r in res['rows'] if r['robot'] == robot]
        L += [f"## {robot} ({rows[0]['dof']} DoF)", '',
              '| operation | method | mode | µs/eval | / Pinocchio | max error | median error |',
              '|---|---|---|---:|---:|---:|---:|']
        for r in rows:
            L.append(f"| {r['op']} | {r['method']} | {r['mode']} | {r['us']:.3g} | {r['ratio_to_pinocchio']:.3g} | "
                     f"{r['err_max']:.1e} | {r['err_median']:.1e} |")
        L.append('')
    return '\n'.join(L)


def chart(res, robot, path):
    plt = common.setup_matplotlib()
    rows = [r for r in res['rows'] if r['robot'] == robot]
    fig, axes = plt.subplots(2, 3, figsize=(15, 8.5))
    for ax, op in zip(axes.ravel(), OPS):
        top = 1e-13
        for r in (r for r in rows if r['op'] == op):
            marker, color = IMPL_STYLE[r['impl']]
            e = r['err_max'] if np.isfinite(r['err_max']) else 1.0
            ax.scatter(r['us'], max(e, 1e-19), marker=marker, color=color,
                       facecolors='none' if r['mode'] == 'batched' else color, s=40)
            ax.annotate(r['method'], (r['us'], max(e, 1e-19)), fontsize=6.5, textcoords='offset points',
                        xytext=(4, -9) if r['mode'] == 'batched' else (4, 3))
            top = max(top, e)
        ax.set_xscale('log')
        ax.set_yscale('log')
        ax.axhline(common.EPS64, color='grey', lw=0.6, ls=':')
        ax.set_ylim(1e-17, top * 10)   # at least 1e-17..1e-12 so that the panels compare
        ax.set_title(op, fontsize=10)
        ax.grid(True, which='major', alpha=0.3)
        ax.set_xlabel('µs per evaluation (batched: per state)', fontsize=8)
        ax.set_ylabel('max relative error vs longdouble', fontsize=8)
        lo, hi = ax.get_xlim()
        ax.set_xlim(lo, hi * 8)  # room for labels
        ax.minorticks_off()      # minor log ticks over ~15 decades made layout take seconds
    names = {'lie_dynamics': 'lie_dynamics (native C where available)',
             'lie_dynamics_python': 'lie_dynamics (Python kernels)'}
    handles = [plt.Line2D([], [], marker=m, color=c, ls='', label=names.get(k, k)) for k, (m, c) in IMPL_STYLE.items()]
    handles.append(plt.Line2D([], [], marker='o', mfc='none', color='k', ls='', label='hollow: batched'))
    fig.legend(handles=handles, loc='lower center', ncol=5, fontsize=8)
    fig.suptitle(f"{robot} ({rows[0]['dof']} DoF): time against error (down and left is better; dotted: float64 eps)")
    fig.subplots_adjust(left=0.06, right=0.98, bottom=0.12, top=0.92, wspace=0.28, hspace=0.32)
    common.savefig(fig, path)


def write(res, out):
    common.write_tables(out, 'accuracy', markdown(res), res, res['rows'])
    for robot in dict.fromkeys(r['robot'] for r in res['rows']):
        chart(res, robot, os.path.join(out, f'accuracy_{robot}.png'))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('--quick', action='store_true')
    ap.add_argument('--out', default=os.path.join(common.HERE, 'out'))
    args = ap.parse_args(argv)
    res = run(args.quick, args.out)
    print(markdown(res))
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
