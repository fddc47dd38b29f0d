"""The demo's contact scenario: the arm tracks the demo trajectory with feedforward + PD, a known
wrench pushes its flange for a while (the simulator applies it and publishes J^T F on
~/external_torques_true), and the dynamics node's momentum observer estimates the external
torques from the measured efforts and raises ~/collision.

Reported: the estimate against J^T F (RMS and max error once the estimate has settled, 5 time
constants after the push starts), the largest estimate during free motion (from the first step
on: not the held initial state), the detection delay (first collision flag after the push starts)
and the false alarms (collision flags rising during free motion: there must be none). The push
window and the gain come from here; the simulator's wrench starts at PUSH_START x duration.
"""
import numpy as np

from ..cli import ros_array
from ..ros.core.cdr import stamp_ns

NAME = 'contact'
LINK = 'flange'
WRENCH = (0.0, 0.0, 0.0, 0.0, 0.0, -30.0)   # (m, f) in the flange frame: 30 N against the tool axis
GAIN = 50.0                                   # 1/s: time constant 20 ms
THRESHOLD = (5.0, 5.0, 5.0, 5.0, 2.0, 2.0, 2.0)   # N m; free motion stays below 0.5 N m (see metrics)
HOLD = 0.01                                   # s
PUSH_START = 0.4                              # x duration
PUSH_LENGTH = 0.2                             # x duration, at most MAX_PUSH s
MAX_PUSH = 1.0
EXTERNAL_TOPIC = '/dynamics_node/external_torques'
COLLISION_TOPIC = '/dynamics_node/collision'
TRUTH_TOPIC = '/sim_node/external_torques_true'
KEYS = ('ext_t', 'ext', 'flag', 'true_t', 'true')


def node_params():
    """dynamics_node overrides of the scenario (on top of the feedforward scenario's). The node is
    told the simulator's joint damping (its URDF <dynamics damping>; the demo's config turns
    friction off): friction the model does not know is reported as external torque."""
    from .. import default_urdf_path, load_urdf
    return {'observer.gain': repr(GAIN), 'collision.threshold': ros_array(THRESHOLD), 'collision.hold_time': repr(HOLD),
            'friction.viscous': ros_array(load_urdf(default_urdf_path()).damping)}


def push_window(duration):
    """(start, length) of the push in simulated seconds."""
    return PUSH_START * duration, min(PUSH_LENGTH * duration, MAX_PUSH)


def sim_params(duration):
    start, length = push_window(duration)
    return {'external.link': LINK, 'external.wrench': ros_array(WRENCH), 'external.start': repr(start),
            'external.duration': repr(length)}


def record(node, rec, depth):
    """Subscribe the demo's recorder to the estimate, the flag and the truth; append to rec.
    Returns whether the estimate and the flag readers have matched their publishers."""
    from sensor_msgs.msg import JointState
    from std_msgs.msg import Bool

    def stamped(key_t, key):
        def on_msg(msg):
            rec[key_t].append(stamp_ns(msg.header.stamp.sec, msg.header.stamp.nanosec) * 1e-9)
            rec[key].append(list(msg.effort))
        return on_msg
    # Every message as it comes (copies of re-sent states too): Bool has no stamp, the node publishes
    # it right after each estimate, both reliable and in order, so the k-th flag is the k-th estimate's.
    ext = node.create_subscription(JointState, EXTERNAL_TOPIC, stamped('ext_t', 'ext'), depth)
    node.create_subscription(JointState, TRUTH_TOPIC, stamped('true_t', 'true'), depth)
    flag = node.create_subscription(Bool, COLLISION_TOPIC, lambda m: rec['flag'].append(bool(m.data)), depth)
    return lambda: ext.get_publisher_count() >= 1 and flag.get_publisher_count() >= 1


def samples(rec):
    """(t, estimate, flag, t_true, true), one sample per stamp (the first copy). The recorder stops
    when the last state arrives, so the last estimates or flags may still be on their way: the
    pairs are the common prefix; None when more than a few are missing (messages lost)."""
    t, flags = np.asarray(rec['ext_t'], dtype=float), np.asarray(rec['flag'], dtype=bool)
    n = min(len(t), len(flags))
    if max(len(t), len(flags)) - n > 10:
        return None
    t, flags = t[:n], flags[:n]
    keep = np.concatenate(([True], np.diff(t) != 0)) if len(t) else np.zeros(0, bool)
    tt = np.asarray(rec['true_t'], dtype=float)
    keep_true = np.concatenate(([True], np.diff(tt) != 0)) if len(tt) else np.zeros(0, bool)
    return t[keep], np.asarray(rec['ext'])[:n][keep], flags[keep], tt[keep_true], np.asarray(rec['true'])[keep_true]


