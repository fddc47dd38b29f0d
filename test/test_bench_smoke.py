"""Smoke test of the benchmark command: `python -m bench --quick` writes well-formed tables and charts.

Runs the quick mode of the speed/accuracy, scaling and stability sections (seconds), and the
core benchmark on a reduced size set; the full run (`make bench`) stays out of CI.
"""
import csv
import os

import pytest

from bench import __main__ as bench_main
from bench import core
from lie_dynamics.codegen import native

PNG_MAGIC = b'\x89PNG\r\n\x1a\n'
CSV_COLUMNS = {
    'accuracy.csv': ['robot', 'dof', 'op', 'method', 'impl', 'mode', 'us', 'ratio_to_pinocchio', 'err_max',
                     'err_median', 'states'],
    'scaling.csv': ['kind', 'n', 'algorithm', 'us', 'ratio', 'slope'],
    'stability.csv': ['scan', 'method', 'x_name', 'x', 'error', 'status'],
}
PNGS = ['accuracy_arm7.png', 'accuracy_chain12.png', 'scaling.png', 'scaling_ratio.png', 'stability_explog.png',
        'stability_chain.png', 'stability_forward_dynamics.png', 'stability_fd_step.png', 'stability_energy.png']


@pytest.fixture(scope='module')
def out(tmp_path_factory):
    d = str(tmp_path_factory.mktemp('bench'))
    assert bench_main.main(['--quick', '--only', 'accuracy,scaling,stability', '--out', d]) == 0
    return d


def _rows(path):
    with open(path, newline='', encoding='utf-8') as fh:
        r = csv.DictReader(fh)
        return r.fieldnames, list(r)


@pytest.mark.parametrize('name', sorted(CSV_COLUMNS))
def test_csv_tables_have_the_documented_columns(out, name):
    cols, rows = _rows(os.path.join(out, name))
    assert cols == CSV_COLUMNS[name]
    assert len(rows) > 10
    for r in rows:
        for key in ('us', 'err_max', 'error', 'x', 'n'):
            if key in r and r[key] not in ('', 'nan', 'inf'):
                float(r[key])   # numeric


def test_markdown_and_charts(out):
    for name in ('accuracy.md', 'scaling.md', 'stability.md', 'index.md'):
        with open(os.path.join(out, name), encoding='utf-8') as fh:
            assert fh.read().startswith('# ')
    for name in PNGS:
        with open(os.path.join(out, name), 'rb') as fh:
            data = fh.read()
        assert data[:8] == PNG_MAGIC and len(data) > 5000, name


def test_every_method_is_measured(out):
    _, rows = _rows(os.path.join(out, 'accuracy.csv'))
    ops = {r['op'] for r in rows}
    assert len(ops) == 6
    for r in rows:   # everything agreed with the longdouble reference at least to float32 level
        assert float(r['err_max']) < 1e-5 or r['method'] == 'forward differences', r


def test_robots_benchmark_compares_the_two_pandas(tmp_path):
    from bench import robots
    rows = robots.run(quick=True, out=str(tmp_path), rounds=1)
    labels = {r['robot'] for r in rows}
    assert {'panda, fingers locked (folded)', 'panda, fingers fixed in the URDF'} <= labels
    assert all(r['bodies'] == 7 for r in rows if r['robot'].startswith('panda'))
    assert all(r['ratio_median'] > 0 for r in rows)
    with open(tmp_path / 'robots.png', 'rb') as fh:
        assert fh.read(8) == PNG_MAGIC


def test_jacobian_section_runs_every_frame_beside_pinocchio(tmp_path):
    assert bench_main.main(['--quick', '--only', 'jacobian', '--out', str(tmp_path)]) == 0
    cols, rows = _rows(os.path.join(str(tmp_path), 'jacobian.csv'))
    assert cols == ['robot', 'n', 'call', 'frame', 'N', 'ours_us', 'pin_us', 'ratio_median', 'ratio_p10', 'ratio_p90',
                    'python_us', 'python_ratio_median', 'native']
    assert {(r['call'], r['frame']) for r in rows if r['N'] == '1'} == \
        {(c, f) for c in ('jacobian', 'J̇q̇') for f in ('world_aligned', 'local', 'world')}
    assert all(float(r['ratio_median']) > 0 and float(r['python_ratio_median']) > 0 for r in rows)
    assert all(r['native'] == str(native.module() is not None) for r in rows)   # the C kernels where they build


