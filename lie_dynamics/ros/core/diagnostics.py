"""What the dynamics node reports, in plain Python (no rclpy import): the counters, the
per-period diagnostics status (level, message, key/value list) and the bounds on any text
that ends up in the log or on /diagnostics.
"""
import re
import threading
import time

# diagnostic_msgs/DiagnosticStatus levels
OK, WARN, ERROR = 0, 1, 2

# Bounds of the inertia report: a URDF with thousands of bad links must not flood the log or
# /diagnostics (log lines per load, characters per line, messages in the diagnostics value).
INERTIA_LOG_LINES = 20
INERTIA_TEXT_MAX = 300
INERTIA_DIAG_MESSAGES = 3
DIAG_TEXT_MAX = 1000


# Longest log line; every diagnostics value is cut to DIAG_TEXT_MAX.
LOG_TEXT_MAX = 1000
# Names shown of a list quoted from input, and characters shown of each.
NAMES_SHOWN = 8
NAME_TEXT_MAX = 60


def clip(text, n):
    """text cut to at most n characters ('...' marks a cut)."""
    return text if len(text) <= n else text[:n - 3] + '...'


_VARYING = re.compile(r"'[^']*'|\"[^\"]*\"|\[[^\]]*\]?|[-+.\w]*\d[-+.\w]*")


def problem_key(text, n=80):
    """The problem class of an error text, to throttle its log lines by: the text without what
    varies from message to message (numbers, quoted names, lists), cut to n characters."""
    return _VARYING.sub('#', text)[:n]


def names_text(names, shown=NAMES_SHOWN):
    """A list of names quoted from input, bounded: at most `shown` names of at most
    NAME_TEXT_MAX characters each, then how many more there are."""
    names = list(names)
    text = repr([clip(str(n), NAME_TEXT_MAX) for n in names[:shown]])
    return text if len(names) <= shown else f'{text[:-1]}, ... (+{len(names) - shown} more)]'


class Throttle:
    """At most one line per `period` seconds for each key (problem class). What is held back is
    counted and reported: with the next line of its class let through, or by due() once the
    period is over, whichever comes first (a burst shorter than the period is not left unsaid)."""

    def __init__(self, period=1.0, clock=time.monotonic):
        self.period = period
        self.clock = clock
        self._last = {}
        self._held = {}   # key -> [count, newest payload] of the lines held back since the last one let through
        self._lock = threading.Lock()   # lines come from the executor and from helper threads

    def check(self, key, now=None, payload=None):
        """None when a line for `key` is held back now (its `payload` kept for due()), else how many
        were held back before it."""
        now = self.clock() if now is None else now
        with self._lock:
            last = self._last.get(key)
            if last is not None and now - last < self.period:
                held = self._held.setdefault(key, [0, None])
                held[0] += 1
                held[1] = payload
                return None
            if len(self._last) > 1000:  # bounded whatever the keys: forget the expired ones already reported
                self._last = {k: t for k, t in self._last.items() if now - t < self.period or k in self._held}
            self._last[key] = now
            held = self._held.pop(key, None)
            return 0 if held is None else held[0]

    def ready(self, key, now=None):
        return self.check(key, now) is not None

    def due(self, now=None):
        """[(payload, n)] for each key whose period is over with lines held back: the newest held
        line, let through now (it opens the key's next period), and how many others it stands for."""
        now = self.clock() if now is None else now
        with self._lock:
            out = []
            for key in [k for k in self._held if now - self._last[k] >= self.period]:
                count, payload = self._held.pop(key)
                self._last[key] = now
                out.append((payload, count - 1))
            return out


def held_text(text, n, period):
    """A log line that stands for n more held back by a Throttle of `period` s."""
    return f'{text} ({n} more like this in the last {period:g} s)' if n else text


class Counters:
    """Totals since start-up (the *_total / *_count diagnostics)."""
    __slots__ = ('received', 'accepted', 'rejected', 'clamp_count', 'velocity_unavailable',
                 'desired_received', 'desired_accepted', 'desired_rejected', 'fallback_events',
                 'trajectories_filled', 'trajectories_rejected')

    def __init__(self):
        for name in self.__slots__:
            setattr(self, name, 0)

    def copy(self):
        new = Counters()
        for name in self.__slots__:
            setattr(new, name, getattr(self, name))
        return new


class Window:
    """One diagnostics period: its start, the counters at its start and the compute times
    (count, sum, max: nothing grows per message)."""

    def __init__(self, counters, now):
        self.counters = counters
        self.restart(now)

    def restart(self, now):
        self.start = now
        self.base = self.counters.copy()
        self.n_times, self.sum_time, self.max_time = 0, 0.0, 0.0

    def add_time(self, seconds):
        self.n_times += 1
        self.sum_time += seconds
        if seconds > self.max_time:
            self.max_time = seconds

    def count(self, name):
        """How much counter `name` grew in this window."""
        return getattr(self.counters, name) - getattr(self.base, name)


