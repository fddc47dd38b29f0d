"""Where and how hard: the contact link and the external wrench from the momentum observer's
residual r (observer.py), after the collision survey of Haddadin, De Luca & Albu-Schaeffer
(T-RO 2017): detection, then isolation and identification.

A single wrench F on link k gives r = J_k^T F (observer.py's sign convention), with J_k the
link's frame Jacobian (jacobian.py, eqs 13-15): column j is joint j's current screw seen from
the link, zero for every joint that does not move link k. So r is zero on every joint that does
not support k, and the support grows from the root outwards: every joint over its threshold
supports the contact link.

Isolation (`isolate`), on a settled residual (`Settling`), per-joint thresholds th and a
tolerance tol_j = TOLERANCE x th_j (above the residual's noise and model error), or, given the
residual's measured noise sigma_j (the std of the r decided on), NOISE_SIGMAS x sigma_j within
[NOISE_FLOOR, 1] x TOLERANCE x th_j (`tolerances`):
  1. over = {j : |r_j| > th_j}; none: no contact.
  2. The candidate bodies are those that every felt joint (|r_j| > tol_j) moves, one per rigid
     group: bodies behind locked joints are rigid with their parent, and the named link (the
     child link of the body's joint) stands for every link fixed to it; a body that a mimic of an
     existing joint moves is a body of its own. None (joints felt on two branches): ambiguous.
  3. A candidate explains r if some wrench on it gives r within tol_j on every joint (the part
     of r outside the range of J_k^T, nonzero only with more supporting joints than its rank;
     for a mean r over a motion, within tol_j of a mean of J_k^T w over it, to first order).
     None: two contacts, ambiguous.
  4. Of those that explain r, the least supported one (on a chain the most proximal) is named;
     several least supported ones (two branches, fingers a mimic moves alike): ambiguous. A body
     further out always explains r too when it has 6 joints or fewer (a wrench on it that leaves
     its own joints quiet), but only if its own joints stay within tol_j: for a contact there
     that is a force whose line passes (nearly) through those joints' axes.
  5. The next bodies out (one joint group beyond the named one) must have felt nothing: a joint
     of theirs over DOUBT x tol_j (but under tol_j) makes the answer ambiguous, for a contact
     there with its line near that axis gives such an r as well as one on the named link.
  6. With 6 supporting joints or more on the named link (its wrench fully seen, rank 6) the line
     of a pure force is fixed: if it passes within `radius` of a next body's skeleton and through
     that body's own joints' axes (their torques within tol_j), a push there gives r as well:
     ambiguous (`_pure_force_line`, `_line_fits`: in closed form, the line being fixed; step 7's
     search would hold the node's thread for many control periods, test_node_loads). This catches
     a push on the next body whose line passes near its axis, which step 5 cannot see below
     DOUBT x tol_j; a push on the named link itself rarely
     has its line there. With fewer joints on the named link that line is free and nearly
     always fits: the check would make every such answer ambiguous, so it is left to strict.
  7. strict: the named link only if no pure force whose line passes within `radius` of a body
     further out that explains r gives r within tol_j (`_point_forces`: the segments from the
     body's origin to its frames and next joints, no meshes); else ambiguous. With fewer than 6
     joints on the named link such a force usually exists, so strict is right far less often.
     The weak tier (`strict_below`, the node's contact.strict_below): a residual whose largest
     |r_j| / th_j is below strict_below is decided by step 7 as well. A push on a link further out
     hides from its own joint j when |F| d < tol_j, d the distance of its line from that axis:
     within d_max = tol_j / |F|, which grows as the push weakens, so the weak pushes are where a
     push near that axis is likely and naming the link before is unsafe (docs/benchmarks.md,
     section 11, measures what it costs in right answers).
  That is the limit of isolation: joint torques alone cannot tell a contact whose own joints feel
  less than DOUBT x the tolerance from one on a link before with fewer than 6 joints
  (docs/benchmarks.md measures how often); the measured noise lowers the tolerance, and with it
  that band, as far as the noise and the model allow.
An ambiguous answer names its candidate links and the reason; it never picks one.

Identification (`link_wrench`): J_k^T w = r in least squares through the SVD of J_k^T (n x 6),
w = (f, m) at the link's origin in link axes (J_k in the 'local' frame: its rows (v, w) pair
with (f, m)), the force scaled by the link's lever L (`lever`: the RMS distance of the origin from
its revolute joints' axes), so that the unknowns (L f, m) are both torques and the rank decision
does not depend on the unit of length (unscaled, J^T's singular values for force and torque
differ by about the lever, and the rank depended on the unit). Singular values below rcond x
the largest (default RCOND) are dropped: with fewer than 6 supporting joints (a link near the
base) or at a singularity only the components the joints see are solved for, the others are 0
(the minimum-norm solution in (L f, m) at the link origin), and the rank and the smallest
singular value used are reported. With full rank the scaling changes nothing. The same fit at a
chosen link is the tool wrench (all contact at that frame), Franka's O_F_ext_hat_K.
`line_of_action` is the line of a pure force with that wrench.

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
from ..spatial import hat3
from .jacobian import target

# Singular values of J^T below RCOND x the largest are not solved for (their components are 0):
# a component seen 1000 times more weakly than the best one would carry 1000 times its noise.
# (On the bundled arm and a Panda at random states within +-pi, about 3 % of the states drop one.)
RCOND = 1e-3
# Singular values below this fraction of the largest are rounding: the range of J^T is the rest.
_EXACT = 1e-10
# Isolation: a joint's torque is explained (or quiet) within TOLERANCE x its threshold (the
# residual's noise and model error must stay below it; docs/node.md: choosing the thresholds).
TOLERANCE = 0.05
# A point contact lies within RADIUS (m) of the segments from a link's origin to its frames and
# next joints (no meshes: a cylinder this thick around the kinematic skeleton).
RADIUS = 0.1
# Settling: every joint changed by at most this fraction of max(|r_j|, th_j) over one time constant.
SETTLE_TOLERANCE = 0.05
# Settling's checkpoints, every this fraction of a time constant: the observer's output is filtered
# over one, so its verdict needs no more, and each checkpoint costs the node's callback tens of us
# (bench.contact's cost table: at a quarter, the flag-up callback read 1.15-1.26x the peer's).
SETTLE_STEP = 0.5
# With the residual's measured noise (std of r as given, per joint): tol_j = NOISE_SIGMAS x noise_j,
# within [NOISE_FLOOR x, 1 x] tolerance x th_j (the floor: model and integration error, which no
# average removes; the ceiling: the fixed tolerance). At 6 sigma a quiet joint reads as felt about
# once in 5e8 samples of Gaussian noise.
NOISE_SIGMAS = 6.0
NOISE_FLOOR = 0.2
# A joint further out than the named link that felt more than DOUBT x tol_j, but not tol_j, may
# carry a contact whose line passes near its axis: ambiguous rather than a guess (2 sigma of
# noise at DOUBT x NOISE_SIGMAS: a quiet joint lands there in 5 % of decisions; the node decides
# an ambiguous answer anew as its mean grows and the noise falls).
DOUBT = 1.0 / 3.0
# The weak tier's bound, the default of isolate and of the node's contact.strict_below: no wrong
# link in docs/benchmarks.md, section 11 (0 turns the tier off: right more often below 2x threshold,
# sometimes wrong). A strict decision costs a few ms (bench.probes.isolation_decision).
STRICT_BELOW = 2.0


class WrenchEstimate(NamedTuple):
    wrench: np.ndarray   # (fx, fy, fz, mx, my, mz), N and N m, at the link origin in link axes
    rank: int            # components solved for (singular values >= rcond x the largest)
    sigma_min: float     # the smallest singular value used (of J^T D, D the force's scaling by `lever`; 0.0
    #                      when rank is 0)
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


def lever(jacobian_local):
    """The length L (m) that makes force and torque comparable for this Jacobian: the RMS distance
    of the frame's origin from the axes of its revolute joints (|v_j| / |w_j| of their columns),
    1.0 when no such axis lies off the origin. It scales with the unit of length, so the rank
    decision of `solve_wrench` does not depend on it."""
    J = np.asarray(jacobian_local, dtype=float)
    sq = J * J
    w2, v2 = sq[3:].sum(axis=0), sq[:3].sum(axis=0)
    rev = w2 > _EXACT * _EXACT * max(float(w2.max(initial=0.0)), 1.0)
    L2 = float(np.mean(v2[rev] / w2[rev])) if rev.any() else 0.0
    return math.sqrt(L2) if L2 > 0 else 1.0


def solve_wrench(jacobian_local, r, rcond=RCOND):
    """WrenchEstimate of J^T w = r for a 6 x n 'local' Jacobian (rows v, w): least squares through
    the SVD of J^T with the force scaled by the frame's lever L (`lever`: the unknowns (L f, m),
    both in N m, so that rcond compares like with like whatever the unit of length), singular
    values below rcond x the largest dropped (module docstring)."""
    J = np.asarray(jacobian_local, dtype=float)
    rcond = _rcond(rcond)
    r = np.asarray(r, dtype=float)
    L = lever(J)
    D = np.ones(6)
    D[:3] = 1.0 / L                                         # w = D w', w' = (L f, m)
    A = J.T * D                                             # J^T D: r = A w'
    U, s, Vt = np.linalg.svd(A, full_matrices=False)        # A = U diag(s) Vt, U (n, 6)
    keep = s >= rcond * s[0] if s.size and s[0] > 0 else np.zeros(s.shape, dtype=bool)
    k = int(keep.sum())
    P = (Vt[:k].T * D[:, None]) @ (U[:, :k] / s[:k]).T      # w = P r
    w = P @ r
    Ur = U[:, s > _EXACT * s[0]] if s.size else U[:, :0]   # the range of J^T, to rounding
    V = np.linalg.svd(A)[2] if J.shape[1] < 6 else Vt      # all six directions when J^T has fewer rows
    # the wrench directions whose components are 0: orthogonal to D x the solved directions of w'
    unseen = np.linalg.qr(V[k:].T / D[:, None])[0] if k < 6 else np.zeros((6, 0))
    return WrenchEstimate(w, k, float(s[k - 1]) if k else 0.0, r - J.T @ w, r - Ur @ (Ur.T @ r), unseen, P)


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


def tolerances(threshold, tolerance=TOLERANCE, noise=None):
    """(n,) tol_j of isolation: tolerance x th_j, or with the residual's measured noise (std per
    joint of the r that is decided on) NOISE_SIGMAS x noise_j kept within [NOISE_FLOOR, 1] x that."""
    th = np.asarray(threshold, dtype=float)
    tol = tolerance * th
    if noise is None:
        return tol
    sig = np.asarray(noise, dtype=float)
    if sig.shape != th.shape or not np.all(np.isfinite(sig)) or np.any(sig < 0):
        raise ValueError(f'noise must be {th.size} finite values >= 0 (one per controlled joint), got {noise!r}')
    return np.clip(NOISE_SIGMAS * sig, NOISE_FLOOR * tol, tol)


def isolate(model, q, r, threshold, tolerance=TOLERANCE, radius=RADIUS, rcond=RCOND, strict=False, noise=None,
            q_from=None, strict_below=STRICT_BELOW):
    """Isolation of the contact link from a settled residual r (n,) at the state q with the
    per-joint thresholds `threshold` (one value or n): the rule of the module docstring, with
    consistency within tol_j (`tolerances`: tolerance x threshold_j, or from `noise`, the measured
    std of r per joint) on each joint and point contacts within `radius` (m) of a link's skeleton.
    `q_from`: when r is a mean over states from q_from to q (the arm yields to a push while the
    mean is taken), step 3 takes r as J_k(q)^T w - c (J_k(q) - J_k(q_from))^T w for some c in
    [0, 1] (to first order in the motion; w the fitted wrench): no single J_k^T gives such a mean.
    `strict_below`: a residual whose largest |r_j| / threshold_j is below this is decided by the
    strict rule (step 7) even without `strict` (default STRICT_BELOW; 0: never; module docstring,
    the weak tier).
    Returns an Isolation; the wrench of an isolated link comes with it."""
    n = model.n
    r = _vector('r', r, n)
    if q_from is not None:
        q_from = _vector('q_from', q_from, n)
    th = broadcast_joints(threshold, n)
    if th is None or not np.all(np.isfinite(th)) or np.any(th <= 0):
        raise ValueError(f'threshold must be one or {n} finite positive values, got {threshold!r}')
    if not (math.isfinite(tolerance) and 0 < tolerance <= 1):
        raise ValueError(f'tolerance must be in (0, 1], got {tolerance!r}')
    if not (math.isfinite(radius) and radius > 0):
        raise ValueError(f'radius must be finite and > 0, got {radius!r}')
    if not (isinstance(strict_below, (int, float)) and math.isfinite(strict_below) and strict_below >= 0):
        raise ValueError(f'strict_below must be finite and >= 0, got {strict_below!r}')
    names, links = model.joint_names, model.body_link_names
    over = np.abs(r) > th
    over_names = tuple(names[j] for j in np.flatnonzero(over))
    if not over.any():
        return Isolation('none', '', (), (), '', None)
    t = tree(model)
    tol = tolerances(th, tolerance, noise)

    def ambiguous(bodies, reason):
        return Isolation('ambiguous', '', tuple(links[b] for b in bodies), over_names, reason, None)

    # step 2: the bodies that every joint felt moves, one per rigid group (locked joints)
    felt = np.abs(r) > tol
    cand = [b for b in np.flatnonzero(np.all(t.support[:, felt], axis=1))
            if model.parent[b] < 0 or t.moving[b] or not (t.support[model.parent[b]] == t.support[b]).all()]
    if not cand:
        return ambiguous((), f'joints over threshold on more than one branch ({", ".join(over_names)}): '
                             'two contacts or more')
    # step 3: some wrench on the body explains r within tol on every joint
    fits = {b: link_wrench(model, q, r, links[b], rcond) for b in cand}

    def explains(b):
        u = fits[b].unexplained
        if np.all(np.abs(u) <= tol):
            return True
        if q_from is None:
            return False
        # a mean over the motion from q_from is, to first order, J(q)^T w - c (J(q) - J(q_from))^T w
        # for some c in [0, 1]: what is left of it (ux, outside the range of J(q)^T) may be left
        Jq = model.jacobian(q, links[b], 'local')
        ux = solve_wrench(Jq, (Jq - model.jacobian(q_from, links[b], 'local')).T @ fits[b].wrench).unexplained
        lo, hi = 0.0, 1.0   # the c with |u + c ux| <= tol on every joint
        for uj, xj, tj in zip(u, ux, tol):
            if abs(xj) <= _EXACT * tj:
                if abs(uj) > tj:
                    return False
                continue
            a, b2 = sorted(((-tj - uj) / xj, (tj - uj) / xj))
            lo, hi = max(lo, a), min(hi, b2)
        return lo <= hi

    whole = [b for b in cand if explains(b)]
    if not whole:
        b = min(cand, key=lambda b: t.support[b].sum())
        j = int(np.argmax(np.abs(fits[b].unexplained) / tol))
        return ambiguous([b], f"no single wrench on link '{links[b]}' explains the external torques (joint "
                              f"'{names[j]}' off by {abs(fits[b].unexplained[j]):.3g}): two contacts?")
    # step 4: the least supported of them (the most proximal on a chain): a body further out
    # explains r only with its own joints quiet
    sub = t.support[whole]
    inner = (sub[:, None, :] <= sub[None, :, :]).all(axis=2) & (sub.sum(axis=1)[:, None] < sub.sum(axis=1)[None, :])
    least = [whole[i] for i in np.flatnonzero(~inner.any(axis=0))]
    if len(least) > 1:
        alike = len({tuple(t.support[b]) for b in least}) == 1
        return ambiguous(least, 'the joints move these links alike (a mimic coupling)' if alike else
                         'a wrench on any of these links gives these external torques')
    k = least[0]
    # step 5: the joints of the next bodies out (candidates one joint group beyond k) felt
    # nothing: no more than DOUBT x tol_j, else a contact there, its line near their axes, may fit
    # as well as one on k (candidates, not only step 3's: a body with more joints than its rank may
    # fail step 3 by the residual's noise alone). Only the next joints: each joint checked is one
    # more chance for noise to land in the band.
    beyond = t.support & ~t.support[k]   # per body, its joints that do not move k
    nxt = [c for c in cand if beyond[c].any() and not (t.support[k] & ~t.support[c]).any()
           and not (beyond[c] & ~t.own[c]).any()]
    doubt = np.zeros(n, dtype=bool)
    for c in nxt:
        doubt |= t.own[c] & (np.abs(r) > DOUBT * tol)
    if doubt.any():
        bodies = [c for c in nxt if (t.own[c] & doubt).any()]
        j = int(np.flatnonzero(doubt)[0])
        return ambiguous([k] + bodies, f"joint '{names[j]}' felt {abs(r[j]):.3g}, near its tolerance "
                                       f'{tol[j]:.3g}: a contact further out, its line near that axis, fits too')
    # step 6: k's wrench fully seen (rank 6) fixes the line of a pure force; if that line may lie
    # on a next body, within `radius` of it and through its own joints' axes (within tol_j), a
    # push there gives r as well: ambiguous (with fewer joints on k such a line is nearly always
    # free, and the node names k as before; docs/benchmarks.md, section 11)
    line = _pure_force_line(model, q, r, tol, k) if fits[k].rank == 6 and nxt else None
    near = [c for c in nxt if _line_fits(model, q, r, tol, c, radius, line)] if line is not None else []
    if near:
        return ambiguous([k] + near, f"a push on link '{links[near[0]]}' whose line passes through the axis of "
                                     'its own joint gives these external torques as well')
    # step 7 (strict, or a weak r: the weak tier): no point contact further out gives r with its own joints quiet
    strict = strict or bool(np.max(np.abs(r) / th) < strict_below)
    further = list(_point_forces(model, q, r, tol, [b for b in whole if b != k], radius)) if strict else []
    if further:
        return ambiguous([k] + further, f"a point contact on link '{links[further[0]]}' would load its own joints "
                                        'as little as measured: the contact may be there')
    return Isolation('isolated', links[k], (links[k],), over_names, '', fits[k])


def _skeleton(model, q, b, poses=None):
    """(origin (3,), ends (m, 3)) in root coordinates: body b's origin and the origins of the link
    frames fixed to it and of the bodies next out (its child joints): the segments a link spans.
    poses: model.forward_kinematics(q), when several bodies are asked."""
    T = model.forward_kinematics(q) if poses is None else poses
    ends = [T[b, :3, :3] @ pose[:3, 3] + T[b, :3, 3] for name, (c, pose) in model.link_frames.items()
            if c == b and name != model.body_link_names[b]]
    ends += [T[c, :3, 3] for c in np.flatnonzero(model.parent == b)]
    return T[b, :3, 3], np.array(ends).reshape(-1, 3)


def _segment_distance(p, o, ends):
    """Distance from p (3,) to the union of the segments o -> ends[i] (a point when ends is empty)."""
    d = ends - o
    dd = np.einsum('ij,ij->i', d, d)
    s = np.clip(np.divide(d @ (p - o), dd, out=np.zeros(len(d)), where=dd > 0), 0.0, 1.0)
    near = o + s[:, None] * d
    return float(np.sqrt(min(np.min(np.sum((near - p) ** 2, axis=1), initial=np.inf), (p - o) @ (p - o))))


def _weighted_world_jacobian(model, q, r, tol, b):
    """(V, W, rw): the 'world' Jacobian's linear and angular rows of body b's link as (n, 3) arrays
    and r, each row weighted by 1 / tol_j: a force f at p gives the weighted torques (V + W x p) f."""
    J = model.jacobian(q, model.body_link_names[b], 'world')
    return J[:3].T / tol[:, None], J[3:].T / tol[:, None], r / tol


def _force_misfit(V, W, rw, p):
    """The weighted torques' misfit of the best force at p (_weighted_world_jacobian's V, W, rw):
    (V + W x p) f - rw, f in least squares."""
    A = V + np.cross(W, p)
    return A @ np.linalg.lstsq(A, rw, rcond=None)[0] - rw


def _pure_force_line(model, q, r, tol, k):
    """(a point, the unit direction) of the line of the pure force that r implies on body k, whose
    wrench is fully seen (rank 6): (f, m) about the root origin from r = V f + W m in least squares
    (weighted by 1 / tol), then the line {p : p x f = m} (closest point f x m / |f|^2), or None
    without a force. Closed form: the node decides at run time, where a search costs too much."""
    V, W, rw = _weighted_world_jacobian(model, q, r, tol, k)
    x = np.linalg.lstsq(np.hstack([V, W]), rw, rcond=None)[0]
    f, m = x[:3], x[3:]
    ff = float(f @ f)
    if not ff > 0:
        return None
    return np.cross(f, m) / ff, f / np.sqrt(ff)


LINE_STEPS = 4   # Gauss-Newton steps of _line_fits


def _line_fits(model, q, r, tol, b, radius, line):
    """Whether the pure force on `line` (a point, a unit direction), where it passes within `radius`
    of body b's skeleton, gives r within tol on every joint as a force on b (f in least squares,
    weighted by 1 / tol, at the line's points nearest each segment of the skeleton)."""
    p0, d = line
    o, ends = _skeleton(model, q, b)
    V, W, rw = _weighted_world_jacobian(model, q, r, tol, b)

    def misfit(p):
        return _force_misfit(V, W, rw, p)
    # the line's point nearest the skeleton (the origin, then each segment o -> o + e)
    near, gap, _ = _nearest_on_lines(p0[None], d[None], o[None], np.vstack([np.zeros(3), ends - o])[None])
    if gap[0] > radius:
        return False
    p = near[0]
    # r's line was fitted to k's joints alone; a few damped Gauss-Newton steps on p (forward
    # differences) spread the misfit over b's joints too, as the strict rule's search does, within
    # the radius: at most LINE_STEPS x 4 + 1 small least-squares fits (_point_forces from this one
    # start, its steps shortened and dropped at a small gain, missed one Panda push of
    # bench.contact --pushes 80 that these full steps find: named wrong, where this says ambiguous)
    h = 1e-4 * radius
    for _ in range(LINE_STEPS):
        res = misfit(p)
        if np.all(np.abs(res) <= 1.0):
            return True
        G = np.stack([(misfit(p + h * a) - res) / h for a in np.eye(3)], axis=1)
        GG = G.T @ G
        p_new = p + np.linalg.solve(GG + (1e-9 * np.trace(GG) + 1e-12) * np.eye(3), -G.T @ res)
        if _segment_distance(p_new, o, ends) > radius:
            return False
        p = p_new
    return bool(np.all(np.abs(misfit(p)) <= 1.0))


