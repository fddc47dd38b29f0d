"""Test-session setup shared by all tests.

ROS 2 environment for tests that start rclpy (set at import, before any `rclpy.init`):
a private log/home directory, discovery limited to this machine, and DDS domains of our own
per pytest-xdist worker, so parallel workers and other runs on the machine do not see each
other's topics. Each domain is reserved with a lock file held for the worker's lifetime
(lie_dynamics.sim.domains): two test runs on one machine (a developer's and CI's, say) can never
share a domain, which once let one run's demo processes command the other's simulated arm.
The log/home directory is removed when the process ends, SIGTERM included (domains.py removes its
lock files then too).
"""
import atexit
import os
import shutil
import signal
import tempfile
import time
import zlib

import pytest

# One BLAS thread per test process, set before numpy loads: two xdist workers on two cores, each
# with a threaded OpenBLAS, oversubscribe the machine, and the calibration fit's small SVDs and QRs
# lose more to thread hand-offs than they gain (test_noise_free_recovery: 18.7 s -> 5.3 s on a
# loaded machine). Results do not depend on it; a value set by the caller is kept.
os.environ.setdefault('OPENBLAS_NUM_THREADS', '1')

from lie_dynamics.sim.domains import reserve_domains  # noqa: E402  (after the BLAS setting)


def _interrupt(*_):
    raise KeyboardInterrupt  # pytest stops the session as on Ctrl-C, then exits through atexit


def _ros_test_environment():
    tmp = tempfile.mkdtemp(prefix='lie_dynamics_ros_')
    atexit.register(shutil.rmtree, tmp, ignore_errors=True)
    if signal.getsignal(signal.SIGTERM) == signal.SIG_DFL:  # exit through atexit, not straight out
        signal.signal(signal.SIGTERM, _interrupt)
    os.environ['ROS_LOG_DIR'] = os.path.join(tmp, 'log')
    os.environ['ROS_HOME'] = os.path.join(tmp, 'ros_home')
    home = os.environ.get('HOME', '')
    if not home or not os.access(home, os.W_OK):
        os.environ['HOME'] = tmp
    os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    os.environ.pop('ROS_STATIC_PEERS', None)
    os.environ.pop('ROS_LOCALHOST_ONLY', None)  # deprecated; conflicts with the range above
    worker = os.environ.get('PYTEST_XDIST_WORKER', 'gw0')
    index = int(worker[2:]) if worker[2:].isdigit() else 0
    # Same base for all workers of one run (shared run id), a different one for other runs.
    run = os.environ.get('PYTEST_XDIST_TESTRUNUID') or f'{os.getpid()}-{time.time_ns()}'
    base = zlib.crc32(run.encode())
    # two per worker: the tests' own, and one for the demo's processes (test_demo.py)
    node_domain, demo_domain = reserve_domains(2, base + 2 * index)
    os.environ['ROS_DOMAIN_ID'] = str(node_domain)
    os.environ['LIE_DYNAMICS_TEST_DEMO_DOMAIN'] = str(demo_domain)


_ros_test_environment()


@pytest.hookimpl(tryfirst=True)
def pytest_configure(config):
    """tmp_path folders of this run under a base of its own, removed when the run ends (pytest's
    default base, <temp dir>/pytest-of-<user>, outlives every run). Workers of pytest-xdist get
    folders inside the controller's base."""
    if config.option.basetemp is None and not hasattr(config, 'workerinput'):
        config.option.basetemp = tempfile.mkdtemp(prefix='lie_dynamics_pytest_')
        config.add_cleanup(lambda: shutil.rmtree(config.option.basetemp, ignore_errors=True))


@pytest.fixture
def ros():
    """test_node.Harness: the dynamics node started over real DDS with a test node beside it,
    closed after the test (one definition for the node tests; a file that needs more subscriptions
    defines its own)."""
    from test_node import Harness   # imports rclpy: only for the tests that ask for it
    h = Harness()
    yield h
    h.close()
