"""URDF -> Model: read, check, parse (yourdfpy, no meshes, no scene), walk, reduce, build.

"Model no more than a scene needs": fixed children are merged into the inertia of the
body they hang from; only the controlled joints (and mimic joints that follow them) are
free; other movable joints are locked at values the caller updates cheaply
(`Model.set_locked`). A locked joint whose subtree holds no controlled joint is folded
into its parent body's inertia (recomputed by set_locked, never recompiled); bodies that
cannot influence a controlled torque are dropped.

What the ROS URDF parser (urdfdom) accepts loads; what it refuses is refused with a
message naming the place. Physically odd inertias follow the inertia policy (inertia.py).
"""
import io
import os
import re
import warnings
import xml.etree.ElementTree as ET

import numpy as np

from .inertia import InertiaWarning, RTOL, check_policy, inertia_scale, link_inertia, repair, violations
from .link_frames import DROPPED, WORLD
from .model import Model

MOVABLE = ('revolute', 'continuous', 'prismatic')
FREE = ('floating', 'planar')
KNOWN = MOVABLE + FREE + ('fixed',)


class URDFWarning(UserWarning):
    """A URDF construct was accepted with a documented interpretation (mimic of a missing
    joint, floating joint above the controlled joints)."""


# ---------------------------------------------------------------------- reading and checks
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


_PREFIX_USE = re.compile(r'</?\s*([A-Za-z_][\w.-]*):[A-Za-z_]|\s([A-Za-z_][\w.-]*):[\w.-]+\s*=')
_PREFIX_DECL = re.compile(r'xmlns:([A-Za-z_][\w.-]*)\s*=')
_ROOT_TAG = re.compile(r'<\s*robot\b')


def _declare_prefixes(xml):
    """urdfdom ignores namespaces; an XML parser refuses a prefix nobody declared (vendor
    files use `drake:` tags without declaring it). Declare each missing one on <robot>."""
    used = {a or b for a, b in _PREFIX_USE.findall(xml)} - {'xml', 'xmlns'}
    missing = sorted(used - set(_PREFIX_DECL.findall(xml)))
    m = _ROOT_TAG.search(xml)
    if not missing or m is None:
        return xml
    decl = ''.join(f' xmlns:{p}="urn:undeclared:{p}"' for p in missing)
    return xml[:m.end()] + decl + xml[m.end():]


def _where(owner, el):
    tag = el.tag.split('}')[-1]
    return f"{owner} <{tag}>" if owner else f'<{tag}>'


def _check_triple(text, what):
    parts = text.split()
    try:
        vals = [float(p) for p in parts]
    except ValueError:
        vals = None
    if vals is None or len(vals) != 3:
        raise ValueError(f'{what}: expected three numbers, got {text!r}')


def _is_xacro(el):
    return 'xacro' in el.tag.split('}')[0].lower() or el.tag.startswith('xacro')


def _check_elements(root):
    """Refuse what urdfdom refuses, naming the element: unexpanded xacro, an xyz/rpy/axis
    without exactly three numbers, <inertia> without ixx/iyy/izz (yourdfpy would put 1.0
    there silently), <mass> without a value."""
    for top in root:
        kind = top.tag.split('}')[-1]
        owner = f"{kind} '{top.get('name')}'" if top.get('name') is not None else ''
        for el in top.iter():
            if _is_xacro(el):
                raise ValueError(f'{_where(owner, el)}: unexpanded xacro element: run the file through xacro first')
            for key, value in el.attrib.items():
                if '$(' in value or '${' in value:
                    raise ValueError(f'{_where(owner, el)} {key}={value!r}: unexpanded xacro expression: '
                                     'run the file through xacro first')
            tag = el.tag.split('}')[-1]
            if tag == 'origin':
                for key in ('xyz', 'rpy'):
                    if key in el.attrib:
                        _check_triple(el.get(key), f'{_where(owner, el)} {key}')
            elif tag == 'axis' and 'xyz' in el.attrib:
                _check_triple(el.get('xyz'), f'{_where(owner, el)} xyz')
            elif tag == 'inertia':
                missing = [k for k in ('ixx', 'iyy', 'izz') if k not in el.attrib]
                if missing:
                    raise ValueError(f"{owner}: <inertia> lacks {', '.join(missing)}")
            elif tag == 'mass' and 'value' not in el.attrib:
                raise ValueError(f'{owner}: <mass> lacks a value')
    if _is_xacro(root):
        raise ValueError('unexpanded xacro at the root element: run the file through xacro first')


