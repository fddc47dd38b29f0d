"""The dynamics node's dynamics terms for other nodes, a per-sample feature (base.py).

Publishes, after the command of an accepted joint_states sample, at most `dynamics.rate`
times a second (0: every accepted state), the terms listed in `dynamics.publish`:

    ~/dynamics/gravity      sensor_msgs/JointState: effort = g(q); position, velocity = the state
                            (unavailable velocities as 0, as the laws use them); name = the joint
                            order; header.stamp = the state's
    ~/dynamics/coriolis     sensor_msgs/JointState: effort = C(q, qd) qd (RNEA at qdd = 0 without
                            gravity: cheaper than forming C), otherwise as gravity
    ~/dynamics/mass_matrix  std_msgs/Float64MultiArray: M(q), n x n row-major;
                            layout.dim[0] = ('rows: j1,j2,...', n, n*n), dim[1] = ('cols: j1,...', n, n)
    ~/dynamics/jacobian     std_msgs/Float64MultiArray: J(q) of dynamics.link in
                            dynamics.jacobian_frame, 6 x n row-major (rows linear then angular);
                            dim[0] = ('rows: vx,vy,vz,wx,wy,wz; frame: <frame>; link: <link>', 6, 6n),
                            dim[1] = ('cols: j1,...', n, n)

Every term is of the node's current model, so the payload, the gravity (parameter, scale or
topic) and the locked joints' measured values apply as for the command; robot_compensates_gravity
does not zero g(q) here (it changes what is commanded, not the robot's dynamics). A term with a
non-finite value is not published (one throttled log line). Rate limiting runs on the states'
stamps (the robot's clock: a replayed or simulated stream is thinned the same way), on the steady
clock for unstamped states; a stamp that goes back restarts it.
"""
import functools
import time

import numpy as np

from .. import interfaces
from ...algorithms import jacobian
from ..core.cdr import joint_state_template, multi_array_template
from ..core.timebase import TimeBase
from ..core.diagnostics import clip
from ..loading.models import at_rest, jacobian_at_rest, tip_link
from .base import Feature

TOPICS = {term: f'~/dynamics/{term}' for term in ('gravity', 'coriolis', 'mass_matrix', 'jacobian')}
ROWS = ('vx', 'vy', 'vz', 'wx', 'wy', 'wz')


def published_terms(settings):
    """The terms dynamics.publish turns on, in TOPICS order."""
    return tuple(t for t in TOPICS if t in settings.dynamics.publish)


def check_link(settings, model):
    """dynamics.link against `model` (None: not loaded yet, nothing to check). Raises ValueError."""
    link = settings.dynamics.link
    if not link or model is None:
        return
    try:   # the link and frame checks of the Jacobian, without generating its kernel here
        jacobian.target(model, link, settings.dynamics.jacobian_frame, None)
    except ValueError as exc:
        raise ValueError(f"dynamics.link '{clip(link, 80)}' cannot be used with robot '{model.name}': "
                         f'{exc}') from None


def matrix_template(rows_label, cols_label, rows, cols):
    """(Template, [data slot]) of a std_msgs/Float64MultiArray of rows x cols, row-major."""
    return multi_array_template(rows * cols, ((rows_label, rows, rows * cols), (cols_label, cols, cols)))


class RateGate:
    """At most `rate` passes a second by ns times (0: every call). The first time passes; a
    time that goes back (a new stream) passes and restarts the count."""

    def __init__(self, rate=0.0):
        self.period = int(round(1e9 / rate)) if rate > 0 else 0
        self.next = None

    def passes(self, t):
        if self.period == 0:
            return True
        nxt = self.next
        if nxt is not None and nxt - self.period <= t < nxt:
            return False
        # on schedule: the next slot; late by more than a period or a new stream: from t
        self.next = nxt + self.period if nxt is not None and nxt <= t < nxt + self.period else t + self.period
        return True


