"""Random URDF generator for the test suite (numpy and string building only).

``random_urdf(seed, n_joints, ...)`` returns the XML text of a fixed-base robot that is
deterministic in ``seed``. It deliberately exercises the parts of URDF that dynamics code
tends to get wrong:

* chains and trees with several branches; element order in the file is sometimes shuffled
  and joint names are chosen so that alphabetical order differs from file order;
* revolute / continuous / prismatic joints with random unit axes (sometimes axis-aligned,
  sometimes negative, sometimes omitted, which means (1, 0, 0));
* random joint origins (xyz and rpy; sometimes no ``<origin>`` at all);
* random ``<inertial>`` origins with rpy and full (non-diagonal) inertia tensors that are
  physically valid (positive principal moments obeying the triangle inequality);
* fixed joints: massless frames, massive fixed links that must be merged into their parent
  body, fixed links in the middle of a chain and on the root;
* links without ``<inertial>``, kept well-posed: the body of every movable joint (its child
  link plus everything rigidly attached to it) has positive mass and a positive definite
  rotational inertia, except that a massless body is allowed when one of its movable
  child joints has a massive body and an axis that is not parallel to the parent joint's
  axis (so the mass matrix stays positive definite);
* mimic joints (``multiplier`` in [-2, 2] away from 0, random ``offset``) whose master is a
  non-mimic joint of the same type (revolute or prismatic);
* an ``<inertial>`` on the root link (which a fixed-base model must ignore).

``n_joints`` is the number of movable joints, mimic joints included. Every movable joint
has ``<limit effort velocity lower upper>`` (continuous: effort and velocity only).
"""

import math

import numpy as np

__all__ = ["random_urdf", "NAMED_CASES", "named_urdf", "rpy_to_matrix"]

MOVABLE = ("revolute", "continuous", "prismatic")

_NAME_POOL = ("shoulder", "elbow", "wrist", "a", "zeta", "mid", "hip", "knee", "b", "yaw",
              "pitch", "roll", "x", "m", "tip")


