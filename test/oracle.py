"""Pinocchio oracle for the tests: Pinocchio's dynamics expressed in this library's coordinates.

Coordinates
-----------
Our joint vector ``q`` (and ``qd``, ``qdd``, ``tau``) has one entry per *controlled* joint,
in the order of ``Oracle.joint_names``. Every other joint of the URDF is either

* a mimic joint: ``q_mimic = multiplier * q_master + offset``, ``qd_mimic = multiplier *
  qd_master`` (its master may itself be controlled or locked), or
* a locked joint: a movable, non-mimic joint held at a constant value (``locked`` dict,
  default 0), with zero velocity and acceleration.

Pinocchio's model is built with ``pin.buildModelFromXML(xml)`` and ``mimic=False`` (the
default in 4.1.0), so every mimic joint is an ordinary independent joint of the full model.
Its configuration differs from ours in two ways:

* joint order: depth-first from the root, but the children of a link are visited in
  alphabetical order of joint name (urdfdom keeps joints in a ``std::map``), not in file
  order;
* a continuous joint is stored as ``(cos θ, sin θ)`` (nq = 2, nv = 1).

``pin_q(q)`` builds Pinocchio's configuration (cos/sin for continuous joints, mimic joints
from their masters, locked joints at their values). The constant matrix ``E`` (nv x n) maps
our velocities to Pinocchio's: ``v = E qd`` (a 1 in the row of each controlled joint, the
multiplier in the row of each mimic joint of a controlled master, 0 for locked joints and
mimics of locked masters). The mimic map is affine, so also ``a = E qdd`` (no drift term).
By virtual work, torques project with ``E.T``: ``tau = E.T tau_pin``, ``M = E.T M_pin E``,
``C = E.T C_pin E``, ``Y = E.T Y_pin``. Pinocchio's tangent-space derivatives of a 1-DoF
continuous joint are derivatives with respect to θ, so ``dtau/dq = E.T dtau_pin/dq E``.

``Oracle.reduced(...)`` takes the same arguments but lets Pinocchio eliminate the locked
joints itself with ``pin.buildReducedModel`` (locked joints, and mimics of locked masters,
welded at their values); the same projection is then applied to the smaller model.

Dynamic parameters are 10 per Pinocchio body (joints 1..njoints-1 in Pinocchio's order),
``(m, m c_x, m c_y, m c_z, I_xx, I_xy, I_yy, I_xz, I_yz, I_zz)`` about the joint frame,
including masses of fixed links merged into the body; ``regressor() @ dynamic_parameters()``
equals ``rnea()``. Which URDF links a body holds is in ``body_links``.
"""

import xml.etree.ElementTree as ET

import numpy as np
import pinocchio as pin

__all__ = ["Oracle", "parse_joints", "tree_order", "default_controlled"]

MOVABLE = ("revolute", "continuous", "prismatic")


def parse_joints(xml):
    """Joints of a URDF in file order: list of dicts (name, type, parent, child, mimic). A mimic
    of a joint that is not a movable joint of the URDF is an independent joint (as in KDL)."""
    root = ET.fromstring(xml)
    movable = {j.get("name") for j in root.findall("joint") if j.get("type") in MOVABLE}
    out = []
    for j in root.findall("joint"):
        mimic = None
        m = j.find("mimic")
        if m is not None and m.get("joint") in movable:
            mimic = dict(joint=m.get("joint"), multiplier=float(m.get("multiplier", 1.0)),
                         offset=float(m.get("offset", 0.0)))
        out.append(dict(name=j.get("name"), type=j.get("type"),
                        parent=j.find("parent").get("link"), child=j.find("child").get("link"),
                        mimic=mimic))
    return out


def tree_order(xml):
    """Joint names depth-first from the root, children in the order they appear in the file."""
    joints = parse_joints(xml)
    links = [lk.get("name") for lk in ET.fromstring(xml).findall("link")]
    childs = {j["child"] for j in joints}
    roots = [lk for lk in links if lk not in childs]
    if len(roots) != 1:
        raise ValueError(f"URDF must have exactly one root link, found {roots}")
    by_parent = {}
    for j in joints:
        by_parent.setdefault(j["parent"], []).append(j)
    order, stack = [], list(reversed(by_parent.get(roots[0], [])))
    while stack:
        j = stack.pop()
        order.append(j["name"])
        stack.extend(reversed(by_parent.get(j["child"], [])))
    return order


def default_controlled(xml):
    """Every movable non-mimic joint, in tree_order."""
    info = {j["name"]: j for j in parse_joints(xml)}
    return [n for n in tree_order(xml) if info[n]["type"] in MOVABLE and info[n]["mimic"] is None]


def _sym(M):
    return np.triu(M) + np.triu(M, 1).T


