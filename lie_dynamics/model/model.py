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

The algorithms are methods of the model through `facade.Algorithms`, pickling through
`pickling.Pickled`; arguments are validated by lie_dynamics.validation (`Model.validate`).
"""
import copy

import numpy as np

from ..algorithms import kinematics
from .facade import Algorithms
from .inertia import RTOL, link_inertia, violations
from .pickling import Pickled
from .joint_names import broadcast_joints
from .inertia import inertia_scale as scale_of  # the constructor's argument has the plain name
from .link_frames import DROPPED, WORLD
from ..spatial import exp6, hat3
from .. import validation
from ..validation import vector as _vector   # check_payload's name for it


def _frozen(x):
    """A read-only float (or int) array: the generated kernels read the model's constants
    once, so an in-place edit would be silently ignored by them; now it raises."""
    a = np.array(x, dtype=float if np.asarray(x).dtype.kind != 'i' else int)
    a.flags.writeable = False
    return a




class Model(Algorithms, Pickled):
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
        self._armature = _frozen(np.zeros(self.n))
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

    @property
    def armature(self):
        """Rotor inertia reflected to each controlled joint, (n,) read-only, in q's coordinates
        (kg m^2; kg for a prismatic joint); 0 by default. Every algorithm uses M + diag(armature):
        inverse dynamics adds armature * qdd, the mass matrix, forward dynamics (both methods),
        their derivatives, the kinetic energy and the observer's momentum carry it; the Coriolis
        matrix and gravity do not change. A mimic joint has none of its own: the value of its
        master's column stands for the whole rotor inertia that column moves."""
        return self._armature

    def set_armature(self, values):
        """Set the armature: one value for every joint or one per controlled joint
        (model.joint_names order), finite and >= 0. Cheap: bumps `version`, no kernel recompiles."""
        try:
            a = broadcast_joints(values, self.n)
        except (TypeError, ValueError):
            raise ValueError(f'armature must be numbers, got {values!r}') from None
        if a is None:
            raise ValueError(f'armature must be one value or {self.n} values (one per joint of '
                             f'{self.joint_names}), got shape {np.shape(values)}')
        if not np.all(np.isfinite(a)):
            raise ValueError(f'armature must be finite, got {a.tolist()}')
        if np.any(a < 0):
            bad = [name for name, v in zip(self.joint_names, a, strict=True) if v < 0]
            raise ValueError(f'armature must be >= 0, got negative values for {bad}')
        self._armature = _frozen(a)
        self._changed()

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
        inertia scale), and the joint has no armature. Their row of M is zero, so forward
        dynamics is undefined. O(nb): a subtree sum over the parent array, so it stays cheap for
        models of thousands of bodies."""
        if not self.n:
            return []
        sub = np.abs(self.J).sum(axis=(1, 2))
        for i in range(self.nb - 1, -1, -1):  # parents come before children
            if self.parent[i] >= 0:
                sub[self.parent[i]] += sub[i]
        tol = 1e-12 * self.inertia_scale
        return [name for k, name in enumerate(self.joint_names)
                if np.all(sub[np.flatnonzero(self.E[:, k])] <= tol) and not self.armature[k] > 0]

    # ------------------------------------------------------------------ input checks
    def check_batch(self, name, x, N=None):
        """(n,) or (N, n) -> (N, n) float array; raises ValueError naming the argument
        (lie_dynamics.validation.batch)."""
        return validation.batch(name, x, self.n, self.joint_names, N)

    def check_states(self, **arrays):
        """validate, by keyword: the first sets the number of states N, the others must match
        it. Returns the (N, n) arrays in that order."""
        return self.validate(tuple(arrays), tuple(arrays.values())).arrays

    def validate(self, names, args):
        """The one validation of a call's per-state arguments (`names` name them in messages):
        a validation.States ((N, n) float arrays, whether the call is one state: its first
        argument is (n,)); the first bad argument raises ValueError naming it
        (lie_dynamics.validation.states)."""
        return validation.states(self.n, names, args, self.joint_names)

    def body_coordinates(self, q):
        """Body joint values x = E q + L q_locked + c0 for a batch q (N, n)."""
        return q @ self.E.T + self.e0

    # ------------------------------------------------------------------ kinematics
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

    def __repr__(self):
        return (f'Model({self.name!r}, n={self.n}, bodies={self.nb}, joints={self.joint_names}, '
                f'locked={self.locked_joint_names})')
