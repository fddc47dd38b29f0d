"""The constant robot model (screws S_i, home poses M_i, spatial inertias J_i, tree).

Like Pinocchio's Model/Data split, a `Model` holds what does not change per call; each
algorithm (rnea.py, ...) works on per-call arrays. The few things a running robot
changes — locked joint values, gravity, payloads — are cheap setters, never a rebuild.

Internally the tree has `nb` bodies, one per modelled movable joint (controlled, mimic
or locked), numbered parents-first. Body coordinates are affine in q:
    x_body = E q + L q_locked + c0
which carries mimic joints (a row with the multiplier in the master's column) and
locked joints (a row in L). Joint torques are tau = E^T tau_body: the master collects
multiplier * tau_mimic.
"""
import copy
import functools

import numpy as np

from ..codegen import runtime
from ..algorithms import aba, aba_derivatives, crba, jacobian, kinematics, lagrangian, regressor, rnea, rnea_derivatives
from .inertia import RTOL, link_inertia, violations
from .inertia import inertia_scale as scale_of  # the constructor's argument has the plain name
from .link_frames import DROPPED, WORLD
from ..spatial import exp6, hat3


def _frozen(x):
    """A read-only float (or int) array: the generated kernels read the model's constants
    once, so an in-place edit would be silently ignored by them; now it raises."""
    a = np.array(x, dtype=float if np.asarray(x).dtype.kind != 'i' else int)
    a.flags.writeable = False
    return a




_PER_LINK = ('_places', '_link_inertias', 'link_frames')   # link -> tuple of values and small arrays


def _pack(table):
    """(keys, columns) of a dict of equal-length tuples; a column of arrays of one shape and
    dtype is stacked into one array, with whether they were all read-only (pickles and copies
    of arrays come back writeable)."""
    columns = []
    for col in zip(*table.values()):
        if all(isinstance(a, np.ndarray) for a in col) and len({(a.shape, a.dtype) for a in col}) == 1:
            columns.append((np.stack(col), not any(a.flags.writeable for a in col)))
        else:
            columns.append((list(col), None))
    return list(table), columns


def _unpack(packed):
    keys, columns = packed
    for values, read_only in columns:
        if read_only:
            values.flags.writeable = False
    return dict(zip(keys, zip(*[list(values) for values, _ in columns])))


def _vector(name, x, n):
    a = np.asarray(x, dtype=float)
    if a.shape != (n,):
        raise ValueError(f'{name} must have shape ({n},), got {a.shape}')
    if not np.all(np.isfinite(a)):
        raise ValueError(f'{name} contains non-finite values')
    return a


def _jointless(states, *shapes):
    """A robot without movable joints (a URDF that only welds links together) is a valid model:
    its calls check their state arguments and return empty results of the usual shapes."""
    def wrap(method):
        @functools.wraps(method)
        def call(self, *args, **kwargs):
            if self.n:
                return method(self, *args, **kwargs)
            given = dict(zip(states, args))
            given.update((k, kwargs[k]) for k in states if k in kwargs)
            first = self.check_states(**given)[0]
            lead = () if np.ndim(given[states[0]]) == 1 else (first.shape[0],)
            out = tuple(np.zeros(lead + sh) for sh in shapes)
            return out if len(out) > 1 else out[0]
        return call
    return wrap


