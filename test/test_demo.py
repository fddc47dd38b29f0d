"""The embedded default, shortened: each demo scenario through the real processes over DDS."""
import os
import select
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from lie_dynamics.sim import demo

DURATION = 2.0  # simulated seconds per scenario


def _domain():
    # reserved for this worker by conftest.py: no other test or test run uses it
    return int(os.environ['LIE_DYNAMICS_TEST_DEMO_DOMAIN'])


def _logs(log_dir):
    return '\n'.join(f'--- {p.name}\n{p.read_text()[-3000:]}' for p in sorted(log_dir.iterdir()))


def _shm_port_files():
    """Fast DDS names its shared-memory port files after RTPS ports, 7400 + 250 * domain + k
    (k < 250): the files of the demo's domain."""
    if not os.path.isdir('/dev/shm'):
        return None
    lo = 7400 + 250 * _domain()
    left = set()
    for name in os.listdir('/dev/shm'):
        digits = name.split('fastrtps_port')[-1].split('_')[0] if 'fastrtps_port' in name else ''
        if digits.isdigit() and lo <= int(digits) < lo + 250:
            left.add(name)
    return left


@pytest.fixture(scope='module')
def shm_before():
    # files a killed process of some earlier run left behind are not this run's doing
    return _shm_port_files()


@pytest.fixture(scope='module')
def runs(tmp_path_factory, shm_before):
    out = {}
    for name in demo.scenarios():
        log_dir = tmp_path_factory.mktemp('logs')
        rec = demo.run_scenario(name, DURATION, domain=_domain(), log_dir=str(log_dir))
        rec['logs'] = _logs(log_dir)
        out[name] = (rec, demo.metrics(name, rec))
    return out


def test_every_process_exits_cleanly(runs):
    for name, (rec, _) in runs.items():
        assert not rec['interrupted']
        # the logs say how far a process that had to be killed (-9) got in its shutdown
        assert rec['exit_codes'] and all(code == 0 for code in rec['exit_codes'].values()), \
            (name, rec['exit_codes'], rec['logs'])
        info = (name, float(rec['t'][0]), float(rec['t'][-1]), len(rec['t']), rec['logs'])
        assert rec['t'][-1] >= DURATION - 1e-3, info  # ran to the end
        assert len(rec['t']) > 0.9 * DURATION * 1000, info  # and the recorder saw (nearly) every state


def test_without_compensation_the_arm_falls(runs):
    assert runs['no compensation'][1]['drift'] > 0.5


def test_gravity_compensation_holds(runs):
    m = runs['gravity compensation'][1]
    assert m['drift'] < 1e-3


def test_feedforward_tracks_clearly_better_than_pd(runs):
    pd, ff = runs['PD only'][1], runs['PD + feedforward'][1]
    assert ff['rms_error'] < 1e-2, runs['PD + feedforward'][0]['logs']
    assert ff['rms_error'] * 5 < pd['rms_error']
    assert ff['max_error'] < pd['max_error']


def test_payload_identification_removes_the_tracking_error(runs):
    """The simulated arm carries 2 kg the node does not know; ~/identify_payload finds it from the
    tracking motion and the error drops."""
    rec, m = runs['payload']
    assert m['identified'] and 'rms_after' in m, (m, rec['logs'])
    assert m['identified_mass'] == pytest.approx(m['true_mass'], rel=0.05) and m['com_error'] < 0.01, m
    assert m['rms_before'] > 0.02 and m['rms_after'] * 3 < m['rms_before'], m


def test_recorded_torques_respect_limits(runs):
    from lie_dynamics import default_urdf_path, load_urdf
    limits = load_urdf(default_urdf_path()).effort_limits
    for name in ('gravity compensation', 'PD + feedforward'):
        rec = runs[name][0]
        # the recorded effort is the motor torque: the command after the node's clamp (and the
        # simulated drive's, which must then have had nothing to do)
        assert np.all(np.abs(rec['tau']) <= limits)