# _point_forces: the starts are a body's origin and points along each segment of its skeleton
# (START_FRACTIONS of it), each also moved half the radius along each root axis (on a joint's
# axis a force gives that joint no torque whatever its direction, and the search would have no
# slope there: a shoulder link's skeleton lies on its joint's axis; two of the moves leave it).
# Every start is searched, at most POINT_STEPS Gauss-Newton steps, each tried at STEP_SIZES of its
# length; a search ends when a step gains less than STALL of its misfit (test_contact_isolation
# checks that it finds every fit that 3,000 sampled points per link find).
START_FRACTIONS = (0.5, 1.0)
POINT_STEPS = 12
STALL = 0.02
STEP_SIZES = np.array([1.0, 0.3, 0.1])
_OFFSETS = np.vstack([np.zeros(3), np.eye(3)])


def _nearest_on_lines(p, d, o, e):
    """For lines through p (S, 3) along unit d (S, 3) and skeletons (origins o (S, 3), segments
    o -> o + e_m, e (S, M, 3); a zero e_m stands for the origin alone): each line's point nearest
    its skeleton (S, 3), that distance (S,) and the skeleton's point nearest the line (S, 3)."""
    def off(v):   # v's component across the line
        return v - d[:, None, :] * np.einsum('sk,smk->sm', d, v)[..., None]
    u, w = off((o - p)[:, None, :]), off(e)
    ww = np.einsum('smk,smk->sm', w, w)
    t = np.clip(np.divide(-np.einsum('smk,smk->sm', u, w), ww, out=np.zeros_like(ww), where=ww > 0), 0.0, 1.0)
    x = o[:, None, :] + t[..., None] * e
    gap = np.linalg.norm(off(x - p[:, None, :]), axis=2)
    i = np.argmin(gap, axis=1)
    s = np.arange(len(p))
    x = x[s, i]
    return p + d * np.einsum('sk,sk->s', d, x - p)[:, None], gap[s, i], x


