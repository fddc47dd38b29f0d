"""The process shell of every node (ros/run.py) under each executor: timers fire, services answer,
SIGTERM/SIGINT stop it cleanly after the last command, and a bad executor choice is refused."""
import contextlib
import os
import signal
import subprocess
import sys
import time

import pytest
import rclpy
from rclpy.executors import SingleThreadedExecutor
from std_msgs.msg import Int32
from std_srvs.srv import Trigger

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
NODE = '''
import sys
from std_msgs.msg import Int32
from std_srvs.srv import Trigger
from rclpy.node import Node
from lie_dynamics.ros.run import run

class Probe(Node):
    def __init__(self):
        super().__init__('run_probe')
        self.pub = self.create_publisher(Int32, 'probe_ticks', 10)
        self.ticks = 0
        self.create_timer(0.02, self.tick)
        self.create_service(Trigger, 'probe_ping', self.ping)

    def tick(self):
        self.ticks += 1
        self.pub.publish(Int32(data=self.ticks))

    def ping(self, request, response):
        response.success, response.message = True, f'ticks {self.ticks}'
        return response

    def note_executor(self, kind):
        print('executor', kind, flush=True)

def last(node):
    print('stopped after', node.ticks, 'ticks', flush=True)

sys.exit(run(Probe, 'run_probe', on_stop=last))
'''


def _start(executor):
    env = dict(os.environ, LIE_DYNAMICS_EXECUTOR=executor)
    return subprocess.Popen([sys.executable, '-c', NODE], cwd=ROOT, env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)


@pytest.fixture
def client():
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    node = rclpy.create_node('run_probe_client', context=ctx)
    ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(node)
    yield node, ex
    ex.shutdown()
    node.destroy_node()
    rclpy.shutdown(context=ctx)


@contextlib.contextmanager
def _started(executor):
    """_start(executor), killed at the end if it still runs (a failed assertion)."""
    proc = _start(executor)
    try:
        yield proc
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()


def _until(ex, cond, timeout=60.0):
    end = time.monotonic() + timeout
    while time.monotonic() < end and not cond():
        ex.spin_once(timeout_sec=0.05)
    return cond()


@pytest.mark.parametrize('executor, sig', [('events', signal.SIGTERM), ('single_threaded', signal.SIGINT)])
def test_timers_services_and_clean_stop(client, executor, sig):
    node, ex = client
    ticks = []
    node.create_subscription(Int32, 'probe_ticks', lambda m: ticks.append(m.data), 10)
    cli = node.create_client(Trigger, 'probe_ping')
    with _started(executor) as proc:
        assert _until(ex, lambda: len(ticks) >= 5), 'timer did not fire'
        assert cli.wait_for_service(timeout_sec=30.0)
        future = cli.call_async(Trigger.Request())
        assert _until(ex, future.done), 'service not answered'
        assert future.result().success and future.result().message.startswith('ticks ')
        proc.send_signal(sig)
        out, err = proc.communicate(timeout=30)
    assert proc.returncode == 0, err
    assert f'executor {executor}' in out and 'stopped after' in out, out + err


def test_an_unknown_executor_is_refused_in_one_line():
    proc = _start('multi')
    out, err = proc.communicate(timeout=60)
    assert proc.returncode == 2
    assert err.strip().splitlines() == [
        'run_probe: invalid configuration: LIE_DYNAMICS_EXECUTOR must be one of events, single_threaded, '
        "got 'multi'"], err


@pytest.mark.parametrize('sig', [signal.SIGINT, signal.SIGTERM])
def test_signals_repeated_while_stopping_do_not_kill_it(client, sig):
    """A stop request repeated while the process stops (a launcher or a demo escalating, Ctrl-C
    pressed again) changes nothing, up to the end of the interpreter's exit: the process still
    exits 0 (the interpreter's finalization puts a Python handler back to the default action)."""
    node, ex = client
    ticks = []
    node.create_subscription(Int32, 'probe_ticks', lambda m: ticks.append(m.data), 10)
    with _started('events') as proc:
        assert _until(ex, lambda: len(ticks) >= 3), 'timer did not fire'
        while proc.poll() is None:
            proc.send_signal(sig)
            time.sleep(0.001)
        out, err = proc.communicate(timeout=30)
    assert proc.returncode == 0, err
    assert 'stopped after' in out, out + err