class Model:
    """Fixed-base kinematic tree for the Lie-group dynamics algorithms."""

    def __init__(self, *, name, joint_names, joint_types, locked_joint_names, lockable_joint_names,
                 mimic_joints, body_joint_names, parent, M, S, E, L, c0, link_frames, link_inertias,
                 effort_limits, velocity_limits, position_lower, position_upper, damping, friction,
                 folded_bodies=(), gravity=(0.0, 0.0, -9.81), inertia_scale=None, body_link_names=None,
                 inertia_report=()):
        """Built by urdf.load_urdf. link_frames: link -> (kind, index, T) with kind 'kept' (index:
        body, WORLD the world), 'folded' (index into folded_bodies) or 'dropped'; T the link's pose in
        that frame. link_inertias: link -> (mass, CoM, inertia about the CoM) in the link frame.
        folded_bodies: locked bodies folded into a parent's inertia (parents first), dicts with
        parent ('kept' | 'folded', index), M, S, column (locked joint), multiplier, offset.
        body_link_names: the child link of each body's joint. inertia_report: the load's per-link
        findings (urdf.py), see physical_consistency."""
        self.name = name
        self.joint_names = list(joint_names)
        self.joint_types = list(joint_types)
        self.n = len(self.joint_names)
        self.locked_joint_names = list(locked_joint_names)
        self.lockable_joint_names = list(lockable_joint_names)
        self.mimic_joints = dict(mimic_joints)
        self.body_joint_names = list(body_joint_names)
        self.body_link_names = list(body_link_names or body_joint_names)
        self.parent = _frozen(np.asarray(parent, dtype=int))
        self.nb = len(self.parent)
        self.M = _frozen(M).reshape(self.nb, 4, 4)
        self.S = _frozen(S).reshape(self.nb, 6)
        self.E = _frozen(E).reshape(self.nb, self.n)
        self.L = _frozen(L).reshape(self.nb, len(self.locked_joint_names))
        self.c0 = _frozen(c0).reshape(self.nb)
        self.effort_limits = _frozen(effort_limits)
        self.velocity_limits = _frozen(velocity_limits)
        self.position_lower = _frozen(position_lower)
        self.position_upper = _frozen(position_upper)
        self.damping = _frozen(damping)
        self.friction = _frozen(friction)
        self._places = dict(link_frames)
        self._link_inertias = dict(link_inertias)
        self._folded = [dict(f) for f in folded_bodies]
        self.folded_joint_names = [f['joint'] for f in self._folded]
        # links on kept bodies never move in their body's frame: their inertia is summed once
        J = np.zeros((self.nb, 6, 6))
        for link, (kind, b, T) in self._places.items():
            if kind == 'kept' and b >= 0 and link in self._link_inertias:
                J[b] += link_inertia(T, self._link_inertias[link])
        self._J_static = J
        self.inertia_scale = float(inertia_scale) if inertia_scale else scale_of(J)
        self._inertia_report = [dict(e) for e in inertia_report]
        self.version = 0  # bumped by every setter: caches of derived values follow it
        self._J_override = None  # with_body_inertias: J as given, whatever the locked values
        self._payloads = {}  # link -> (mass, CoM, inertia about the CoM) in the link frame
        self._locked_values = np.zeros(len(self.locked_joint_names))
        self._locked_index = {name: k for k, name in enumerate(self.locked_joint_names)}
        self.gravity_vector = gravity
        self._precompute()
        self._update_offsets()

    # ------------------------------------------------------------------ structure
    def _precompute(self):
        nb = self.nb
        # ancestor-or-self matrix: anc[i, j] = 1 when body j lies on the path root -> i
        anc = np.eye(nb)
        for i in range(nb):
            if self.parent[i] >= 0:
                anc[i] += anc[self.parent[i]]
        self.ancestors = _frozen(anc)
        self.depth = _frozen(anc.sum(axis=1).astype(int))
        # Pointer jumping: world poses in ceil(log2(depth)) batched products instead of nb.
        jump = self.parent.copy()
        jumps = []
        while np.any(jump >= 0):
            idx = np.flatnonzero(jump >= 0)
            jumps.append((idx, jump[idx].copy()))
            jump[idx] = jump[jump[idx]]
            jump[idx[jump[idx] < 0]] = -1  # already reached the root
        # f_i(x) = M_i exp([S_i] x) = M_i + sin x B1 + (1 - cos x) B2 + x B3 + (x - sin x) B4
        # (paper eqs 10-12, unit rotation axis or pure translation). Written this way, a
        # revolute joint has B3 = B4 = 0, so large angles lose no digits.
        w, v = self.S[:, :3], self.S[:, 3:]
        K = hat3(w)
        K2 = K @ K
        C = np.zeros((nb, 4, 4, 4))
        C[:, 0, :3, :3] = K
        C[:, 1, :3, :3] = K2
        C[:, 1, :3, 3] = np.einsum('bij,bj->bi', K, v)
        C[:, 2, :3, 3] = v
        C[:, 3, :3, 3] = np.einsum('bij,bj->bi', K2, v)
        self.pointer_jumps = tuple(jumps)  # (bodies, their 2^k-th ancestors) per doubling step
        # f_i(x) = M_i @ (I + sin x B1 + (1 - cos x) B2 + x B3 + (x - sin x) B4) as (nb, 4, 16)
        self.transform_coefficients = _frozen(np.einsum('bij,bkjl->bkil', self.M, C).reshape(nb, 4, 16))

    # ------------------------------------------------------------------ settable state
    @property
    def gravity_vector(self):
        """Gravity in the URDF root frame (m/s^2); enters as base acceleration (0, -g)."""
        return self._g.copy()

    @gravity_vector.setter
    def gravity_vector(self, g):
        self._g = _vector('gravity', g, 3)
        # base acceleration Vd_0 = (0, -g): gravity enters the RNEA as an upward acceleration (eq 16)
        self.base_acceleration = _frozen(np.concatenate([np.zeros(3), -self._g]))
        self._changed()

    def set_gravity(self, g):
        self.gravity_vector = g

    def set_locked(self, values):
        """Set locked joint values from {name: value}. Cheap; no rebuild.

        Names of lockable joints the reduction dropped (they cannot influence the
        controlled torques) are accepted and ignored.
        """
        changed = False
        for name, value in dict(values).items():
            if name in self._locked_index:
                v = float(value)
                if not np.isfinite(v):
                    raise ValueError(f"locked joint '{name}': non-finite value {value}")
                self._locked_values[self._locked_index[name]] = v
                changed = True
            elif name in self.lockable_joint_names:
                continue
            elif name in self.joint_names:
                raise ValueError(f"joint '{name}' is controlled, not locked")
            elif name in self.mimic_joints:
                raise ValueError(f"joint '{name}' is a mimic joint: set its master "
                                 f"'{self.mimic_joints[name][0]}' instead")
            else:
                raise ValueError(f"unknown joint '{name}'")
        if changed:
            self._update_offsets()

    @property
    def locked_values(self):
        return dict(zip(self.locked_joint_names, self._locked_values.tolist()))

    def _update_offsets(self):
        """Locked values changed: body offsets, folded-body poses, link frames, inertias."""
        self.e0 = _frozen(self.L @ self._locked_values + self.c0)
        self._changed()
        folded = []  # (kept body, pose in its frame) per folded body
        for f in self._folded:
            kind, p = f['parent']
            b, X = (p, np.eye(4)) if kind == 'kept' else folded[p]
            x = f['multiplier'] * self._locked_values[f['column']] + f['offset']
            folded.append((b, X @ f['M'] @ exp6(f['S'] * x)))
        frames = {}
        for link, (kind, b, T) in self._places.items():
            if kind == 'folded':
                fb, X = folded[b]
                frames[link] = (fb, _frozen(X @ T))
            else:
                frames[link] = (b if kind == 'kept' else DROPPED, _frozen(T))
        self.link_frames = frames
        if self._J_override is not None:
            self.J_links = self._J_override
        elif self._folded or not hasattr(self, 'J_links'):
            J = self._J_static.copy()
            for link, (kind, _, _) in self._places.items():
                if kind == 'folded' and link in self._link_inertias:
                    b, T = frames[link]
                    J[b] += link_inertia(T, self._link_inertias[link])
            self.J_links = _frozen(J)  # links as written in the URDF (folded ones included), no payloads
        self._update_inertia()

    def set_payload(self, link, mass, com, inertia=None):
        """Attach a rigid payload to `link` (replaces any previous one on that link).

        com: CoM in the link frame (m). inertia: about the CoM in the link frame, a 3x3
        matrix or (ixx, ixy, ixz, iyy, iyz, izz); None = point mass. Checked by `check_payload`.
        """
        m, c, I = self.check_payload(link, mass, com, inertia)
        self._payloads[link] = (m, c, I)
        self._update_inertia()

    def check_payload(self, link, mass, com, inertia=None):
        """The one payload check (set_payload's, and a caller's that validates first): (mass, CoM (3,),
        symmetric inertia about the CoM (3, 3)) of a payload `set_payload` would accept, or
        ValueError naming the problem. The link must move a controlled joint (a payload fixed to
        the world or to a dropped body changes no torque: taking one would hide a wrong link name);
        the inertia passes the one consistency rule (inertia.violations) at the model's own scale.
        Changes nothing."""
        place = self.link_frames.get(link)
        if place is None:
            raise ValueError(f"unknown link '{link}' for payload: not a link of robot '{self.name}'")
        if place[0] < 0:
            raise ValueError(f"payload link '{link}' is not a link that moves a controlled joint (fixed to the "
                             'world or to a dropped body: a payload there changes no torque)')
        m = float(mass)
        if not np.isfinite(m) or m < 0:
            raise ValueError(f'payload mass must be finite and >= 0, got {mass}')
        c = _vector('payload com', com, 3)
        if inertia is None:
            I = np.zeros((3, 3))
        else:
            I = np.asarray(inertia, dtype=float)
            if I.shape == (6,):
                xx, xy, xz, yy, yz, zz = I
                I = np.array([[xx, xy, xz], [xy, yy, yz], [xz, yz, zz]])
            if I.shape != (3, 3) or not np.all(np.isfinite(I)):
                raise ValueError('payload inertia must be a finite 3x3 matrix or 6 values '
                                 '(ixx, ixy, ixz, iyy, iyz, izz)')
            bad = violations(m, I, RTOL * self.inertia_scale)
            if bad:
                raise ValueError('payload inertia is not physically valid: '
                                 + '; '.join(f'{rule}: {detail}' for rule, detail in bad))
        return m, c, 0.5 * (I + I.T)

    def clear_payload(self, link=None):
        """Remove the payload of `link`, or all payloads."""
        if link is None:
            self._payloads.clear()
        else:
            self._payloads.pop(link, None)
        self._update_inertia()

    def _changed(self):
        self.version = getattr(self, 'version', -1) + 1

    def _update_inertia(self):
        J = self.J_links.copy()
        for link, mic in self._payloads.items():
            b, T = self.link_frames[link]
            if b >= 0:  # payloads on the world or on dropped bodies change no controlled torque
                J[b] += link_inertia(T, mic)
        self.J = _frozen(J)
        self._changed()

    def with_body_inertias(self, J):
        """A copy whose bodies carry the spatial inertias J (nb, 6, 6) as written (payloads and
        folded links included in J: the copy has neither)."""
        new = copy.deepcopy(self)  # no kernel is copied: they live in codegen.runtime, shared by structure
        new._payloads = {}
        new._J_override = _frozen(np.asarray(J, dtype=float).reshape(self.nb, 6, 6))
        new._update_offsets()
        return new

    def physical_consistency(self):
        """Per-link report: the load's inertia check (inertia policy of load_urdf) and the
        controlled joints that move no mass (`massless_joints`), as dicts with link, rule, message
        and repaired; empty when every modelled link is consistent."""
        out = [dict(e) for e in self._inertia_report]
        for name in self.massless_joints():
            b = int(np.flatnonzero(np.asarray(self.body_joint_names) == name)[0])
            link = self.body_link_names[b]
            out.append(dict(link=link, rule='massless moving body', repaired=False,
                            message=f"link '{link}': massless moving body: joint '{name}' moves no mass or "
                                    'inertia (its row of the mass matrix is zero, forward dynamics is undefined)'))
        return out

    def massless_joints(self):
        """Controlled joints that move no mass and no inertia at all: every body the joint drives
        carries, with its whole subtree, a zero spatial inertia (up to 1e-12 of the model's
        inertia scale). Their row of M is zero, so forward dynamics is undefined. O(nb): a
        subtree sum over the parent array, so it stays cheap for models of thousands of bodies."""
        if not self.n:
            return []
        sub = np.abs(self.J).sum(axis=(1, 2))
        for i in range(self.nb - 1, -1, -1):  # parents come before children
            if self.parent[i] >= 0:
                sub[self.parent[i]] += sub[i]
        tol = 1e-12 * self.inertia_scale
        return [name for k, name in enumerate(self.joint_names)
                if np.all(sub[np.flatnonzero(self.E[:, k])] <= tol)]

    # ------------------------------------------------------------------ input checks
    def check_batch(self, name, x, N=None):
        """(n,) or (N, n) -> (N, n) float array; raises ValueError naming the argument."""
        a = np.asarray(x, dtype=float)
        if a.ndim == 1 and a.shape[0] == self.n:
            a = a[None]
        elif not (a.ndim == 2 and a.shape[1] == self.n):
            raise ValueError(f'{name} must have shape ({self.n},) or (N, {self.n}) for joints '
                             f'{self.joint_names}, got {np.shape(x)}')
        if N is not None and a.shape[0] != N:
            raise ValueError(f'{name} has {a.shape[0]} states, expected {N}')
        if not np.all(np.isfinite(a)):
            raise ValueError(f'{name} contains non-finite values')
        return a

    def check_states(self, **arrays):
        """check_batch for the state arguments of one call, in keyword order: the first sets the
        number of states N, the others must match it. Returns the (N, n) arrays in that order."""
        return self.validate(tuple(arrays), tuple(arrays.values()))[0]

    def validate(self, names, args):
        """The one validation of a call's per-state arguments (`names` name them in messages):
        ((N, n) float arrays, whether the call is one state: its first argument is (n,)).
        The common case is one check: arrays of one shape, (n,) or (N, n), with a finite sum
        (float64 ones are not copied). Anything else is checked argument by argument
        (check_batch: the first sets N), and the first bad one raises ValueError naming it."""
        try:
            arrs = [np.asarray(x, dtype=float) for x in args]
        except (ValueError, TypeError):
            arrs = None
        if arrs is not None:
            shape = arrs[0].shape
            if len(shape) in (1, 2) and shape[-1] == self.n and all(x.shape == shape for x in arrs):
                with np.errstate(over='ignore', invalid='ignore'):   # overflow only means: check exactly
                    s = sum(float(x.sum()) for x in arrs)
                if s - s == 0.0:
                    return ([x[None] for x in arrs] if len(shape) == 1 else arrs), len(shape) == 1
        out, N = [], None
        for name, x in zip(names, args, strict=True):
            a = self.check_batch(name, x, N)
            N = a.shape[0]
            out.append(a)
        return out, np.ndim(args[0]) == 1

    def body_coordinates(self, q):
        """Body joint values x = E q + L q_locked + c0 for a batch q (N, n)."""
        return q @ self.E.T + self.e0

    # ------------------------------------------------------------------ algorithms
    @_jointless(('q', 'qd', 'qdd'), (0,))
    def inverse_dynamics(self, q, qd, qdd, wrenches=None, with_gravity=True, out=None):
        """tau = M(q) qdd + C(q, qd) qd + g(q) - J^T F_ext: the Lie-group RNEA (paper eqs 16-21).

        wrenches: optional {link: (m, f)} external wrench acting on the link, expressed in
        the link frame. with_gravity=False leaves g(q) out. Single state (n,) or batch (N, n).
        out: optional float64 array of the result's shape, written and returned (no allocation).
        """
        return rnea.inverse_dynamics(self, q, qd, qdd, wrenches, with_gravity, out)

    @_jointless(('q',), (0,))
    def gravity(self, q, out=None):
        """Gravity compensation torques g(q) (RNEA with V = 0, Vdot_0 = (0, -g)); out: as inverse_dynamics."""
        return rnea.gravity(self, q, out)

    @_jointless(('q', 'qd'), (0,))
    def coriolis_term(self, q, qd):
        """C(q, qd) qd = inverse_dynamics(q, qd, 0) without gravity."""
        return rnea.inverse_dynamics(self, q, qd, np.zeros_like(np.asarray(qd, dtype=float)), None,
                                     with_gravity=False)

    def forward_kinematics(self, q):
        """World poses (N, nb, 4, 4) or (nb, 4, 4) of every modelled body frame."""
        single = np.ndim(q) == 1
        T = kinematics.world_poses(self, self.body_coordinates(self.check_batch('q', q)))
        return T[0] if single else T

    def link_pose(self, link, q):
        """Pose of any URDF link in the root frame (fixed links included)."""
        if link not in self.link_frames:
            raise ValueError(f"unknown link '{link}'")
        b, T = self.link_frames[link]
        if b == DROPPED:
            raise ValueError(f"link '{link}' is not modelled (it cannot influence the controlled joints)")
        if b == WORLD:
            return T.copy() if np.ndim(q) == 1 else np.broadcast_to(T, (len(q), 4, 4)).copy()
        return self.forward_kinematics(q)[..., b, :, :] @ T

    def jacobian(self, q, link, frame='world_aligned', point=None):
        """6 x n Jacobian of `link`'s frame, or of `point` fixed in it (in the link frame, m): maps q̇
        (columns in q's order) to the frame's velocity. (6, n) for q (n,), (N, 6, n) for (N, n).
        Rows LINEAR THEN ANGULAR (vx vy vz wx wy wz), as Pinocchio and geometry_msgs/Twist; the
        paper's twists are (w, v). frame, as Pinocchio's getFrameJacobian: 'world_aligned'
        (LOCAL_WORLD_ALIGNED: ṗ and w in root axes), 'local' (LOCAL: the same in the frame's own
        axes) or 'world' (WORLD: the spatial twist, linear part at the root origin; `point` changes
        nothing). Paper eqs 13-15. Mimic joints add to their master's column; locked joints add
        nothing. A link that no controlled joint moves gets all zeros. Unknown link or frame, bad
        point: ValueError. Details: algorithms/jacobian.py."""
        return jacobian.jacobian(self, q, link, frame, point)

    def jacobian_dot_times_qd(self, q, qd, link, frame='world_aligned', point=None):
        """J̇q̇ for `jacobian(q, link, frame, point)`: (6,) or (N, 6), rows linear then angular. Equal
        to Pinocchio's getFrameClassicalAcceleration at q̈ = 0, so J q̈ + J̇q̇ is the classical
        acceleration: in 'world_aligned' (p̈, ẇ) in root axes (exactly J̇q̇), in 'local' the same in
        the frame's axes, in 'world' that of the body-fixed point at the root origin (the last two
        are J̇q̇ plus (w x v, 0) of the frame's twist). Details: algorithms/jacobian.py."""
        return jacobian.jacobian_dot_times_qd(self, q, qd, link, frame, point)

    def __repr__(self):
        return (f'Model({self.name!r}, n={self.n}, bodies={self.nb}, joints={self.joint_names}, '
                f'locked={self.locked_joint_names})')

    def __getstate__(self):
        """Pickling (a model built in another process) and deepcopy carry the constant data, and
        which arrays are read-only: numpy's pickles come back writeable. The per-link tables
        travel as a few stacked arrays: thousands of small arrays would take the unpickling
        process's interpreter lock for tens of ms. (The kernels and their caches live in codegen,
        keyed by the object, and are rebuilt where the copy is used.)"""
        state = dict(self.__dict__)
        state['_read_only'] = [k for k, v in state.items() if isinstance(v, np.ndarray) and not v.flags.writeable]
        for k in _PER_LINK:
            state[k] = _pack(state[k])
        return state

    def __setstate__(self, state):
        read_only = state.pop('_read_only', ())
        for k in _PER_LINK:
            state[k] = _unpack(state[k])
        self.__dict__.update(state)
        for k in read_only:
            getattr(self, k).flags.writeable = False

    # --- Lagrangian dynamics, forward dynamics, derivatives, regressor (lagrangian.py, crba.py, aba.py, ...) ---
    @_jointless(('q',), (0, 0))
    def mass_matrix(self, q, method='crba', out=None):
        """M(q), (n, n) or (N, n, n). method: 'crba' (composite rigid body, O(n^2); a generated
        kernel for small models, the fastest) or 'closed_form' (S^T G^T J G S, paper eq 39, O(n^3)).
        out: as inverse_dynamics."""
        if method == 'closed_form':
            M = lagrangian.mass_matrix(self, q)
            return runtime.deliver(M, runtime.check_out(out, M.shape))
        if method == 'crba':
            return crba.mass_matrix(self, q, out)
        raise ValueError(f"unknown mass matrix method {method!r}: use 'closed_form' or 'crba'")

    @_jointless(('q',), (0, 0, 0))
    def christoffel(self, q):
        """Christoffel symbols of the first kind Gamma[i, j, k] (paper eq 40), (n, n, n) or (N, n, n, n)."""
        return lagrangian.christoffel(self, q)

    @_jointless(('q', 'qd'), (0, 0))
    def coriolis_matrix(self, q, qd, method='christoffel'):
        """C(q, qd) from the Christoffel symbols: C qd = coriolis_term(q, qd), Mdot - 2C skew.

        method: 'christoffel' (eqs 40-42 from dM/dq, O(n^3)) or 'recursive' (the same matrix as
        1/2 dtau/dqd of the differentiated RNEA, O(n^2); a generated kernel for small models,
        several times faster)."""
        if method == 'christoffel':
            return lagrangian.coriolis_matrix(self, q, qd)
        if method == 'recursive':
            return rnea_derivatives.coriolis_matrix(self, q, qd)
        raise ValueError(f"unknown Coriolis matrix method {method!r}: use 'christoffel' or 'recursive'")

    @_jointless(('q',), (0, 0, 0))
    def mass_matrix_derivatives(self, q):
        """dM/dq: D[..., a, :, :] = dM/dq_a (Proposition 1 applied to eq 39)."""
        return lagrangian.mass_matrix_derivatives(self, q)

    @_jointless(('q',), (0,))
    def gravity_potential(self, q):
        """g(q) = dU/dq from the potential energy (paper eqs 43-45); equals gravity(q)."""
        return lagrangian.gravity(self, q)

    @_jointless(('q',), ())
    def potential_energy(self, q):
        """U(q) = -sum_i m_i g . c_i (paper eq 43)."""
        return lagrangian.potential_energy(self, q)

    @_jointless(('q', 'qd'), ())
    def kinetic_energy(self, q, qd):
        """1/2 qd^T M(q) qd."""
        return lagrangian.kinetic_energy(self, q, qd)

    @_jointless(('q', 'qd', 'tau'), (0,))
    def forward_dynamics(self, q, qd, tau, wrenches=None, method='cholesky', out=None):
        """qdd with inverse_dynamics(q, qd, qdd, wrenches) = tau; method 'cholesky' or 'aba' (O(n)).
        out: as inverse_dynamics."""
        return aba.forward_dynamics(self, q, qd, tau, wrenches, method, out)

    @_jointless(('q', 'qd', 'qdd'), (0, 0), (0, 0))
    def inverse_dynamics_derivatives(self, q, qd, qdd, wrenches=None):
        """(dtau/dq, dtau/dqd), analytic (rnea_derivatives.py)."""
        return rnea_derivatives.inverse_dynamics_derivatives(self, q, qd, qdd, wrenches)

    @_jointless(('q', 'qd', 'tau'), (0, 0), (0, 0), (0, 0))
    def forward_dynamics_derivatives(self, q, qd, tau, wrenches=None):
        """(dqdd/dq, dqdd/dqd, dqdd/dtau = M^-1) at qdd = forward_dynamics(q, qd, tau)."""
        return aba_derivatives.forward_dynamics_derivatives(self, q, qd, tau, wrenches)

    @_jointless(('q', 'qd', 'qdd'), (0, 0))
    def regressor(self, q, qd, qdd):
        """Y with inverse_dynamics(q, qd, qdd) = Y @ inertial_parameters(), (n, 10 nb) or (N, n, 10 nb)."""
        return regressor.regressor(self, q, qd, qdd)

    def inertial_parameters(self):
        """(10 nb,) parameters (m, m c, I_xx, I_xy, I_yy, I_xz, I_yz, I_zz) per body, about the body frame."""
        return regressor.inertial_parameters(self)

    def with_inertial_parameters(self, pi, check=True):
        """Copy of this model with the given inertial parameters (payloads folded in)."""
        return regressor.with_inertial_parameters(self, pi, check)

    def with_calibration(self, calibration):
        """Copy with a calibration (a CalibrationResult or a calibration.yaml path) applied:
        lie_dynamics.calibration.result.with_calibration."""
        from ..calibration.result import with_calibration
        return with_calibration(self, calibration)