def _point_forces(model, q, r, tol, bodies, radius):
    """{body: a point of the line} for the bodies of `bodies` (a list) on which a pure force whose
    line passes within `radius` of the body's skeleton gives r within tol on every joint. The
    torques of a force f at p are A(p) f, A(p)_j = v_j + w_j x p (the 'world' Jacobian's columns),
    weighted by 1 / tol; f in least squares for each p (variable projection: the misfit's Jacobian
    in p is -P (f x w_j)_j, P the projector off A's columns, f held), p by Gauss-Newton from every
    start (START_FRACTIONS, _OFFSETS) of every body at once, each step tried at STEP_SIZES at
    once and the best kept: a few dozen small batched numpy calls a step (scipy's least_squares,
    start by start, held the node's thread for tens of ms). Each point tried is first moved to
    its line's point nearest the skeleton (a force's torques do not depend on the point taken on
    its line) and kept within the radius."""
    if not bodies:
        return []
    rw = r / tol
    poses = model.forward_kinematics(q)
    skel = [_skeleton(model, q, b, poses) for b in bodies]
    m = 1 + max(len(ends) for _, ends in skel)
    frac = np.array(START_FRACTIONS)[:, None, None]
    V, W, O, E, P, owner = [], [], [], [], [], []
    for i, (b, (o, ends)) in enumerate(zip(bodies, skel)):
        Vb, Wb, _ = _weighted_world_jacobian(model, q, r, tol, b)
        e = np.zeros((m, 3))
        e[1:1 + len(ends)] = ends - o
        pts = np.vstack([o[None], (o + frac * (ends - o)).reshape(-1, 3)])
        count = len(pts) * len(_OFFSETS)
        P.append((pts[:, None, :] + 0.5 * radius * _OFFSETS).reshape(-1, 3))
        V.append(np.broadcast_to(Vb, (count,) + Vb.shape))
        W.append(np.broadcast_to(Wb, (count,) + Wb.shape))
        O.append(np.broadcast_to(o, (count, 3)))
        E.append(np.broadcast_to(e, (count,) + e.shape))
        owner.append(np.full(count, i))
    V, W, O, E, p, owner = (np.concatenate(a) for a in (V, W, O, E, P, owner))
    k = len(STEP_SIZES)
    tiled = {1: (V, W), k: (np.tile(V, (k, 1, 1)), np.tile(W, (k, 1, 1)))}
    O1, E1 = np.tile(O, (k, 1)), np.tile(E, (k, 1, 1))
    eye = np.eye(3)

    def evaluate(p, copies=1):   # A (S, n, 3), the inverse of its Gram matrix (ridged), f (S, 3), the misfit (S, n)
        Vc, Wc = tiled[copies]
        A = Vc + Wc @ hat3(p)   # rows v_j + w_j x p: (u^T [p]x) = (u x p)^T
        G = np.swapaxes(A, 1, 2) @ A
        G += (1e-12 * np.trace(G, axis1=1, axis2=2) + 1e-300)[:, None, None] * eye
        Gi = np.linalg.inv(G)
        f = (Gi @ (rw @ A)[..., None])[..., 0]
        return A, Gi, f, rw - (A @ f[..., None])[..., 0]

    A, Gi, f, res = evaluate(p)
    cost = np.einsum('sj,sj->s', res, res)
    found = {}   # body index: a point of its line
    live = np.ones(len(p), dtype=bool)
    for step in range(POINT_STEPS + 1):
        hit = live & (np.abs(res).max(axis=1) <= 1.0)
        if hit.any():
            for s in np.flatnonzero(hit):
                found.setdefault(int(owner[s]), p[s].copy())
            live &= ~np.isin(owner, list(found))
        if step == POINT_STEPS or not live.any():
            break
        Mf = -W @ hat3(f)                                           # d(A f)/dp: rows f x w_j
        J = A @ (Gi @ (np.swapaxes(A, 1, 2) @ Mf)) - Mf             # the misfit's: -P Mf
        JJ = np.swapaxes(J, 1, 2) @ J
        JJ += (1e-6 * np.trace(JJ, axis1=1, axis2=2) + 1e-300)[:, None, None] * eye   # along f: no slope
        delta = np.linalg.solve(JJ, (res[:, None, :] @ J).transpose(0, 2, 1))[..., 0]
        # at most a radius, then the step sizes at once, each taken to the point of its line (the
        # force's present direction) nearest the skeleton, within the radius
        delta *= np.minimum(1.0, radius / np.maximum(np.sqrt(np.einsum('sk,sk->s', delta, delta)), 1e-300))[:, None]
        p1 = (p[None] - STEP_SIZES[:, None, None] * delta[None]).reshape(-1, 3)
        d = np.tile(f / np.maximum(np.sqrt(np.einsum('sk,sk->s', f, f)), 1e-300)[:, None], (k, 1))
        p1, gap, x = _nearest_on_lines(p1, d, O1, E1)
        p1 += (x - p1) * np.maximum(1.0 - radius / np.maximum(gap, 1e-300), 0.0)[:, None]
        A1, Gi1, f1, res1 = evaluate(p1, k)
        cost1 = np.einsum('sj,sj->s', res1, res1).reshape(k, -1)
        best = np.argmin(cost1, axis=0)
        i = best * len(p) + np.arange(len(p))
        cost1 = cost1[best, np.arange(len(p))]
        gain = cost - cost1
        better = live & (gain > 0)
        i = i[better]
        p[better], A[better], Gi[better], f[better], res[better], cost[better] = (
            p1[i], A1[i], Gi1[i], f1[i], res1[i], cost1[better])
        live &= gain > STALL * cost   # a search that gains less than STALL of its misfit is done
    return {b: found[i] for i, b in enumerate(bodies) if i in found}


