"""The embedded default: the bundled arm, simulated, held and driven by the dynamics node.

    make demo                      # 10 s per scenario
    make demo ARGS="--duration 0"  # feedforward tracking until Ctrl-C, live status line
                                   # (last 2 s; into a file: a line every 10 s); the plot
                                   # and table cover the last minute

Each scenario starts real processes (sim_node, dynamics_node, trajectory_source) talking
over DDS on this machine in a DDS domain of its own, records joint_states in this process,
and stops everything (SIGINT, then SIGKILL after a grace period; also on Ctrl-C):
  1. no compensation        the arm falls            max drift (rad)
  2. gravity compensation   the arm holds its pose   max drift (rad), target < 1e-3
  3. tracking               PD only vs PD + model feedforward: RMS tracking error (rad)
  4. contact                feedforward tracking, a push on the flange: the node's external-torque
                            estimate against J^T F, detection delay, false alarms (contact_demo.py)
  5. payload                feedforward tracking with a load the node does not know, then
                            ~/identify_payload: RMS error before and after, identified vs true
                            mass and CoM (payload_demo.py)
  6. calibration           the simulated arm is not its URDF: hold, excitation recorded by the
                            node, identify_dynamics, hold again and track a held-out motion with the
                            calibration (calibration_demo.py; 2 x duration s of excitation)
Prints a table and writes a PNG (joint angles and torques over time), a CSV of the metrics and
the processes' logs (<out>/logs/<scenario>/).
The simulator runs in lockstep with the controller (each step waits for the command answering
the last state, and in the tracking scenarios for the desired state of the next step), so the
numbers do not depend on how loaded the machine is, and it steps as soon as the answers are in.
"""
import collections
import itertools
import os
import re
import signal
import subprocess
import sys
import tempfile
import time

import numpy as np

from .. import default_urdf_path
from ..cli import ros_array
from .domains import reserve_domains
from . import calibration_demo, contact_demo, payload_demo
from .trajectory_source import desired_state
from ..model.urdf import load_urdf
from ..ros.core.cdr import stamp_ns

HOME = [0.0, -0.6, 0.0, 2.0, 0.0, 1.6, 0.8]   # an arm pose with large gravity torques
AMPLITUDE = [0.4, 0.3, 0.4, 0.3, 0.5, 0.4, 0.5]
FREQUENCY = [0.3, 0.25, 0.35, 0.3, 0.4, 0.35, 0.45]
KP = [60.0, 60.0, 60.0, 60.0, 15.0, 15.0, 15.0]
KD = [8.0, 8.0, 8.0, 8.0, 1.5, 1.5, 1.5]
# Unbounded runs (duration 0) keep only this much history (plot, final table), so memory stays
# bounded over hours; the live status line looks at the last STATUS_WINDOW_S.
HISTORY_S = 60.0
# The simulator steps with the held command only after this long without an answer (a dead
# controller); shorter waits made results depend on machine load.
LOCKSTEP_TIMEOUT = 2.0
STATUS_WINDOW_S = 2.0

# set by Ctrl-C / SIGTERM in the demo's main: the loops stop at their next check (check_stop). A
# list appended to, as ros/run.py's stop flag: no lock (threading.Event.set takes one, which a
# second signal arriving inside set() would wait on forever)
STOP = []
STATUS_LOG_PERIOD_S = 10.0  # status lines into a file or pipe (not a terminal): at most this often
# where trajectory_source publishes and the node (desired_topic ~/desired) listens
DESIRED_TOPIC = '/dynamics_node/desired'
PKG_DIR = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))  # lie_dynamics/
CONFIG = os.path.join(os.path.dirname(PKG_DIR), 'config', 'arm7_gravity.yaml')