def _prepare(text):
    """XML text -> text yourdfpy can parse, after the checks urdfdom would make."""
    xml = text.lstrip('\ufeff \t\r\n')  # urdfdom accepts blank lines before <?xml ...?>
    if '<!ENTITY' in xml:
        raise ValueError('URDF declares XML entities (<!ENTITY ...>): refused, entity expansion is '
                         'a known attack and urdfdom does not expand them')
    xml = _declare_prefixes(xml)
    try:
        root = ET.fromstring(xml)
    except ET.ParseError as exc:
        raise ValueError(f'malformed URDF XML: {exc}') from None
    if root.tag.split('}')[-1] != 'robot':
        raise ValueError(f'malformed URDF: root element is <{root.tag}>, expected <robot>')
    _check_elements(root)
    return xml


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
    """(mass, CoM, inertia about the CoM) of a link in its own frame; None when absent."""
    inertial = link.inertial
    if inertial is None:
        return None
    m = float(inertial.mass if inertial.mass is not None else 0.0)
    I = np.zeros((3, 3)) if inertial.inertia is None else np.asarray(inertial.inertia, dtype=float)
    if not np.isfinite(m) or not np.all(np.isfinite(I)):
        raise ValueError(f"link '{link.name}': non-finite mass or inertia")
    T = _origin(inertial.origin)
    # <inertial><origin rpy> rotates the tensor only; the CoM is the origin's xyz.
    R = T[:3, :3]
    return m, T[:3, 3].copy(), R @ (0.5 * (I + I.T)) @ R.T


# ---------------------------------------------------------------------- tree
def _graph(robot):
    """Links by name, joints by name, the root link and each link's child joints (file order)."""
    links = {ln.name: ln for ln in robot.links}
    if len(links) != len(robot.links):
        raise ValueError('URDF has duplicate link names')
    jmap, child_of = {}, {}
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
        raise ValueError(f'URDF has several root links {roots}: it must have exactly one')
    children = {name: [] for name in links}
    for j in robot.joints:  # file order is kept: it defines the default joint order
        children[j.parent].append(j)
    return links, jmap, roots[0], children


def _walk(links, root, children, as_fixed=()):
    """Depth-first walk (a joint's subtree before its next sibling). Returns the links in walk
    order, link -> (body, pose in that body's frame) with body WORLD the world, and the bodies
    (one per movable or free joint not in `as_fixed`, parents first)."""
    link_body = {root: (WORLD, np.eye(4))}
    bodies, order, stack, seen = [], [], [(root, None)], set()
    while stack:
        name, j = stack.pop()
        if name in seen:
            raise ValueError(f"URDF kinematic graph has a cycle through link '{name}'")
        seen.add(name)
        order.append(name)
        if j is not None:
            b, T = link_body[j.parent]
            X = T @ _origin(j.origin)
            if j.type in MOVABLE + FREE and j.name not in as_fixed:
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
    return order, link_body, bodies


def _mimics(jmap, movable):
    """Mimic joint -> (master, multiplier, offset) with q = multiplier * q_master + offset,
    following chains. A mimic of a joint that does not exist (or is not movable) is warned
    about and stays an independent joint, as in KDL and Pinocchio."""
    out = {}

    def resolve(name, depth=0):
        if name in out:
            return out[name]
        j = jmap[name]
        if j.mimic is None or j.type not in MOVABLE:
            return name, 1.0, 0.0
        if depth > len(jmap):
            raise ValueError(f"mimic joints form a loop at '{name}'")
        master = j.mimic.joint
        if master not in jmap or jmap[master].type not in MOVABLE:
            return name, 1.0, 0.0
        m, a, c = resolve(master, depth + 1)
        mult = 1.0 if j.mimic.multiplier is None else float(j.mimic.multiplier)
        off = 0.0 if j.mimic.offset is None else float(j.mimic.offset)
        return m, mult * a, mult * c + off

    for name in movable:
        j = jmap[name]
        if j.mimic is None:
            continue
        master = j.mimic.joint
        if master not in jmap or jmap[master].type not in MOVABLE:
            warnings.warn(f"joint '{name}' mimics '{master}', which is not a movable joint of this URDF: "
                          'treated as an independent joint', URDFWarning, stacklevel=4)
            continue
        out[name] = resolve(name)
    return out


def _controlled(joints, jmap, independent, mimic_of):
    if joints is None:
        return list(independent)
    if isinstance(joints, str) or not all(isinstance(x, str) for x in joints):
        raise ValueError('joints must be a list of joint names')
    joints = list(joints)
    if len(set(joints)) != len(joints):
        raise ValueError(f'joints lists a name twice: {joints}')
    for name in joints:
        if name not in jmap:
            raise ValueError(f"unknown joint '{name}' (URDF movable joints: {independent})")
        if jmap[name].type in FREE:
            raise ValueError(f"joint '{name}' is {jmap[name].type}: only revolute, continuous and "
                             'prismatic joints can be controlled')
        if jmap[name].type == 'fixed':
            raise ValueError(f"joint '{name}' is fixed and cannot be controlled")
        if name in mimic_of:
            raise ValueError(f"joint '{name}' is a mimic joint of '{mimic_of[name][0]}': "
                             'control its master instead')
    return joints


