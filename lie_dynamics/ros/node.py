"""ROS 2 node: gravity compensation / torque feedforward from joint_states to ros2_control effort
commands, and feedforward efforts for joint_trajectory_controller trajectories.

    ros2 run lie_dynamics dynamics_node --ros-args --params-file config/arm7_gravity.yaml
    python -m lie_dynamics.dynamics_node --ros-args -p urdf_path:=config/arm7.urdf

The rclpy shell of the plain-Python parts below it (ros/__init__.py; behaviour: docs/node.md; the
topics, services, QoS: interfaces.py; parameters, services: control.py). Per joint_states message
(docs/architecture.md): bytes -> core/cdr.py sample -> the core's command, published -> the accepted
result to each of the FEATURES -> one event queue -> the paced log. The timer runs on the steady
clock (a stopped /clock must not stop the watchdog). Heavy work runs off it: loading/, trajectories/.
"""
import collections
import os
import sys
import threading
import time

from rclpy.clock import Clock, ClockType
from rclpy.node import Node

from . import interfaces
from .control import Control
from .core.cdr import JointStateDecoder, read_joint_trajectory, sample_of
from .core.compensator import Compensator
from .core.fused import FusedCommand
from .core.log import LOG_LINES_PER_CALLBACK, LOG_LINES_PER_S, LOG_THROTTLE_S, EventLog, guarded
from .core.params import HELP_DESCRIPTION, HELP_EXAMPLE, PARAMS, help_rows
from .core.watchdog import Every, tick_period
from .features.base import Features
from .features.contact_topics import ContactTopics
from .features.dynamics_topics import DynamicsTopics
from .features.gravity_topic import GravityTopic
from .features.payload_services import PayloadServices
from .features.recording import RecordService
from .interfaces import (DESCRIPTION_QOS, JOINT_STATES_QOS, NO_PUB_EVENTS, NO_SUB_EVENTS, SERVICE_QOS,
                         SERVICE_QUEUE, TRAJECTORY_QOS)
from .loading.background import Background
from .loading.parameter_change import start_source
from .loading.sources import Sources
from .outputs import Outputs
from .run import node_parser, run
from .trajectories.trajectory_process import child_config

__all__ = ['DESCRIPTION_QOS', 'FEATURES', 'JOINT_STATES_QOS', 'LOG_THROTTLE_S', 'NO_PUB_EVENTS', 'NO_SUB_EVENTS',
           'SERVICE_QOS', 'SERVICE_QUEUE', 'TRAJECTORY_QOS', 'DynamicsNode', 'main']

# The per-sample features (features/base.py), each made as cls(node), in the order they run and
# report. A new one is its module in features/ and one line here.
FEATURES = (
    ContactTopics,     # ~/external_torques, ~/collision: the momentum observer
    GravityTopic,      # <gravity_topic>: the gravity in force before each command
    PayloadServices,   # ~/set_payload, ~/identify_payload (records accepted samples)
    DynamicsTopics,    # ~/dynamics/*
    RecordService,     # ~/record (records accepted samples for calibration)
)


# The features' work after a command runs in executor tasks of about this length (_run_later): a
# state arriving meanwhile waits at most for the rest of a task (this, or one longer step), and
# each task costs one executor dispatch (a few microseconds with the EventsExecutor).
LATER_SLICE_S = 50e-6
# A node that cannot keep up (more work per state than a period) runs the queued steps in the
# callback once more than this many wait: the observer's steps are never dropped, and its backlog
# must not grow; the input's depth-1 queue then drops states, as before.
LATER_MAX_STEPS = 32
# The fused command path (core/fused.py): a state repeating the last layout, in the common case,
# from its bytes to the command's in one native call; off: the Python path for every state (the
# same bytes). LIE_DYNAMICS_FUSED_COMMAND=0 turns it off (benchmarks compare the two).
FUSED_COMMAND = os.environ.get('LIE_DYNAMICS_FUSED_COMMAND', '1').strip() != '0'
# At most this long at start-up (run.py: settle), the node waits until it has discovered its
# trajectory process before it serves. Fast DDS's shared-memory transport, the first time a
# participant sends to a new peer's port, checks that the peer's listener is alive; when another
# process checked it within the same interval it sleeps healthy_check_timeout_ms / 3 (1000 / 3 ms)
# holding the participant's send lock, and rclpy publishes holding the interpreter lock: the node
# stopped for 334 ms (no command, no timer) in 12 of 60 runs of bench.probes.tail_trace, ~3 s
# after start, when its trajectory process joined (benchmarks.md section 5). Discovered before the
# first command, that check costs nothing. (Any other participant joining later still can.)
TRAJECTORIES_JOIN_S = 10.0