def metrics(rec):
    """Estimate error, largest free-motion estimate, detection delay, false alarms (see module)."""
    out = {'estimates': len(rec['ext_t']), 'flags': len(rec['flag'])}
    s = samples(rec)
    if s is None or not len(s[0]) or not len(s[3]):
        return out
    t, ext, flags, tt, true = s
    out['estimates'] = len(t)
    pushed = np.flatnonzero(np.abs(true).max(axis=1) > 0)
    if not len(pushed):
        return out
    start, end = tt[pushed[0]], tt[pushed[-1]]
    settle = 5.0 / GAIN
    truth = np.array([np.interp(t, tt, true[:, j]) for j in range(true.shape[1])]).T
    during = (t >= start + settle) & (t <= end)
    # Free motion starts with the first step. The initial state (stamp 0) is the simulator holding
    # the arm until the answers are in, its motor torque 0: the node times unstamped states with
    # its own clock, so its estimate of that holding torque grows with the copies, up to g(q0),
    # for however long a loaded machine makes the hold (and the first copy may miss the recorder).
    free = ((t > 0) & (t < start)) | (t > end + settle + HOLD)
    err = ext[during] - truth[during]
    out.update(push_start=float(start), push_end=float(end), true_max=float(np.abs(true).max()))
    if during.any():
        out['rms_estimate_error'] = float(np.sqrt(np.mean(err ** 2)))
        out['max_estimate_error'] = float(np.abs(err).max())
    if free.any():
        out['free_max_estimate'] = float(np.abs(ext[free]).max())
    rising = np.flatnonzero(flags & ~np.concatenate(([False], flags[:-1])))
    after = rising[t[rising] >= start]
    out['detection_delay'] = float(t[after[0]] - start) if len(after) else float('nan')
    out['false_alarms'] = int(np.count_nonzero(free[rising]))
    return out


def plot_panel(ax, rec):
    """True J^T F (dashed) against the estimate (solid) per joint, the collision flag shaded (the
    figure's legend names them)."""
    s = samples(rec)
    if s is None:
        return
    t, ext, flags, tt, true = s
    if len(tt):
        ax.plot(tt, true, lw=1.2, ls='--')
        ax.set_prop_cycle(None)
    if len(t):
        ax.plot(t, ext, lw=0.9)
        if flags.any():
            lo, hi = ax.get_ylim()
            ax.fill_between(t, lo, hi, where=flags, color='red', alpha=0.15, lw=0, label='~/collision')
            ax.set_ylim(lo, hi)
    ax.set_ylabel('external torque (Nm)')


def table(rows):
    """The contact rows as printed lines (empty when the scenario did not run)."""
    rows = [r for r in rows if r.get('scenario') == NAME]
    if not rows:
        return []
    cols = (('rms_estimate_error', 'RMS est. error (Nm)', '{:.3g}'), ('max_estimate_error', 'max est. error (Nm)',
                                                                      '{:.3g}'),
            ('true_max', 'max |J^T F| (Nm)', '{:.3g}'), ('free_max_estimate', 'free-motion max (Nm)', '{:.3g}'),
            ('detection_delay', 'detection delay (ms)', None), ('false_alarms', 'false alarms', '{:d}'))
    lines = ['', f"{'contact':10s} " + ' '.join(f'{h:>21s}' for _, h, _ in cols)]
    for r in rows:
        cells = []
        for key, _, fmt in cols:
            v = r.get(key)
            text = '' if v is None else (f'{1e3 * v:.1f}' if fmt is None else fmt.format(v))
            cells.append(f'{text:>21s}')
        lines.append(f"{r['scenario']:10s} " + ' '.join(cells))
    return lines


CSV_HEADER = 'scenario,estimates,rms_estimate_error,max_estimate_error,true_max,free_max_estimate,' \
             'detection_delay,false_alarms'


def csv_lines(rows):
    keys = CSV_HEADER.split(',')
    return [CSV_HEADER] + [','.join(str(r.get(k, '')) for k in keys) for r in rows if r.get('scenario') == NAME]