def test_contact_is_estimated_and_flagged_without_false_alarms(runs):
    """The pushes on the forearm and the flange: the node's estimate follows J^T F, ~/collision
    rises within a few time constants of the push and never during free motion, the link is isolated."""
    m = runs['contact'][1]
    info = dict(m)
    assert m['true_max'] > 5.0, info                                   # the push did reach the joints
    assert m['rms_estimate_error'] < 0.02 * m['true_max'], info
    assert m['free_max_estimate'] < 0.2 * min(demo.contact_demo.THRESHOLD), info
    assert 0 < m['detection_delay'] < 0.1, info
    assert m['false_alarms'] == 0, info
    # the two pushes in turn: each isolated at its link; the flange's (7 supporting joints) wrench
    # recovered on the moving arm (2 s run: 5.8 % and 0.42 cm measured)
    assert (m['push1_link'], m['push1_isolated']) == ('link4', 'link4'), info
    assert (m['push2_link'], m['push2_isolated']) == ('flange', 'link7'), info
    assert m['push2_force_error'] < 10.0 and m['push2_line_cm'] < 1.0, info


def test_no_shared_memory_left_behind(runs, shm_before):
    """Once every process of the scenarios has stopped, none of them left a port file behind."""
    if shm_before is None:
        pytest.skip('no /dev/shm on this system')
    assert not _shm_port_files() - shm_before


