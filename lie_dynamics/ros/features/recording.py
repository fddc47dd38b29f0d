"""The dynamics node's recording for calibration, a per-sample feature (base.py).

    ~/record   std_srvs/SetBool: true starts recording the accepted joint_states with their
               measured efforts; false stops, writes them as an mcap rosbag2 folder (topic
               /joint_states, sensor_msgs/msg/JointState: the controlled joints in the command's
               order, the header stamps as received) under `recording_dir`, and answers with its
               path. Read it with lie_dynamics.calibration.recordings (or `ros2 bag`).

A recording lasts at most `recording_max_s` seconds of joint_states (stamp time; the steady clock
for unstamped states); then it stops by itself, is written, and says so in one log line (the next
`false` answers with its path). A recording also stops when the controlled joints change. Samples
without finite efforts are left out and counted: calibration needs the measured torques. The efforts are
recorded raw, as measured: `calibration_file`'s effort offsets are not subtracted, since a
re-calibration identifies them again from these efforts.

Nothing of it delays the command: on the control path a sample costs a few row copies into
preallocated chunks (`SampleLog`, after the command went out; no check: the writer leaves out
samples without efforts). The messages are serialized and
written by a child process (`python -m lie_dynamics.ros.features.recording`, started with exec as
the model builder is: the pipe protocol of core/pipe.py), to which a writer thread of the node hands the
chunks over a pipe (the interpreter lock is free while it writes or waits). The service is served
by a hidden helper node with its own two-thread executor (as ~/identify_payload: its answer waits
for the file, and a second call meanwhile is answered at once).
"""
import os
import queue
import sys
import threading
import time

import numpy as np
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.executors import MultiThreadedExecutor
from rclpy.node import Node

from .. import interfaces
from ..core.diagnostics import DIAG_TEXT_MAX, clip
from ..core.timebase import TimeBase
from ..core.pipe import child_setup, receive, send, start_child
from .base import Feature

TOPIC = '/joint_states'
CHUNK = 4096                 # samples per preallocated block
WRITE_TIMEOUT_S = 600.0      # a writer child that answers no later is taken for hung and killed
SHUTDOWN_WRITE_S = 60.0      # how long a node that goes waits for its last recording to be written


def default_dir():
    """Where recordings go when recording_dir is empty: $ROS_HOME/lie_dynamics/recordings
    (ROS_HOME defaults to ~/.ros, as for ROS logs)."""
    home = os.environ.get('ROS_HOME') or os.path.join(os.path.expanduser('~'), '.ros')
    return os.path.join(home, 'lie_dynamics', 'recordings')


def new_folder(base, now=None):
    """A path for a new rosbag2 folder under `base`, named as `ros2 bag record` names its own
    (rosbag2_YYYY_MM_DD-HH_MM_SS), with a suffix if it exists."""
    name = time.strftime('rosbag2_%Y_%m_%d-%H_%M_%S', time.localtime(now))
    path, k = os.path.join(base, name), 1
    while os.path.lexists(path):
        k += 1
        path = os.path.join(base, f'{name}_{k}')
    return path


class SampleLog:
    """Accepted samples of n joints in CHUNK-row blocks: header stamp (ns, 0: none), receive time
    (ns, wall clock: the bag's time), q, velocity (NaN: absent), effort; `span`, the seconds
    covered by the core/timebase.py rule. `add` is the control
    path's part; the blocks are handed to the writer once the log is closed."""

    def __init__(self, names, max_s, clock=time.monotonic, wall=time.time_ns):
        self.names = names
        self.n = len(names)
        self.max_s = max_s
        self.time = TimeBase(clock)   # the one rule for a sample's time (stamp, else the steady clock)
        self.wall = wall
        self.blocks = []
        self.size = 0               # samples kept
        self._fill = CHUNK
        self.span = 0.0             # s covered (each time base counts from its own first sample)

    def add(self, sample):
        """One accepted sample; True once recording_max_s is covered. (Samples without finite
        efforts are kept here and left out by the writer: no check on the control path.)"""
        stamp = sample.stamp
        t = self.time.seconds(stamp)
        if t > self.span:
            self.span = t
        if self._fill == CHUNK:
            self.blocks.append((np.zeros(CHUNK, np.int64), np.zeros(CHUNK, np.int64),
                                *(np.empty((CHUNK, self.n)) for _ in range(3))))
            self._fill = 0
        stamps, log, q, qd, effort = self.blocks[-1]
        k = self._fill
        stamps[k], log[k] = stamp, self.wall()
        q[k] = sample.q
        # the message's own arrays mapped here (SampleResult.columns): a fancy index into the row,
        # a third of what building the sample's mapped copies costs
        cols, v, e = sample.columns, sample.message_velocity, sample.message_effort
        qd[k] = v[cols] if len(v) else np.nan
        effort[k] = e[cols] if len(e) else np.nan
        self._fill = k + 1
        self.size += 1
        return self.span >= self.max_s

    def chunks(self):
        """The blocks, the last one cut to its filled rows: (stamps, log times, q, qd, effort)."""
        for i, block in enumerate(self.blocks):
            k = self._fill if i == len(self.blocks) - 1 else CHUNK
            yield tuple(a[:k] for a in block)


