"""The trajectory process: ~/trajectory_in -> ~/trajectory_out served by a child process, in
plain Python (no rclpy import): this is the node's side; the child is trajectory_process.py.

rclpy holds the interpreter lock while it takes a serialized message and while it publishes
one: 31-53 ms each for a 100,000-point trajectory (20 MB), before any code of the node runs,
which delayed the node's replies by as much. The child has its own rclpy context and node; it
subscribes and publishes the node's resolved topic names with the node's QoS, reads the point
count from the message's header, asks the node for the fill (`Rejected`, or the
`fill.TrajectoryFill` snapshot of the running model and settings, sent pickled only when it
changed since the last one), fills and publishes there. The node decides and counts as
before (`fill.TrajectoryInput`: `job` / `done`): the child's outcomes, log lines
included, come back over the pipe and go through the node's one throttled log path.

Messages (pickled, length first, core/pipe.py: send / receive). Node to child: the start
configuration (dict: domain_id, name, namespace, topic_in, topic_out, qos), then per question
('go', seq, TrajectoryFill or None (the last one still holds), max_trajectory_points) or
('no', seq). Child to node: ('ask', seq, points), ('done', error, note, kind) as
`TrajectoryInput.done` takes them, and ('alive',) from its executor loop once subscribed, then
every `heartbeat` s (HEARTBEAT_S; sent with the start configuration).

A child that dies, whose fill takes longer than `timeout` s, or that is silent (no message of
any kind) for longer than SILENT_S s, or START_S s from its start to its first message, is
reported once (a fill under way is counted as rejected; a hung child, stopped or stuck, idle or
not, is killed) and a new one starts; until it has subscribed, trajectories are not received.
Silence excludes the time the child's main thread waited for a CPU (Linux schedstat): the child
runs niced, and on an overloaded machine its loop waited up to 8.4 s at a time for one (load
average 13 on 2 cores) while doing nothing wrong; killing it would only cost a restart, which is
slower still. The node's reader thread stamps each message; `collect`, which the node's timer
calls (not each sample), compares the stamp with the clock.

The child never outlives the node: `stop` ends it. End of input tells it to leave the ROS graph
(its Fast DDS shared-memory files go with its participant) and exit; it has STOP_S s for that
from the first `stop` (the node asks before its own teardown, which runs meanwhile), then it is
killed. It also asks the kernel for SIGKILL when the thread that started it ends. A child
killed here (hung, or too slow to stop) does not remove its Fast DDS shared-memory segment: the
node removes it (remove_dead_segments).
"""
import fcntl
import os
import pickle
import select
import subprocess
import threading
import time

from ..core.pipe import receive, send, start_child

FILL_TIMEOUT_S = 120.0   # a fill that takes longer is taken for hung (100,000 points: about 1 s)
RESTART_S = 5.0          # a child that keeps dying is started at most this often
HEARTBEAT_S = 1.0        # the child says it is alive at least this often
SILENT_S = 5.0           # a child silent longer is taken for hung (its CPU waits excluded: see above)
START_S = 60.0           # its first message (Python, rclpy and DDS started) may take this long
STOP_S = 3.0             # from end of input to its exit (then SIGKILL): within a launcher's 5 s for the node
CHILD = 'lie_dynamics.ros.trajectories.trajectory_process'