def report(core, window, now):
    """(level, message, [(key, value-string)]) of a Compensator for `window` ending at `now`."""
    dt = max(now - window.start, 1e-9)
    n_times = window.n_times
    accepted, rejected = window.count('accepted'), window.count('rejected')
    clamped, desired_rejected = window.count('clamp_count'), window.count('desired_rejected')
    m = core.model
    s = core.settings
    c = core.count
    wd = core.watchdog
    msgs, level = [], OK
    report_, repaired = core.inertia_report, core.inertia_repaired
    if m is None:
        level, msgs = ERROR, [f'no robot model (loading {core.loading})' if core.loading else
                              'no robot model (waiting for robot_description)']
    else:
        if wd.last_valid_time is None:
            level = WARN
            msgs.append('waiting for joint_states')
        elif wd.stale:
            level = WARN
            msgs.append(f"joint_states stale: {s.stale_action}")
        elif s.mode != 'gravity' and not core.desired_is_fresh(now):
            level = WARN
            msgs.append(f"mode {s.mode}: " + ('no desired state yet' if core.desired_time is None else
                                                'desired state stale') + ': gravity fallback')
        if core.description_error:
            level = max(level, WARN)
            msgs.append('last robot description rejected, previous model kept')
        if report_:
            level = max(level, WARN)
            msgs.append(f'{len(report_)} link(s) with inconsistent inertia'
                        + (f' ({repaired} repaired)' if repaired else ''))
        if rejected:
            level = max(level, WARN)
            msgs.append(f'{rejected} joint_states rejected')
        if clamped:
            level = max(level, WARN)
            msgs.append(f'{clamped} commands clamped')
        if core.loading:
            msgs.append(f'loading {core.loading}')
        if not s.enabled:
            msgs.append('disabled' if core.silent else 'disabling (ramping down)')
        if desired_rejected:
            level = max(level, WARN)
            msgs.append(f'{desired_rejected} desired states rejected')
        if not msgs:
            msgs.append('compensating' if s.mode == 'gravity' else s.mode)
    values = [
        ('model_loaded', str(m is not None)),
        ('model_name', m.name if m is not None else ''),
        ('model_source', core.model_info),
        ('model_state', f'loading {core.loading}' if core.loading else ('ready' if m is not None else 'none')),
        ('description_update', s.description_update),
        ('joint_count', str(m.n if m is not None else 0)),
        ('joints', ','.join(core.layout or [])),
        ('locked_joints', ','.join(m.locked_joint_names) if m is not None else ''),
        ('enabled', str(s.enabled)),
        ('ramp_level', f'{core.ramp.level:.3f}'),
        ('mode', s.mode),
        ('control_law', core.law or ''),
        ('desired_age_ms', f'{1e3 * (now - core.desired_time):.1f}' if core.desired_time is not None else 'inf'),
        ('desired_received_total', str(c.desired_received)),
        ('desired_accepted_total', str(c.desired_accepted)),
        ('desired_rejected_total', str(c.desired_rejected)),
        ('desired_fallback_events', str(c.fallback_events)),
        ('trajectories_filled_total', str(c.trajectories_filled)),
        ('trajectories_rejected_total', str(c.trajectories_rejected)),
        ('input_rate_hz', f'{accepted / dt:.1f}'),
        ('executor', core.executor),
        ('compute_time_mean_ms', f'{1e3 * window.sum_time / n_times:.4f}' if n_times else 'nan'),
        ('compute_time_max_ms', f'{1e3 * window.max_time:.4f}' if n_times else 'nan'),
        ('received_total', str(c.received)),
        ('accepted_total', str(c.accepted)),
        ('rejected_total', str(c.rejected)),
        ('stale', str(wd.waiting)),
        ('stale_action', s.stale_action),
        ('stale_events', str(wd.stale_events)),
        ('clamp_count', str(c.clamp_count)),
        ('velocity_unavailable_count', str(c.velocity_unavailable)),
        ('last_error', core.last_error),
        ('description_error', core.description_error),
        ('inertia_policy', s.inertia_policy),
        ('inertia_warnings', str(len(report_))),
        ('inertia_repaired', str(repaired)),
        ('inertia_report', clip(' | '.join(r['message'] for r in report_[:INERTIA_DIAG_MESSAGES]), DIAG_TEXT_MAX)),
    ]
    # every value bounded, whatever the model or the input
    return level, clip('; '.join(msgs), DIAG_TEXT_MAX), [(k, clip(v, DIAG_TEXT_MAX)) for k, v in values]
