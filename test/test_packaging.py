"""colcon build of the package into a temporary workspace, then start the installed executable
the way `ros2 run lie_dynamics dynamics_node` resolves it:
ament_index_python.get_package_prefix('lie_dynamics')/lib/lie_dynamics/dynamics_node.
"""
import ast
import importlib.util
import os
import re
import shutil
import signal
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

rclpy = pytest.importorskip('rclpy')
pytest.importorskip('colcon_core')

from rclpy.context import Context  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from sensor_msgs.msg import JointState  # noqa: E402
from std_msgs.msg import Float64MultiArray  # noqa: E402

from oracle import Oracle  # noqa: E402

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SOURCES = ('setup.py', 'setup.cfg', 'package.xml', 'resource', 'lie_dynamics', 'config', 'launch')


def _wait(pred, timeout, what):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if pred():
            return
        time.sleep(0.005)
    raise AssertionError(f'timed out waiting for {what}')


def test_launch_file_compiles():
    path = os.path.join(ROOT, 'launch', 'dynamics.launch.py')
    with open(path) as fh:
        tree = ast.parse(fh.read(), path)  # launch/launch_ros are not installable here: read it
    calls = [n for n in ast.walk(tree) if isinstance(n, ast.Call) and isinstance(n.func, ast.Name)]
    declared = {c.args[0].value for c in calls if c.func.id == 'DeclareLaunchArgument'}
    assert {'params_file', 'namespace', 'trajectory_out'} <= declared
    (node,) = [c for c in calls if c.func.id == 'Node']
    ns = next(k.value for k in node.keywords if k.arg == 'namespace')  # the argument reaches the node
    assert ast.unparse(ns) == "LaunchConfiguration('namespace')"


def _check_setup_bash(ws):
    """`source install/setup.bash` (colcon-bash) puts the package on the ament index and the path:
    the installed executable is found the way `ros2 run` finds it, and answers --help."""
    assert (ws / 'install' / 'setup.bash').is_file()
    script = ('source install/setup.bash && "$PY" -c "from ament_index_python.packages import get_package_prefix; '
              'print(get_package_prefix(\'lie_dynamics\'))" && '
              'install/lie_dynamics/lib/lie_dynamics/dynamics_node --help')
    env = {k: v for k, v in os.environ.items() if k not in ('AMENT_PREFIX_PATH', 'COLCON_PREFIX_PATH')}
    r = subprocess.run(['bash', '-c', script], cwd=ws, env=dict(env, PY=sys.executable), capture_output=True,
                       text=True, timeout=120)
    assert r.returncode == 0, r.stdout + r.stderr
    prefix, usage = r.stdout.split('\n', 1)
    assert prefix == str(ws / 'install' / 'lie_dynamics') and usage.startswith('usage: dynamics_node'), r.stdout