class DynamicsTopics(Feature):
    """dynamics.* settings -> the ~/dynamics/* topics of `node` (publishers are made when a term
    is first switched on, then kept)."""

    name = 'dynamics'
    later = coalesce = True   # its work only publishes, and only the newest state's terms are worth it

    def __init__(self, node, clock=time.monotonic):
        super().__init__()
        self._node = node
        self.time = TimeBase(clock)   # the rate gate's time: header stamps, else the steady clock
        self._pubs = {}
        self.terms = ()
        self.link = self.frame = ''
        self.rate = None
        self.gate = RateGate()
        self.published = {t: 0 for t in TOPICS}
        self.skipped = 0
        self._names = None
        self._writers = {}

    def check(self, settings, model):
        check_link(settings, model)

    def kernels(self, settings):
        # each term's Model call (on_sample), at rest
        calls = {'gravity': (at_rest, 'gravity'), 'coriolis': (at_rest, 'coriolis_term', 2),
                 'mass_matrix': (at_rest, 'mass_matrix'),
                 'jacobian': (jacobian_at_rest, settings.dynamics.link, settings.dynamics.jacobian_frame)}
        return tuple(calls[t] for t in published_terms(settings))

    def configure(self, settings, model, derived):
        terms = published_terms(settings)
        self.frame = settings.dynamics.jacobian_frame
        self.link = ''
        if model is not None and 'jacobian' in terms:
            try:
                check_link(settings, model)
                self.link = settings.dynamics.link or tip_link(model)
            except ValueError as exc:  # a new description without that link: the rest goes on
                self.events.append(('error', 'dynamics:link', f'~/dynamics/jacobian off: {exc}'))
                terms = tuple(t for t in terms if t != 'jacobian')
        for t in terms:   # published at every state: serialized through the handle (stop() releases it)
            if t not in self._pubs:
                self._pubs[t] = interfaces.serialized_publisher(self._node, TOPICS[t])
        if settings.dynamics.rate != self.rate:
            self.rate = settings.dynamics.rate
            self.gate = RateGate(self.rate)
        self.terms = terms
        self.active = bool(terms) and model is not None
        self._names = None  # labels and names are set again on the next sample

    def _label(self, names):
        """The messages' writers for this joint order (published as bytes: a cdr.Writer per term,
        the template's constant pieces joined with the stamp and the arrays), and one buffer that
        holds every term's value (`_views`: views into it, written with out=) so that one
        finiteness test covers them all."""
        self._names = names
        joined = ','.join(names)
        n = len(names)
        writers = {}
        for term in ('gravity', 'coriolis'):
            t, stamp_at, slots = joint_state_template(names)
            writers[term] = t.writer(slots, stamp_at)
        for term, (t, slots) in (
                ('mass_matrix', matrix_template(f'rows: {joined}', f'cols: {joined}', n, n)),
                ('jacobian', matrix_template(f"rows: {','.join(ROWS)}; frame: {self.frame}; link: {self.link}",
                                             f'cols: {joined}', 6, n))):
            writers[term] = t.writer(slots)
        self._writers = writers
        self._buffer = np.zeros(2 * n + n * n + 6 * n)   # a term not published keeps zeros
        g, c, m, j = np.split(self._buffer, np.cumsum([n, n, n * n]))
        self._views = {'gravity': g, 'coriolis': c, 'mass_matrix': m.reshape(n, n), 'jacobian': j.reshape(6, n)}

    def on_sample(self, s):
        for step in self.steps(s):
            step()

    def steps(self, s):
        """One step publishing every term for sample s (none when the rate gate holds it back):
        the terms together cost less than one executor task's slice, and each step more is a
        dispatch and a colder cache."""
        t = self.time.seconds(s.stamp)
        if self.time.switched:  # another time base: a new stream
            self.gate.next = None
        if not self.gate.passes(round(t * 1e9)):
            return ()
        if s.names is not self._names:
            self._label(s.names)
        return (functools.partial(self._publish, s),)

    def _publish(self, s):
        """Compute every term at sample s into its view of the buffer and publish each; a term
        that raised or has a non-finite value is skipped (said once), the others published."""
        model, q, values = s.model, s.q, self._views
        failed = {}
        for term in self.terms:
            try:
                if term == 'gravity':
                    model.gravity(q, out=values[term])
                elif term == 'coriolis':
                    model.coriolis_term(q, s.qd, out=values[term])
                elif term == 'mass_matrix':
                    model.mass_matrix(q, out=values[term])
                else:
                    values[term][...] = model.jacobian(q, self.link, self.frame)
            except (ValueError, ArithmeticError) as exc:
                failed[term] = f'{type(exc).__name__}: {exc}'
        if not np.isfinite(self._buffer).all():   # rare: which term (the others are published)
            failed.update((t, 'non-finite values') for t in self.terms
                          if t not in failed and not np.isfinite(values[t]).all())
        for term in self.terms:
            if term in failed:
                self.skipped += 1
                self.events.append(('warn', f'dynamics:{term}', clip(
                    f'~/dynamics/{term} not published for the state at stamp {s.stamp * 1e-9:.9f} s: '
                    f'{failed[term]}', 300)))
                continue
            if term in ('gravity', 'coriolis'):
                data = self._writers[term].message((q, s.qd, values[term]), s.stamp)
            else:
                data = self._writers[term].message((values[term],))
            self._pubs[term].publish(data)
            self.published[term] += 1

    def stop(self):
        for pub in self._pubs.values():
            pub.close()

    def report(self, level, message):
        return level, message, self._values()

    def _values(self):
        if not self.active:
            return [('dynamics_topics', 'off')]
        rate = f'{1e9 / self.gate.period:g} Hz' if self.gate.period else 'every state'
        out = [('dynamics_topics', f"{', '.join(self.terms)} ({rate})")]
        if 'jacobian' in self.terms:
            out.append(('dynamics_jacobian', f'{self.link} ({self.frame})'))
        out.append(('dynamics_skipped_count', str(self.skipped)))
        return out
