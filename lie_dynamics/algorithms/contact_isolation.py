"""Where and how hard: the contact link and the external wrench from the momentum observer's
residual r (observer.py), after the collision survey of Haddadin, De Luca & Albu-Schaeffer
(T-RO 2017): detection, then isolation and identification.

A single wrench F on link k gives r = J_k^T F (observer.py's sign convention), with J_k the
link's frame Jacobian (jacobian.py, eqs 13-15): column j is joint j's current screw seen from
the link, zero for every joint that does not move link k. So r is zero on every joint that does
not support k, and the support grows from the root outwards: every joint over its threshold
supports the contact link.

Isolation (`isolate`), on a settled residual (`Settling`) and per-joint thresholds th:
  1. over = {j : |r_j| > th_j}; none: no contact.
  2. The candidate bodies are those whose supporting joints include every joint of `over`; the
     isolated body is the least supported of them: on a chain the most proximal, the body of the
     most distal joint over its threshold (a candidate with more supporting joints is further
     out, and step 4 rules it out). No candidate (joints over threshold on two branches) or
     several least supported ones: ambiguous. Bodies behind locked joints are rigid with their
     parent: the named link (the child link of the body's joint) stands for every link fixed to
     it. A body that a mimic of an existing joint moves is a body of its own, so a master joint
     whose mimic moves another branch (two gripper fingers) is ambiguous.
  3. Every joint that does not move the isolated link must be quiet, |r_j| <= quiet th_j: a
     joint beyond the link between quiet th_j and th_j may be a contact further out that stays
     under its thresholds (a joint on another branch, a second contact): ambiguous.
  4. Some wrench on the isolated link must explain r to within th_j on every joint (the part of
     r outside the range of J_k^T, nonzero only with more supporting joints than 6, e.g. 7 on a
     7-DoF arm): otherwise two contacts, ambiguous.
  5. No wrench on the next body beyond (the one with the fewest additional supporting joints, on
     each branch) that gives what the link's joints show may load the joints that body adds
     within quiet th_j of what r shows: otherwise a contact there whose own joints stay under
     their thresholds (a push along the last joint's axis) gives the same r: ambiguous. With all
     6 components seen (rank 6 with singular values above RULE_RCOND x the largest) the wrench
     is fixed and this is checked always. With fewer (a link near the base, a singularity) the
     unseen components are free: `strict` fits them to the measured
     joints (least squares weighted by 1 / th_j), and then such a link whose next joint stays
     quiet is nearly always ambiguous (joint torques alone cannot tell it from the next link
     out); without `strict` (the default) the answer is the literal rule's, right unless the
     contact is further out with its own joints under their thresholds. That is the limit of
     isolation (docs/benchmarks.md measures both).
An ambiguous answer names its candidate links and the reason; it never picks one.

Identification (`link_wrench`): J_k^T w = r in least squares through the SVD of J_k^T (n x 6),
w = (f, m) at the link's origin in link axes (J_k in the 'local' frame: its rows (v, w) pair
with (f, m)). Singular values below rcond x the largest (default RCOND) are dropped: with fewer
than 6 supporting joints (a link near the base) or at a singularity only the components the joints see
are solved for, the others are 0 (the minimum-norm solution at the link origin), and the rank
and the smallest singular value used are reported. The same fit at a chosen link is the tool
wrench (all contact at that frame), Franka's O_F_ext_hat_K. `line_of_action` is the line of a
pure force with that wrench.

Settling: the observer is a first-order filter (rdot = K (tau_ext - r)), so while the residual
rises the proximal joints cross their thresholds first and a literal rule names a proximal link;
`Settling` says when r has stopped changing (over one time constant 1/K every joint changed by
at most `tolerance` x max(|r_j|, th_j); after a step that is about 3.6 time constants, r within
3 % of its final value).
"""
import collections
import math
from typing import NamedTuple, Optional

import numpy as np

from ..codegen import runtime
from ..model.joint_names import broadcast_joints
from .jacobian import target

# Singular values of J^T below RCOND x the largest are not solved for (their components are 0):
# a component seen 1000 times more weakly than the best one would carry 1000 times its noise.
# (On the bundled arm and a Panda at random states within +-pi, about 3 % of the states drop one.)
RCOND = 1e-3
# Step 5 of isolation trusts a component of the wrench only above this fraction of the largest
# singular value: with 1e-3 (RCOND), a pushed link's wrench fitted at the link before it near a
# singularity predicted its joint's torque far from the truth and named the wrong link.
RULE_RCOND = 1e-2
# Singular values below this fraction of the largest are rounding: the range of J^T is the rest.
_EXACT = 1e-10
# A joint that does not move the isolated link is quiet below QUIET x its threshold.
QUIET = 0.5
# Settling: every joint changed by at most this fraction of max(|r_j|, th_j) over one time constant.
SETTLE_TOLERANCE = 0.05