def test_contact_section_pushes_each_robot_and_times_the_node(tmp_path):
    from bench import contact
    iso, ident, tool, cost = contact.run(quick=True, out=str(tmp_path), pushes=3)
    robots = {name for name, _, _ in contact.robots()}
    assert {r['robot'] for r in iso} == robots and {r['robot'] for r in tool} == robots
    assert all(r['pushes'] >= 1 and 0 <= r['default_right_pct'] <= 100 for r in iso)
    assert all(r['strict_wrong_pct'] <= r['default_wrong_pct'] for r in iso)   # strict only adds 'ambiguous'
    # exact efforts: the tool wrench is the pushed one (lag only)
    assert all(r['force_error_median_pct'] < 2 for r in tool if r['noise'] == 0)
    assert {(r['flag'], r['case']) for r in cost} >= {('up', 'isolation on'), ('down', 'isolation on'),
                                                      ('up, weak', 'isolation on')}
    assert all(r['collision'] == r['flag'].startswith('up') for r in cost)
    # the weak push through joint 4's axis is never named link3 (the weak tier: ambiguous, or not decided yet)
    assert all(r['link'] == '' for r in cost if r['flag'] == 'up, weak')
    assert [r['link'] for r in cost if r['flag'] == 'up' and r['case'] != 'isolation stubbed (peer)'] == ['link7'] * 2
    assert os.path.exists(tmp_path / 'contact.csv') and os.path.exists(tmp_path / 'contact.md')


def test_core_benchmark_still_runs(tmp_path):
    res = core.run(quick=True, sizes=(1, 100), rounds=2)
    core.write(res, str(tmp_path))
    assert {r['impl'] for r in res['rows']} == set(core.IMPLS)
    with open(tmp_path / 'core.png', 'rb') as fh:
        assert fh.read(8) == PNG_MAGIC


def test_compare_takes_the_median_over_pairs(tmp_path, capsys):
    import json

    from bench import compare

    def run(name, ratio):
        d = tmp_path / name
        d.mkdir()
        rows = [{'impl': 'lie_dynamics', 'op': 'gravity', 'N': 1, 'ratio_to_pinocchio': ratio}]
        (d / 'core.json').write_text(json.dumps({'rows': rows}))
        return str(d)
    # one busy pair (+50 %) among three: the median change is +10 %, still a regression
    folders = [run('b1', 1.0), run('a1', 1.5), run('b2', 1.0), run('a2', 1.1), run('b3', 2.0), run('a3', 2.2)]
    assert compare.main(folders) == 0
    out = capsys.readouterr().out
    assert '| core: gravity, N = 1 | 1 | 1.5 | +10.0 % **slower** |' in out
    # one busy pair among quiet ones: median(+50, 0, 0) = 0, no regression
    assert compare.main(folders[:2] + [run('b4', 1.0), run('a4', 1.0), run('b5', 3.0), run('a5', 3.0)]) == 0
    assert '1 rows, 0 slower' in capsys.readouterr().out
    with pytest.raises(SystemExit):
        compare.main(folders[:3])


def test_ab_times_two_package_copies_in_one_process(tmp_path):
    """bench.probes.ab against this very tree: the copy is imported as a second package, agrees with
    the original on every row, and every row gets a positive ratio (no timing threshold)."""
    import json
    import sys

    import lie_dynamics
    from bench.probes import ab

    root = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(ab.__file__))))   # this tree
    try:
        assert ab.main([root, '--quick', '--out', str(tmp_path)]) == 0
        before = sys.modules[ab.BEFORE_NAME]
        assert before is not lie_dynamics and before.Model is not lie_dynamics.Model
    finally:
        for key in [k for k in sys.modules if k == ab.BEFORE_NAME or k.startswith(ab.BEFORE_NAME + '.')]:
            del sys.modules[key]
    with open(tmp_path / 'ab.md', encoding='utf-8') as fh:
        assert fh.read().startswith('# ')
    with open(tmp_path / 'ab.png', 'rb') as fh:
        assert fh.read(8) == PNG_MAGIC
    with open(tmp_path / 'ab.json', encoding='utf-8') as fh:
        result = json.load(fh)
    rows = result['rows']
    assert len(rows) >= 4 and result['meta']['before_modules'] > 1
    for r in rows:
        assert r['status'] == 'ok', r
        assert r['max_rel_diff'] <= ab.AGREE_RTOL
        assert r['ratio'] > 0 and r['before_us'] > 0 and r['after_us'] > 0 and r['pin_us'] > 0