class Oracle:
    """Pinocchio dynamics in our coordinates (see the module docstring)."""

    def __init__(self, xml, joints=None, locked=None, gravity=(0.0, 0.0, -9.81), _reduce=False):
        info = {j["name"]: j for j in parse_joints(xml)}
        self.joint_names = list(default_controlled(xml) if joints is None else joints)
        locked = dict(locked or {})
        for n in self.joint_names:
            if n not in info or info[n]["type"] not in MOVABLE:
                raise ValueError(f"{n!r} is not a movable joint of the URDF")
            if info[n]["mimic"] is not None:
                raise ValueError(f"{n!r} is a mimic joint and cannot be controlled")
            if n in locked:
                raise ValueError(f"{n!r} is both controlled and locked")
        for n in locked:
            if n not in info or info[n]["type"] not in MOVABLE or info[n]["mimic"] is not None:
                raise ValueError(f"{n!r} cannot be locked (not a movable non-mimic joint)")
        self.n = len(self.joint_names)
        index = {n: k for k, n in enumerate(self.joint_names)}

        # Role of every movable URDF joint:
        # ("ctrl", k) | ("const", value) | ("mimic", k, multiplier, offset)
        roles = {}
        for n, j in info.items():
            if j["type"] not in MOVABLE or j["mimic"] is not None:
                continue
            roles[n] = ("ctrl", index[n]) if n in index else ("const", float(locked.get(n, 0.0)))
        for n, j in info.items():
            if j["type"] not in MOVABLE or j["mimic"] is None:
                continue
            mm = j["mimic"]
            if mm["joint"] not in roles:
                raise ValueError(f"mimic joint {n!r}: master {mm['joint']!r} is not a movable "
                                 "non-mimic joint")
            r = roles[mm["joint"]]
            if r[0] == "ctrl":
                roles[n] = ("mimic", r[1], mm["multiplier"], mm["offset"])
            else:
                roles[n] = ("const", mm["multiplier"] * r[1] + mm["offset"])
        self.roles = roles
        self.locked = {n: r[1] for n, r in roles.items() if r[0] == "const"}

        full = pin.buildModelFromXML(xml)  # mimic=False: mimic joints are independent joints
        self.full_model = full
        if _reduce:
            q_ref = self._pin_q_for(full, np.zeros(self.n))
            lock_ids = [full.getJointId(n) for n in self.locked]
            model = pin.buildReducedModel(full, lock_ids, q_ref) if lock_ids else full.copy()
        else:
            model = full
        model.gravity.linear = np.asarray(gravity, dtype=float)
        self.model = model
        self.data = model.createData()
        self.nv = model.nv

        E = np.zeros((model.nv, self.n))
        for i in range(1, model.njoints):
            name = model.names[i]
            r = roles[name]
            iv = model.joints[i].idx_v
            if r[0] == "ctrl":
                E[iv, r[1]] = 1.0
            elif r[0] == "mimic":
                E[iv, r[1]] = r[2]
        self.E = E
        self.has_mimic = any(r[0] == "mimic" for r in roles.values())
        # Pinocchio bodies -> URDF links they carry (the child link of the joint plus fixed links).
        self.body_links = {model.names[i]: [] for i in range(1, model.njoints)}
        for f in model.frames:
            if f.type == pin.FrameType.BODY and f.parentJoint > 0:
                self.body_links[model.names[f.parentJoint]].append(f.name)

    @classmethod
    def reduced(cls, xml, joints=None, locked=None, gravity=(0.0, 0.0, -9.81)):
        """Same as Oracle(...), but the locked joints are removed by pin.buildReducedModel."""
        return cls(xml, joints=joints, locked=locked, gravity=gravity, _reduce=True)

    # ---- coordinate maps ----
    def _pin_q_for(self, model, q):
        q = np.asarray(q, dtype=float)
        out = np.zeros(model.nq)
        for i in range(1, model.njoints):
            jm = model.joints[i]
            r = self.roles[model.names[i]]
            if r[0] == "ctrl":
                th = q[r[1]]
            elif r[0] == "mimic":
                th = r[2] * q[r[1]] + r[3]
            else:
                th = r[1]
            if jm.nq == 2:  # continuous: (cos, sin)
                out[jm.idx_q:jm.idx_q + 2] = (np.cos(th), np.sin(th))
            elif jm.nq == 1:
                out[jm.idx_q] = th
            else:
                raise ValueError(f"unsupported joint {model.names[i]!r} ({jm.shortname()})")
        return out

    def pin_q(self, q):
        """Pinocchio configuration (model.nq,) for our q."""
        return self._pin_q_for(self.model, q)

    def pin_v(self, qd):
        return self.E @ np.asarray(qd, dtype=float)

    # ---- dynamics ----
    def rnea(self, q, qd, qdd):
        tau = pin.rnea(self.model, self.data, self.pin_q(q), self.pin_v(qd), self.pin_v(qdd))
        return self.E.T @ tau

    def gravity(self, q):
        return self.E.T @ pin.computeGeneralizedGravity(self.model, self.data, self.pin_q(q))

    def crba(self, q):
        M = _sym(np.reshape(pin.crba(self.model, self.data, self.pin_q(q)), (self.nv, self.nv)))
        Mr = self.E.T @ M @ self.E
        return 0.5 * (Mr + Mr.T)

    def nonlinear(self, q, qd):
        """Coriolis/centrifugal + gravity torques: rnea(q, qd, 0)."""
        h = pin.nonLinearEffects(self.model, self.data, self.pin_q(q), self.pin_v(qd))
        return self.E.T @ h

    def coriolis_matrix(self, q, qd):
        C = pin.computeCoriolisMatrix(self.model, self.data, self.pin_q(q), self.pin_v(qd))
        C = np.reshape(C, (self.nv, self.nv))
        return self.E.T @ C @ self.E

    def _is_permutation(self):
        return self.E.shape[0] == self.E.shape[1] and np.all((self.E == 0) | (self.E == 1)) \
            and np.all(self.E.sum(axis=0) == 1) and np.all(self.E.sum(axis=1) == 1)

    def aba(self, q, qd, tau):
        tau = np.asarray(tau, dtype=float)
        if self._is_permutation():
            a = pin.aba(self.model, self.data, self.pin_q(q), self.pin_v(qd), self.E @ tau)
            return self.E.T @ a
        return np.linalg.solve(self.crba(q), tau - self.nonlinear(q, qd))

    def rnea_derivatives(self, q, qd, qdd):
        """(dtau/dq, dtau/dqd), each (n, n), in our coordinates."""
        dq, dv, _ = pin.computeRNEADerivatives(self.model, self.data, self.pin_q(q),
                                               self.pin_v(qd), self.pin_v(qdd))
        nv = self.model.nv
        dq, dv = np.reshape(dq, (nv, nv)), np.reshape(dv, (nv, nv))
        return self.E.T @ dq @ self.E, self.E.T @ dv @ self.E

    def regressor(self, q, qd, qdd):
        """(n, 10 * nbodies): rnea(q, qd, qdd) == regressor(...) @ dynamic_parameters()."""
        Y = pin.computeJointTorqueRegressor(self.model, self.data, self.pin_q(q),
                                            self.pin_v(qd), self.pin_v(qdd))
        return self.E.T @ np.reshape(Y, (self.model.nv, -1))  # nv == 1 comes back 1-D

    def dynamic_parameters(self):
        """10 parameters per Pinocchio body (joints 1..njoints-1, Pinocchio order)."""
        return np.concatenate([self.model.inertias[i].toDynamicParameters()
                               for i in range(1, self.model.njoints)])

    def body_names(self):
        """Pinocchio joint names for the bodies of dynamic_parameters(), in order."""
        return [self.model.names[i] for i in range(1, self.model.njoints)]

    # ---- energies and kinematics (for independent checks) ----
    def kinetic_energy(self, q, qd):
        qp, v = self.pin_q(q), self.pin_v(qd)
        return float(pin.computeKineticEnergy(self.model, self.data, qp, v))

    def potential_energy(self, q):
        return float(pin.computePotentialEnergy(self.model, self.data, self.pin_q(q)))

    def frame_pose(self, q, frame):
        """4x4 pose of a URDF link (or joint) frame in the root frame."""
        pin.framesForwardKinematics(self.model, self.data, self.pin_q(q))
        return self.data.oMf[self._frame_id(frame)].homogeneous.copy()

    def _frame_id(self, frame):
        # A joint and a link may share a name (e.g. "flange"): prefer the link frame.
        if self.model.existFrame(frame, pin.FrameType.BODY):
            return self.model.getFrameId(frame, pin.FrameType.BODY)
        return self.model.getFrameId(frame)

    # ---- frame Jacobians ----
    REFERENCE = {'world_aligned': pin.LOCAL_WORLD_ALIGNED, 'local': pin.LOCAL, 'world': pin.WORLD}

    def _frame_at(self, frame, point):
        """(parent joint, placement in it) of a URDF link's frame, moved to `point` (in that frame)."""
        f = self.model.frames[self._frame_id(frame)]
        placement = f.placement if point is None else f.placement * pin.SE3(np.eye(3), np.asarray(point, float))
        return f.parentJoint, placement

    def frame_jacobian(self, q, frame, reference, point=None):
        """pin.getFrameJacobian of a link frame (or of `point` in it), (6, n) in our columns;
        reference 'world_aligned' | 'local' | 'world'."""
        joint, placement = self._frame_at(frame, point)
        pin.computeJointJacobians(self.model, self.data, self.pin_q(q))
        J = pin.getFrameJacobian(self.model, self.data, joint, placement, self.REFERENCE[reference])
        return J @ self.E

    def frame_classical_acceleration(self, q, qd, qdd, frame, reference, point=None):
        """pin.getFrameClassicalAcceleration (linear, angular) of a link frame (or of `point` in it)."""
        joint, placement = self._frame_at(frame, point)
        pin.forwardKinematics(self.model, self.data, self.pin_q(q), self.pin_v(qd), self.pin_v(qdd))
        return pin.getFrameClassicalAcceleration(self.model, self.data, joint, placement,
                                                 self.REFERENCE[reference]).vector.copy()