class Recorder:
    """One recording at a time. begin, add and stop run under the node's lock (add on the control
    path); `write` (the writer thread) turns a stopped SampleLog into a rosbag2 folder."""

    def __init__(self):
        self.log = None            # the SampleLog being filled (None: not recording)
        self.folder = ''           # where the current or last one goes
        self.pending = None        # the write of a recording that stopped by itself, until `false` takes it
        self.written = self.failed = 0
        self.last = ''

    def begin(self, names, settings):
        """Start recording for the joints `names`. Raises ValueError (refused)."""
        if self.log is not None:
            raise ValueError(f'already recording ({self.log.size} samples so far, into {self.folder})')
        if not names:
            raise ValueError('no robot model loaded: nothing to record yet')
        base = settings.recording_dir or default_dir()
        self.folder = new_folder(os.path.expanduser(base))
        self.log = SampleLog(names, settings.recording_max_s)
        self.pending = None
        return self.folder

    def add(self, sample):
        """One accepted sample; returns the reason when the recording stops by itself, else None."""
        log = self.log
        if sample.names is not log.names and list(sample.names) != list(log.names):
            return 'the controlled joints changed'
        if log.add(sample):
            return f'recording_max_s ({log.max_s:g} s) reached'
        return None

    def stop(self):
        """End the recording: the SampleLog to write (None when none ran)."""
        log, self.log = self.log, None
        return log


class WriterProcess:
    """The child that writes rosbag2 folders, started on first use by the thread that uses it (it
    dies with that thread: build_process.child_setup)."""

    def __init__(self):
        self._proc = None

    def write(self, folder, log):
        """Write `log` (a stopped SampleLog) into the new folder; returns (messages written,
        samples left out without efforts). Raises ValueError with the reason (the child's error,
        or the child lost)."""
        proc = self._proc
        if proc is None or proc.poll() is not None:
            proc = self._proc = start_child(__name__)
        try:
            fd = proc.stdin.fileno()
            send(fd, ('begin', folder, list(log.names), TOPIC))
            for chunk in log.chunks():   # one block at a time: never one large pickle under the lock
                send(fd, ('chunk', chunk))
            send(fd, ('end',))
            answer = receive(proc.stdout.fileno(), time.monotonic() + WRITE_TIMEOUT_S, time.monotonic)
        except OSError as exc:
            answer = ('lost', str(exc))
        if not isinstance(answer, tuple) or answer[0] != 'ok':
            self.stop()
            why = answer[1] if isinstance(answer, tuple) and answer[0] == 'error' else 'the writer process was lost'
            raise ValueError(f'{folder} not written: {why}')
        return answer[1], answer[2]

    def stop(self):
        proc, self._proc = self._proc, None
        if proc is None:
            return
        for f in (proc.stdin, proc.stdout):
            try:
                f.close()
            except OSError:
                pass
        try:
            proc.wait(timeout=2.0)   # it ends at end of input
        except Exception:  # noqa: BLE001 - a hung child is killed
            proc.kill()
            proc.wait()