def test_compile_section_measures_every_family_of_the_arm(tmp_path):
    """bench.compile --quick on the arm: a row per kernel family with its first use, its load
    from the cache and a call-time ratio (no timing threshold); nothing left in the temp folder."""
    from bench import compile as compile_bench
    if native.module() is None:
        pytest.skip('no working C compiler')
    rows = compile_bench.run(quick=True, out=str(tmp_path), robots=['arm7'])
    assert {r['family'] for r in rows} == set(compile_bench.FAMILIES)
    for r in rows:
        assert r['nodes'] > 0 and r['first_s'] > 0 and r['load_ms'] > 0, r
    table = (tmp_path / 'compile.md').read_text(encoding='utf-8')
    assert all(f'| arm7 | {fam} |' in table for fam in compile_bench.FAMILIES)


def test_looped_section_measures_both_forms(tmp_path):
    """bench.looped on an 8-body chain: a row per family with the straight-line and the looped
    kernel's first use and ratios to Pinocchio (the Jacobians: the straight-line kernel's), a table
    written; THRESHOLDS as before."""
    from bench import looped as looped_bench
    from lie_dynamics.codegen import runtime
    if native.module() is None:
        pytest.skip('no working C compiler')
    before = dict(runtime.THRESHOLDS)
    rows = looped_bench.measure(['chain8'], list(looped_bench.FAMILIES), rounds=1)
    assert runtime.THRESHOLDS == before
    assert [r['family'] for r in rows] == list(looped_bench.FAMILIES)
    for r in rows:
        assert r['straight_first_s'] > 0 and r['straight_ratio'] > 0, r
        if r['family'] in looped_bench.JACOBIANS:   # no looped form: the straight-line kernel alone
            assert 'looped_ratio' not in r, r
        else:
            assert r['looped_first_s'] > 0 and r['looped_ratio'] > 0, r
    assert looped_bench.main(['--robots', 'chain8', '--families', 'aba', '--rounds', '1', '--out', str(tmp_path)]) == 0
    assert '| chain8 | aba |' in (tmp_path / 'looped.md').read_text(encoding='utf-8')


def test_node_loads_trace_reports_the_node_side(tmp_path):
    """bench.node_loads --trace: the traced node writes its callbacks and log lines, and each
    event row gets the window's longest callback with its CPU and wait."""
    import json
    import subprocess
    import sys

    from bench import node_loads
    path = tmp_path / 'trace.json'
    env = dict(os.environ, LIE_DYNAMICS_NODE_TRACE=str(path))
    done = subprocess.run([sys.executable, '-m', 'bench.probes.node_trace', '--help'], env=env, capture_output=True,
                          text=True, timeout=120)
    assert done.returncode == 0 and 'dynamics_node' in done.stdout
    assert json.loads(path.read_text()) == {'callbacks': [], 'lines': []}
    trace = {'callbacks': [[1.0, 0.004, 0.001, 0.0025], [1.5, 0.002, 0.0015, 0.0], [9.0, 0.05, 0.05, 0.0]],
             'lines': [[1.2, 0.0007], [9.0, 0.01]]}
    side = node_loads._node_side(trace, 0.5, 2.0)
    assert side == pytest.approx({'cb_wall_ms': 4.0, 'cb_cpu_ms': 1.0, 'cb_wait_ms': 2.5, 'cb_max_cpu_ms': 1.5,
                                  'line_ms': 0.7})
    row = dict(event='e', runs=1, quiet_gap_ms=3.0, event_gap_ms=5.0, widened_ms=2.0, send_widened_ms=1.0, replies=9,
               sent=10, event_s=0.3, **side)
    table = node_loads.markdown([row], False, 0)
    assert '| 4.00 (1.00 / 2.50) | 1.50 | 0.70 |' in table


