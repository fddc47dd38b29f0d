"""URDF -> Model: parse with yourdfpy (no meshes, no scene), validate, merge, reduce.

"Model no more than a scene needs": fixed children are merged into the inertia of the
body they hang from; only the controlled joints (and mimic joints that follow them) are
free; other movable joints are locked at values the caller updates cheaply
(`Model.set_locked`); bodies that cannot influence a controlled torque are dropped.
"""
import io
import os
import xml.etree.ElementTree as ET

import numpy as np

from .model import Model
from .se3 import spatial_inertia

MOVABLE = ('revolute', 'continuous', 'prismatic')
KNOWN = MOVABLE + ('fixed', 'floating', 'planar')


def _read_source(source):
    """Return URDF XML text from a path or an XML string."""
    if not isinstance(source, (str, bytes, os.PathLike)):
        raise ValueError(f'URDF source must be a file path or an XML string, got {type(source).__name__}')
    if isinstance(source, bytes):
        source = source.decode()
    text = str(source)
    if text.lstrip().startswith('<'):
        return text
    if not os.path.isfile(text):
        raise ValueError(f'URDF file not found: {text!r} (pass a path or an XML string)')
    with open(text, encoding='utf-8') as fh:
        return fh.read()


def _check_inertia_attributes(xml):
    """yourdfpy silently fills missing ixx/iyy/izz with 1.0; insist they are written."""
    try:
        root = ET.fromstring(xml)
    except ET.ParseError as exc:
        raise ValueError(f'malformed URDF XML: {exc}') from None
    if root.tag != 'robot':
        raise ValueError(f'malformed URDF: root element is <{root.tag}>, expected <robot>')
    for link in root.iter('link'):
        for inertia in link.findall('inertial/inertia'):
            missing = [k for k in ('ixx', 'iyy', 'izz') if k not in inertia.attrib]
            if missing:
                raise ValueError(f"link '{link.get('name')}': <inertia> lacks {', '.join(missing)}")
        for mass in link.findall('inertial/mass'):
            if 'value' not in mass.attrib:
                raise ValueError(f"link '{link.get('name')}': <mass> lacks a value")


def _parse(xml):
    import yourdfpy  # imported here: only loading needs it

    try:
        urdf = yourdfpy.URDF.load(io.BytesIO(xml.encode()), build_scene_graph=False, load_meshes=False,
                                  build_collision_scene_graph=False, load_collision_meshes=False)
    except Exception as exc:  # yourdfpy/lxml raise many types for bad XML
        raise ValueError(f'malformed URDF: {type(exc).__name__}: {exc}') from None
    return urdf.robot


def _origin(T):
    return np.eye(4) if T is None else np.asarray(T, dtype=float)


def _link_inertia(link):
    """Spatial inertia of a link about its own frame (None when massless/absent)."""
    inertial = link.inertial
    if inertial is None:
        return None
    m = float(inertial.mass if inertial.mass is not None else 0.0)
    I = np.zeros((3, 3)) if inertial.inertia is None else np.asarray(inertial.inertia, dtype=float)
    if not np.isfinite(m) or not np.all(np.isfinite(I)):
        raise ValueError(f"link '{link.name}': non-finite mass or inertia")
    if m < 0:
        raise ValueError(f"link '{link.name}': negative mass {m}")
    I = 0.5 * (I + I.T)
    ev = np.linalg.eigvalsh(I)
    scale = max(np.max(np.abs(ev)), 1e-300)
    if ev[0] < -1e-9 * scale:
        raise ValueError(f"link '{link.name}': inertia tensor is not positive semi-definite "
                         f"(principal moments {ev.tolist()})")
    if ev[0] + ev[1] < ev[2] - 1e-9 * scale:
        raise ValueError(f"link '{link.name}': inertia violates the triangle inequality "
                         f"(principal moments {ev.tolist()})")
    T = _origin(inertial.origin)
    # <inertial><origin rpy> rotates the tensor only; the CoM is the origin's xyz.
    R = T[:3, :3]
    return m, T[:3, 3].copy(), R @ I @ R.T


def _inertia_in(T_body_link, mic):
    """Spatial inertia J (about the body frame) of a link at T_body_link."""
    m, com, Ic = mic
    R, p = T_body_link[:3, :3], T_body_link[:3, 3]
    return spatial_inertia(m, R @ com + p, R @ Ic @ R.T)


