"""The demo's contact scenario: the arm tracks the demo trajectory with feedforward + PD, known
wrenches push two links in turn, the forearm (link4) and then the flange (the simulator applies
them and publishes J^T F on ~/external_torques_true), and the dynamics node's momentum observer
estimates the external torques from the measured efforts, raises ~/collision, isolates the link
and estimates the wrench (~/contact/wrench).

Reported: the estimate against J^T F (RMS and max error once the estimate has settled, 5 time
constants after the push starts), the largest estimate during free motion (from the first step
on: not the held initial state), the detection delay (first collision flag after the push starts)
and the false alarms (collision flags rising during free motion: there must be none); per push,
the link isolated against the link pushed (its body link), the force error of the last wrench of
the push (% of |F|) and the distance from its line of action to the pushed point. The push
windows and the gain come from here; push i starts at PUSH_STARTS[i] x duration.
"""
import numpy as np

from ..cli import ros_array
from ..ros.core.cdr import stamp_ns

NAME = 'contact'
# (link, pushed point in its frame (m), force in its frame (N), the body link isolation names)
# the forearm's push loads its most loaded joint to about 2.4x its threshold: above the weak tier
# (contact.strict_below 2), where a push with fewer than 6 supporting joints is named; at 40 N (1.7x)
# the node says ambiguous, as it must (a contact further out fits as well)
PUSHES = (('link4', (-0.04, -0.2, 0.0), (60.0, 0.0, 0.0), 'link4'),    # the forearm, 20 cm from the elbow
          ('flange', (0.05, 0.0, 0.0), (0.0, 20.0, -30.0), 'link7'))   # 5 cm off the tool axis
PUSH_STARTS = (0.3, 0.6)                      # x duration
GAIN = 50.0                                   # 1/s: time constant 20 ms
THRESHOLD = (5.0, 5.0, 5.0, 5.0, 2.0, 2.0, 2.0)   # N m; free motion stays below 0.5 N m (see metrics)
HOLD = 0.01                                   # s
PUSH_LENGTH = 0.2                             # x duration, at most MAX_PUSH s
MAX_PUSH = 1.0
EXTERNAL_TOPIC = '/dynamics_node/external_torques'
COLLISION_TOPIC = '/dynamics_node/collision'
TRUTH_TOPIC = '/sim_node/external_torques_true'
WRENCH_TOPIC = '/dynamics_node/contact/wrench'
KEYS = ('ext_t', 'ext', 'flag', 'true_t', 'true', 'wrench_t', 'wrench_link', 'wrench')


def node_params():
    """dynamics_node overrides of the scenario (on top of the feedforward scenario's). The node is
    told the simulator's joint damping (its URDF <dynamics damping>; the demo's config turns
    friction off): friction the model does not know is reported as external torque."""
    from .. import default_urdf_path, load_urdf
    return {'observer.gain': repr(GAIN), 'collision.threshold': ros_array(THRESHOLD), 'collision.hold_time': repr(HOLD),
            'friction.viscous': ros_array(load_urdf(default_urdf_path()).damping)}


def wrench_of(push):
    """(m, f) in the pushed link's frame of a PUSHES entry: a pure force at its point."""
    _, p, f, _ = push
    return tuple(np.cross(p, f)) + tuple(f)


def push_windows(duration):
    """[(start, length)] of the pushes in simulated seconds."""
    return [(k * duration, min(PUSH_LENGTH * duration, MAX_PUSH)) for k in PUSH_STARTS]


def sim_params(duration):
    out = {}
    for i, (push, (start, length)) in enumerate(zip(PUSHES, push_windows(duration), strict=True)):
        tag = '' if i == 0 else str(i + 1)
        out.update({f'external.link{tag}': push[0], f'external.wrench{tag}': ros_array(wrench_of(push)),
                    f'external.start{tag}': repr(start), f'external.duration{tag}': repr(length)})
    return out


def link_names():
    """The bundled arm's links, in the model's order (the index ~/contact/wrench's link is recorded as)."""
    from .. import default_urdf_path, load_urdf
    return list(load_urdf(default_urdf_path()).link_frames)