def _reduce(bodies, driven):
    """Masks over bodies: `keep` (a driven body or an ancestor of one: modelled), `below` (in a
    driven body's subtree), `fold` (below a driven body with no driven body underneath:
    folded into the parent's inertia). Everything else cannot influence a controlled torque."""
    nb = len(bodies)
    keep = np.zeros(nb, dtype=bool)
    below = np.zeros(nb, dtype=bool)
    for i in range(nb):  # parents come before children in `bodies`
        p = bodies[i]['parent']
        below[i] = driven[i] or (p >= 0 and below[p])
    for i in np.flatnonzero(driven):
        while i >= 0 and not keep[i]:
            keep[i] = True
            i = bodies[i]['parent']
    return keep, below, below & ~keep


# ---------------------------------------------------------------------- inertia policy
def _apply_policy(policy, link_inertias, scale):
    """Check every modelled link once (inertia.violations) and act by the policy. Returns the
    (possibly repaired) inertias and the per-link report."""
    tol = RTOL * scale
    report = []
    out = {}
    for name, mic in link_inertias.items():
        m, com, Ic = mic
        found = violations(m, Ic, tol)
        if not found:
            out[name] = mic
            continue
        text = '; '.join(f'{rule}: {detail}' for rule, detail in found)
        entry = dict(link=name, rule=', '.join(r for r, _ in found), message=f"link '{name}': {text}",
                     repaired=False)
        if policy == 'repair':
            m2, Ic2 = repair(m, Ic)
            entry.update(repaired=True, message=f"{entry['message']}; repaired to mass {m2:.6g} kg, principal "
                         f"moments [{', '.join(f'{v:.6g}' for v in np.linalg.eigvalsh(Ic2))}] kg m^2")
            mic = (m2, com, Ic2)
        report.append(entry)
        out[name] = mic
    return out, report


