"""Charts of the stability map (bench/stability.py): one PNG per scan, written next to its tables."""
import os

import numpy as np

from bench import common

# The two axes of the forward-dynamics scan (also the x_name of its rows).
RATIO = 'distal/proximal mass ratio'
TILT = 'axis tilt (rad)'


def _label(ax, xlabel, ylabel, title):
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    ax.grid(True, which='major', alpha=0.3)
    ax.legend(fontsize=7)


def _save(fig, out, name, paths):
    fig.tight_layout()
    paths.append(os.path.join(out, name))
    common.savefig(fig, paths[-1])


def charts(res, out):
    plt = common.setup_matplotlib()
    paths = []
    # 1. exp/log
    e = res['explog']
    fig, axes = plt.subplots(1, 2, figsize=(13, 5.5), sharey=True)
    colors = {'lie_dynamics': 'C0', 'naive closed form': 'C1', 'Modern Robotics': 'C3'}
    styles = {'exp3': '-', 'log3': '--', 'exp6': ':', 'log6': '-.'}
    for ax, where in zip(axes, ('0', 'pi')):
        for m in dict.fromkeys(r['method'] for r in e['rows']):
            impl, fn = m.rsplit(' ', 1)
            pts = [(r['x'], r['error']) for r in e['rows'] if r['method'] == m and r['where'] == where]
            x, y = zip(*pts)
            y = np.where(np.isfinite(y), np.maximum(y, 1e-19), 1e1)   # NaN/inf drawn at the top
            ax.loglog(x, y, styles[fn], color=colors[impl], marker='.', ms=3, label=m)
        ax.axhline(e['tol'], color='k', lw=0.8)
        ax.axhspan(e['tol'], 20, color='red', alpha=0.06)
        ax.set_xlabel('θ' if where == '0' else 'π − θ')
        ax.set_title(f'near θ = {"0" if where == "0" else "π"} (shaded: error > {e["tol"]:.0e}; NaN drawn at 10)')
        ax.set_ylim(1e-19, 20)
        ax.grid(True, which='major', alpha=0.3)
    axes[0].set_ylabel('error (exp: matrix entries; log: relative)')
    handles, labels = axes[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc='lower center', ncol=6, fontsize=7)
    fig.tight_layout(rect=(0, 0.08, 1, 1))
    paths.append(os.path.join(out, 'stability_explog.png'))
    common.savefig(fig, paths[-1])
    # 2. chain length
    c = res['chain_length']
    fig, ax = plt.subplots(figsize=(7.5, 5))
    for k, m in enumerate(dict.fromkeys(r['method'] for r in c['rows'])):
        pts = [(r['x'], r['error']) for r in c['rows'] if r['method'] == m]
        ax.loglog(*zip(*pts), marker='o', ms=3, color=f'C{k}', ls='--' if 'float32' in m else '-',
                  label=f"{m} (~n^{c['growth_exponent'][m]:.1f})")
    for dt, v in c['tol'].items():
        ax.axhline(v, color='k', lw=0.7, ls=':')
        ax.text(2, v * 1.3, f'1000 ulps {dt}', fontsize=7)
    _label(ax, 'joints (random serial chain)', 'max relative torque error vs longdouble',
           'RNEA error growth with chain length')
    _save(fig, out, 'stability_chain.png', paths)
    # 3. forward dynamics
    f = res['forward_dynamics']
    fig, axes = plt.subplots(1, 2, figsize=(13, 5), sharey=True)
    for ax, xn in zip(axes, (RATIO, TILT)):
        for k, m in enumerate(dict.fromkeys(r['method'] for r in f['rows'])):
            pts = sorted((r['x'], r['error'], r['status']) for r in f['rows'] if r['method'] == m and r['x_name'] == xn
                         and (r['x'] >= 1e-20 or r['x'] == 0))   # ratios 1e-50, 1e-300: table only
            pts = [(x if x > 0 else 1e-10, y, s) for x, y, s in pts]   # tilt 0 drawn at 1e-10
            ok = [(x, min(max(y, 1e-19), 10)) for x, y, s in pts if not s.startswith('raised')]
            if ok:
                ax.loglog(*zip(*ok), marker='o', ms=3, color=f'C{k}', label=m)
            raised = [x for x, _, s in pts if s.startswith('raised')]
            if raised:
                ax.scatter(raised, [3.0 * 1.6 ** k] * len(raised), marker='x', color=f'C{k}', s=40,
                           label=f'{m}: raises')
        cond = sorted((m['x'] if m['x'] > 0 else 1e-10, m['cond']) for m in f['conditioning']
                      if m['x_name'] == xn and (m['x'] >= 1e-20 or m['x'] == 0))
        ax.loglog(*zip(*[(x, min(c_ * common.EPS64, 10)) for x, c_ in cond]), color='grey', ls=':',
                  label='cond(M) · eps')
        ax.axhline(f['tol'], color='k', lw=0.8)
        ax.axhspan(f['tol'], 50, color='red', alpha=0.06)
        xs = [x if x > 0 else 1e-10 for x, *_ in cond]
        ax.set_xlim(max(xs) * 3, min(xs) / 3)
        ax.set_ylim(1e-17, 50)
        ax.set_xlabel(xn + (' (0 drawn at 1e-10)' if xn == TILT else ''))
        ax.grid(True, which='major', alpha=0.3)
        ax.legend(fontsize=7)
    axes[0].set_title('scale: bundled arm, masses graded along the chain', fontsize=10)
    axes[1].set_title('geometry: two nearly coaxial joints, massless link between', fontsize=10)
    axes[0].set_ylabel('max relative error in qdd vs longdouble ABA')
    _save(fig, out, 'stability_forward_dynamics.png', paths)
    # 4. FD step
    d = res['fd_step']
    fig, ax = plt.subplots(figsize=(7.5, 5))
    for k, m in enumerate(dict.fromkeys(r['method'] for r in d['rows'])):
        pts = [(r['x'], max(r['error'], 1e-19)) for r in d['rows'] if r['method'] == m]
        ax.loglog(*zip(*pts), marker='o', ms=3, color=f'C{k}', label=m)
    for k, (m, v) in enumerate(d['flat'].items()):
        ax.axhline(max(v, 1e-19), color=f'C{k + 3}', ls='--', label=f'{m} ({v:.1e})')
    ax.axhline(d['tol'], color='k', lw=0.8)
    _label(ax, 'step h', 'max relative error of (dtau/dq, dtau/dqd)',
           'finite-difference step against error (bundled arm)')
    _save(fig, out, 'stability_fd_step.png', paths)
    # 5. energy
    en = res['energy']
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(13, 5))
    for k, (label, tr) in enumerate(en['traces'].items()):
        y = np.abs(np.array(tr['rel_dE']))
        a1.semilogy(tr['t'][1:], np.maximum(y[1:], 1e-17), color=f'C{k}', label=label)
    a1.axhline(en['tol'], color='k', lw=0.8)
    a1.set_xlabel('t (s)')
    a1.set_ylabel('|E(t) − E(0)| / max kinetic energy')
    a1.set_title(f"energy error over time, dt = {en['trace_dt']:g} s")
    a1.legend(fontsize=7)
    a1.grid(True, which='major', alpha=0.3)
    for k, m in enumerate(en['boundaries']):
        pts = sorted((r['x'], r['error']) for r in en['rows'] if r['method'] == m)
        x, y = zip(*pts)
        y = np.where(np.isfinite(y), np.maximum(y, 1e-17), 1e3)
        a2.loglog(x, y, marker='o', ms=4, color=f'C{k}', label=m)
    a2.axhline(en['tol'], color='k', lw=0.8)
    a2.axhspan(en['tol'], 2e3, color='red', alpha=0.06)
    a2.set_xlabel('dt (s)')
    a2.set_ylabel(f"max relative energy error over {en['duration']:g} s (diverged: drawn at 1e3)")
    a2.set_title('energy drift against step')
    a2.legend(fontsize=7)
    a2.grid(True, which='major', alpha=0.3)
    _save(fig, out, 'stability_energy.png', paths)
    return paths
