"""Command-line entry points: bad arguments or input give one line and exit status 2, never a
traceback; --help documents the input formats with an example.

Every case runs the module the way a user does (`python -m lie_dynamics.<module>`); the ROS
nodes inherit conftest's private ROS environment and are refused before they spin.
"""
import importlib.util
import os
import re
import subprocess
import sys

import pytest

from lie_dynamics.trajectory import read_csv

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
ARM = os.path.join(ROOT, 'config', 'arm7.urdf')
TIMEOUT = 120  # generous: a loaded machine is slow to start Python, numpy and rclpy


# entry point -> module run with -m (the simulator's nodes live in lie_dynamics.sim)
MODULES = {'sim_node': 'lie_dynamics.sim.sim_node', 'trajectory_source': 'lie_dynamics.sim.trajectory_source'}


def _run(module, *args):
    return subprocess.run([sys.executable, '-m', MODULES.get(module, f'lie_dynamics.{module}'), *args], check=False,
                          cwd=ROOT,
                          capture_output=True, text=True, timeout=TIMEOUT)


def _assert_refused(r, *fragments):
    """Exit status 2, exactly one non-empty line on stderr containing fragments, no traceback."""
    out = r.stdout + r.stderr
    assert r.returncode == 2, out
    assert 'Traceback' not in out, out
    lines = r.stderr.splitlines()
    assert len(lines) == 1 and lines[0].strip(), out
    for f in fragments:
        assert f in lines[0], out


@pytest.fixture
def csv_file(tmp_path):
    def make(text):
        path = tmp_path / 'traj.csv'
        path.write_text(text)
        return str(path)
    return make


def test_trajectory_refuses_csv_without_pos_prefix(csv_file):
    """The reported case: a new user's columns `time, joint1, ...`."""
    r = _run('trajectory', ARM, csv_file('time, joint1, joint2\n0, 0.0, 0.0\n0.1, 0.1, 0.0\n'), '-o', 'unused.csv')
    _assert_refused(r, "column 2 ('joint1') is not time, pos.<joint>", 'pos.joint1')


@pytest.mark.parametrize('args, fragments', [
    ([], ['the following arguments are required', '(see --help)']),
    ([ARM, 'no_such_file.csv', '-o', 'unused.csv'], ['No such file or directory', 'no_such_file.csv']),
    (['no_such.urdf', 'CSV', '-o', 'unused.csv'], ['URDF file not found']),
    ([ARM, 'CSV', '-o', os.path.join('no_such_dir', 'out.csv')], ['No such file or directory']),
])
def test_trajectory_refuses_bad_arguments(csv_file, args, fragments):
    good = csv_file('time,pos.joint1\n0,0\n0.1,0.1\n')
    _assert_refused(_run('trajectory', *[good if a == 'CSV' else a for a in args]), *fragments)


def test_trajectory_names_the_file_for_a_bad_trajectory(csv_file):
    path = csv_file('time,pos.joint1\n0,0\n0,0.1\n')
    _assert_refused(_run('trajectory', ARM, path, '-o', 'unused.csv'), path, 'times must increase strictly')


def test_fill_trajectory_executable_reports_under_its_name(csv_file):
    """The console script calls the same main; its errors carry the executable's name."""
    script = "import sys; sys.argv[0] = 'fill_trajectory'; from lie_dynamics.trajectory import main; sys.exit(main())"
    r = subprocess.run([sys.executable, '-c', script, ARM, csv_file('time,joint1\n0,0\n'), '-o', 'unused.csv'],
                       check=False, cwd=ROOT, capture_output=True, text=True, timeout=TIMEOUT)
    _assert_refused(r, 'fill_trajectory: error:', "'joint1'")


@pytest.mark.parametrize('text, msg', [
    ('time,pos.a,pos.a\n0,0,0\n', "column 'pos.a' appears twice"),
    ('time,pos.a,vel.b\n0,0,0\n', "column 'vel.b' has no pos.b column"),
    ('time,pos.a,pos.b,vel.a\n0,0,0,0\n', r"vel.<joint> columns must cover every joint or none; missing \['vel.b'\]"),
    ('time,pos.a\n0,0\n1,0,5\n', 'line 3 has 3 values, the header has 2 columns'),
    ('time,pos.a\n0,0\n1,x\n', "line 3: non-numeric value 'x' in column 'pos.a'"),
    ('pos.a\n0\n', "no 'time' column"),
    ('time,pos.\n0,0\n', "column 2 \\('pos.'\\) is not time"),
])
def test_read_csv_names_the_problem(tmp_path, text, msg):
    path = tmp_path / 'bad.csv'
    path.write_text(text)
    with pytest.raises(ValueError, match=msg):
        read_csv(path)


def test_read_csv_accepts_a_spreadsheet_bom_and_output_columns(tmp_path):
    path = tmp_path / 'in.csv'
    path.write_text('\ufefftime,pos.a,eff.a\n0,0.5,1\n\n0.1,0.6,2\n', encoding='utf-8')
    traj = read_csv(path)
    assert traj['joint_names'] == ['a'] and traj['positions'].tolist() == [[0.5], [0.6]]


@pytest.mark.parametrize('args, fragments', [
    (['--urdf', 'no_such.urdf'], ['URDF file not found']),
    (['--noise', '0'], ['argument --noise: must be a finite number > 0']),
    (['--duration', 'nan'], ['argument --duration']),
    (['--seed', '-1'], ['argument --seed: must be an integer >= 0']),
])
def test_identification_refuses_bad_arguments(args, fragments):
    _assert_refused(_run('identification', *args), *fragments)