class DynamicsNode(Node):
    """Dynamics node. features: the per-sample feature types (FEATURES); extra keyword arguments
    go to rclpy's Node (context, overrides)."""

    def __init__(self, node_name='dynamics_node', features=FEATURES, **kwargs):
        super().__init__(node_name, **kwargs)
        self.background = None
        self.features = None
        self.outputs = None
        # the features' work after each command, in steps (_after_command): [(feature, step)]
        self._later = collections.deque()
        self._executor = None      # the executor whose tasks run them (defer_to); None: at once
        self._scheduled = False    # a _run_later task is queued
        self.dropped_steps = 0     # queued steps of a coalescing feature replaced by a newer state's
        try:
            self._construct(features)
        except BaseException:
            # refused at start-up: no worker thread may outlive the node, and the rcl node goes
            # too (a half-made node keeps its /rosout publisher, which rcl shares by logger name
            # with the next node of the same name in this process: that node's log would be lost)
            self.destroy_node()
            raise

    def _construct(self, features):
        values = interfaces.declare_parameters(self, PARAMS)
        self.core = Compensator(values)  # ValueError on an invalid configuration
        self.events = self.core.events   # the one event queue: the core's and every feature's
        self.features = Features(events=self.events)   # registered in _start, once worker threads exist
        self.lock = threading.RLock()  # services/parameters vs. callbacks when spun by several threads
        self.sources = Sources()      # the running model's source, the last topic message
        self._decoder = JointStateDecoder()   # keeps the last name list: decoded once per stream
        # the fused command path (None: off, the Python path for every message; FUSED_COMMAND)
        self.fused = FusedCommand(self.core, self._decoder) if FUSED_COMMAND else None
        self.outputs = Outputs(self, self.core.settings.command_topic)
        self.event_log = EventLog(self.outputs.log_line, pace=LOG_LINES_PER_CALLBACK,   # lines per callback
                                  rate=LOG_LINES_PER_S)                               # and per second
        self._samples = 0   # joint_states callbacks (the timer writes every waiting line when none came)
        # ~/trajectory_in and ~/trajectory_out: served by a process of their own (trajectories/process.py)
        self.background = Background(self.core, self.sources, trajectories=child_config(self),
                                     kernels=lambda settings: self.features.kernels(settings))
        self._start(self.core.settings, features)

    def _start(self, settings, features):
        """The rest of the start-up, once worker threads exist (__init__ stops them if this raises)."""
        interfaces.subscription(self, 'robot_description', self._on_description)
        interfaces.subscription(self, 'joint_states', self.on_joint_state)   # raw: read by core/cdr.py
        desired = interfaces.subscription(self, '<desired_topic>', self._on_desired, settings.desired_topic)
        self.core.note_context(desired_topic=desired.topic_name)
        self._diag = Every(settings.diagnostics_period)
        self._timer = self.create_timer(tick_period(settings.stale_timeout, self._diag.period), self._on_timer,
                                        clock=Clock(clock_type=ClockType.STEADY_TIME))
        self.outputs.joint_state(settings.publish_joint_state)
        for make in features:
            self.features.add(make(self))
        self.control = Control(self, self._check)   # parameters, ~/set_enabled, ~/reload_model

        source = start_source(settings)   # loaded in this thread: nothing to keep answering yet
        if source is not None:
            err = self.background.load_now(*source)   # one that cannot load (a typo in a launch file): exit 2
            if err is not None:
                raise ValueError(err)
        self._check(self.core.settings)  # exit 2
        self.features.configure_if_changed(self.core)
        if self.core.model is None:
            self.background.expect_description()
            topic = self.resolve_topic_name('robot_description')
            self.log_event('info', None, f"no robot model yet: waiting for '{topic}' "
                           '(publishing nothing until a model is loaded)')
        self.drain_events(None)

    def _check(self, settings):
        """The checks of settings that need the layout or the model (ValueError): the features'."""
        self.features.check(settings, self.core.model)

    def set_tick_period(self):
        """The timer's period after a stale_timeout change (tick_period)."""
        period = tick_period(self.core.settings.stale_timeout, self._diag.period)
        self._timer.timer_period_ns = int(period * 1e9)

    def note_executor(self, kind):
        """The kind of executor that spins the node (run.py), shown in the diagnostics."""
        self.core.note_context(executor=kind)

    def defer_to(self, executor):
        """Run the features' work after each command in steps, one per task of `executor` (run.py
        passes the EventsExecutor, whose create_task is cheap; _after_command); None: at once."""
        self._executor = executor

    def settle(self, timeout=TRAJECTORIES_JOIN_S, cancel=None, poll=0.01):
        """(run.py, before the node serves) Wait until this node has discovered its trajectory
        process (its ~/trajectory_in subscription), at most `timeout` s (TRAJECTORIES_JOIN_S says
        why) or until cancel() is true (a stop signal). True once discovered or without one;
        False on the timeout, a cancel or a child that died."""
        tp = self.background.trajectories
        if tp is None:
            return True
        topic, end = tp.config['topic_in'], time.monotonic() + timeout
        while not self.count_subscribers(topic):
            if tp.pid is None or time.monotonic() >= end or (cancel is not None and cancel()):
                return False
            time.sleep(poll)
        return True

    def destroy_node(self):
        if self.background is not None:   # it leaves the ROS graph while the node's teardown runs
            self.background.stop_trajectories()
        if self.features is not None:
            try:
                with self.lock:   # the last states' queued work, while the publishers exist
                    self._run_all_later()
            except Exception:  # noqa: BLE001 - best effort: the node is going
                self._later.clear()
            self.features.stop()
        if self.outputs is not None:
            self.outputs.close()
        if self.background is not None:   # lines still held back are said before the node goes
            self.event_log.close()
        done = super().destroy_node()
        if self.background is not None:   # waits for the trajectory process (killed if it lingers)
            self.background.stop()
        return done

    @property
    def contact_monitor(self):
        """The external-torque observer and collision flag (contact.ContactMonitor)."""
        return self.features.get('contact').monitor

    # ------------------------------------------------------------------ input
    @guarded
    def _on_description(self, msg):
        with self.lock:
            self.sources.topic_xml = msg.data
            self.background.request('topic', msg.data, skip_identical=True)
            self.drain_events()

    @guarded
    def on_joint_state(self, msg):
        """The joint_states callback: the serialized message (bytes, as the subscription delivers
        it) or a sensor_msgs/JointState (benchmarks drive it in-process with either)."""
        t0 = time.perf_counter()
        self._samples += 1
        with self.lock, self.background.deferred():   # no kernel is built on the control path
            core = self.core
            background = self.background
            features = self.features
            fused = self.fused
            done = None
            prepared = fused is not None and type(msg) is bytes and core.layout is not None
            if prepared:
                background.swap_in()   # a new model swaps in here, between two commands (cheap: none)
                features.before_command(core)
                done = fused.command(msg, self.outputs.writers(len(core.layout), core.layout))
            if done is not None:   # the fused path's command (core/fused.py), then the core's bookkeeping
                try:
                    self.outputs.publish(*done)
                finally:
                    fused.accepted()
            else:                  # the Python path decides (and after a declined fused path)
                try:
                    sample = self._decoder.read(msg) if isinstance(msg, bytes) else sample_of(msg)
                except ValueError as exc:
                    core.refuse_malformed('joint_states', str(exc))
                    self.drain_events()
                    return
                if not prepared:
                    background.swap_in()
                    features.before_command(core)
                tau = core.on_sample(sample)
                if tau is not None:
                    self.outputs.command(tau, core.layout, sample.stamp)   # the input's stamp (ns)
            # after the command, never delaying it: the features' work, then the loader's bookkeeping
            self._after_command(features)
            background.collect()
            if self.events or self.event_log.waiting:
                self.drain_events()
            core.record_compute_time(time.perf_counter() - t0)

    @guarded
    def _on_desired(self, data):
        with self.lock:
            try:
                names, points = read_joint_trajectory(data, one=True)
            except ValueError as exc:
                self.core.refuse_malformed('desired', str(exc))
            else:
                self.core.on_desired(names, points)
            if self.events:
                self.drain_events()

    def configure_features(self):
        """Configure the features for the core's settings and model if they changed (parameters
        applied), the work still queued for earlier states run first, under the configuration it
        was queued with."""
        with self.lock:
            self._run_later_if_changed()
            self.features.configure_if_changed(self.core)

    def _after_command(self, features):
        """(under the lock) The features' work for the state just commanded (Features.steps): at
        once without an executor to defer to (defer_to); with one, the steps of the features
        marked `later` are queued and run in executor tasks (_run_later), so that a state arriving
        meanwhile has its command out first, and its steps of a coalescing feature (the dynamics
        topics) replace the older state's still queued."""
        self._run_later_if_changed()
        if self._executor is None:
            features.feed(self.core)
            return
        later = self._later
        queued = []
        for f, step in features.steps(self.core):
            if f.later:
                queued.append((f, step))
            else:
                step()
        if not queued:
            return
        newer = {f for f, _ in queued if f.coalesce}
        if newer and later:
            kept = [x for x in later if x[0] not in newer]
            self.dropped_steps += len(later) - len(kept)
            later.clear()
            later.extend(kept)
        later.extend(queued)
        if len(later) > LATER_MAX_STEPS:   # falling behind: catch up now, as the callback did before
            self._run_all_later()
            return
        if not self._scheduled:
            self._scheduled = True
            self._executor.create_task(self._run_later)

    @guarded
    def _run_later(self):
        """(an executor task) Queued steps of the features' work for up to LATER_SLICE_S; the
        rest in the next task, queued behind whatever arrived meanwhile."""
        with self.lock, self.background.deferred():
            later = self._later
            end = time.perf_counter() + LATER_SLICE_S
            try:
                while later:
                    later.popleft()[1]()
                    if time.perf_counter() >= end:
                        break
            finally:
                self._scheduled = bool(later)
                if later:
                    self._executor.create_task(self._run_later)
                if self.events or self.event_log.waiting:
                    self.drain_events()

    def _run_later_if_changed(self):
        """(under the lock) The older states' queued work now, under the configuration it was
        queued with, if the core's settings or model changed since (before the features are
        configured anew)."""
        if self._later and self.features.changed(self.core):
            self._run_all_later()

    def _run_all_later(self):
        """(under the lock) Every queued step now, in order."""
        later = self._later
        while later:
            later.popleft()[1]()

    # ------------------------------------------------------------------ log
    def log_event(self, severity, key, text):
        """One log line of the node itself, through the one event queue: at most one per `key`
        (the problem class) every LOG_THROTTLE_S s, paced like every other."""
        with self.lock:
            self.events.append((severity, key, text))
            self.drain_events()

    def drain_events(self, limit=LOG_LINES_PER_CALLBACK):
        """The one event queue (core and features) into the log, and up to `limit` of its
        waiting lines written within LOG_LINES_PER_S a second (None: all of them, at once: start-up)."""
        with self.lock:
            self.event_log.events(self.features.drain())
            self.event_log.flush(limit, rated=limit is not None)

    # ------------------------------------------------------------------ timer
    @guarded
    def _on_timer(self):
        with self.lock, self.background.deferred():
            self.background.collect()
            self.features.before_command(self.core)
            cmd = self.core.tick()
            if cmd is not None:
                self.outputs.command(cmd, self.core.layout)   # stamped now
            if self.events:
                self.drain_events()
        with self.lock:   # (helper threads drain the queue too)
            self.event_log.tick(self._samples)   # held-back lines; the waiting ones if no joint_states came
        if self._diag.due():
            self._publish_diagnostics()
            if self.sources.topic_xml is None:
                for who, text in self.outputs.description_publisher_problems():
                    self.log_event('warn', f'description:qos:{who}', text)

    def _publish_diagnostics(self):
        with self.lock:
            level, message, values = self.features.report(*self.core.diagnostics())
            m = self.core.model
        self.outputs.diagnostics(level, message, values, m.name if m is not None else '')

    def shutdown_command(self):
        """Publish the stale_action command once (the effort controller holds the last command)."""
        with self.lock:
            self.event_log.events(self.features.drain())   # what was said before: logged at close
            cmd = self.core.final_command()
            self.features.drain()   # its stale line: the node is not stale, it is going (said below)
            if cmd is None:
                return False
            self.outputs.command(cmd, self.core.layout)
        self.outputs.wait_for_command_acked(0.5)
        return True


def _on_stop(node):
    node.background.stop_trajectories()   # first: it leaves the ROS graph while the node stops
    if node.shutdown_command():
        node.log_event('info', None, 'shutting down: published the stale_action command once')


def main(args=None):
    """Entry point of `ros2 run lie_dynamics dynamics_node`: --help prints usage, arguments outside
    --ros-args and a start-up configuration that cannot work exit with status 2 (run.run)."""
    parser = node_parser('dynamics_node', HELP_DESCRIPTION, help_rows(), HELP_EXAMPLE)
    return run(DynamicsNode, 'dynamics_node', args, on_stop=_on_stop, parser=parser)


if __name__ == '__main__':
    sys.exit(main())