def rpy_to_matrix(rpy):
    """URDF fixed-axis roll-pitch-yaw: R = Rz(yaw) Ry(pitch) Rx(roll)."""
    r, p, y = rpy
    cr, sr, cp, sp, cy, sy = (math.cos(r), math.sin(r), math.cos(p), math.sin(p),
                              math.cos(y), math.sin(y))
    return np.array([
        [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
        [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
        [-sp, cp * sr, cp * cr],
    ])


def _random_rotation(rng):
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    w, x, y, z = q
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def _unit(rng):
    v = rng.normal(size=3)
    return v / np.linalg.norm(v)


def _f(x):
    """Shortest round-trip text for a float (so the XML carries full precision)."""
    x = float(x)
    if x == 0.0:
        return "0"
    return repr(x)


def _vec(v):
    return " ".join(_f(x) for x in v)


def _random_inertial(rng, inertial_rpy, mass_range=(0.1, 5.0)):
    """Mass, CoM, inertial rpy and a valid 3x3 tensor (about the CoM, inertial frame)."""
    mass = float(math.exp(rng.uniform(math.log(mass_range[0]), math.log(mass_range[1]))))
    # Solid box: principal moments satisfy the triangle inequality strictly.
    dx, dy, dz = rng.uniform(0.02, 0.3, size=3)
    principal = mass / 12.0 * np.array([dy * dy + dz * dz, dx * dx + dz * dz, dx * dx + dy * dy])
    R0 = _random_rotation(rng)  # non-diagonal tensor even in the inertial frame
    inertia = R0 @ np.diag(principal) @ R0.T
    inertia = 0.5 * (inertia + inertia.T)
    com = rng.uniform(-0.2, 0.2, size=3)
    if rng.random() < 0.1:
        com = np.zeros(3)
    if inertial_rpy:
        rpy = np.array([rng.uniform(-math.pi, math.pi), rng.uniform(-1.5, 1.5),
                        rng.uniform(-math.pi, math.pi)])
    else:
        rpy = np.zeros(3)
    omit_origin = (not inertial_rpy) and (not com.any())
    return dict(mass=mass, com=com, rpy=rpy, inertia=inertia, omit_origin=omit_origin)


def _random_origin(rng):
    u = rng.random()
    if u < 0.05:
        return None  # no <origin> element: identity
    length = rng.uniform(0.02, 0.35)
    xyz = _unit(rng) * length
    if rng.random() < 0.1:
        xyz = np.zeros(3)
    v = rng.random()
    if v < 0.15:
        rpy = np.zeros(3)
    elif v < 0.35:  # Panda-style quarter turns
        rpy = rng.choice([-math.pi / 2, 0.0, math.pi / 2, math.pi], size=3)
    else:
        rpy = np.array([rng.uniform(-math.pi, math.pi), rng.uniform(-1.5, 1.5),
                        rng.uniform(-math.pi, math.pi)])
    return dict(xyz=xyz, rpy=np.asarray(rpy, dtype=float))


def _random_axis(rng):
    u = rng.random()
    if u < 0.08:
        return None  # omitted: URDF default (1, 0, 0)
    if u < 0.28:
        a = np.zeros(3)
        a[rng.integers(3)] = rng.choice([-1.0, 1.0])
        return a
    return _unit(rng)


def _axis_vec(axis):
    return np.array([1.0, 0.0, 0.0]) if axis is None else np.asarray(axis, dtype=float)


def _origin_R(origin):
    return np.eye(3) if origin is None else rpy_to_matrix(origin["rpy"])


def random_urdf(seed, n_joints, tree=False, joint_types=MOVABLE, fixed_links=True,
                mimic=False, inertial_rpy=True, massless_links=True, fixed_prob=0.25):
    """Return the XML of a random fixed-base robot with ``n_joints`` movable joints.

    seed: int, makes the result deterministic.
    n_joints: number of movable joints (1..30 is what the tests use), mimic joints included.
    tree: branch the kinematic tree (several branches) instead of a serial chain.
    joint_types: movable joint types to draw from.
    fixed_links: add fixed joints (massless frames and massive links to be merged).
    mimic: turn some joints into mimics of an earlier non-mimic joint of the same type
        (needs a revolute or prismatic type and n_joints >= 2).
    inertial_rpy: give inertial origins a random rpy (else rpy 0, tensors still full).
    massless_links: allow links without <inertial> (the model is kept well-posed).
    fixed_prob: probability of inserting a fixed link before / after each movable joint.
    """
    if n_joints < 1:
        raise ValueError("n_joints must be >= 1")
    joint_types = tuple(joint_types)
    for t in joint_types:
        if t not in MOVABLE:
            raise ValueError(f"unknown movable joint type {t!r}")
    rng = np.random.default_rng(seed)

    links = []   # dicts: name, inertial (or None)
    joints = []  # dicts: name, type, parent, child, origin, axis, limit, dynamics, mimic
    counter = {"link": 0, "joint": 0}

    def new_link(inertial):
        counter["link"] += 1
        name = f"{rng.choice(_NAME_POOL)}_link{counter['link']}"
        links.append(dict(name=name, inertial=inertial))
        return name

    def new_joint_name(kind):
        counter["joint"] += 1
        return f"{rng.choice(_NAME_POOL)}_{kind}{counter['joint']}"

    def add_fixed(parent, massive):
        inertial = _random_inertial(rng, inertial_rpy) if massive else None
        child = new_link(inertial)
        joints.append(dict(name=new_joint_name("fixed"), type="fixed", parent=parent,
                           child=child, origin=_random_origin(rng), axis=None, limit=None,
                           dynamics=None, mimic=None))
        return child

    root = "base_link"
    root_inertial = _random_inertial(rng, inertial_rpy) if rng.random() < 0.5 else None
    links.append(dict(name=root, inertial=root_inertial))
    if fixed_links and rng.random() < 0.4:
        add_fixed(root, massive=rng.random() < 0.7)  # immovable: merged into the world

    movable_children = []  # child link of each movable joint, in creation order
    tip = root
    types = [str(rng.choice(joint_types)) for _ in range(n_joints)]
    for k in range(n_joints):
        if not tree or k == 0:
            parent = tip
        elif tree and n_joints >= 3 and k == max(2, n_joints // 2):
            parent = root  # guarantee a second branch from the root
        elif rng.random() < 0.55:
            parent = tip
        else:
            parent = links[int(rng.integers(len(links)))]["name"]
        if fixed_links and rng.random() < fixed_prob:
            parent = add_fixed(parent, massive=rng.random() < 0.6)
        has_inertial = not (massless_links and rng.random() < 0.2)
        child = new_link(_random_inertial(rng, inertial_rpy) if has_inertial else None)
        jtype = types[k]
        if jtype == "revolute":
            lo, hi = -rng.uniform(0.5, 3.0), rng.uniform(0.5, 3.0)
            limit = dict(effort=rng.uniform(5, 300), velocity=rng.uniform(0.5, 5),
                         lower=lo, upper=hi)
        elif jtype == "prismatic":
            lo, hi = -rng.uniform(0.05, 0.5), rng.uniform(0.05, 0.5)
            limit = dict(effort=rng.uniform(50, 1000), velocity=rng.uniform(0.1, 2),
                         lower=lo, upper=hi)
        else:
            limit = dict(effort=rng.uniform(5, 300), velocity=rng.uniform(0.5, 5))
        dynamics = None
        if rng.random() < 0.7:
            dynamics = dict(damping=rng.uniform(0, 2), friction=rng.uniform(0, 1))
        joints.append(dict(name=new_joint_name(jtype[:4]), type=jtype, parent=parent,
                           child=child, origin=_random_origin(rng), axis=_random_axis(rng),
                           limit=limit, dynamics=dynamics, mimic=None))
        movable_children.append(child)
        tip = child
        if fixed_links and rng.random() < fixed_prob:
            fx = add_fixed(child, massive=rng.random() < 0.6)
            if rng.random() < 0.5:
                tip = fx  # the chain continues from the fixed link

    movable = [j for j in joints if j["type"] in MOVABLE]

    # Mimic joints: master is an earlier non-mimic joint of the same (revolute/prismatic) type.
    if mimic and n_joints >= 2:
        n_mimic = 0
        for idx in range(1, len(movable)):
            j = movable[idx]
            want = rng.random() < 0.3 or (idx == len(movable) - 1 and n_mimic == 0)
            if not want:
                continue
            if j["type"] == "continuous" or (n_mimic == 0 and idx == len(movable) - 1):
                # Pick a type we can mimic from the earlier masters.
                kinds = [m["type"] for m in movable[:idx]
                         if m["mimic"] is None and m["type"] in ("revolute", "prismatic")]
                if not kinds:
                    continue
                if j["type"] not in kinds:
                    j["type"] = kinds[0]
                    lo, hi = ((-2.0, 2.0) if j["type"] == "revolute" else (-0.3, 0.3))
                    j["limit"] = dict(effort=100.0, velocity=2.0, lower=lo, upper=hi)
            masters = [m for m in movable[:idx] if m["mimic"] is None and m["type"] == j["type"]]
            if not masters:
                continue
            master = masters[int(rng.integers(len(masters)))]
            mult = rng.uniform(0.3, 2.0) * rng.choice([-1.0, 1.0])
            span = 0.5 if j["type"] == "revolute" else 0.05
            offset = rng.uniform(-span, span)
            if rng.random() < 0.15:
                offset = None  # attribute omitted: default 0
            j["mimic"] = dict(joint=master["name"], multiplier=mult, offset=offset)
            n_mimic += 1

    # Well-posedness: every movable joint's body must carry mass, or be a massless
    # intermediate body followed by a massive body on a non-parallel axis.
    by_name = {lk["name"]: lk for lk in links}
    children_of = {}
    for j in joints:
        children_of.setdefault(j["parent"], []).append(j)

    def body_group(link):
        """Links rigidly attached to `link` (via fixed joints) with their rotation from `link`."""
        out, stack = [], [(link, np.eye(3))]
        while stack:
            name, R = stack.pop()
            out.append((name, R))
            for j in children_of.get(name, []):
                if j["type"] == "fixed":
                    stack.append((j["child"], R @ _origin_R(j["origin"])))
        return out

    def body_mass(link):
        return sum(by_name[n]["inertial"]["mass"] for n, _ in body_group(link)
                   if by_name[n]["inertial"] is not None)

    for j in reversed(movable):
        child = j["child"]
        if body_mass(child) > 0.0:
            continue
        ok = False
        axis = _axis_vec(j["axis"])
        for name, R in body_group(child):
            for c in children_of.get(name, []):
                if c["type"] not in MOVABLE or body_mass(c["child"]) <= 0.0:
                    continue
                a2 = R @ _origin_R(c["origin"]) @ _axis_vec(c["axis"])
                if np.linalg.norm(np.cross(axis, a2)) > 0.5:
                    ok = True
        if not (ok and rng.random() < 0.7):
            by_name[child]["inertial"] = _random_inertial(rng, inertial_rpy)

    # ---- XML ----
    def link_xml(lk):
        ine = lk["inertial"]
        if ine is None:
            return f'  <link name="{lk["name"]}"/>'
        I = ine["inertia"]
        s = [f'  <link name="{lk["name"]}">', "    <inertial>"]
        if not ine["omit_origin"]:
            s.append(f'      <origin xyz="{_vec(ine["com"])}" rpy="{_vec(ine["rpy"])}"/>')
        s.append(f'      <mass value="{_f(ine["mass"])}"/>')
        s.append(f'      <inertia ixx="{_f(I[0, 0])}" ixy="{_f(I[0, 1])}" ixz="{_f(I[0, 2])}" '
                 f'iyy="{_f(I[1, 1])}" iyz="{_f(I[1, 2])}" izz="{_f(I[2, 2])}"/>')
        s += ["    </inertial>", "  </link>"]
        return "\n".join(s)

    def joint_xml(j):
        s = [f'  <joint name="{j["name"]}" type="{j["type"]}">',
             f'    <parent link="{j["parent"]}"/>', f'    <child link="{j["child"]}"/>']
        if j["origin"] is not None:
            o = j["origin"]
            s.append(f'    <origin xyz="{_vec(o["xyz"])}" rpy="{_vec(o["rpy"])}"/>')
        if j["type"] != "fixed" and j["axis"] is not None:
            s.append(f'    <axis xyz="{_vec(j["axis"])}"/>')
        lim = j["limit"]
        if lim is not None:
            ev = f'effort="{_f(lim["effort"])}" velocity="{_f(lim["velocity"])}"'
            if "lower" in lim:
                lu = f'lower="{_f(lim["lower"])}" upper="{_f(lim["upper"])}"'
                s.append(f'    <limit {ev} {lu}/>')
            else:
                s.append(f'    <limit {ev}/>')
        if j["dynamics"] is not None:
            s.append(f'    <dynamics damping="{_f(j["dynamics"]["damping"])}" '
                     f'friction="{_f(j["dynamics"]["friction"])}"/>')
        if j["mimic"] is not None:
            m = j["mimic"]
            off = "" if m["offset"] is None else f' offset="{_f(m["offset"])}"'
            s.append(f'    <mimic joint="{m["joint"]}" multiplier="{_f(m["multiplier"])}"{off}/>')
        s.append("  </joint>")
        return "\n".join(s)

    elements = [link_xml(lk) for lk in links] + [joint_xml(j) for j in joints]
    if rng.random() < 0.3:
        order = rng.permutation(len(elements))
        elements = [elements[i] for i in order]
    return ('<?xml version="1.0"?>\n'
            f'<robot name="random_{int(seed)}_{int(n_joints)}">\n'
            + "\n".join(elements) + "\n</robot>\n")


# Representative cases shared across the test suite: name -> random_urdf kwargs.
NAMED_CASES = {
    "chain1": dict(seed=1, n_joints=1),
    "chain2": dict(seed=2, n_joints=2, joint_types=("revolute",)),
    "chain7": dict(seed=7, n_joints=7),
    "chain30": dict(seed=30, n_joints=30),
    "tree12": dict(seed=12, n_joints=12, tree=True),
    "tree20_mimic": dict(seed=20, n_joints=20, tree=True, mimic=True),
    "mixed_types": dict(seed=5, n_joints=10, tree=True,
                        joint_types=("revolute", "continuous", "prismatic")),
    "fixed_heavy": dict(seed=3, n_joints=6, fixed_links=True, fixed_prob=0.9),
    "no_fixed": dict(seed=8, n_joints=6, fixed_links=False, massless_links=False),
    "no_inertial_rpy": dict(seed=9, n_joints=6, inertial_rpy=False),
    "mimic": dict(seed=11, n_joints=8, mimic=True, joint_types=("revolute", "prismatic")),
    "prismatic_only": dict(seed=4, n_joints=5, joint_types=("prismatic",)),
    "continuous_only": dict(seed=6, n_joints=5, joint_types=("continuous",)),
}


def named_urdf(name):
    """XML of one of NAMED_CASES."""
    return random_urdf(**NAMED_CASES[name])


def with_payload(xml, link, mass, com, inertia):
    """The URDF with a rigid payload fixed to `link` (what Model.set_payload adds), so that an
    independent parser sees the same robot. inertia: (ixx, ixy, ixz, iyy, iyz, izz) about the CoM."""
    ixx, ixy, ixz, iyy, iyz, izz = inertia
    return xml.replace('</robot>', f'''
  <link name="test_payload"><inertial><origin xyz="{com[0]} {com[1]} {com[2]}"/><mass value="{mass}"/>
    <inertia ixx="{ixx}" ixy="{ixy}" ixz="{ixz}" iyy="{iyy}" iyz="{iyz}" izz="{izz}"/></inertial></link>
  <joint name="test_payload_joint" type="fixed"><parent link="{link}"/><child link="test_payload"/></joint>
</robot>''')
