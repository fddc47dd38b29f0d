"""The trajectory process (started by process.py, which describes it): a node of
its own, `<node name>_trajectories` in the node's namespace, that takes ~/trajectory_in
serialized, asks the dynamics node for the fill, fills and publishes ~/trajectory_out, on the
dynamics node's resolved topic names with its QoS, in the dynamics node's DDS domain.

    python -m lie_dynamics.ros.trajectories.trajectory_process PARENT_PID   (stdin / stdout: the pipe)

It logs nothing itself: its outcomes go back over the pipe, with ('alive',) from the executor
loop at least every `heartbeat` s of the start configuration (a loop that stops, stopped or
stuck, gets the process killed and replaced). At end of its input it leaves the ROS graph and
exits at once; it dies with the thread that started it.
"""
import os
import sys
import threading
import time

import rclpy
from rclpy.context import Context
from rclpy.event_handler import PublisherEventCallbacks, SubscriptionEventCallbacks
from rclpy.executors import SingleThreadedExecutor
from rclpy.qos import QoSProfile
from rclpy.serialization import deserialize_message
from rclpy.signals import SignalHandlerOptions
from trajectory_msgs.msg import JointTrajectory

from .. import interfaces
from ..core.pipe import child_setup, receive, send
from ..loading.background import TRIM_BYTES, release_memory
from ..loading.worker import Worker
from .trajectory_cdr import Unsupported, arrays, head, read, write
from .trajectory_msgs import set_point_efforts, trajectory_arrays

REPLACED = 'a newer trajectory arrived before it was filled'


def child_config(node):
    """What the trajectory process of the dynamics node `node` needs to stand in for it: its DDS
    domain, a name and namespace, the node's resolved ~/trajectory_in and ~/trajectory_out and
    their QoS (interfaces.py)."""
    q = interfaces.INTERFACES['~/trajectory_in'].qos
    return dict(domain_id=node.context.get_domain_id(), name=f'{node.get_name()}_trajectories',
                namespace=node.get_namespace(), topic_in=node.resolve_topic_name('~/trajectory_in'),
                topic_out=node.resolve_topic_name('~/trajectory_out'),
                qos=dict(depth=q.depth, history=q.history, reliability=q.reliability, durability=q.durability))


class Filler:
    """One fill at a time in a worker thread; a trajectory waiting is replaced by a newer one."""

    def __init__(self, out, publish):
        self.out = out
        self.publish = publish
        self.ended = threading.Event()
        self._send_lock = threading.Lock()
        self._cv = threading.Condition()
        self._answers = {}
        self._seq = 0
        self.job = None            # the node's last TrajectoryFill
        self.worker = Worker('lie_dynamics_fill', slots=('trajectory',))

    def send(self, msg):
        with self._send_lock:
            send(self.out, msg)

    def on_trajectory(self, data):
        """The subscription's callback (serialized message)."""
        self.worker.outcomes()   # (nothing to read in them: every job reports over the pipe)
        if self.worker.submit('trajectory', 'trajectory', lambda: self._job(data)) is not None:
            self.send(('done', REPLACED, None, 'replaced'))

    def read_answers(self):
        """The node's answers (a thread of its own); end of input ends the process."""
        while True:
            try:
                msg = receive(0)
            except (OSError, ValueError, EOFError):
                msg = None
            if msg is None:
                break
            with self._cv:
                self._answers[msg[1]] = msg
                self._cv.notify_all()
        self.ended.set()
        with self._cv:
            self._cv.notify_all()

    def _ask(self, points):
        self._seq += 1
        seq = self._seq
        self.send(('ask', seq, points))
        with self._cv:
            while seq not in self._answers and not self.ended.is_set():
                self._cv.wait()
            return self._answers.pop(seq, None)

    def _job(self, data):
        try:
            done = self._fill(data)
            if done is not None:
                self.send(done)
        except OSError:   # the node is gone
            self.ended.set()
        finally:
            if len(data) > TRIM_BYTES:
                release_memory()

    def _fill(self, data):
        """The ('done', error, note, kind) of one trajectory, or None (the node refused it and counted it)."""
        try:
            points = head(data)[1]
        except Unsupported:
            points = 0   # counted once deserialized
        except ValueError as exc:
            return ('done', str(exc), None, 'malformed')
        answer = self._ask(points)
        if answer is None or answer[0] == 'no':
            return None   # refused by the node, which counted it
        _, _, job, cap = answer
        if job is not None:
            self.job = job
        try:
            return ('done', None, self._fill_message(self.job, data, cap), None)
        except ValueError as exc:
            return ('done', str(exc), None, 'malformed')
        except Exception as exc:  # noqa: BLE001 - reported by the node, never the end of this process
            return ('done', f'{type(exc).__name__}: {exc}', None, 'malformed')

    def _fill_message(self, job, data, cap):
        """Fill and publish; the clamp note or None. Raises ValueError for a rejected trajectory."""
        try:
            traj = read(data)
        except Unsupported:
            msg = deserialize_message(data, JointTrajectory)
            if len(msg.points) > cap:
                raise ValueError(f'{len(msg.points)} points, more than max_trajectory_points ({cap})') from None
            efforts, note = job.fill(msg.joint_names, trajectory_arrays(msg.joint_names, msg.points))
            set_point_efforts(msg.points, efforts)
            self.publish(msg)
            return note
        efforts, note = job.fill(traj['joint_names'], arrays(traj))
        self.publish(write(traj, efforts))
        return note


def main(argv=None):
    argv = sys.argv if argv is None else argv
    out = child_setup(int(argv[1]) if len(argv) > 1 else None)
    config = receive(0) if out is not None else None
    if config is None:
        return 0
    ctx = Context()
    rclpy.init(context=ctx, domain_id=config['domain_id'], signal_handler_options=SignalHandlerOptions.NO)
    node = rclpy.create_node(config['name'], namespace=config['namespace'], context=ctx, enable_rosout=False,
                             start_parameter_services=False)
    qos = QoSProfile(**config['qos'])
    pub = node.create_publisher(JointTrajectory, config['topic_out'], qos,
                                event_callbacks=PublisherEventCallbacks(use_default_callbacks=False))
    filler = Filler(out, pub.publish)
    node.create_subscription(JointTrajectory, config['topic_in'], filler.on_trajectory, qos, raw=True,
                             event_callbacks=SubscriptionEventCallbacks(use_default_callbacks=False))
    threading.Thread(target=filler.read_answers, name='lie_dynamics_answers', daemon=True).start()
    ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(node)
    beat, next_beat = config['heartbeat'], 0.0
    try:
        while not filler.ended.is_set():
            now = time.monotonic()
            if now >= next_beat:   # from this loop: a stuck executor is silent too
                filler.send(('alive',))
                next_beat = now + beat
            ex.spin_once(timeout_sec=min(0.1, beat))
    except OSError:   # the node is gone
        pass
    finally:
        # Leave the graph first, nothing before: no stale endpoint is matched after this, and
        # the participant's shared-memory files go with it (a fill still running is of no use
        # any more: the node stops reading). The node kills a child that takes too long.
        node.destroy_node()
        ctx.try_shutdown()
    return 0


if __name__ == '__main__':
    code = main()
    sys.stderr.flush()
    # Out of the graph: the interpreter's teardown (its threads, rclpy's and Fast DDS's
    # destructors: a second of CPU for a starved niced process) would only delay the node's
    # exit, which waits for this one.
    os._exit(code)