def _switch(t, cpu, prev, pid, state, nxt, nxt_pid):
    """A tracefs sched_switch line as the kernel writes it with record-tgid."""
    tgid = f'{pid:7d}' if pid else '-------'
    return (f'{prev}-{pid} ({tgid}) [{cpu:03d}] d..2. {t:.6f}: sched_switch: prev_comm={prev} prev_pid={pid} '
            f'prev_prio=120 prev_state={state} ==> next_comm={nxt} next_pid={nxt_pid} next_prio=120')


SCHED_TRACE = [
    '# tracer: nop',
    _switch(10.0, 0, 'python', 100, 'S', 'cc1', 300),
    _switch(10.0005, 1, 'sleep', 200, 'S', 'swapper/1', 0),
    '          <idle>-0       (-------) [001] dNs4. 10.001000: sched_wakeup: comm=python pid=100 prio=120 '
    'target_cpu=000',
    _switch(10.005, 0, 'cc1', 300, 'R', 'python', 100),
    _switch(10.0045, 1, 'swapper/1', 0, 'R', 'sleep', 200),
    _switch(10.006, 0, 'python', 100, 'R+', 'cc1', 300),
    _switch(10.0062, 0, 'cc1', 300, 'R', 'python', 100),
    'not a trace line',
]


def test_sched_trace_finds_each_wait_for_a_cpu_and_what_held_it():
    """bench.probes.sched_trace's analysis on a hand-written trace: the node's thread waits 4 ms behind
    cc1 while the other CPU idles 3.5 of them, then 0.2 ms after a preemption."""
    from bench.probes import sched_trace
    events = list(sched_trace.parse(SCHED_TRACE))
    assert len(events) == 7 and events[2][2] == 'sched_wakeup' and events[2][5] is None
    out, tgid_of, busy = sched_trace.waits(sorted(events))
    assert [w[0] for w in out[100]] == pytest.approx([0.004, 0.0002])
    assert [w[2:] for w in out[100]] == [(0, 0), (0, 0)]   # queued on, ran on
    assert tgid_of[100] == 100 and tgid_of[300] == 300
    rows, long_waits = sched_trace.summary(out, tgid_of, busy, {100: 'node', 300: 'compiler'})
    node = next(r for r in rows if r['process'] == 'node')
    assert node['waits'] == 2 and node['long'] == 1 and node['long_other_cpu_idle'] == 1
    assert node['max_ms'] == pytest.approx(4.0)
    d, role, cpu, idle, held = long_waits[0]
    assert (role, cpu) == ('node', 0) and idle == pytest.approx(0.0035)
    assert held[0][1] == 'cc1/300 (compiler)' and held[0][0] == pytest.approx(0.004)
    text = sched_trace.markdown(rows, long_waits, 'kernel facts')
    assert '| node | 2 |' in text
    assert 'queued on CPU 0 held by cc1/300 (compiler) 4.00 ms; another CPU idle 3.50 ms' in text