def within(r, ref, scale, threshold, tolerance=SETTLE_TOLERANCE):
    """Is every joint of r within tolerance x max(|scale_j|, th_j) of ref (a NaN: not)? The one
    settling test: Settling's (ref an older checkpoint, scale r) and the node's drift test of a
    settled stretch (ref and scale the stretch's mean, contact_link.ContactIsolation)."""
    return bool(np.all(np.abs(r - ref) <= tolerance * np.maximum(np.abs(scale), threshold)))


class Settling:
    """Whether the residual has stopped changing (module docstring): `update(t, r, threshold)`
    returns True once every joint changed by at most tolerance x max(|r_j|, th_j) since a
    checkpoint one to 1 + SETTLE_STEP `window`s old (one observer time constant, 1 / K).
    Checkpoints are taken, and the verdict renewed, every SETTLE_STEP window (`step`); in between
    a sample costs one comparison (`checked`: the time of the last checkpoint). `reset()` forgets
    the history. The r given are kept as they are (not copied): give a new array each time, as
    the observer does."""

    def __init__(self, window, tolerance=SETTLE_TOLERANCE):
        if not (math.isfinite(window) and window > 0 and math.isfinite(tolerance) and tolerance > 0):
            raise ValueError(f'settling window and tolerance must be finite and > 0, got {window!r}, {tolerance!r}')
        self.window, self.tolerance = float(window), float(tolerance)
        self.step = SETTLE_STEP * self.window
        self.reset()

    def reset(self):
        self._history = collections.deque()
        self.checked, self._verdict = -math.inf, False

    def update(self, t, r, threshold):
        if self.checked <= t < self.checked + self.step:   # a clock that jumps back checks anew
            return self._verdict
        self.checked = t
        h = self._history
        h.append((t, r))
        while len(h) > 2 and h[1][0] <= t - self.window + 1e-9:   # keep one checkpoint a window old
            h.popleft()
        t0, r0 = h[0]
        rn = np.asarray(r, dtype=float)
        self._verdict = t - t0 >= self.window - 1e-9 and within(rn, r0, rn, threshold, self.tolerance)
        return self._verdict
