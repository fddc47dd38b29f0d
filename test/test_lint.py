"""The linter (ruff, configured in ruff.toml) passes on the whole repository, and the math core
imports no ROS package."""
import os
import subprocess
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
ROS_FREE = ('spatial', 'model', 'algorithms', 'codegen', 'trajectory', 'cli', 'laws', 'identification',
            'sim.arm', 'sim.integrators', 'ros.params', 'ros.compensator')


def test_ruff_is_clean():
    r = subprocess.run([sys.executable, '-m', 'ruff', 'check', '--no-cache', '.'], cwd=ROOT, capture_output=True,
                       text=True, timeout=300)
    assert r.returncode == 0, r.stdout[-5000:] + r.stderr[-2000:]


def test_math_core_imports_no_ros_package():
    """Every module of the math core (and the ROS-free decision logic) imports without rclpy."""
    code = ('import importlib, pkgutil, sys, lie_dynamics\n'
            f'names = {ROS_FREE!r}\n'
            'for mod in pkgutil.walk_packages(lie_dynamics.__path__, "lie_dynamics."):\n'
            '    short = mod.name.split(".", 1)[1]\n'
            '    if any(short == n or short.startswith(n + ".") for n in names):\n'
            '        importlib.import_module(mod.name)\n'
            'bad = sorted(m for m in sys.modules if m.split(".")[0] in ("rclpy", "rosidl_runtime_py", "pinocchio"))\n'
            'print(bad)\n'
            'sys.exit(1 if bad else 0)\n')
    r = subprocess.run([sys.executable, '-c', code], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stdout + r.stderr