def record(node, rec, depth):
    """Subscribe the demo's recorder to the estimate, the flag and the truth; append to rec.
    Returns whether the estimate and the flag readers have matched their publishers."""
    from geometry_msgs.msg import WrenchStamped
    from sensor_msgs.msg import JointState
    from std_msgs.msg import Bool

    def stamped(key_t, key):
        def on_msg(msg):
            rec[key_t].append(stamp_ns(msg.header.stamp.sec, msg.header.stamp.nanosec) * 1e-9)
            rec[key].append(list(msg.effort))
        return on_msg
    # Every message as it comes (copies of re-sent states too): Bool has no stamp, the node publishes
    # it right after each estimate, both reliable and in order, so the k-th flag is the k-th estimate's.
    links = link_names()

    def on_wrench(msg):   # the link as its index in link_names() (the record holds numbers only)
        rec['wrench_t'].append(stamp_ns(msg.header.stamp.sec, msg.header.stamp.nanosec) * 1e-9)
        rec['wrench_link'].append(links.index(msg.header.frame_id) if msg.header.frame_id in links else -1)
        f, m = msg.wrench.force, msg.wrench.torque
        rec['wrench'].append((f.x, f.y, f.z, m.x, m.y, m.z))
    node.create_subscription(WrenchStamped, WRENCH_TOPIC, on_wrench, depth)
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
    pushed = np.abs(true).max(axis=1) > 0
    if not pushed.any():
        return out
    edges = np.flatnonzero(np.diff(np.concatenate(([0], pushed.astype(int), [0]))))
    windows = [(tt[a], tt[b - 1]) for a, b in zip(edges[::2], edges[1::2], strict=True)]   # the pushes
    settle = 5.0 / GAIN
    truth = np.array([np.interp(t, tt, true[:, j]) for j in range(true.shape[1])]).T
    during = np.zeros(len(t), bool)
    free = t > 0
    for start, end in windows:
        during |= (t >= start + settle) & (t <= end)
        free &= (t < start) | (t > end + settle + HOLD)
    # Free motion starts with the first step. The initial state (stamp 0) is the simulator holding
    # the arm until the answers are in, its motor torque 0: the node times unstamped states with
    # its own clock, so its estimate of that holding torque grows with the copies, up to g(q0),
    # for however long a loaded machine makes the hold (and the first copy may miss the recorder).
    err = ext[during] - truth[during]
    start, end = windows[0][0], windows[-1][1]
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
    for i, (push, (a, b)) in enumerate(zip(PUSHES, windows, strict=False)):
        out.update(push_metrics(i + 1, push, rec, a, b))
    return out


def push_metrics(i, push, rec, start, end):
    """push{i}_link (pushed), push{i}_isolated (the link of the last nonzero ~/contact/wrench of the
    push, '' if none), and when it is the pushed link's body link: push{i}_supporting (its
    supporting joints: with fewer than 6 only the components they see are solved for),
    push{i}_force_error (% of |F|) and push{i}_line_cm (the line of action's distance from the
    pushed point)."""
    from .. import default_urdf_path, load_urdf
    from ..algorithms.contact_isolation import line_of_action, supporting_joints
    link, p, f, body = push
    out = {f'push{i}_link': link, f'push{i}_isolated': ''}
    last = [k for k, tw in enumerate(rec.get('wrench_t', ())) if start <= tw <= end and any(rec['wrench'][k])]
    if not last:
        return out
    k = last[-1]
    j = int(rec['wrench_link'][k])
    out[f'push{i}_isolated'] = link_names()[j] if j >= 0 else '?'
    if out[f'push{i}_isolated'] != body:
        return out
    model = load_urdf(default_urdf_path())
    out[f'push{i}_supporting'] = int(supporting_joints(model, body).sum())   # < 6: not every component seen
    pose = model.link_frames[link][1]   # the pushed link in its body link's frame
    R, o = pose[:3, :3], pose[:3, 3]
    f_b, p_b = R @ np.asarray(f), R @ np.asarray(p) + o
    w = np.asarray(rec['wrench'][k], dtype=float)
    out[f'push{i}_force_error'] = float(100 * np.linalg.norm(w[:3] - f_b) / np.linalg.norm(f_b))
    line = line_of_action(w)
    if line is not None:
        out[f'push{i}_line_cm'] = float(100 * np.linalg.norm(np.cross(p_b - line[0], line[1])))
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
        for i in range(1, len(PUSHES) + 1):
            if f'push{i}_link' not in r:
                continue
            fe, ln = r.get(f'push{i}_force_error'), r.get(f'push{i}_line_cm')
            lines.append(f"{'':10s} push {i} on {r[f'push{i}_link']}: isolated "
                         f"{r[f'push{i}_isolated'] or 'nothing'}, force error "
                         f"{'-' if fe is None else f'{fe:.2g} %'}, line of action "
                         f"{'-' if ln is None else f'{ln:.2g} cm'} from the pushed point"
                         + (f" ({r[f'push{i}_supporting']} supporting joints)" if f'push{i}_supporting' in r else ''))
    return lines


_PUSH_KEYS = ('link', 'isolated', 'supporting', 'force_error', 'line_cm')
CSV_HEADER = ('scenario,estimates,rms_estimate_error,max_estimate_error,true_max,free_max_estimate,'
              'detection_delay,false_alarms,'
              + ','.join(f'push{i}_{k}' for i in range(1, len(PUSHES) + 1) for k in _PUSH_KEYS))


def csv_lines(rows):
    keys = CSV_HEADER.split(',')
    return [CSV_HEADER] + [','.join(str(r.get(k, '')) for k in keys) for r in rows if r.get('scenario') == NAME]