def scenarios():
    """name -> (dynamics node overrides or None, with trajectory source?)."""
    # The simulator has no Coulomb friction to cancel. Lockstep runs slower than real time and
    # waits for each command, so the node's wall-clock timeouts (0.1 s, meant for a real robot)
    # are relaxed: a loaded machine must not turn a late message into a fallback command.
    common = {'friction.coulomb': '[0.0]', 'stale_timeout': '1.0', 'desired_timeout': '1.0'}
    gains = dict(common, kp=ros_array(KP), kd=ros_array(KD))
    tracking = dict(gains, mode='feedforward')
    return {
        'no compensation': (None, False),
        'gravity compensation': (dict(common, mode='gravity'), False),
        'PD only': (dict(gains, mode='pd'), True),
        'PD + feedforward': (tracking, True),
        contact_demo.NAME: (dict(tracking, **contact_demo.node_params()), True),
        payload_demo.NAME: (tracking, True),
    }


# After SIGINT, a process has this long to stop before it is killed
STOP_GRACE_S = 5.0
# Once the simulator has ended, the recorder stops after this long without a new state
DRAIN_QUIET_S = 10.0


class Stack:
    """The processes of one scenario; always cleaned up (context manager)."""

    def __init__(self, env, log_dir):
        self.env, self.log_dir, self.procs = env, log_dir, []
        self.exit_codes = {}  # name -> return code once stopped (negative: killed by a signal)
        self.self_ending = set()  # processes with a step budget: let them finish before signalling

    def start(self, name, module, params, params_file=None, ends_by_itself=False):
        args = [sys.executable, '-m', module, '--ros-args']
        if params_file:  # a file first: the -p overrides after it win
            args += ['--params-file', params_file]
        for k, v in params.items():
            args += ['-p', f'{k}:={v}']
        log = open(os.path.join(self.log_dir, name + '.log'), 'w')
        self.procs.append((name, subprocess.Popen(args, env=self.env, stdout=log, stderr=subprocess.STDOUT,
                                                  cwd=os.path.dirname(PKG_DIR)), log))
        if ends_by_itself:
            self.self_ending.add(name)

    def check(self):
        """Raise if a process died; returns True once every self-ending process has finished."""
        for name, p, _ in self.procs:
            code = p.poll()
            if code is not None and not (code == 0 and name in self.self_ending):
                raise RuntimeError(f'{name} exited with code {code}; its log ends:\n{self.log_tail(name)}')
        return bool(self.self_ending) and all(p.poll() is not None for name, p, _ in self.procs
                                              if name in self.self_ending)

    def log_tail(self, name, lines=20):
        with open(os.path.join(self.log_dir, name + '.log'), errors='replace') as fh:
            return ''.join(collections.deque(fh, lines))

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        from .sim_node import DELIVER_TIMEOUT_S
        finished = exc[0] is None
        # a process that ends by itself is not asked to stop while it may still be delivering its
        # last states and exiting (a loaded machine takes seconds): its own bound, then the grace
        deadline = time.monotonic() + DELIVER_TIMEOUT_S + STOP_GRACE_S
        for name, p, _ in self.procs:
            if finished and name in self.self_ending:
                try:
                    p.wait(timeout=max(0.1, deadline - time.monotonic()))
                except subprocess.TimeoutExpired:
                    pass
        for _, p, _ in self.procs:
            if p.poll() is None:
                p.send_signal(signal.SIGINT)
        deadline = time.monotonic() + STOP_GRACE_S
        for _, p, log in self.procs:
            try:
                p.wait(timeout=max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
            log.close()
        self.exit_codes = {name: p.returncode for name, p, _ in self.procs}
        return False


def record_states(node, rec):
    """Subscribe `node` to joint_states, appending each simulated step's stamp, positions,
    velocities and efforts to rec['t'], rec['q'], rec['qd'], rec['tau']."""
    from sensor_msgs.msg import JointState

    def on_state(msg):
        t = stamp_ns(msg.header.stamp.sec, msg.header.stamp.nanosec) * 1e-9
        if rec['t'] and t == rec['t'][-1]:
            return  # the simulator re-sent an unanswered state: one sample per simulated step
        rec['t'].append(t)
        rec['q'].append(list(msg.position))
        rec['qd'].append(list(msg.velocity))
        rec['tau'].append(list(msg.effort))
    # deep enough for a whole default run: a reader that falls behind must not drop the oldest states
    node.create_subscription(JointState, 'joint_states', on_state, 20000)


def log_folder(out, name):
    """Where the demo writes the process logs of a scenario: <out>/logs/<scenario>/."""
    return os.path.abspath(os.path.join(out, 'logs', re.sub(r'[^a-z0-9]+', '_', name.lower()).strip('_')))


def run_scenario(name, duration, rate=1000.0, status=None, domain=None, log_dir=None):
    """Run one scenario for `duration` simulated seconds (0: until Ctrl-C). Returns a record dict.
    The processes' output goes to log_dir/<process>.log; without log_dir to a temporary folder,
    removed at the end (a process that fails is reported with the end of its log)."""
    if log_dir is None:
        with tempfile.TemporaryDirectory(prefix='lie_dynamics_demo_') as tmp:
            return run_scenario(name, duration, rate, status, domain, tmp)
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    node_params, with_traj = scenarios()[name]
    payload = name == payload_demo.NAME
    if payload:  # identify.duration follows the scenario's duration
        node_params = dict(node_params, **payload_demo.node_params(duration))
    env = dict(os.environ)
    env['ROS_DOMAIN_ID'] = str(domain if domain is not None else reserve_domains(1)[0])
    env.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    os.makedirs(log_dir, exist_ok=True)
    steps = int(round(duration * rate)) if duration > 0 else 0
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=int(env['ROS_DOMAIN_ID']))
    keep = None if steps else max(1, int(HISTORY_S * rate))
    contact = name == contact_demo.NAME
    rec = {k: collections.deque(maxlen=keep) for k in ('t', 'q', 'qd', 'tau') + (contact_demo.KEYS if contact else ())
           + (payload_demo.KEYS if payload else ())}
    interrupted = False
    stack = node = ex = None
    try:
        node = rclpy.create_node('demo_recorder', context=ctx)
        ex = SingleThreadedExecutor(context=ctx)
        ex.add_node(node)

        record_states(node, rec)
        # the node's estimate topics reach the recorder before the simulator starts
        estimates_matched = contact_demo.record(node, rec, 20000) if contact else (lambda: True)
        caller = payload_demo.Caller(node, rec, duration) if payload else None
        stack = Stack(env, log_dir)
        with stack:
            if node_params is not None:
                if os.path.isfile(CONFIG):
                    stack.start('dynamics_node', 'lie_dynamics.dynamics_node', node_params, CONFIG)
                else:  # installed without the source tree's config/
                    stack.start('dynamics_node', 'lie_dynamics.dynamics_node',
                                dict({'urdf_path': default_urdf_path()}, **node_params))
                # the recorder's own reader counts too
                if not _wait(ex, lambda: node.count_subscribers('joint_states') >= 2 and estimates_matched(), 20.0,
                             stack):
                    raise RuntimeError('dynamics_node did not come up')
            if with_traj:
                stack.start('trajectory_source', 'lie_dynamics.sim.trajectory_source',
                            {'home': ros_array(HOME), 'amplitude': ros_array(AMPLITUDE),
                             'frequency': ros_array(FREQUENCY),
                             # the dynamics node's desired reader matched before the first state
                             'min_subscribers': str(int(node_params is not None))})
                if not _wait(ex, lambda: node.count_subscribers('joint_states') >= 2 + (node_params is not None),
                             20.0, stack):
                    raise RuntimeError('trajectory_source did not come up')
            stack.start('sim_node', 'lie_dynamics.sim.sim_node',
                        {'rate': f'{rate:.1f}', 'initial_positions': ros_array(HOME),
                         'lockstep': 'true' if node_params is not None else 'false',
                         # without a controller nothing ever commands: the arm must fall from the start
                         'hold_until_command': 'true' if node_params is not None else 'false',
                         'lockstep_timeout': f'{LOCKSTEP_TIMEOUT:.1f}',
                         'min_subscribers': str(1 + (node_params is not None) + with_traj),
                         'max_steps': str(steps), **(contact_demo.sim_params(duration) if contact else {}),
                         **(payload_demo.sim_params() if payload else {}),
                         # the tracking scenarios also wait for the desired state of the next step
                         **({'lockstep_stamped_topic': DESIRED_TOPIC} if with_traj and node_params else {})},
                        ends_by_itself=steps > 0)
            last_check = last_status = 0.0
            drain_until, drained = None, 0
            try:
                while True:
                    ex.spin_once(timeout_sec=0.05)  # one callback: keep this loop lean, it must not lag
                    check_stop()
                    if caller is not None:
                        caller.tick()
                    if steps and rec['t'] and rec['t'][-1] >= duration - 0.5 / rate:
                        break
                    now = time.monotonic()
                    if drain_until is not None and now > drain_until:
                        break  # the simulator is done: what has not arrived by now will not
                    if now - last_check > 0.2:
                        last_check = now
                        n = len(rec['t'])
                        # the simulator is done: take what still comes, until DRAIN_QUIET_S pass without a
                        # state (a loaded machine leaves this reader seconds behind the simulator)
                        if stack.check() and (drain_until is None or n > drained):
                            drain_until, drained = now + DRAIN_QUIET_S, n
                    if status and now - last_status > 1.0 and rec['t']:
                        last_status = now
                        status(name, tail(rec, int(STATUS_WINDOW_S * rate)))
            except KeyboardInterrupt:  # keep what was recorded; the caller reports it
                interrupted = True
    finally:
        # destroy the reader explicitly: a leftover one would count as "ready" for the next sim
        if ex is not None:
            ex.shutdown()
        if node is not None:
            node.destroy_node()
        rclpy.shutdown(context=ctx)
    out = {k: np.array(v, dtype=float) for k, v in rec.items()}
    out['interrupted'] = interrupted
    out['exit_codes'] = stack.exit_codes
    return out


