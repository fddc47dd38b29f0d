"""Why each wrong or ambiguous isolation answer of the contact bench happens, push by push
(docs/benchmarks.md, section 11).

    python -m bench.probes.contact_answers [--pushes 80] [--above 0]

The pushes of `python -m bench.contact --pushes N` (seed 0: the same random states, links, points,
forces and noise; its tool pushes are drawn and skipped), through the node's own parts
(ContactMonitor, ContactIsolation, the default rule only). For every push whose answer is wrong
(another link named at any time of the push) or ambiguous at its end, at least --above times the
threshold force: the link pushed and the link its body names, the answer and its reason, the
joints the pushed body adds to the named link's (its own joints when the answer is wrong): the
torque J^T F they feel against their threshold and against the tolerance at the decision, and
the named link's rank. Then the right, ambiguous and wrong counts per robot, noise level and band
of the threshold multiple (the bench's isolation table, default rule).
"""
import argparse

import numpy as np

import bench.contact as bc
from lie_dynamics.algorithms import contact_isolation as ci
from lie_dynamics.ros.features.contact_link import ContactIsolation


class _Recording(ContactIsolation):
    """The node's part, recording each decision with the tolerance it was made with."""

    def __init__(self):
        super().__init__()
        self.decided = []   # (t, Isolation, tol)

    def _checkpoint(self, t, q, r, threshold):
        before = self.isolation
        super()._checkpoint(t, q, r, threshold)
        if self.isolation is not before:   # a decision (isolate returns a new answer each time)
            a = self._all
            whole = a[1] / a[0]
            tol = ci.tolerances(threshold, self.tolerance, self._noise(whole, a[2] / a[0], t - self._start))
            self.decided.append((t, self.isolation, tol))


def _push(model, settings, q0, link, wrench_mf, rng, noise):
    iso = _Recording()
    iso.adopt(settings, model)
    named, last = set(), [None, None]

    def sample(t, sim, out, pubs):
        if bc.START <= t < bc.START + bc.PUSH_S:
            if pubs['default'].link:
                named.add(pubs['default'].link)
            last[:] = iso.isolation, sim.external_torque.copy()
    bc.run_push(model, settings, q0, link, wrench_mf, rng, noise, {'default': iso},
                bc.START + bc.PUSH_S + bc.AFTER_S, sample)
    return named, last[0], last[1], [d for d in iso.decided if bc.START <= d[0] < bc.START + bc.PUSH_S]


def run(pushes, above):
    rng = np.random.default_rng(0)
    steps = int(round((bc.START + bc.PUSH_S + bc.AFTER_S) / bc.DT))
    counts = {}
    for name, model, _ in bc.robots():
        settings = bc.settings_for(model)
        th = np.asarray(settings.collision.threshold)
        tree = ci.tree(model)
        links = bc.pushable_links(model)
        for noise in (0.0, bc.NOISE):
            for _ in range(pushes):   # the draws of bench.contact.push_isolation, in its order
                drawn = bc.draw_push(model, links, th, rng)
                if drawn is None:
                    continue
                q0, link, p, f, mult = drawn
                named, final, tau, decided = _push(model, settings, q0, link, np.concatenate([np.cross(p, f), f]),
                                                   rng, noise)
                expected = bc.body_link(model, link)
                wrong = any(x != expected for x in named)
                answer = 'wrong' if wrong else 'right' if final is not None and final.link == expected else 'ambiguous'
                band = '1-2x' if mult < 2 else '2-5x'
                key = (name, noise, band)
                counts.setdefault(key, {'right': 0, 'ambiguous': 0, 'wrong': 0})[answer] += 1
                if answer == 'right' or mult < above:
                    continue
                e = model.body_link_names.index(expected)
                shown = final
                if wrong:
                    shown = next((iso for _, iso, _ in decided if iso.link and iso.link != expected), final)
                if shown is not None and shown.link:
                    added = tree.support[e] & ~tree.support[model.body_link_names.index(shown.link)]
                else:
                    added = tree.own[e]
                tol = decided[-1][2] if decided else np.full(model.n, np.nan)
                rank = shown.wrench.rank if shown is not None and shown.wrench is not None else '-'
                why = shown.reason if shown is not None and shown.reason else ''
                joints = ', '.join(f'{model.joint_names[j]} {tau[j] / th[j]:+.4f} th ({abs(tau[j]) / tol[j]:.2f} tol)'
                                   for j in np.flatnonzero(added))
                print(f'{name}, noise {noise}, x{mult:.2f}: pushed {link} ({expected}) -> {answer}'
                      f"{' ' + ', '.join(sorted(named)) if wrong else ''}; rank {rank}; {why[:110]}"
                      f'\n    joints the pushed body adds: {joints or "none"}')
            for band in ('1-2x', '2-5x'):
                c = counts.get((name, noise, band))
                if c:
                    n = sum(c.values())
                    print(f'{name}, noise {noise}, {band}: {n} pushes, right {100 * c["right"] / n:.1f} %, ambiguous '
                          f'{100 * c["ambiguous"] / n:.1f} %, wrong {100 * c["wrong"] / n:.1f} % ({c["wrong"]})')
            for _ in range(max(4, pushes // 5)):   # bench.contact.tool_pushes' draws, skipped
                bc.random_state(model, rng)
                rng.normal(size=3)
                rng.uniform(1.0, 5.0)
                rng.normal(size=3)
                rng.normal(size=(steps, model.n))


def main(argv=None):
    ap = argparse.ArgumentParser(prog='python -m bench.probes.contact_answers', description=__doc__.split('\n')[0])
    ap.add_argument('--pushes', type=int, default=80, help='pushes per robot and noise level (as bench.contact)')
    ap.add_argument('--above', type=float, default=0.0, help='list only pushes of at least this threshold multiple')
    args = ap.parse_args(argv)
    run(args.pushes, args.above)


if __name__ == '__main__':
    main()