class RecordService(Feature):
    """~/record of a DynamicsNode `node` (its public core, lock, log_event): active while it
    records; the writer thread writes each stopped recording in turn."""

    name = 'recording'

    def __init__(self, node):
        super().__init__()
        self.node = node
        self.recorder = Recorder()
        self._jobs = queue.Queue()
        # started now, idle until a recording stops: no thread is started on the control path
        self._writer = threading.Thread(target=self._write_loop, name='lie_dynamics_record_writer', daemon=True)
        self._writer.start()
        self._helper = Node(f'_{node.get_name()}_record', namespace=node.get_namespace(), context=node.context,
                            start_parameter_services=False, enable_rosout=False, use_global_arguments=False)
        interfaces.service(self._helper, '~/record', self._srv_record, f'{node.get_fully_qualified_name()}/record',
                           callback_group=ReentrantCallbackGroup())
        self._executor = MultiThreadedExecutor(num_threads=2, context=node.context)
        self._executor.add_node(self._helper)
        self._thread = threading.Thread(target=self._spin, name='lie_dynamics_record', daemon=True)
        self._thread.start()

    @property
    def active(self):
        return self.recorder.log is not None

    def on_sample(self, sample):
        """(control path, under the node's lock) Keep the sample; a recording that ends by
        itself is handed to the writer thread."""
        r = self.recorder
        why = r.add(sample)
        if why is not None:
            r.pending = self._hand_over(r.stop(), r.folder, why)

    def report(self, level, message):
        r = self.recorder
        state = f'recording ({r.log.size} samples)' if r.log is not None else 'idle'
        return level, message, [('recording', state), ('recording_last', r.last),
                                ('recordings_written', str(r.written))]

    def stop(self):
        log = self.recorder.stop()   # a recording still running when the node goes is written
        if log is not None and log.size:
            self._hand_over(log, self.recorder.folder, 'the node is shutting down')
        self._executor.shutdown(timeout_sec=2.0)
        self._thread.join(timeout=2.0)
        self._helper.destroy_node()
        self._jobs.put(None)   # after the jobs queued: a recording stopped now is still written
        self._writer.join(timeout=SHUTDOWN_WRITE_S)

    # ------------------------------------------------------------------ writing
    def _hand_over(self, log, folder, why=None):
        """Queue `log` for the writer thread; returns the job (its `done` event, then `result`)."""
        job = _Job(log, folder, why)
        self._jobs.put(job)
        return job

    def _write_loop(self):
        proc = WriterProcess()
        try:
            while True:
                job = self._jobs.get()
                if job is None:
                    return
                job.run(proc, self)
        finally:
            proc.stop()

    def finished(self, job):
        """(writer thread) A recording was written or failed: counted and, for one that stopped
        by itself, logged and kept for the next `false`."""
        node, r = self.node, self.recorder
        with node.lock:
            if job.ok:
                r.written += 1
            else:
                r.failed += 1
            r.last = job.result
            if job.why is not None:
                text = (f'~/record stopped by itself ({job.why}): {job.written} samples written to {job.result}'
                        if job.ok else f'~/record stopped by itself ({job.why}); {job.result}')
                node.log_event('info' if job.ok else 'error', None, text)

    # ------------------------------------------------------------------ service
    def _spin(self):
        try:
            self._executor.spin()
        except Exception:  # noqa: BLE001 - the context shut down under it: nothing left to serve
            pass

    def _srv_record(self, request, response):
        node, r = self.node, self.recorder
        with node.lock:
            settings = node.core.settings
            if request.data:
                try:
                    folder = r.begin(node.core.layout if node.core.model is not None else None, settings)
                except ValueError as exc:
                    response.success, response.message = False, clip(f'refused: {exc}', DIAG_TEXT_MAX)
                    return response
                node.log_event('info', None, f'~/record: recording into {folder}')   # one per call: never held back
                response.success = True
                response.message = (f"recording into {folder} (at most {settings.recording_max_s:g} s; "
                                    'false stops it and writes the file)')
                return response
            log = r.stop()
            if log is None:
                job, r.pending = r.pending, None   # one that stopped by itself: its outcome, once
                if job is None:
                    response.success, response.message = False, 'not recording'
                    return response
            elif log.size == 0:
                response.success = False
                response.message = 'nothing recorded: no accepted joint_states; no file written'
                return response
            else:
                job = self._hand_over(log, r.folder)
        job.done.wait()
        response.success, response.message = job.ok, clip(job.result, DIAG_TEXT_MAX)
        return response


class _Job:
    """A stopped recording for the writer thread: `result` is the folder's path, or the error."""

    def __init__(self, log, folder, why):
        self.log, self.folder, self.why = log, folder, why
        self.done = threading.Event()
        self.ok, self.result, self.written = False, '', 0

    def run(self, proc, feature):
        try:
            os.makedirs(os.path.dirname(self.folder), exist_ok=True)
            self.written, left_out = proc.write(self.folder, self.log)
            self.ok, self.result = True, self.folder
            if left_out:
                self.result += f' ({left_out} samples without efforts left out)'
        except (ValueError, OSError) as exc:
            self.result = f'not written: {exc}'
        except Exception as exc:  # noqa: BLE001 - reported like the others; the caller still gets its answer
            self.result = f'not written: {type(exc).__name__}: {exc}'
        try:
            feature.finished(self)
        finally:
            self.done.set()   # a `false` call waits for this whatever happened


def serve(parent=None):
    """The writer child's loop: ('begin', folder, names, topic), ('chunk', arrays)..., ('end',)
    in; ('ok', messages written, samples left out without efforts) or ('error', text) out."""
    from ...calibration.recordings import write_joint_states

    out = child_setup(parent)
    if out is None:
        return
    while True:
        request = receive(0)
        if request is None:
            return
        _, folder, names, topic = request
        parts = []
        while True:
            item = receive(0)
            if item is None:
                return
            if item[0] == 'end':
                break
            parts.append(item[1])
        try:
            cols = [np.concatenate([p[i] for p in parts]) for i in range(5)]
            keep = np.isfinite(cols[4]).all(axis=1)   # calibration needs the measured efforts
            if not keep.any():
                raise ValueError(f'none of the {len(keep)} samples recorded has finite efforts: '
                                 'nothing to calibrate from')
            stamps, log_ns, q, qd, effort = (c[keep] for c in cols)
            count = write_joint_states(folder, names, stamps, q, qd, effort, topic=topic, log_ns=log_ns)
            answer = ('ok', count, int(len(keep) - count))
        except Exception as exc:  # noqa: BLE001 - any failure goes back as text
            answer = ('error', f'{type(exc).__name__}: {exc}' if not isinstance(exc, ValueError) else str(exc))
        send(out, answer)


if __name__ == '__main__':
    serve(int(sys.argv[1]) if len(sys.argv) > 1 else None)