class WrenchEstimate(NamedTuple):
    wrench: np.ndarray   # (fx, fy, fz, mx, my, mz), N and N m, at the link origin in link axes
    rank: int            # components solved for (singular values >= rcond x the largest)
    sigma_min: float     # the smallest singular value used (0.0 when rank is 0)
    misfit: np.ndarray   # r - J^T wrench (n,): what the solved components leave
    unexplained: np.ndarray   # (n,) the part of r that no wrench on this link can give (outside
    #                           the range of J^T: nonzero only with more joints than the rank)
    unseen: np.ndarray   # (6, 6 - rank) orthonormal wrench directions not solved for (their components are 0)
    inverse: np.ndarray  # (6, n): wrench = inverse @ r (the truncated pseudo-inverse of J^T, for other r at this q)


class Isolation(NamedTuple):
    status: str          # 'none' (no joint over threshold), 'isolated' or 'ambiguous'
    link: str            # the isolated link ('' unless isolated)
    candidates: tuple    # the links in question (isolated: the link; ambiguous: those it could be)
    over: tuple          # joints over their threshold
    reason: str          # why ambiguous ('' otherwise)
    wrench: Optional[WrenchEstimate]   # of the isolated link (None otherwise)


class _Tree(NamedTuple):
    support: np.ndarray  # (nb, n) bool: joint j moves body b
    own: np.ndarray      # (nb, n) bool: the joints that move b and not its parent
    below: np.ndarray    # (nb, nb) bool: below[k, d], d is k or a descendant of k
    moving: np.ndarray   # (nb,) bool: a controlled joint (or a mimic of one) drives the body's joint


def _tree(model):
    moves = model.E != 0
    support = (model.ancestors @ moves) > 0
    parent = np.where(model.parent >= 0, model.parent, 0)
    above = np.where((model.parent >= 0)[:, None], support[parent], False)
    return _Tree(support, support & ~above, model.ancestors.T > 0, moves.any(axis=1))


def tree(model):
    """The structure isolation reads (cached for the model's lifetime)."""
    return runtime.structural(model, ('contact_tree',), lambda: _tree(model))


def supporting_joints(model, link):
    """(n,) bool: the controlled joints that move `link` (a mimic's master moves the mimic's
    links; locked joints move nothing). Unknown link: ValueError with close matches."""
    b = target(model, link, 'local', None)[0]
    return tree(model).support[b].copy() if b >= 0 else np.zeros(model.n, dtype=bool)


def check_moving_link(model, link):
    """ValueError unless `link` is a link of the model that a controlled joint moves (a wrench on
    any other link leaves r at zero: nothing to estimate)."""
    b = target(model, link, 'local', None)[0]   # unknown link: the close matches
    if b >= 0 and tree(model).support[b].any():
        return
    why = ('it is fixed to the root link' if b == -1 else
           'the model dropped it (no controlled joint can move it)' if b < 0 else
           'only locked joints lie between it and the root')
    raise ValueError(f"link '{link}' moves with no controlled joint ({why}): a wrench on it gives no "
                     'external joint torque')


def _vector(name, x, n):
    a = np.asarray(x, dtype=float)
    if a.shape != (n,) or not np.all(np.isfinite(a)):
        raise ValueError(f'{name} must be {n} finite values (one per controlled joint), got shape {a.shape}')
    return a


def _rcond(rcond):
    if not (isinstance(rcond, (int, float)) and math.isfinite(rcond) and 0 < rcond < 1):
        raise ValueError(f'rcond must be a finite number in (0, 1), got {rcond!r}')
    return float(rcond)