def _request_stop(*_):
    if STOP:  # asked twice: stop at once
        raise KeyboardInterrupt
    STOP.append(True)


def check_stop():
    """KeyboardInterrupt once a stop was requested (STOP)."""
    if STOP:
        raise KeyboardInterrupt


def tail(rec, n):
    """The last n samples of a record of deques, as lists (cost O(n), not O(history))."""
    return {k: list(itertools.islice(reversed(v), n))[::-1] for k, v in rec.items()}


def _wait(ex, cond, timeout, stack):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if cond():
            return True
        ex.spin_once(timeout_sec=0.05)
        check_stop()
        stack.check()
    return False


def metrics(name, rec):
    """Numbers the demo reports (and the tests assert)."""
    q, t = rec['q'], rec['t']
    out = {'scenario': name, 'samples': len(t), 'duration': float(t[-1] - t[0]) if len(t) else 0.0}
    if not len(t):
        return out
    if name in ('no compensation', 'gravity compensation'):
        out['drift'] = float(np.max(np.abs(q - np.asarray(HOME))))
    else:
        qd_des = desired_state(t[:, None], np.asarray(HOME), np.asarray(AMPLITUDE), np.asarray(FREQUENCY))[0]
        err = q - qd_des
        out['rms_error'] = float(np.sqrt(np.mean(err ** 2)))
        out['max_error'] = float(np.max(np.abs(err)))
    if name == contact_demo.NAME:
        out.update(contact_demo.metrics(rec))
    if name == payload_demo.NAME:
        out.update(payload_demo.metrics(rec, lambda t: desired_state(t[:, None], np.asarray(HOME),
                                                                   np.asarray(AMPLITUDE), np.asarray(FREQUENCY))[0]))
    return out