@pytest.mark.parametrize('args, fragments', [
    (['--duration', '-1'], ['argument --duration: must be > 0 seconds, or 0 to run until Ctrl-C']),
    (['--rate', '0'], ['argument --rate']),
    (['--scenarios', 'flying'], ["invalid choice: 'flying'"]),
    (['--out', os.path.join('config', 'arm7.urdf', 'sub')], ['error:']),  # a file where a folder must go
])
def test_demo_refuses_bad_arguments_before_starting_anything(args, fragments):
    _assert_refused(_run('demo', *args), *fragments)


@pytest.mark.parametrize('args, fragments', [
    (['--ros-args', '-p', 'rate'], ["sim_node: error: Failed to parse ROS arguments", "'-p rate'"]),
    (['--ros-args', '-p', 'rate:=500'], ['sim_node: invalid configuration', "expecting type 'DOUBLE'"]),
    (['--ros-args', '-p', 'max_steps:=-1'], ['sim_node: invalid configuration: max_steps must be >= 0']),
    (['--ros-args', '-p', 'urdf_path:=no_such.urdf'], ["urdf_path 'no_such.urdf'"]),
    (['--ros-args', '--no-such-flag'], ['unknown ROS arguments']),
    (['--rate', '500.0'], ['sim_node: error: unrecognized arguments: --rate 500.0']),
])
def test_sim_node_refuses_bad_arguments(args, fragments):
    _assert_refused(_run('sim_node', *args), *fragments)


@pytest.mark.parametrize('args, fragments', [
    (['--bogus'], ['dynamics_node: error: unrecognized arguments: --bogus']),
    (['urdf_path:=config/arm7.urdf'], ['unrecognized arguments']),  # forgot --ros-args -p
    (['--ros-args', '--no-such-flag'], ['unknown ROS arguments']),
    (['--ros-args', '-p', 'kp'], ['dynamics_node: error: Failed to parse ROS arguments']),
    (['--ros-args', '-p', 'kp:=[1.0,-1.0]'], ['dynamics_node: invalid configuration', 'kp must be >= 0']),
])
def test_dynamics_node_refuses_bad_arguments(args, fragments):
    """Arguments outside --ros-args are the parser's; those after it reach rclpy (a refused -p value)."""
    _assert_refused(_run('dynamics_node', *args), *fragments)


@pytest.mark.parametrize('args, fragments', [
    (['--ros-args', '-p', 'home:=[0.0,1.0]', '-p', 'amplitude:=[0.1,0.2,0.3]'], ['different joint counts']),
    (['--ros-args', '-p', 'lead:=.nan'], ['lead must be finite']),
    (['--ros-args', '-p', 'min_subscribers:=-1'], ['min_subscribers must be >= 0']),
    (['--ros-args', '--params-file', 'no_such.yaml'], ["Couldn't parse params file"]),
    (['home:=[0.0]'], ['unrecognized arguments']),  # forgot --ros-args -p
])
def test_trajectory_source_refuses_bad_arguments(args, fragments):
    _assert_refused(_run('trajectory_source', *args), 'trajectory_source:', *fragments)


@pytest.mark.parametrize('module, fragments', [
    ('trajectory', ['time, pos.<joint>..., [vel.<joint>...], [acc.<joint>...]',
                    'time,pos.joint1,pos.joint2,vel.joint1,vel.joint2\n  0.00,0.0,0.50,0.0,0.0',
                    'python -m lie_dynamics.trajectory config/arm7.urdf traj.csv -o traj_eff.csv']),
    ('identification', ['--noise', '--duration', '--seed', '--quick', 'python -m lie_dynamics.identification']),
    ('demo', ['or 0 to run the tracking scenario', 'Negative values are refused', 'python -m lie_dynamics.demo']),
    ('dynamics_node', ['--ros-args', 'urdf_path:=', 'mode:=gravity', 'kp:=[0.0]', 'docs/node.md',
                       'python -m lie_dynamics.dynamics_node --ros-args -p urdf_path:=config/arm7.urdf']),
    ('sim_node', ['--ros-args', 'rate:=1000.0', 'initial_positions:=[0.0]', 'max_steps:=0',
                  'ros2 run lie_dynamics sim_node --ros-args']),
    ('trajectory_source', ['--ros-args', 'home:=[0.0]', 'amplitude:=[0.3]', 'frequency:=[0.25]', 'lead:=0.001',
                           'python -m lie_dynamics.sim.trajectory_source --ros-args']),
])
def test_help_documents_the_formats_with_an_example(module, fragments):
    r = _run(module, '--help')
    assert r.returncode == 0 and not r.stderr, r.stdout + r.stderr
    assert 'example' in r.stdout
    for f in fragments:
        assert f in r.stdout, (f, r.stdout)


def test_every_documented_module_command_exists():
    """Each `python -m lie_dynamics...` written in the docs, help texts and config comments names a
    module that exists (the restructuring once left `python -m lie_dynamics.trajectory_source`)."""
    names = set()
    for folder in ('.', 'docs', 'config', 'launch', 'lie_dynamics', 'bench'):
        for path, dirs, files in os.walk(os.path.join(ROOT, folder)):
            dirs[:] = [] if folder == '.' else [d for d in dirs if d != '__pycache__']
            for f in files:
                if f.endswith(('.md', '.py', '.yaml')):
                    with open(os.path.join(path, f), encoding='utf-8') as fh:
                        names |= set(re.findall(r'python -m (lie_dynamics(?:\.\w+)*)', fh.read()))
    assert 'lie_dynamics.dynamics_node' in names and 'lie_dynamics.sim.sim_node' in names, names
    missing = sorted(n for n in names if importlib.util.find_spec(n) is None)
    assert not missing, missing
