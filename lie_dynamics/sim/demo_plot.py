"""The demo's picture: one pair of panels per scenario (joint angles above, torques below) in a
grid of up to three columns, one legend above the panels naming every colour and line style."""
import math

import numpy as np

from . import contact_demo, payload_demo

COLUMNS = 3
FONT = 11
JOINT_COLOURS = [f'C{i}' for i in range(10)]


def _legend_handles(n_joints, names):
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    handles = [Line2D([], [], color=JOINT_COLOURS[i % 10], lw=2, label=f'joint{i + 1}') for i in range(n_joints)]
    handles += [Line2D([], [], color='0.3', lw=1.5, label='measured q; τ_ext estimate'),
                Line2D([], [], color='0.3', lw=1.5, ls='--', label='desired q_d; true Jᵀ F')]
    if contact_demo.NAME in names:
        handles.append(Patch(color='red', alpha=0.15, label='~/collision raised'))
    if payload_demo.NAME in names:
        handles += [Line2D([], [], color='0.45', lw=1.5, ls=':', label='~/identify_payload called'),
                    Line2D([], [], color='k', lw=1.5, ls='-.', label='~/identify_payload answered')]
    return handles


def plot(records, path, home, desired, notes=None):
    """records: scenario name -> record (t, q, tau, ...); home: q_home; desired(t) -> q_d (N, n);
    notes: scenario name -> its result in a few words (under the title). Writes a PNG readable
    at a glance (about 1600 px wide)."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    names = list(records)
    cols = min(COLUMNS, len(names))
    rows = math.ceil(len(names) / cols)
    home = np.asarray(home)
    with plt.rc_context({'font.size': FONT, 'axes.titlesize': FONT + 2, 'axes.titleweight': 'bold',
                         'axes.labelsize': FONT, 'legend.fontsize': FONT}):
        fig = plt.figure(figsize=(5.4 * cols, 5.6 * rows + 1.2), layout='constrained')
        grid = fig.add_gridspec(2 * rows, cols)
        for k, name in enumerate(names):
            r, c = divmod(k, cols)
            ax_q = fig.add_subplot(grid[2 * r, c])
            ax_tau = fig.add_subplot(grid[2 * r + 1, c], sharex=ax_q)
            _panels(ax_q, ax_tau, name, records[name], home, desired, (notes or {}).get(name))
        fig.legend(handles=_legend_handles(len(home), names), loc='outside lower center', ncols=6, frameon=False)
        fig.suptitle('lie_dynamics demo: bundled 7-DoF arm simulated at 1 kHz, commanded by the dynamics node',
                     fontsize=FONT + 4)
        fig.savefig(path, dpi=100)
        plt.close(fig)


def _panels(ax_q, ax_tau, name, rec, home, desired, note):
    t = rec['t']
    held = 'compensation' in name   # the arm should stay at q_home: show the drift from it
    if len(t):
        ax_q.plot(t, rec['q'] - home if held else rec['q'], lw=1.2)
        if not held:
            ax_q.set_prop_cycle(None)
            ax_q.plot(t, desired(t), lw=1.0, ls='--')
        if name == contact_demo.NAME:
            contact_demo.plot_panel(ax_tau, rec)
        else:
            ax_tau.plot(t, rec['tau'], lw=1.2)
        if not np.any(rec['tau']):
            ax_tau.text(0.5, 0.6, 'no controller: zero torque', transform=ax_tau.transAxes, ha='center',
                        color='0.3')
    if name == payload_demo.NAME:
        payload_demo.mark(ax_q, rec)
        payload_demo.mark(ax_tau, rec, label=False)
    ax_q.set_title(f'{name}\n{note}' if note else name)
    ax_q.set_ylabel('q − q_home (rad)' if held else 'q (rad)')
    if name != contact_demo.NAME:
        ax_tau.set_ylabel('motor torque (Nm)')
    ax_tau.set_xlabel('simulated time (s)')
    ax_q.tick_params(labelbottom=False)
    for ax in (ax_q, ax_tau):
        ax.grid(alpha=0.3)