def test_log_line_bench_times_both_paths():
    """bench.probes.log_line runs (its own process: it starts rclpy) and reports both logging paths."""
    import subprocess
    import sys
    done = subprocess.run([sys.executable, '-m', 'bench.probes.log_line', '--rounds', '1', '--lines', '3'],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    rows = [ln for ln in done.stdout.splitlines() if ln.startswith("| rclpy's Python logger |")
            or ln.startswith('| Outputs.log_line (C call) |')]
    assert len(rows) == 2 and rows[0].endswith('| 1.000× |')


def test_command_publish_probe_times_every_path():
    """bench.probes.command_publish runs (its own process: it starts rclpy) and reports its five paths."""
    import subprocess
    import sys
    done = subprocess.run([sys.executable, '-m', 'bench.probes.command_publish', '--rounds', '1', '--joints', '3'],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    rows = [ln for ln in done.stdout.splitlines() if ln.startswith('| command') or ln.startswith('| echo')]
    assert len(rows) == 5 and rows[0].endswith('| 1.00 |') and rows[2].endswith('| 1.00 |')


def test_node_steps_probe_times_each_feature_and_the_fused_command():
    """bench.probes.node_steps runs (its own process: it starts rclpy): every feature's steps and the
    callback timed, every command of its stream made by the fused command path (none without the
    native backend: LIE_DYNAMICS_NATIVE=0 or no compiler)."""
    import subprocess
    import sys

    from lie_dynamics.codegen import native
    done = subprocess.run([sys.executable, '-m', 'bench.probes.node_steps', '--states', '60'],
                          capture_output=True, text=True, timeout=180)
    assert done.returncode == 0, done.stderr
    rows = {ln.split('|')[1].strip() for ln in done.stdout.splitlines() if ln.startswith('| ') and 'µs' not in ln}
    assert {'contact', 'dynamics', 'callback, all of it'} <= rows, done.stdout
    fused = 0 if native.module() is None else 60
    assert f'fused command path: {fused} of 60 commands; clamped: 0' in done.stdout
    assert 'coriolis_term: ' in done.stdout


def test_observer_node_probe_times_both_input_forms():
    """bench.probes.observer_node runs (its own process: it starts rclpy), times the four ways a message
    reaches the node, and the peer's ratio to itself is 1."""
    import subprocess
    import sys
    done = subprocess.run([sys.executable, '-m', 'bench.probes.observer_node', '--rounds', '1', '--per-round', '20'],
                          capture_output=True, text=True, timeout=180)
    assert done.returncode == 0, done.stderr
    rows = [ln for ln in done.stdout.splitlines() if ln.startswith('| objects') or ln.startswith('| serialized')]
    assert len(rows) == 18, done.stdout   # 2 forms x (3 cases at once + 3 deferred, callback and total)
    assert all('| 1.00 |' in ln for ln in rows if 'observer off' in ln)


def test_record_gaps_probe_runs():
    """bench.probes.record_gaps runs (its own process: it starts rclpy) and reports the three phases,
    the recording written."""
    import subprocess
    import sys
    done = subprocess.run([sys.executable, '-m', 'bench.probes.record_gaps', '--seconds', '0.2', '--rate', '200',
                           '--rounds', '2'],
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    rows = [line for line in done.stdout.splitlines() if line.startswith('| ')]
    assert [r.split('|')[1].strip() for r in rows[1:]] == ['idle', 'recording', 'writing'], done.stdout
    assert 'written: rosbag2_' in done.stdout and int(rows[2].split('|')[2]) == 40   # 2 rounds of 20


def test_calls_section_times_one_call_and_batches_beside_pinocchio(tmp_path):
    from bench import calls
    res = calls.run(quick=True, out=str(tmp_path), robots=calls.ROBOTS[:1])
    cases = {r['case'] for r in res['one_state']}
    assert {'inverse_dynamics', 'inverse_dynamics_out', 'gravity', 'gravity_out', 'ufunc_out'} <= cases
    assert all(r['ratio'] > 0 for r in res['one_state'])
    (batch,) = res['batches']
    assert batch['N'] == 100 and batch['vs_pin_loop'] > 0 and batch['vs_rnea_in_parallel_1'] > 0
    assert os.path.exists(tmp_path / 'calls.md')


def test_batch_sincos_probe_times_the_orders_and_the_upper_halves():
    """bench.probes.batch_sincos on a few states: the three orders give the same values (checked
    in run) and every figure is a time."""
    if native.module() is None:
        pytest.skip('no working C compiler')
    from bench.probes import batch_sincos
    r = batch_sincos.run(states=64, rounds=1)
    assert set(r['sincos_ns']) == {'in order', 'grouped', 'sorted'} and min(r['sincos_ns'].values()) > 0
    assert all(v['bare'] > 0 and v['call_path'] > 0 and v['ratio'] > 0 for v in r['after'].values())


def test_jacobian_call_probe_times_the_four_paths():
    """bench.probes.jacobian_call on the bundled arm: the method, its Python form and the bound kernel
    agree to the bit before they are timed beside Pinocchio, one row per family."""
    if native.module() is None:
        pytest.skip('no working C compiler')
    from bench.probes import jacobian_call
    rows = jacobian_call.rows('arm7', 1)
    assert [r['family'] for r in rows] == ['jacobian', 'jacobian_dot']
    for r in rows:
        assert r['n'] == 7 and all(r[f'{k}_us'] > 0 and r[f'{k}_ratio'] > 0 for k in ('method', 'python', 'kernel'))