def plot(records, path):
    """The PNG of the runs (demo_plot.py), each scenario titled with its result."""
    from .demo_plot import plot as draw
    notes = {}
    for name, rec in records.items():
        m = metrics(name, rec)
        if 'drift' in m:
            notes[name] = f"max drift {m['drift']:.1e} rad"
        elif 'rms_error' in m:
            notes[name] = f"RMS tracking error {m['rms_error']:.1e} rad"
    draw(records, path, HOME, lambda t: desired_state(t[:, None], np.asarray(HOME), np.asarray(AMPLITUDE),
                                                      np.asarray(FREQUENCY))[0], notes)


class StatusLine:
    """The live status of an unbounded run. On a terminal one line rewritten in place (about once a
    second, as run_scenario calls it); into a file or pipe a plain line at most every `period`
    seconds, so a log does not fill with carriage returns."""

    def __init__(self, stream, period=STATUS_LOG_PERIOD_S, clock=time.monotonic):
        self.stream, self.period, self.clock = stream, period, clock
        self.tty = stream.isatty()
        self.last = None

    def __call__(self, name, rec):
        now = self.clock()
        if not self.tty and self.last is not None and now - self.last < self.period:
            return
        self.last = now
        m = metrics(name, {k: np.asarray(v, dtype=float) for k, v in rec.items()})
        err = m.get('rms_error', m.get('drift', np.nan))
        line = (f"{name:22s} t = {rec['t'][-1]:7.2f} s  {'rms error' if 'rms_error' in m else 'drift'} "
                f"(last {STATUS_WINDOW_S:g} s) {err:.2e} rad")
        self.stream.write(f'\r{line}   ' if self.tty else line + '\n')
        self.stream.flush()