def solve_wrench(jacobian_local, r, rcond=RCOND):
    """WrenchEstimate of J^T w = r for a 6 x n 'local' Jacobian (rows v, w): least squares through
    the SVD, singular values below rcond x the largest dropped (module docstring)."""
    J = np.asarray(jacobian_local, dtype=float)
    rcond = _rcond(rcond)
    r = np.asarray(r, dtype=float)
    U, s, Vt = np.linalg.svd(J.T, full_matrices=False)      # J^T = U diag(s) Vt, U (n, 6)
    keep = s >= rcond * s[0] if s.size and s[0] > 0 else np.zeros(s.shape, dtype=bool)
    k = int(keep.sum())
    P = Vt[:k].T @ (U[:, :k] / s[:k]).T
    w = P @ r
    Ur = U[:, s > _EXACT * s[0]] if s.size else U[:, :0]   # the range of J^T, to rounding
    V = np.linalg.svd(J.T)[2] if J.shape[1] < 6 else Vt   # all six directions when J^T has fewer rows
    return WrenchEstimate(w, k, float(s[k - 1]) if k else 0.0, r - J.T @ w, r - Ur @ (Ur.T @ r), V[k:].T, P)


def link_wrench(model, q, r, link, rcond=RCOND):
    """The wrench on `link` (at its origin, link axes) that explains the residual r (n,) at the
    state q in least squares: solve_wrench of the link's 'local' Jacobian. A link no controlled
    joint moves gives rank 0."""
    n = model.n
    return solve_wrench(model.jacobian(_vector('q', q, n), link, 'local'), _vector('r', r, n), rcond)


def line_of_action(wrench, tol=1e-9):
    """(point, direction, pitch) of the pure force that has this wrench (f, m) at the origin:
    the point of the line closest to the origin, f x m / |f|^2, the unit direction f / |f|, and
    m . f / |f|^2 (m, 0 for a pure force: what the line does not explain). None when |f| <= tol."""
    w = np.asarray(wrench, dtype=float)
    f, m = w[:3], w[3:]
    ff = float(f @ f)
    if not ff > tol * tol:
        return None
    return np.cross(f, m) / ff, f / math.sqrt(ff), float(m @ f) / ff


def isolate(model, q, r, threshold, quiet=QUIET, rcond=RCOND, strict=False):
    """Isolation of the contact link from a settled residual r (n,) at the state q with the
    per-joint thresholds `threshold` (one value or n): the rule of the module docstring. Returns
    an Isolation; the wrench of an isolated link comes with it. strict: step 5 also for a link
    whose wrench is not fully seen (else only for rank 6)."""
    n = model.n
    r = _vector('r', r, n)
    th = broadcast_joints(threshold, n)
    if th is None or not np.all(np.isfinite(th)) or np.any(th <= 0):
        raise ValueError(f'threshold must be one or {n} finite positive values, got {threshold!r}')
    if not 0 <= quiet <= 1:
        raise ValueError(f'quiet must be in [0, 1], got {quiet!r}')
    names, links = model.joint_names, model.body_link_names
    over = np.abs(r) > th
    over_names = tuple(names[j] for j in np.flatnonzero(over))
    if not over.any():
        return Isolation('none', '', (), (), '', None)
    t = tree(model)

    def ambiguous(bodies, reason):
        return Isolation('ambiguous', '', tuple(links[b] for b in bodies), over_names, reason, None)

    cand = np.all(t.support[:, over], axis=1)
    if not cand.any():
        return ambiguous((), f'joints over threshold on more than one branch ({", ".join(over_names)}): '
                             'two contacts or more')
    # the least supported candidates: a body with more supporting joints is further out (step 4
    # rules it out by its quiet joints); among bodies with one support, those rigid with their
    # parent (locked joints) are their parent, those a mimic moves are bodies of their own
    sup = t.support[cand]
    fewer = (sup[:, None, :] <= sup[None, :, :]).all(axis=2) & (sup.sum(axis=1)[:, None] < sup.sum(axis=1)[None, :])
    least = np.zeros(model.nb, dtype=bool)
    least[np.flatnonzero(cand)[~fewer.any(axis=0)]] = True
    reps = [b for b in np.flatnonzero(least) if model.parent[b] < 0 or not least[model.parent[b]] or t.moving[b]]
    if len(reps) > 1:
        alike = all((t.support[b] == t.support[reps[0]]).all() for b in reps)
        return ambiguous(reps, 'the joints over threshold move these links alike (a mimic coupling)' if alike else
                         'the joints over threshold fit links on several branches')
    k = reps[0]
    loud = ~t.support[k] & (np.abs(r) > quiet * th)
    if loud.any():
        j = int(np.flatnonzero(loud)[0])
        beyond = bool(t.below[k][t.own[:, j]].any())
        where = 'beyond it: the contact may be further out' if beyond else 'on another branch: a second contact?'
        return ambiguous([k], f"joint '{names[j]}' does not move link '{links[k]}' but its external torque is "
                              f'{abs(r[j]) / th[j]:.0%} of its threshold ({where})')
    est = link_wrench(model, q, r, links[k], rcond)
    bad = np.abs(est.unexplained) > th
    if bad.any():
        j = int(np.flatnonzero(bad)[0])
        return ambiguous([k], f"no single wrench on link '{links[k]}' explains the external torques (joint "
                              f"'{names[j]}' off by {abs(est.unexplained[j]):.3g}): two contacts?")
    # step 5 on the components seen well enough to rule a link out (a nearly unseen one would
    # carry the lag and the noise of r, times 1 / sigma, into the prediction)
    sure = est if est.rank < 6 else link_wrench(model, q, r, links[k], max(rcond, RULE_RCOND))
    alike = _further_alike(model, t, q, r, th * quiet, k, sure) if strict or sure.rank == 6 else []
    if alike:
        return ambiguous([k] + alike, f"a wrench on link '{links[alike[0]]}' that gives what link '{links[k]}' "
                                      'shows would load its own joints as little as measured: the contact may be '
                                      'there')
    return Isolation('isolated', links[k], (links[k],), over_names, '', est)


