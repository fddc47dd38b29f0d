"""The demo's payload scenario: the simulated arm carries a load on tool0 that its
robot_description does not show (sim_node payload.*), while the dynamics node tracks the demo
trajectory with feedforward + PD. Its model lacks the load, so the tracking error grows; at
CALL_AT x duration the demo calls ~/identify_payload, which records RECORD x duration seconds of
the same tracking motion, fits the load and sets payload.*; the error then drops back.

Reported: RMS tracking error before the call and over the last AFTER x duration (once the
new payload has settled), the true and the identified mass and CoM (read back from the node's
parameters, as `ros2 param get` would), and whether the service succeeded.
"""
import numpy as np

from .. import default_urdf_path
from ..cli import ros_array
from ..model.urdf import load_urdf

NAME = 'payload'
LINK = 'tool0'
MASS = 2.0                                     # kg
COM = (0.03, -0.02, 0.08)                      # m, tool0 frame
INERTIA = (0.012, 0.0, 0.0, 0.014, 0.0, 0.008)  # kg m^2 about the CoM
CALL_AT = 0.15                                 # x duration: when the demo calls ~/identify_payload
RECORD = 0.3                                   # x duration: identify.duration
# The error after is measured over the last AFTER x duration, and at least SETTLE s after the
# answer (the blend is ramp_time = 0.2 s; the PD loop of joint 2 then needs ~2 s to settle)
AFTER = 0.25
SETTLE = 0.3
START = 0.1                                    # x duration: the error before is measured from here
SERVICE = '/dynamics_node/identify_payload'
PARAMS = '/dynamics_node/get_parameters'
KEYS = ('id_call_t', 'id_done_t', 'id_success', 'id_mass', 'id_com')


def node_params(duration):
    """dynamics_node overrides (on top of the feedforward scenario's). The simulator's joints have
    URDF damping: the node models it as viscous friction, so the fit does not take it for payload."""
    return {'identify.link': LINK, 'identify.duration': repr(RECORD * duration),
            'friction.viscous': ros_array(load_urdf(default_urdf_path()).damping)}


def sim_params():
    return {'payload.link': LINK, 'payload.mass': repr(MASS), 'payload.com': ros_array(COM),
            'payload.inertia': ros_array(INERTIA)}


class Caller:
    """Calls ~/identify_payload from the demo's recorder node once the simulation passes
    CALL_AT x duration, then reads payload.mass and payload.com back; `tick()` from the demo loop
    (the recorder's executor completes the futures). Results go into rec (numbers only)."""

    def __init__(self, node, rec, duration):
        from rcl_interfaces.srv import GetParameters
        from std_srvs.srv import Trigger
        self.rec, self.call_at = rec, CALL_AT * duration
        self.trigger, self.get = node.create_client(Trigger, SERVICE), node.create_client(GetParameters, PARAMS)
        self.request, self.get_request = Trigger.Request(), GetParameters.Request(names=['payload.mass',
                                                                                         'payload.com'])
        self.future = None
        self.state = 'waiting'
        self.message = ''

    def tick(self):
        rec = self.rec
        t = rec['t'][-1] if rec['t'] else 0.0
        if self.state == 'waiting' and t >= self.call_at and self.trigger.service_is_ready():
            self.future, self.state = self.trigger.call_async(self.request), 'calling'
            rec['id_call_t'].append(t)
        elif self.state == 'calling' and self.future.done():
            res = self.future.result()
            self.message = res.message
            rec['id_done_t'].append(t)
            rec['id_success'].append(float(res.success))
            self.future, self.state = (self.get.call_async(self.get_request), 'reading') if res.success else (None,
                                                                                                            'done')
        elif self.state == 'reading' and self.future.done():
            values = self.future.result().values
            rec['id_mass'].append(values[0].double_value)
            rec['id_com'].append(list(values[1].double_array_value))
            self.state = 'done'


def metrics(rec, desired):
    """RMS tracking error before the call and after the identified payload settled; true and
    identified mass and CoM. desired(t) -> q_d (N, n)."""
    t, q = rec['t'], rec['q']
    out = {'true_mass': MASS, 'true_com': list(COM), 'identified': bool(len(rec['id_success']) and
                                                                       rec['id_success'][0] > 0)}
    if not len(t) or not len(rec['id_call_t']):
        return out
    err = np.sqrt(np.mean((q - desired(t)) ** 2, axis=1))
    before = (t >= START * (t[-1] - t[0]) + t[0]) & (t < rec['id_call_t'][0])
    if before.any():
        out['rms_before'] = float(np.sqrt(np.mean(err[before] ** 2)))
    if len(rec['id_done_t']):
        after = t >= max(rec['id_done_t'][0] + SETTLE, t[-1] - AFTER * (t[-1] - t[0]))
        if after.any():
            out['rms_after'] = float(np.sqrt(np.mean(err[after] ** 2)))
    if len(rec['id_mass']):
        out['identified_mass'] = float(rec['id_mass'][0])
        out['identified_com'] = [float(c) for c in rec['id_com'][0]]
        out['com_error'] = float(np.linalg.norm(np.asarray(out['identified_com']) - COM))
    return out


def mark(ax, rec, label=True):
    """The ~/identify_payload call and its answer as vertical lines on a panel, each named at the
    top of the panel (label) and in the figure's legend."""
    for key, style, colour, text in (('id_call_t', ':', '0.45', 'call'), ('id_done_t', '-.', 'k', 'answer')):
        for x in rec[key]:
            ax.axvline(x, color=colour, ls=style, lw=1.5)
            if label:
                ax.annotate(text, (x, 1.0), xycoords=('data', 'axes fraction'), xytext=(3, -3),
                            textcoords='offset points', va='top', ha='left', color=colour,
                            bbox=dict(boxstyle='round,pad=0.15', fc='white', ec='none', alpha=0.8))


def table(rows):
    rows = [r for r in rows if r.get('scenario') == NAME]
    if not rows:
        return []
    head = (f"{'payload':10s} {'RMS err. before (rad)':>21s} {'RMS err. after (rad)':>21s} {'mass true (kg)':>15s} "
            f"{'mass ident. (kg)':>17s} {'CoM true (m)':>22s} {'CoM identified (m)':>24s} {'|CoM err| (m)':>13s}")
    lines = ['', head]
    for r in rows:
        def num(key, fmt, r=r):
            return fmt.format(r[key]) if key in r else ''
        com = '[' + ', '.join(f'{c:.3f}' for c in r['identified_com']) + ']' if 'identified_com' in r else (
            'refused' if not r.get('identified') else '')
        lines.append(f"{r['scenario']:10s} {num('rms_before', '{:.3e}'):>21s} {num('rms_after', '{:.3e}'):>21s} "
                     f"{r['true_mass']:15.3f} {num('identified_mass', '{:.3f}'):>17s} "
                     f"{'[' + ', '.join(f'{c:.3f}' for c in r['true_com']) + ']':>22s} {com:>24s} "
                     f"{num('com_error', '{:.1e}'):>13s}")
    return lines


CSV_HEADER = 'scenario,rms_before,rms_after,true_mass,identified_mass,com_error,identified'


def csv_lines(rows):
    keys = CSV_HEADER.split(',')
    return [CSV_HEADER] + [','.join(str(r.get(k, '')) for k in keys) for r in rows if r.get('scenario') == NAME]