def test_demo_main_writes_table_png_and_csv(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv('ROS_DOMAIN_ID', str(_domain()))
    assert demo.main(['--duration', '0.3', '--scenarios', 'gravity compensation', '--out', str(tmp_path)]) == 0
    text = capsys.readouterr().out
    assert 'gravity compensation' in text and 'plot:' in text
    png = tmp_path / 'demo.png'
    assert png.read_bytes()[:8] == b'\x89PNG\r\n\x1a\n' and png.stat().st_size > 10000
    lines = (tmp_path / 'demo_metrics.csv').read_text().splitlines()
    assert lines[0] == 'scenario,samples,drift,rms_error,max_error' and lines[1].startswith('gravity compensation,')


def test_unbounded_run_keeps_bounded_history_and_stops_cleanly(tmp_path, monkeypatch):
    """duration 0 runs until interrupted: only the last HISTORY_S of samples are kept, the status
    callback sees the last STATUS_WINDOW_S, and an interrupt stops every process cleanly."""
    monkeypatch.setattr(demo, 'HISTORY_S', 0.05)   # 50 samples at 1 kHz
    before = _shm_port_files()
    windows = []

    def status(name, window):   # called about once a second
        windows.append(window)
        if window['t'][-1] > 0.2 or len(windows) >= 60:   # well past the kept history (or give up)
            raise KeyboardInterrupt   # what Ctrl-C does in the demo's loop

    rec = demo.run_scenario('PD + feedforward', 0.0, status=status, domain=_domain(), log_dir=str(tmp_path))
    assert rec['interrupted'] and len(windows) < 60
    assert 0 < len(rec['t']) <= 50 and np.all(np.diff(rec['t']) > 0)
    assert rec['t'][-1] > 0.05                           # it ran past the kept history
    last = windows[-1]
    assert 0 < len(last['t']) <= 50 and last['t'] == sorted(last['t'])
    assert len(last['q']) == len(last['t']) and len(last['q'][-1]) == 7
    assert rec['exit_codes'] and all(code == 0 for code in rec['exit_codes'].values()), rec['exit_codes']
    if before is not None:
        assert not _shm_port_files() - before


# The demo as a user runs it, in a process of its own whose TMPDIR is private (so only its files are
# seen), in the DDS domain conftest.py reserved for this worker's demo processes.
DEMO = ('import os, sys\n'
        'from lie_dynamics.sim import demo\n'
        "demo.reserve_domains = lambda count, start=None: [int(os.environ['LIE_DYNAMICS_TEST_DEMO_DOMAIN'])]\n"
        'sys.exit(demo.main(sys.argv[1:]))\n')
ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _demo_process(tmp_path, *args):
    tmp = tmp_path / 'tmp'
    tmp.mkdir()
    return tmp, subprocess.Popen([sys.executable, '-c', DEMO, '--out', str(tmp_path / 'out'), *args], cwd=ROOT,
                                 env=dict(os.environ, TMPDIR=str(tmp)), stdout=subprocess.PIPE,
                                 stderr=subprocess.STDOUT, text=True)


def test_demo_leaves_nothing_in_the_temp_dir_and_logs_in_the_output_folder(tmp_path):
    tmp, proc = _demo_process(tmp_path, '--duration', '0.3', '--scenarios', 'gravity compensation', 'PD only')
    out = proc.communicate(timeout=300)[0]
    assert proc.returncode == 0, out
    assert os.listdir(tmp) == [], out
    logs = tmp_path / 'out' / 'logs'
    assert sorted(p.name for p in logs.iterdir()) == ['gravity_compensation', 'pd_only']
    assert sorted(p.name for p in (logs / 'pd_only').iterdir()) == ['dynamics_node.log', 'sim_node.log',
                                                                    'trajectory_source.log']
    assert 'simulating lie_arm7' in (logs / 'pd_only' / 'sim_node.log').read_text()


@pytest.mark.parametrize('sig', [signal.SIGTERM, signal.SIGINT])
def test_demo_stopped_by_sigterm_or_ctrl_c_cleans_up(tmp_path, sig):
    """--duration 0 runs until stopped: SIGTERM or Ctrl-C (SIGINT) stops every process, keeps the
    results and leaves nothing in the temp dir."""
    tmp, proc = _demo_process(tmp_path, '--duration', '0')
    sim_log = tmp_path / 'out' / 'logs' / 'pd_feedforward' / 'sim_node.log'
    end = time.monotonic() + 120
    while time.monotonic() < end and proc.poll() is None and not (
            sim_log.exists() and 'simulating' in sim_log.read_text()):
        time.sleep(0.1)
    time.sleep(1.0)  # let it run a little
    proc.send_signal(sig)
    out = proc.communicate(timeout=120)[0]
    assert proc.returncode == 0 and 'interrupted: processes stopped' in out, out
    assert '\r' not in out  # stdout is a pipe: no status line rewritten in place
    assert (tmp_path / 'out' / 'demo.png').exists(), out
    assert os.listdir(tmp) == [], out


def _window(t):
    return {'t': [t - 0.001, t], 'q': [demo.HOME, demo.HOME], 'qd': [[0.0] * 7] * 2, 'tau': [[0.0] * 7] * 2}


def test_status_line_is_rewritten_on_a_terminal_and_throttled_into_a_file():
    """--duration 0 calls the status about once a second: on a terminal each call rewrites the
    line in place; into a file (a log) only every STATUS_LOG_PERIOD_S, one plain line each."""
    import io
    clock = [0.0]
    log = io.StringIO()
    status = demo.StatusLine(log, clock=lambda: clock[0])
    for k in range(35):  # 35 s of calls, one a second
        clock[0] = float(k)
        status('gravity compensation', _window(k + 1.0))
    lines = log.getvalue().splitlines()
    assert '\r' not in log.getvalue() and len(lines) == 4  # at 0, 10, 20 and 30 s
    assert lines[1].startswith('gravity compensation') and 't =   11.00 s' in lines[1]
    master, follower = os.openpty()
    try:
        with open(follower, 'w', closefd=False) as tty:
            status = demo.StatusLine(tty, clock=lambda: clock[0])
            for k in range(3):
                clock[0] = float(k)
                status('gravity compensation', _window(k + 1.0))
        # the pty hands over what was written in pieces (one write per read on a loaded machine):
        # read until the three rewrites are there or nothing more comes
        text = ''
        while text.count('\r') < 3 and select.select([master], [], [], 5.0)[0]:
            text += os.read(master, 10000).decode()
    finally:
        os.close(master)
        os.close(follower)
    assert text.count('\r') == 3 and '\n' not in text


def test_contact_metrics_leave_the_held_initial_state_out_of_free_motion():
    """The simulator holds its initial state (stamp 0) until the answers are in; the node times
    those copies with its own clock, and its estimate of the holding torque grows with them (to
    g(q0), the collision flag up). When the first copy misses the recorder, a later one stands for
    stamp 0: it is not free motion, and the push is still measured the same."""
    cd = demo.contact_demo
    a = (1 - cd.GAIN * 5e-4) / (1 + cd.GAIN * 5e-4)   # the observer's response per 1 ms step
    k = np.arange(2001)
    true = np.zeros((len(k), 7))
    true[(k >= 800) & (k < 1200), 1] = 10.0
    ext, r = [], np.zeros(7)
    for row in true:
        r = a * r + (1 - a) * row
        ext.append(r.copy())
    hold = [np.eye(7)[1] * g for g in (16.7, 16.72)]   # later copies of the held state
    t = np.concatenate(([0.0, 0.0], k[1:] * 1e-3))
    ext = hold + ext[1:]
    rec = {'ext_t': t, 'ext': ext, 'flag': [bool(np.any(np.abs(e) > cd.THRESHOLD)) for e in ext],
           'true_t': k * 1e-3, 'true': true}
    m = cd.metrics(rec)
    assert m['free_max_estimate'] < 0.2 * min(cd.THRESHOLD) and m['false_alarms'] == 0, m
    assert m['push_start'] == 0.8 and 0 < m['detection_delay'] < 0.1, m