def _further_alike(model, t, q, r, tol, k, est):
    """The next bodies beyond k (the fewest supporting joints more than k's) on which some wrench
    with k's visible components (est: at k's origin in k's axes; its unseen ones free) would give
    the joints they add what r shows, within tol (a least-squares fit of the unseen components,
    weighted by 1 / tol)."""
    more = np.flatnonzero(np.all(t.support >= t.support[k], axis=1) & (t.support.sum(axis=1) > t.support[k].sum()))
    if not more.size:
        return []
    sub = t.support[more]
    inner = (sub[:, None, :] <= sub[None, :, :]).all(axis=2) & (sub.sum(axis=1)[:, None] < sub.sum(axis=1)[None, :])
    nxt = [d for d in more[~inner.any(axis=0)] if model.parent[d] < 0 or t.moving[d]
           or not (t.support[model.parent[d]] == t.support[d]).all()]
    T = model.link_pose(model.body_link_names[k], q)
    R, p = T[:3, :3], T[:3, 3]
    X = np.zeros((6, 6))   # (f, m) at k's origin in k's axes -> at the root origin in root axes
    X[:3, :3] = X[3:, 3:] = R
    X[3:, :3] = np.cross(p[:, None], R, axis=0)   # [p] R
    out = []
    for d in nxt:
        extra = t.support[d] & ~t.support[k]
        P = model.jacobian(q, model.body_link_names[d], 'world')[:, extra].T @ X / tol[extra][:, None]
        miss = P @ est.wrench - r[extra] / tol[extra]
        if est.unseen.shape[1]:   # the unseen components chosen to match the measured joints best
            A = P @ est.unseen
            miss = miss - A @ np.linalg.lstsq(A, miss, rcond=None)[0]
        if np.all(np.abs(miss) <= 1.0):
            out.append(int(d))
    return out


class Settling:
    """Whether the residual has stopped changing (module docstring): `update(t, r, threshold)`
    returns True once, over the last `window` seconds (one observer time constant, 1 / K), every
    joint changed by at most tolerance x max(|r_j|, th_j); checked at most every quarter window
    (the verdict in between is the last one). `reset()` forgets the history. The r given are
    kept as they are (not copied): give a new array each time, as the observer does."""

    def __init__(self, window, tolerance=SETTLE_TOLERANCE):
        if not (math.isfinite(window) and window > 0 and math.isfinite(tolerance) and tolerance > 0):
            raise ValueError(f'settling window and tolerance must be finite and > 0, got {window!r}, {tolerance!r}')
        self.window, self.tolerance = float(window), float(tolerance)
        self.reset()

    def reset(self):
        self._history = collections.deque()
        self._checked, self._verdict = -math.inf, False

    def update(self, t, r, threshold):
        h = self._history
        h.append((t, r))
        while len(h) > 2 and h[1][0] <= t - self.window:   # keep one sample at least a window old
            h.popleft()
        if t - self._checked < 0.25 * self.window and t >= self._checked:
            return self._verdict   # checked a quarter window ago at most (cost per sample)
        t0, r0 = h[0]
        rn = np.asarray(r, dtype=float)
        self._checked = t
        self._verdict = bool(t - t0 >= self.window - 1e-9 and np.all(
            np.abs(rn - r0) <= self.tolerance * np.maximum(np.abs(rn), threshold)))
        return self._verdict