def test_colcon_build_and_ros2_run_resolution(tmp_path):
    src = tmp_path / 'src' / 'lie_dynamics'
    src.mkdir(parents=True)
    for name in SOURCES:
        s = os.path.join(ROOT, name)
        if os.path.isdir(s):
            shutil.copytree(s, src / name, ignore=shutil.ignore_patterns('__pycache__', '*.egg-info'))
        else:
            shutil.copy(s, src / name)
    build = subprocess.run([sys.executable, '-m', 'colcon', 'build', '--base-paths', 'src'],
                           cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert build.returncode == 0, build.stdout[-3000:] + build.stderr[-3000:]

    if importlib.util.find_spec('colcon_bash') is not None:   # requirements-dev.txt installs it
        _check_setup_bash(tmp_path)
    install = tmp_path / 'install' / 'lie_dynamics'
    env = dict(os.environ)
    # what `source install/setup.bash` would do, plus the venv's own ament prefix (ROS wheels)
    env['AMENT_PREFIX_PATH'] = os.pathsep.join(
        [str(install), sys.prefix] + [p for p in os.environ.get('AMENT_PREFIX_PATH', '').split(os.pathsep) if p])
    site = install / 'lib' / f'python{sys.version_info.major}.{sys.version_info.minor}' / 'site-packages'
    env['PYTHONPATH'] = os.pathsep.join([str(site)] + [p for p in env.get('PYTHONPATH', '').split(os.pathsep)
                                                       if p])
    probe = subprocess.run(
        [sys.executable, '-c', 'from ament_index_python.packages import get_package_prefix as g, '
                               'get_package_share_directory as s; print(g("lie_dynamics")); '
                               'print(s("lie_dynamics"))'],
        env=env, capture_output=True, text=True, timeout=60)
    assert probe.returncode == 0, probe.stderr
    prefix, share = probe.stdout.split()
    assert prefix == str(install)
    exe = os.path.join(prefix, 'lib', 'lie_dynamics', 'dynamics_node')
    assert os.path.isfile(exe) and os.access(exe, os.X_OK)
    usage = subprocess.run([exe, '--help'], env=env, capture_output=True, text=True, timeout=120)
    assert usage.returncode == 0 and usage.stdout.startswith('usage: dynamics_node'), usage.stdout + usage.stderr
    for other in ('sim_node', 'trajectory_source', 'demo', 'fill_trajectory', 'excitation_trajectory',
                  'identify_dynamics'):
        path = os.path.join(prefix, 'lib', 'lie_dynamics', other)
        assert os.path.isfile(path) and os.access(path, os.X_OK), other
    assert os.path.isfile(site / 'lie_dynamics' / 'data' / 'arm7.urdf')  # the embedded default model
    assert os.path.isfile(site / 'lie_dynamics' / 'codegen' / 'native_call.c')  # the native call path's source
    for part in ('native_method.c', 'native_command.c'):   # included by native_call.c
        assert os.path.isfile(site / 'lie_dynamics' / 'codegen' / part)
    for f in ('config/arm7_gravity.yaml', 'config/wall_mount_payload.yaml', 'config/arm7.urdf',
              'launch/dynamics.launch.py', 'package.xml'):
        assert os.path.isfile(os.path.join(share, f)), f

    # Start it as `ros2 run lie_dynamics dynamics_node --ros-args --params-file <share>/config/...`
    proc = subprocess.Popen([exe, '--ros-args', '--params-file', os.path.join(share, 'config', 'arm7_gravity.yaml'),
                             '-p', 'stale_timeout:=30.0'],
                            env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    ctx = Context()
    rclpy.init(context=ctx)
    ex = SingleThreadedExecutor(context=ctx)
    node = rclpy.create_node('packaging_tester', context=ctx)
    cmds = []
    node.create_subscription(Float64MultiArray, '/effort_controller/commands', lambda m: cmds.append(np.array(m.data)),
                             10)
    pub = node.create_publisher(JointState, 'joint_states', 10)
    ex.add_node(node)
    spin = threading.Thread(target=ex.spin, daemon=True)
    spin.start()
    try:
        _wait(lambda: pub.get_subscription_count() >= 1 and node.count_publishers('/effort_controller/commands') >= 1,
              60, 'the installed node (discovery)')
        joints = [f'joint{i}' for i in range(1, 8)]
        q = np.array([0.1, -0.6, 0.3, 1.8, -0.2, 1.5, 0.4])
        # joint_states is best effort: a sample sent while the reader is still matching may be
        # lost, so repeat until the first command comes back (as a 100+ Hz stream would)
        end = time.monotonic() + 30
        while not cmds and time.monotonic() < end:
            pub.publish(JointState(name=joints, position=q.tolist()))
            time.sleep(0.05)
        assert cmds, 'no command from the installed node'
        time.sleep(0.2)
        del cmds[1:]
        with open(os.path.join(share, 'config', 'arm7.urdf')) as fh:
            ref = Oracle(fh.read(), joints=joints).gravity(q)
        np.testing.assert_allclose(cmds[0], ref, atol=1e-9, rtol=0)
        # Ctrl-C: the node applies stale_action (gravity at the last state) once and exits cleanly
        proc.send_signal(signal.SIGINT)
        assert proc.wait(timeout=30) == 0
        _wait(lambda: len(cmds) >= 2, 5, 'the shutdown command')
        np.testing.assert_allclose(cmds[1], ref, atol=1e-9, rtol=0)
        out = proc.stdout.read()
        assert str(share) in out  # the installed copy of the config and URDF was used
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        ex.shutdown(timeout_sec=2.0)
        spin.join(timeout=5)
        node.destroy_node()
        ctx.try_shutdown()


def _console_scripts():
    """The console_scripts names setup.py declares."""
    with open(os.path.join(ROOT, 'setup.py')) as fh:
        return re.findall(r"'(\w+) = lie_dynamics[\w.]*:main'", fh.read())


def test_the_console_scripts_are_the_documented_executables():
    assert sorted(_console_scripts()) == ['demo', 'dynamics_node', 'excitation_trajectory', 'fill_trajectory',
                                          'identify_dynamics', 'sim_node', 'trajectory_source']


@pytest.mark.parametrize('name', ['dynamics_node', 'sim_node', 'trajectory_source', 'demo', 'fill_trajectory',
                                  'excitation_trajectory', 'identify_dynamics'])
def test_console_script_in_the_venv_answers_help(name):
    """`make venv` installs the package (pip install -e .): each console script sits next to the
    interpreter and prints its usage under its own name."""
    path = os.path.join(os.path.dirname(sys.executable), name)
    if not os.path.exists(path):
        pytest.skip(f'{name} is not next to {sys.executable}: this interpreter has the package on its path '
                    'without installing it (`make venv` installs it with pip install -e .)')
    r = subprocess.run([path, '--help'], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0 and not r.stderr, r.stdout + r.stderr
    assert r.stdout.startswith(f'usage: {name} '), r.stdout
