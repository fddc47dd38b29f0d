"""Where and how hard, for the dynamics node: the contact link and the external wrench from the
observer's estimate, in plain Python (no rclpy import). The math is
lie_dynamics.algorithms.contact_isolation; this module decides when to use it.

`ContactIsolation.update(t, q, r, collision)`, after each observer sample (contact.py's
ContactMonitor: the estimate r, its time t in s, the debounced flag), returns what to publish:

  * the wrench of the isolated link (link name, (fx fy fz mx my mz) at its origin in its axes)
    while the flag is up and a link is isolated: at every sample while the residual changes, and
    while it is settled at every checkpoint (half a time constant, ci.SETTLE_STEP), the wrench of
    its mean over the last MEAN_WINDOWS time constants at the current configuration (MOVE_RAD), corrected for
    the observer's lag (the effort noise averaged out; unchanged in between, so not sent again);
    one zero wrench (the last link's, '' if none was) when the flag falls;
  * the tool wrench (`contact.wrench_frame`, all contact at that link) at every sample, when set
    (of the same mean while settled);
  * the isolated link when it changes: '' while nothing is in contact, while the residual
    settles, and when the answer is ambiguous.

Isolation is decided on a settled residual only (contact_isolation.Settling, window one observer
time constant 1 / min(observer.gain)), once each time it settles, DECIDE_WINDOWS time constants
into the settled stretch, on the stretch's mean (over the motion since the stretch began:
isolate's q_from) with its measured noise (`_noise`: the scatter of the stretch's checkpoints,
or the residual's mean square with the flag down, `_free`, whichever is larger), so the
tolerances are NOISE_SIGMAS x that noise where it allows; an ambiguous answer is decided anew
while the stretch grows (its noise falls), each time it has grown REDECIDE_GROWTH times. After
the flag rises the link stays '' until then, and while the residual changes again (the push
grows or moves) the last decision holds until it settles anew. The Jacobians and the isolation
run only while the flag is up, except the tool wrench's; a fit (Jacobian and SVD) serves while it
is younger than one time constant or the joints have not moved (REFIT_RAD) since: w = inverse r. A model, gravity,
payload or observer change (contact.REINIT_KEYS) and a paused observer start it anew, as they
start the observer anew.
"""
import collections
from typing import NamedTuple, Optional

import numpy as np

from ...algorithms import contact_isolation as ci
from ..core.diagnostics import WARN, clip
from .contact import REINIT_KEYS

ZERO = np.zeros(6)
# The wrenches read the mean residual of the last MEAN_WINDOWS time constants while it is settled:
# the effort noise averaged out (the observer alone averages over about two), the rise's tail gone.
MEAN_WINDOWS = 20.0
# Isolation waits until the settled stretch spans this many time constants: the mean's noise then
# is about 0.55 of one sample's (`_noise`), and it falls as the stretch grows.
DECIDE_WINDOWS = 5.0
# An ambiguous answer is decided anew once the stretch has grown this many times since the last
# decision (and at the end of the mean's span): the mean's noise falls as the square root of its
# span, so a decision at every checkpoint would repeat nearly the same one, and a strict decision
# (contact.strict_below) costs a few ms on the node's thread (bench.probes.isolation_decision).
REDECIDE_GROWTH = 1.25
# The residual's noise with the flag down: a running mean square over FREE_WINDOWS time constants
# (a checkpoint every half), used once it has FREE_MIN checkpoints, from FREE_WAIT time constants
# after the flag falls or the observer starts (the decay of a contact's residual, the observer's
# start, are no noise).
FREE_WINDOWS, FREE_MIN, FREE_WAIT = 50.0, 8, 5.0
# The mean keeps the checkpoints whose joints lie within MOVE_RAD (rad or m) of the current ones:
# J^T F of a fixed wrench changes by about that fraction of itself.
MOVE_RAD = 2e-3
# A fit serves while the joints move less than this (rad or m) from where it was made: the
# Jacobian's change stays below about 1e-4 of the wrench (no new SVD while the arm is held).
REFIT_RAD = 1e-4


class Published(NamedTuple):
    wrench: Optional[tuple]     # (link, (6,) wrench) for ~/contact/wrench, or None
    tool: Optional[np.ndarray]  # (6,) for ~/contact/tool_wrench, or None
    link: Optional[str]         # for ~/contact/link when it changed, or None


_NOTHING = Published(None, None, None)


def check_wrench_frame(settings, model):
    """contact.wrench_frame against `model` (None: not loaded yet): ValueError with the close matches
    or the reason (contact.rcond's range is checked with the other parameters, params.py)."""
    frame = settings.contact.wrench_frame
    if frame and model is not None:
        try:
            ci.check_moving_link(model, frame)
        except ValueError as exc:
            raise ValueError(f"contact.wrench_frame '{clip(frame, 80)}' cannot be used with robot "
                             f"'{model.name}': {exc}") from None