def load_urdf(source, joints=None, gravity=(0.0, 0.0, -9.81)):
    """Build a `Model` from a URDF file path or XML string.

    joints: the controlled joints, in the order of q (default: every movable non-mimic
    joint, depth-first tree order). Other movable joints are locked (value 0 until
    `Model.set_locked`). gravity: in the URDF root frame, m/s^2.
    Raises ValueError naming the culprit for any malformed or unsupported input.
    """
    xml = _read_source(source)
    _check_inertia_attributes(xml)
    robot = _parse(xml)

    links = {ln.name: ln for ln in robot.links}
    if len(links) != len(robot.links):
        raise ValueError('URDF has duplicate link names')
    jmap = {}
    child_of = {}
    for j in robot.joints:
        if j.name in jmap:
            raise ValueError(f"duplicate joint name '{j.name}'")
        jmap[j.name] = j
        if j.type not in KNOWN:
            raise ValueError(f"joint '{j.name}': unknown type '{j.type}'")
        for end in (j.parent, j.child):
            if end not in links:
                raise ValueError(f"joint '{j.name}' refers to unknown link '{end}'")
        if j.child in child_of:
            raise ValueError(f"link '{j.child}' has two parent joints ('{child_of[j.child]}', '{j.name}'): "
                             'a URDF must be a tree (closed loops are not supported)')
        child_of[j.child] = j.name
    roots = [name for name in links if name not in child_of]
    if len(roots) != 1:
        if not roots:
            raise ValueError('URDF kinematic graph has a cycle (no root link)')
        raise ValueError(f"URDF has several root links {roots}: it must have exactly one")
    root = roots[0]

    children = {name: [] for name in links}
    for j in robot.joints:  # file order is kept: it defines the default joint order
        children[j.parent].append(j)

    # Depth-first walk. Every link gets (body of its nearest movable ancestor joint, pose in that
    # body's frame); body -1 is the world (root link and everything fixed to it).
    link_body = {root: (-1, np.eye(4))}
    bodies = []  # dicts: joint, parent body, M (pose in parent body at q=0), axis, type
    order, stack, seen = [], [(root, None)], set()
    while stack:  # depth-first: a joint's subtree comes before its next sibling
        name, j = stack.pop()
        if name in seen:
            raise ValueError(f"URDF kinematic graph has a cycle through link '{name}'")
        seen.add(name)
        order.append(name)
        if j is not None:
            b, T = link_body[j.parent]
            X = T @ _origin(j.origin)
            if j.type in MOVABLE or j.type in ('floating', 'planar'):
                axis = np.array([1.0, 0.0, 0.0]) if j.axis is None else np.asarray(j.axis, dtype=float)
                na = np.linalg.norm(axis)
                if j.type in MOVABLE and (not np.isfinite(na) or na < 1e-12):
                    raise ValueError(f"joint '{j.name}': axis must be a non-zero finite vector")
                bodies.append(dict(joint=j, parent=b, M=X, axis=axis / na if na > 0 else axis))
                link_body[name] = (len(bodies) - 1, np.eye(4))
            else:
                link_body[name] = (b, X)
        stack.extend((c.child, c) for c in reversed(children[name]))
    if len(seen) != len(links):
        raise ValueError(f'URDF links not connected to the root: {sorted(set(links) - seen)}')

    body_of_joint = {bd['joint'].name: i for i, bd in enumerate(bodies)}
    movable = [bd['joint'].name for bd in bodies if bd['joint'].type in MOVABLE]

    # Mimic resolution: q_j = a * q_master_root + c, following mimic chains.
    def resolve(name, depth=0):
        j = jmap[name]
        if j.mimic is None or j.type not in MOVABLE:
            return name, 1.0, 0.0
        if depth > len(jmap):
            raise ValueError(f"mimic joints form a loop at '{name}'")
        master = j.mimic.joint
        if master not in jmap or jmap[master].type not in MOVABLE:
            raise ValueError(f"joint '{name}' mimics '{master}', which is not a movable joint of this URDF")
        m, a, c = resolve(master, depth + 1)
        mult = 1.0 if j.mimic.multiplier is None else float(j.mimic.multiplier)
        off = 0.0 if j.mimic.offset is None else float(j.mimic.offset)
        return m, mult * a, mult * c + off

    mimic_of = {name: resolve(name) for name in movable if jmap[name].mimic is not None}
    independent = [name for name in movable if name not in mimic_of]

    if joints is None:
        joints = list(independent)
    else:
        if isinstance(joints, str) or not all(isinstance(x, str) for x in joints):
            raise ValueError('joints must be a list of joint names')
        joints = list(joints)
        if len(set(joints)) != len(joints):
            raise ValueError(f'joints lists a name twice: {joints}')
        for name in joints:
            if name not in jmap:
                raise ValueError(f"unknown joint '{name}' (URDF movable joints: {independent})")
            if jmap[name].type in ('floating', 'planar'):
                raise ValueError(f"joint '{name}' is {jmap[name].type}: only revolute, continuous and "
                                 'prismatic joints can be controlled')
            if jmap[name].type == 'fixed':
                raise ValueError(f"joint '{name}' is fixed and cannot be controlled")
            if name in mimic_of:
                raise ValueError(f"joint '{name}' is a mimic joint of '{mimic_of[name][0]}': "
                                 'control its master instead')
    if not joints:
        raise ValueError('no joints to control (the URDF has no movable joint)')
    ctrl_index = {name: k for k, name in enumerate(joints)}
    locked_all = [name for name in independent if name not in ctrl_index]

    # Driven bodies: controlled joints and mimics of them. Keep their subtrees and ancestors.
    nb_all = len(bodies)
    driven = [i for i, bd in enumerate(bodies)
              if bd['joint'].name in ctrl_index or mimic_of.get(bd['joint'].name, ('',))[0] in ctrl_index]
    keep = np.zeros(nb_all, dtype=bool)
    in_subtree = np.zeros(nb_all, dtype=bool)
    for i in range(nb_all):  # parents come before children in `bodies`
        p = bodies[i]['parent']
        in_subtree[i] = i in driven or (p >= 0 and in_subtree[p])
    keep |= in_subtree
    for i in driven:
        p = bodies[i]['parent']
        while p >= 0 and not keep[p]:
            keep[p] = True
            p = bodies[p]['parent']
    for i in np.flatnonzero(keep):
        bd = bodies[i]
        if bd['joint'].type in ('floating', 'planar'):
            where = 'above' if not in_subtree[i] else 'inside the subtree of'
            raise ValueError(f"joint '{bd['joint'].name}' is {bd['joint'].type} and sits {where} the controlled "
                             'joints: a fixed-base model cannot contain it')

    new_index = -np.ones(nb_all, dtype=int)
    new_index[keep] = np.arange(int(keep.sum()))
    kept = np.flatnonzero(keep)
    nb = len(kept)
    locked = [name for name in locked_all
              if keep[body_of_joint[name]] or any(keep[body_of_joint[m]] for m, r in mimic_of.items()
                                                  if r[0] == name)]
    locked_index = {name: k for k, name in enumerate(locked)}

    parent = np.array([new_index[bodies[i]['parent']] if bodies[i]['parent'] >= 0 else -1 for i in kept],
                      dtype=int)
    M = np.array([bodies[i]['M'] for i in kept]).reshape(nb, 4, 4)
    S = np.zeros((nb, 6))
    E = np.zeros((nb, len(joints)))
    L = np.zeros((nb, len(locked)))
    c0 = np.zeros(nb)
    body_joint = []
    for k, i in enumerate(kept):
        j = bodies[i]['joint']
        body_joint.append(j.name)
        if j.type == 'prismatic':
            S[k, 3:] = bodies[i]['axis']
        else:
            S[k, :3] = bodies[i]['axis']
        master, a, c = mimic_of.get(j.name, (j.name, 1.0, 0.0))
        if master in ctrl_index:
            E[k, ctrl_index[master]] = a
        else:
            L[k, locked_index[master]] = a
        c0[k] = c

    # Inertia: every link's inertia goes to the body it is rigidly attached to.
    J = np.zeros((nb, 6, 6))
    link_frames = {}
    for name in order:
        b, T = link_body[name]
        nbi = new_index[b] if b >= 0 else -1
        link_frames[name] = (int(nbi) if b < 0 or keep[b] else -2, T)
        mic = _link_inertia(links[name])
        if mic is None or b < 0 or not keep[b]:
            continue
        J[nbi] += _inertia_in(T, mic)

    def limits(name):
        j = jmap[name]
        lim = j.limit
        eff = np.inf if lim is None or lim.effort is None else float(lim.effort)
        vel = np.inf if lim is None or lim.velocity is None else float(lim.velocity)
        lo, hi = -np.inf, np.inf
        if j.type != 'continuous' and lim is not None:
            lo = -np.inf if lim.lower is None else float(lim.lower)
            hi = np.inf if lim.upper is None else float(lim.upper)
        dyn = j.dynamics
        damp = 0.0 if dyn is None or dyn.damping is None else float(dyn.damping)
        fric = 0.0 if dyn is None or dyn.friction is None else float(dyn.friction)
        return eff, vel, lo, hi, damp, fric

    lim = np.array([limits(name) for name in joints]).reshape(len(joints), 6)
    return Model(
        name=robot.name, joint_names=joints, joint_types=[jmap[n].type for n in joints],
        locked_joint_names=locked, lockable_joint_names=locked_all,
        mimic_joints={m: r for m, r in mimic_of.items()},
        body_joint_names=body_joint, parent=parent, M=M, S=S, J=J, E=E, L=L, c0=c0,
        link_frames=link_frames, effort_limits=lim[:, 0], velocity_limits=lim[:, 1],
        position_lower=lim[:, 2], position_upper=lim[:, 3], damping=lim[:, 4], friction=lim[:, 5],
        gravity=gravity)