class TrajectoryProcess:
    """One child at a time. on_ask(child, seq, points) is called in the reader thread when the
    child asks for a fill; `answer(child, ...)` replies (any thread); `collect` (control path) returns what came
    back since: [('done', error, note, kind)] and the loss of a child as ('lost', text, busy)."""

    def __init__(self, config, on_ask, timeout=FILL_TIMEOUT_S, clock=time.monotonic, cpu_wait=None):
        self.config = dict(config)
        self.on_ask = on_ask
        self.timeout = timeout
        self.clock = clock
        self.cpu_wait = cpu_wait_s if cpu_wait is None else cpu_wait   # cpu_wait(pid): seconds, like clock
        self.heartbeat = HEARTBEAT_S   # what the next child started is told
        self.silent = SILENT_S
        self.start_timeout = START_S
        self.started = 0           # children started so far
        self.has_messages = False  # a plain attribute test on the control path
        self._lock = threading.Lock()
        self._messages = []
        self._proc = None
        self._sent = None          # what the child holds: the last TrajectoryFill sent
        self._busy = None          # when the answer that started the child's fill was sent
        self._last_start = None
        self._mark = None          # (child process, clock(), its cpu_wait, heard): its start or last message
        self._stopping = False
        self._told = None          # (child process, time.monotonic()): when stop ended its input
        self.stop_timeout = STOP_S
        self.exit_code = None      # of the last child ended here (negative: the signal that killed it)

    @property
    def pid(self):
        """The running child's pid, or None."""
        proc = self._proc
        return proc.pid if proc is not None and proc.poll() is None else None

    @property
    def last_heard(self):
        """When (clock()) the running child last sent a message, or None."""
        mark, proc = self._mark, self._proc
        return mark[1] if mark is not None and mark[3] and proc is not None and mark[0] is proc else None

    @property
    def busy(self):
        """A fill is under way in the child."""
        return self._busy is not None

    def start(self):
        """Start a child (none running); at most once every RESTART_S s after the first."""
        now = self.clock()
        if self._stopping or self._proc is not None or (
                self._last_start is not None and now - self._last_start < RESTART_S):
            return False
        self._last_start = now
        proc = start_child(CHILD)
        self._mark = (proc, now, self.cpu_wait(proc.pid), False)
        self._proc, self._sent, self._busy = proc, None, None
        self.started += 1
        try:
            send(proc.stdin.fileno(), dict(self.config, heartbeat=self.heartbeat))
        except OSError:   # died at once: the reader reports it
            pass
        threading.Thread(target=self._read, args=(proc, self.started), name='lie_dynamics_trajectories',
                         daemon=True).start()
        return True

    @property
    def running(self):
        """A child was started and has not been found dead or stopped yet."""
        return self._proc is not None

    def answer(self, child, seq, job, cap):
        """Answer question `seq` of `child` (the number on_ask gave; a child since replaced is
        not answered): job a TrajectoryFill (fill, with max_trajectory_points `cap`)
        or None (refused: the node counts it). The model is pickled only when the child does not
        hold this snapshot yet. (Worker thread: pickling a large model takes milliseconds.)"""
        proc = self._proc
        if proc is None or child != self.started:
            return
        if job is None:
            msg = ('no', seq)
        else:
            held = self._sent
            same = held is not None and len(held[0]) == len(job) and all(
                a is b for a, b in zip(held[0], job)) and held[1] == job.model.version
            msg = ('go', seq, None if same else job, cap)
            self._sent = (job, job.model.version)
            self._busy = self.clock()   # before it is sent: its 'done' may come back at once
        try:
            send(proc.stdin.fileno(), msg)
        except (OSError, ValueError):   # the child is gone (or its pipe closed): the reader reports it
            pass

    def _read(self, proc, child):
        """The child's messages (this thread waits on the pipe without the interpreter lock)."""
        fd = proc.stdout.fileno()
        while True:
            try:
                msg = receive(fd)
            except (OSError, ValueError, EOFError, pickle.UnpicklingError):
                msg = None
            if msg is None:
                break
            if self._proc is proc:   # (one assignment: the control path reads it whole)
                self._mark = (proc, self.clock(), self.cpu_wait(proc.pid), True)
            if msg[0] == 'alive':
                continue
            if msg[0] == 'ask':
                self.on_ask(child, msg[1], msg[2])
            else:
                if msg[0] == 'done':
                    self._busy = None
                with self._lock:
                    self._messages.append(msg)
                    self.has_messages = True
        try:
            proc.stdout.close()   # here: closed by another thread, its number could be reused under this read
        except OSError:
            pass
        with self._lock:
            if self._proc is proc and not self._stopping:
                self._messages.append(('ended', proc))
                self.has_messages = True

    def collect(self):
        """The child's messages since the last call, a lost child reported (once) and a new one
        started: [('done', error, note, kind) or ('lost', text, busy)] (control path)."""
        out = []
        if self.has_messages:
            with self._lock:
                msgs, self._messages = self._messages, []
                self.has_messages = False
            for m in msgs:
                if m[0] != 'ended':
                    out.append(m)
                elif m[1] is self._proc:
                    busy = self.busy
                    code = self._end(m[1])
                    why = f'signal {-code}' if code < 0 else f'exit status {code}'
                    out.append(('lost', f'the trajectory process ended ({why})', busy))
        proc = self._proc
        if proc is not None:
            why = self._hung(proc)
            if why is not None:
                busy = self.busy
                self._end(proc, kill=True)
                out.append(('lost', f'the trajectory process {why} and was killed', busy))
        return out

    def _hung(self, proc):
        """Why the running child `proc` is taken for hung, or None."""
        now, since, mark = self.clock(), self._busy, self._mark
        if since is not None and now - since > self.timeout:
            return f'did not finish a fill within {self.timeout:g} s'
        if mark is None or mark[0] is not proc:
            return None
        _, at, waited, heard = mark
        limit = self.silent if heard else self.start_timeout
        if now - at <= limit:   # (the common case: nothing more is read)
            return None
        if now - at - (self.cpu_wait(proc.pid) - waited) <= limit or _unread(proc):
            return None
        return f'was silent for {limit:g} s' if heard else f'sent nothing within {limit:g} s of its start'

    def _end(self, proc, kill=False, timeout=2.0):
        """End `proc` (end of input first; SIGKILL if asked or if it lingers `timeout` s): its
        exit code. A killed child leaves the graph without its participant's cleanup: its Fast
        DDS segments are removed here (remove_dead_segments)."""
        if self._proc is proc:
            self._proc, self._busy = None, None
        segments = dds_segments(proc.pid) if kill or proc.poll() is None else ()
        if kill:
            proc.kill()
        try:
            proc.stdin.close()
        except OSError:
            pass
        try:
            proc.wait(timeout=timeout)   # ends on end of input, after leaving the ROS graph
        except subprocess.TimeoutExpired:
            kill = True
            proc.kill()
            proc.wait()
        if kill:
            remove_dead_segments(segments)
        self.exit_code = proc.returncode
        return proc.returncode

    def stop(self, wait=True):
        """End the child; none starts again. The first call ends its input; with `wait`, wait
        for it to exit until STOP_S s after that, then SIGKILL (wait=False: the caller goes on
        with its own teardown meanwhile and calls stop() later)."""
        self._stopping = True
        proc = self._proc
        if proc is None:
            return
        told = self._told
        if told is None or told[0] is not proc:   # (a child started meanwhile is told too)
            told = self._told = (proc, time.monotonic())
            try:
                proc.stdin.close()
            except OSError:
                pass
        if wait:
            self._end(proc, timeout=max(0.0, told[1] + self.stop_timeout - time.monotonic()))