class ContactIsolation:
    """The decisions of the module docstring. `adopt(settings, model)` on every configuration;
    `update(...)` per observer sample; `reset()` when the observer pauses."""

    def __init__(self):
        self.events = []
        self.inbox = []             # the observer's lines (ContactMonitor.events), passed on by flush()
        self._pending = None        # the collision line, held until the link is decided
        self.settings = self.model = None
        self.frame = ''
        self.rcond = ci.RCOND
        self.strict = False
        self.strict_below = ci.STRICT_BELOW
        self.tolerance, self.radius = ci.TOLERANCE, ci.RADIUS
        self.settling = None
        self.isolation = None       # the last decision (contact_isolation.Isolation) while the flag is up
        self.link = ''              # the link last published on ~/contact/link
        self.up = False             # a wrench went out since the flag rose: a zero one is owed
        self.wrench_link = ''
        self.tool = self.wrench = None   # the last WrenchEstimates (diagnostics)
        self.decisions = 0
        self.flag = False           # the collision flag of the last sample
        self._settled = False       # the residual was settled at the last sample of the flag
        self._fits = {}             # 'link' / 'tool' -> (link, time, WrenchEstimate) of the last fit
        self.residual = None        # the r of the last wrenches: the mean over a settled stretch, else the sample's
        self._mean, self._sum = collections.deque(), None   # (t, r) of the settled stretch, their sum
        self._decided = False       # the settled stretch's decision is made
        self._all = None            # [count, sum, sum of squares] of the whole stretch's checkpoints
        self._start = 0.0           # the time the settled stretch began
        self._next = 0.0            # the time of its next decision
        self._q_start = None        # the joints then (the stretch's mean spans the motion from there)
        self._gain = 1.0            # the observer's gain K (1/s, one or per joint)
        self._between, self._count = 0.0, 0   # the sum of r over the samples since the last checkpoint, their count
        self._free_ms, self._free_n, self._free_next = None, 0, None   # the flag-down noise (_free)
        self._mean_span = 0.0
        self._held = None           # (link wrench, tool wrench, mean r) of the last checkpoint

    def adopt(self, settings, model):
        if settings is self.settings and model is self.model:
            return
        old = self.settings
        reinit = model is not self.model or old is None or settings.differs(old, REINIT_KEYS)
        self.settings, self.model = settings, model
        self.rcond = settings.contact.rcond
        self.strict = settings.contact.strict_isolation
        self.strict_below = settings.contact.strict_below
        self.tolerance, self.radius = settings.contact.tolerance, settings.contact.link_radius
        self.frame = settings.contact.wrench_frame
        if self.frame and model is not None:
            try:
                check_wrench_frame(settings, model)
            except ValueError as exc:   # a new description without that link: the rest goes on
                self.events.append(('error', 'contact:frame', f'~/contact/tool_wrench off: {exc}'))
                self.frame = ''
        if model is not None:
            gain = np.atleast_1d(np.asarray(settings.observer.gain, dtype=float))
            self.settling = ci.Settling(1.0 / float(gain.min()))
            self._gain = gain
            self._mean_span = MEAN_WINDOWS * self.settling.window
        if reinit:
            self.reset()
            self._free_ms, self._free_n, self._free_next = None, 0, None

    def reset(self):
        """Forget the history and the decision (the observer starts anew); a zero wrench stays owed."""
        if self.settling is not None:
            self.settling.reset()
        self.isolation = None
        self._settled = False
        self._fits = {}
        self._free_next = None   # the noise record waits out the observer's new start

    def _fit(self, kind, t, q, link, est=None):
        """The fit (WrenchEstimate: its inverse maps r to the wrench) on `link` at q: est, or the
        last one while it is younger than one time constant (the estimate r lags the contact by as
        much) or the joints have moved less than REFIT_RAD since, else a new one."""
        last = self._fits.get(kind)
        if est is None and last is not None and last[0] == link:
            if last[1] <= t < last[1] + self.settling.window:
                return last[2]
            if np.abs(q - last[3]).max() <= REFIT_RAD:   # held still: good for another time constant
                self._fits[kind] = (link, t, last[2], last[3])
                return last[2]
        if est is None:
            est = ci.link_wrench(self.model, q, np.zeros(self.model.n), link, self.rcond)
        self._fits[kind] = (link, t, est, np.array(q, dtype=float))
        return est

    def update(self, t, q, r, collision, threshold):
        """One observer sample: Published."""
        if not collision:
            if self.flag or self._free_next is None:   # the flag fell, the observer (re)started: no noise
                self._free_next = t + FREE_WAIT * self.settling.window
            elif t >= self._free_next:
                self._free(t, r)
        if not (collision or self.up or self.frame or self.link or self._settled) and self.isolation is None:
            self.flag, self.residual = False, r   # the flag down and nothing owed: nothing to decide
            return _NOTHING
        st = self.settling
        if collision and self._settled and st.checked < t < st.checked + st.step:   # held (cost)
            self._between += r   # for the integral of r (_checkpoint): one operation a sample
            self._count += 1
            return Published(None, self._held[1], None)
        self.flag = collision
        wrench = tool = None
        settled = False
        if collision:
            settled = st.update(t, r, threshold)
            if settled and st.checked == t:
                self._checkpoint(t, q, r, threshold)
            self._settled = settled
            iso = self.isolation
            if iso is not None and iso.link:
                self.wrench_link, self.up = iso.link, True
                if settled:
                    wrench = (iso.link, self._held[0])
                else:
                    self.wrench = self._fit('link', t, q, iso.link)
                    wrench = (iso.link, self.wrench.inverse @ r)
        else:
            if self.up:
                wrench, self.up = (self.wrench_link, ZERO), False
            if self.isolation is not None or self._settled:
                self.reset()
        if self.frame:
            if settled:
                tool = self._held[1]
            else:
                self.tool = self._fit('tool', t, q, self.frame)
                tool = self.tool.inverse @ r
        self.residual = self._held[2] if settled else r
        link = self.isolation.link if self.isolation is not None else ''
        changed = None
        if link != self.link:
            self.link = changed = link
        return Published(wrench, tool, changed)

    def _checkpoint(self, t, q, r, threshold):
        """A checkpoint of a settled stretch (every half time constant: the samples in between only
        add to the integral of r, in update). The decision once the stretch
        spans DECIDE_WINDOWS time constants, on the mean of its checkpoints with that mean's noise
        (`_noise`; an ambiguous one decided anew at later checkpoints, the mean longer). The
        wrenches of the external torque's time mean over the checkpoints of the last MEAN_WINDOWS
        time constants within MOVE_RAD of the current joints (the observer's lag corrected), held
        until the next checkpoint."""
        m = self._mean
        q = np.array(q, dtype=float)
        new = not self._settled
        if not new and m:   # a drift the mean would lag starts a new stretch too
            prev = self._sum / len(m)
            new = not ci.within(r, prev, prev, threshold)
        if new:
            m.clear()
            self._sum = np.zeros_like(r)
            self._decided, self._start = False, t
            self._next = t + DECIDE_WINDOWS * self.settling.window
            self._all = [0, np.zeros_like(r), np.zeros_like(r)]
            self._q_start = q
        # the integral of r from the stretch's start, a trapezoid over every sample (the held ones summed
        # in update, equally spaced), as the observer's own integral: the lag correction needs it
        if m:
            area = m[-1][3] + (t - m[-1][0]) / (self._count + 1) * (self._between + 0.5 * (r + m[-1][1]))
        else:
            area = np.zeros_like(r)
        self._between, self._count = 0.0, 0
        m.append((t, r, q, area))
        self._sum += r
        a = self._all   # the whole stretch (isolation: which joints feel r does not change as the arm yields)
        a[0] += 1
        a[1] += r
        a[2] += r * r
        # the mean is of one configuration: J^T F changes as the arm yields to the push
        while t - m[0][0] > self._mean_span or np.abs(q - m[0][2]).max() > MOVE_RAD:
            self._sum -= m.popleft()[1]
        span = t - m[0][0]
        if span > 0:   # the observer lags: mean tau_ext over [t0, t] = (integral of r + (r(t) - r(t0)) / K) / T
            mean = (area - m[0][3] + (r - m[0][1]) / self._gain) / span
        else:
            mean = self._sum / len(m)
        if not self._decided and t >= self._next - 1e-9:
            # on the plain mean of the whole stretch: its lag scales every joint alike, and a joint
            # a contact does not load stays unloaded as the arm yields; the least noisy mean
            whole = a[1] / a[0]
            iso = ci.isolate(self.model, q, whole, threshold, self.tolerance, self.radius, self.rcond, self.strict,
                             noise=self._noise(whole, a[2] / a[0], t - self._start), q_from=self._q_start,
                             strict_below=self.strict_below)
            if self.isolation is None or iso.status != self.isolation.status or iso.link != self.isolation.link:
                self._log(iso)
            self.isolation = iso
            # an ambiguous answer is decided anew while the mean grows (its noise falls), once the
            # stretch has grown REDECIDE_GROWTH times since, and at the end of the mean's span
            last = self._mean_span - self.settling.step
            self._decided = iso.status != 'ambiguous' or t - self._start >= last
            self._next = self._start + min(REDECIDE_GROWTH * (t - self._start), last)
            if iso.link:
                self._fit('link', t, q, iso.link, iso.wrench)
        link = self.isolation.link if self.isolation is not None else ''
        if link:
            self.wrench = self._fit('link', t, q, link)
        if self.frame:
            self.tool = self._fit('tool', t, q, self.frame)
        self._held = (self.wrench.inverse @ mean if link else None,
                      self.tool.inverse @ mean if self.frame else None, mean)

    def _free(self, t, r):
        """Every half time constant with the flag down: the residual's mean square per joint,
        a running mean over the last FREE_WINDOWS time constants (noise and free-motion model
        error, what a quiet joint reads)."""
        self._free_next = t + self.settling.step
        self._free_n += 1
        a = max(1.0 / self._free_n, ci.SETTLE_STEP / FREE_WINDOWS)
        self._free_ms = (1 - a) * self._free_ms + a * (r * r) if self._free_ms is not None else r * r

    def _noise(self, mean, square, span):
        """(n,) the std of a mean residual over `span` s per joint (mean and mean square of its
        checkpoints), from the checkpoints' scatter about it or the flag-down mean square (`_free`),
        whichever is larger: the observer's output is a first-order (Ornstein-Uhlenbeck) process of
        time constant tau, whose mean over T has variance var 2 (tau/T)^2 (T/tau - 1 + exp(-T/tau)).
        A drift counts as noise."""
        var = np.maximum(square - mean * mean, 0.0)
        if self._free_ms is not None and self._free_n >= FREE_MIN:   # a longer record: fewer chance lows
            var = np.maximum(var, self._free_ms)
        x = max(span + self.settling.step, self.settling.step) / self.settling.window
        return np.sqrt(var * min(1.0, 2.0 / (x * x) * (x - 1.0 + np.exp(-x))))

    def flush(self):
        """Pass the observer's lines on to `events`, the collision line once the link is decided
        (`_log`: one line says both), or said undecided when the flag falls or the observer
        pauses first."""
        for event in self.inbox:
            if self._pending is not None and event[1] in ('collision', 'collision:clear'):
                self._say_pending('not decided: the estimate did not settle while the flag was up')
            if event[1] == 'collision':
                self._pending = event
            else:
                self.events.append(event)
        self.inbox.clear()

    def _say_pending(self, where):
        severity, key, text = self._pending
        self._pending = None
        self.events.append((severity, key, clip(f'{text}; contact link {where}', 600)))

    def _log(self, iso):
        self.decisions += 1
        if iso.status == 'isolated':
            w = iso.wrench
            where = (f"'{iso.link}': force {np.linalg.norm(w.wrench[:3]):.3g} N, torque "
                     f'{np.linalg.norm(w.wrench[3:]):.3g} N m at its origin (rank {w.rank} of 6)')
        else:
            where = f'ambiguous: {iso.reason}'
            if iso.candidates:
                where += f" (links {', '.join(repr(c) for c in iso.candidates)})"
        if self._pending is not None:   # the collision line, with the link
            self._say_pending(where)
        elif iso.status == 'isolated':
            self.events.append(('warn', 'collision:link', clip(
                f"collision at link {where}; joints over threshold: {', '.join(iso.over)}", 400)))
        else:
            self.events.append(('warn', 'collision:link', clip(f'collision, contact link {where}', 400)))

    def where(self):
        """The contact link for the diagnostics' message: " at link 'x'", ' (contact link
        ambiguous)' or ''."""
        iso = self.isolation
        return '' if iso is None else f" at link '{iso.link}'" if iso.link else ' (contact link ambiguous)'

    def report(self, level, values):
        """(level, [(key, value)]) of the diagnostics: the link, its wrench's conditioning, the tool's."""
        iso = self.isolation
        status = ('settling' if self.flag else 'no contact') if iso is None else iso.status
        if iso is not None and iso.status == 'ambiguous':
            level = max(level, WARN)
            status = f'ambiguous: {iso.reason}'
        out = [('contact_link', self.link), ('contact_isolation', status)]
        w = self.wrench if iso is not None and iso.link else None
        out += [('contact_wrench_rank', '' if w is None else str(w.rank)),
                ('contact_wrench_sigma_min', '' if w is None else f'{w.sigma_min:.4g}'),
                ('contact_wrench_frame', self.frame or 'off')]
        t = self.tool if self.frame else None
        out += [('contact_tool_wrench_rank', '' if t is None else str(t.rank)),
                ('contact_tool_wrench_sigma_min', '' if t is None else f'{t.sigma_min:.4g}'),
                ('contact_rcond', f'{self.rcond:g}')]
        return level, list(values) + out