EPILOG = """\
--duration: simulated seconds per scenario, > 0; or 0 to run the tracking scenario
  (PD + feedforward) until Ctrl-C with a live status line (rewritten in place on a
  terminal; into a file or pipe a line every 10 s). Negative values are refused.
scenarios: {names}
output (in --out): demo_metrics.csv (scenario, samples, drift, rms_error, max_error; rad)
  and demo.png (joint angles and torques over simulated time); with the contact scenario also
  demo_contact.csv (estimate error, largest free-motion estimate and J^T F in N m, detection
  delay in s, false alarms); with the calibration scenario demo_calibration.csv and calibration/
  (plant.yaml, excitation.csv, recordings/, calibration.yaml, report/);
  logs/<scenario>/<process>.log, the output of every process (sim_node, dynamics_node,
  trajectory_source). Nothing is left in the temp dir.
examples:
  python -m lie_dynamics.demo                          # every scenario, 10 s each
  python -m lie_dynamics.demo --duration 3 --scenarios 'gravity compensation'
  python -m lie_dynamics.demo --duration 0             # until Ctrl-C
"""


def main(argv=None):
    """Run the scenarios, print the table, write the PNG and the CSV; 0 on success, 2 on bad arguments."""
    from ..cli import CliParser, number, run_cli

    names = list(scenarios()) + [calibration_demo.NAME]
    ap = CliParser('lie_dynamics.demo', description=__doc__.split('\n')[0],
                   epilog=EPILOG.format(names=', '.join(repr(n) for n in names)))
    ap.add_argument('--duration', type=number(low=0, what='> 0 seconds, or 0 to run until Ctrl-C'), default=10.0,
                    help='simulated seconds per scenario, > 0; 0: until Ctrl-C (default 10)')
    # the simulator is handed the rate with one decimal: below 1 Hz that would round it to 0
    ap.add_argument('--rate', type=number(low=1), default=1000.0, help='simulation rate, Hz, >= 1 (default 1000)')
    ap.add_argument('--out', default='demo_out', help='output folder for the PNG and CSV (default demo_out)')
    ap.add_argument('--scenarios', nargs='*', default=None, choices=names, metavar='NAME',
                    help='subset of the scenarios (default: all)')
    # Only the preparation counts as input: an error while the scenarios run is a failure, not bad input.
    return _run(run_cli(ap, _prepare, argv))