def cpu_wait_s(pid):
    """Seconds the main thread of process `pid` has spent waiting for a CPU (Linux
    /proc/<pid>/schedstat: run_delay), or 0.0 where that is not known."""
    try:
        with open(f'/proc/{pid}/schedstat', 'rb') as fh:
            return int(fh.read().split()[1]) * 1e-9
    except (OSError, ValueError, IndexError):
        return 0.0


SHM_DIR = '/dev/shm'


def dds_segments(pid):
    """Names of the Fast DDS shared-memory segments (`fastrtps_<hex>`, not the ports) that
    process `pid` maps: its own and those of the participants it read from."""
    try:
        with open(f'/proc/{pid}/maps') as fh:
            paths = {line.split(None, 5)[5].rstrip('\n') for line in fh if SHM_DIR + '/fastrtps_' in line}
    except (OSError, IndexError):
        return set()
    names = {os.path.basename(p.removesuffix(' (deleted)')) for p in paths}
    return {n for n in names if not n.startswith('fastrtps_port') and not n.endswith('_el')}


def remove_dead_segments(names):
    """Remove the segments among `names` whose participant is dead, with their `_el` lock file:
    Fast DDS holds a lock (flock) on `<segment>_el` for the life of the participant that made the
    segment, so a lock taken here means a dead owner, and its random name is never made again (a
    process that still maps it keeps its mapping). Ports are left alone: their names are reused,
    and Fast DDS takes over a dead one itself. Returns the names removed."""
    removed = []
    for name in sorted(names):
        try:
            fd = os.open(os.path.join(SHM_DIR, name + '_el'), os.O_RDWR)
        except OSError:   # no lock file: not a segment of this kind, or gone
            continue
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:   # its participant lives
            os.close(fd)
            continue
        try:
            for path in (os.path.join(SHM_DIR, name), os.path.join(SHM_DIR, name + '_el')):
                try:
                    os.remove(path)
                except FileNotFoundError:
                    pass
            removed.append(name)
        except OSError:
            pass
        finally:
            os.close(fd)
    return removed


def _unread(proc):
    """Output of `proc` waits in the pipe (the reader thread has yet to stamp it: this process was
    itself stopped or starved, not the child), or the reader closed it (the child ended: reported)."""
    try:
        return bool(select.select([proc.stdout], [], [], 0)[0])
    except (OSError, ValueError):
        return True