# ---------------------------------------------------------------------- build
def load_urdf(source, joints=None, gravity=(0.0, 0.0, -9.81), inertia='warn', calibration=None):
    """Build a `Model` from a URDF file path or XML string.

    joints: the controlled joints, in the order of q (default: every movable non-mimic
    joint, depth-first tree order). Other movable joints are locked (value 0 until
    `Model.set_locked`). gravity: in the URDF root frame, m/s^2.
    inertia: what to do with a physically inconsistent link inertia (inertia.py) on a body
    that ends up in the model: 'warn' (compute with it as written; one InertiaWarning per
    link), 'strict' (ValueError) or 'repair' (nearest consistent tensor; InertiaWarning with
    the before and after values). `Model.physical_consistency()` returns the report.
    calibration: a calibration.yaml path (or CalibrationResult) applied to the loaded model
    (`Model.with_calibration`: identified inertias, friction as damping and friction).
    Raises ValueError naming the culprit for any malformed or unsupported input.
    """
    policy = check_policy(inertia)
    robot = _parse(_prepare(_read_source(source)))
    links, jmap, root, children = _graph(robot)
    order, link_body, bodies = _walk(links, root, children)
    movable = [bd['joint'].name for bd in bodies if bd['joint'].type in MOVABLE]
    mimic_of = _mimics(jmap, movable)
    independent = [name for name in movable if name not in mimic_of]
    joints = _controlled(joints, jmap, independent, mimic_of)
    ctrl_index = {name: k for k, name in enumerate(joints)}

    def driven_mask(bodies):
        return np.array([bd['joint'].name in ctrl_index or mimic_of.get(bd['joint'].name, ('',))[0] in ctrl_index
                         for bd in bodies], dtype=bool)

    keep, below, fold = _reduce(bodies, driven_mask(bodies))
    above = [bd['joint'].name for i, bd in enumerate(bodies) if bd['joint'].type in FREE and keep[i] and not below[i]]
    for i in np.flatnonzero(below):
        bd = bodies[i]
        if bd['joint'].type in FREE:
            raise ValueError(f"joint '{bd['joint'].name}' is {bd['joint'].type} and sits inside the subtree of the "
                             'controlled joints: a fixed-base model cannot contain it')
    if above:  # as kdl_parser does: a free joint above the controlled ones is fixed at the identity
        warnings.warn(f"{', '.join(repr(a) for a in above)}: floating/planar joint above the controlled joints "
                      'treated as fixed at the identity (gravity stays in the root frame)', URDFWarning, stacklevel=2)
        order, link_body, bodies = _walk(links, root, children, as_fixed=set(above))
        keep, below, fold = _reduce(bodies, driven_mask(bodies))

    nb_all = len(bodies)
    body_of_joint = {bd['joint'].name: i for i, bd in enumerate(bodies)}
    kept = np.flatnonzero(keep)
    new_index = -np.ones(nb_all, dtype=int)
    new_index[kept] = np.arange(len(kept))
    locked_all = [name for name in independent if name not in ctrl_index]
    used = keep | fold
    locked = [name for name in locked_all
              if used[body_of_joint[name]] or any(used[body_of_joint[m]] for m, r in mimic_of.items() if r[0] == name)]
    locked_index = {name: k for k, name in enumerate(locked)}

    def coordinate(i):
        """(column kind, column, multiplier, offset) of body i's coordinate."""
        name = bodies[i]['joint'].name
        master, a, c = mimic_of.get(name, (name, 1.0, 0.0))
        if master in ctrl_index:
            return 'q', ctrl_index[master], a, c
        return 'locked', locked_index[master], a, c

    def screw(i):
        s = np.zeros(6)
        if bodies[i]['joint'].type == 'prismatic':
            s[3:] = bodies[i]['axis']
        else:
            s[:3] = bodies[i]['axis']
        return s

    nb = len(kept)
    parent = np.array([new_index[bodies[i]['parent']] if bodies[i]['parent'] >= 0 else -1 for i in kept], dtype=int)
    M = np.array([bodies[i]['M'] for i in kept]).reshape(nb, 4, 4)
    S = np.array([screw(i) for i in kept]).reshape(nb, 6)
    E = np.zeros((nb, len(joints)))
    L = np.zeros((nb, len(locked)))
    c0 = np.zeros(nb)
    for k, i in enumerate(kept):
        kind, col, a, c = coordinate(i)
        (E if kind == 'q' else L)[k, col] = a
        c0[k] = c

    # Folded bodies: parents first, each attached to a kept body or an earlier folded one.
    folded = np.flatnonzero(fold)
    fold_index = {int(i): k for k, i in enumerate(folded)}
    folded_bodies = []
    for i in folded:
        p = bodies[i]['parent']
        _, col, a, c = coordinate(i)
        folded_bodies.append(dict(parent=('kept', int(new_index[p])) if keep[p] else ('folded', fold_index[p]),
                                  M=bodies[i]['M'], S=screw(i), column=col, multiplier=a, offset=c,
                                  joint=bodies[i]['joint'].name))

    # Every link hangs from a kept body (its inertia is part of J), a folded body, the world
    # or a dropped body (neither changes a controlled torque: not checked, not modelled).
    link_inertias, link_frames, link_home = {}, {}, {}
    home = {WORLD: np.eye(4)}
    for i, bd in enumerate(bodies):
        home[i] = home[bd['parent']] @ bd['M']
    for name in order:
        b, T = link_body[name]
        if b == WORLD:
            link_frames[name] = ('kept', WORLD, T)
        elif keep[b]:
            link_frames[name] = ('kept', int(new_index[b]), T)
        elif fold[b]:
            link_frames[name] = ('folded', fold_index[b], T)
        else:
            link_frames[name] = ('dropped', DROPPED, T)
        mic = _link_inertia(links[name])
        if mic is not None and b >= 0 and (keep[b] or fold[b]):
            link_inertias[name] = mic
            link_home[name] = home[b] @ T
    scale = inertia_scale(np.array([link_inertia(link_home[n], mic) for n, mic in link_inertias.items()])
                          .reshape(-1, 6, 6))
    link_inertias, report = _apply_policy(policy, link_inertias, scale)

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
    model = Model(
        name=robot.name, joint_names=joints, joint_types=[jmap[n].type for n in joints],
        locked_joint_names=locked, lockable_joint_names=locked_all,
        mimic_joints={m: r for m, r in mimic_of.items()},
        body_joint_names=[bodies[i]['joint'].name for i in kept],
        body_link_names=[bodies[i]['joint'].child for i in kept], parent=parent, M=M, S=S, E=E, L=L, c0=c0,
        link_frames=link_frames, link_inertias=link_inertias, folded_bodies=folded_bodies,
        effort_limits=lim[:, 0], velocity_limits=lim[:, 1],
        position_lower=lim[:, 2], position_upper=lim[:, 3], damping=lim[:, 4], friction=lim[:, 5],
        gravity=gravity, inertia_scale=scale, inertia_report=report)
    report = model.physical_consistency()
    if report and policy == 'strict':
        raise ValueError("physically inconsistent inertia (inertia='strict'; 'warn' computes with it, 'repair' "
                         'fixes it): ' + '; '.join(e['message'] for e in report))
    for entry in report:
        warnings.warn(entry['message'], InertiaWarning, stacklevel=2)
    return model if calibration is None else model.with_calibration(calibration)