def _prepare(args):
    """Checks that need more than argparse: an unusable --out, a broken bundled model."""
    os.makedirs(args.out, exist_ok=True)
    load_urdf(default_urdf_path())
    return args


def _run(args):
    # Ctrl-C and SIGTERM (a closing terminal, a CI timeout) stop the run cleanly: no orphans, no DDS
    # leftovers, the results so far written. The handler only sets a flag that the loops check: an
    # exception raised inside an rclpy call (where a signal usually lands) is not a clean stop.
    STOP.clear()
    previous = {sig: signal.signal(sig, _request_stop) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        records = _scenarios(args)
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    _report(args, records)
    return 0


def _scenarios(args):
    """Run the chosen scenarios (or the unbounded one); name -> record of those that ran."""
    status = StatusLine(sys.stdout)
    records = {}
    try:
        for name in (['PD + feedforward'] if args.duration <= 0 else
                     args.scenarios or list(scenarios()) + [calibration_demo.NAME]):
            if args.duration > 0:
                print(f'running: {name} ({args.duration:g} s simulated)', flush=True)
            if name == calibration_demo.NAME:   # phases of its own, figures of its own
                records[name] = calibration_demo.run(args.duration, args.rate, args.out, log_folder(args.out, name))
            else:
                records[name] = run_scenario(name, max(args.duration, 0.0), args.rate, status=status,
                                             log_dir=log_folder(args.out, name))
            print()
            if records[name]['interrupted']:
                raise KeyboardInterrupt
    except KeyboardInterrupt:
        print('\ninterrupted: processes stopped')
    return records


def _report(args, records):
    """The table, the CSVs and the PNG."""
    calibration = records.pop(calibration_demo.NAME, None)
    rows = [metrics(n, r) for n, r in records.items()]
    print(f"\n{'scenario':24s} {'samples':>8s} {'max drift (rad)':>16s} {'RMS error (rad)':>16s} "
          f"{'max error (rad)':>16s}")
    for r in rows:
        cells = (f'{r[k]:16.3e}' if k in r else ' ' * 16 for k in ('drift', 'rms_error', 'max_error'))
        print(f"{r['scenario']:24s} {r['samples']:8d} " + ' '.join(cells))  # not applicable: empty
    with open(os.path.join(args.out, 'demo_metrics.csv'), 'w') as fh:
        fh.write('scenario,samples,drift,rms_error,max_error\n')
        for r in rows:
            fh.write(f"{r['scenario']},{r['samples']},{r.get('drift', '')},{r.get('rms_error', '')},"
                     f"{r.get('max_error', '')}\n")
    contact = contact_demo.table(rows)
    if contact:
        print('\n'.join(contact))
        with open(os.path.join(args.out, 'demo_contact.csv'), 'w') as fh:
            fh.write('\n'.join(contact_demo.csv_lines(rows)) + '\n')
    payload = payload_demo.table(rows)
    if payload:
        print('\n'.join(payload))
        with open(os.path.join(args.out, 'demo_payload.csv'), 'w') as fh:
            fh.write('\n'.join(payload_demo.csv_lines(rows)) + '\n')
    if calibration is not None:
        print('\n'.join(calibration_demo.table(calibration)))
        with open(os.path.join(args.out, 'demo_calibration.csv'), 'w') as fh:
            fh.write('\n'.join(calibration_demo.csv_lines(calibration)) + '\n')
    if records:
        png = os.path.abspath(os.path.join(args.out, 'demo.png'))
        plot(records, png)
        print(f'plot: {png}')


if __name__ == '__main__':
    sys.exit(main())
