"""Sanity checks of the test fixtures: the random URDF generator, the Pinocchio oracle and
the bundled arm. If these fail, the comparison tests against the oracle mean nothing."""

import io
import math
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest
import yourdfpy

from oracle import Oracle, default_controlled, parse_joints, tree_order
from robots import NAMED_CASES, named_urdf, random_urdf, rpy_to_matrix

ROOT = Path(__file__).resolve().parent.parent
ARM7 = ROOT / "config" / "arm7.urdf"
CASES = sorted(NAMED_CASES)
MIMIC_CASES = [c for c in CASES if NAMED_CASES[c].get("mimic")]


def _yourdfpy(xml):
    return yourdfpy.URDF.load(io.BytesIO(xml.encode()), build_scene_graph=False, load_meshes=False,
                              build_collision_scene_graph=False, load_collision_meshes=False)


def _state(rng, n, scale=1.0):
    q = rng.uniform(-1.5, 1.5, n) * scale
    return q, rng.normal(size=n) * scale, rng.normal(size=n) * scale


@pytest.fixture(scope="module")
def oracles():
    return {c: Oracle(named_urdf(c)) for c in CASES}


# ---------------------------------------------------------------- generator ----

@pytest.mark.parametrize("case", CASES)
def test_case_loads_everywhere(case):
    xml = named_urdf(case)
    assert xml == named_urdf(case), "generator is not deterministic"
    info = parse_joints(xml)
    movable = [j for j in info if j["type"] in ("revolute", "continuous", "prismatic")]
    assert len(movable) == NAMED_CASES[case]["n_joints"]
    model = pin.buildModelFromXML(xml)
    assert model.nv == len(movable)
    assert sorted(model.names[1:]) == sorted(j["name"] for j in movable)
    robot = _yourdfpy(xml)
    assert sorted(robot.actuated_joint_names) == sorted(default_controlled(xml))
    assert len(robot.robot.links) == len(ET.fromstring(xml).findall("link"))


def _inertials(xml):
    for link in ET.fromstring(xml).findall("link"):
        ine = link.find("inertial")
        if ine is None:
            continue
        a = {k: float(v) for k, v in ine.find("inertia").attrib.items()}
        I = np.array([[a["ixx"], a["ixy"], a["ixz"]], [a["ixy"], a["iyy"], a["iyz"]],
                      [a["ixz"], a["iyz"], a["izz"]]])
        yield link.get("name"), float(ine.find("mass").get("value")), I


@pytest.mark.parametrize("seed", range(40))
def test_generator_validity(seed):
    """Valid inertias, limits on every movable joint, sane mimic, SPD mass matrix, 1..30 joints."""
    n = 1 + (seed * 7) % 30
    xml = random_urdf(seed, n, tree=seed % 2 == 1, mimic=seed % 3 == 0)
    for name, m, I in _inertials(xml):
        ev = np.linalg.eigvalsh(I)
        assert m > 0 and ev[0] > 0, name
        assert ev[0] + ev[1] >= ev[2] * (1 + 1e-9), name
    root = ET.fromstring(xml)
    types = {j.get("name"): j.get("type") for j in root.findall("joint")}
    for j in root.findall("joint"):
        if j.get("type") == "fixed":
            continue
        lim = j.find("limit")
        assert lim is not None and float(lim.get("effort")) > 0 and float(lim.get("velocity")) > 0
        if j.get("type") != "continuous":
            assert float(lim.get("lower")) < float(lim.get("upper"))
        ax = j.find("axis")
        if ax is not None:
            assert abs(np.linalg.norm([float(x) for x in ax.get("xyz").split()]) - 1) < 1e-12
        mm = j.find("mimic")
        if mm is not None:
            master = mm.get("joint")
            assert types[master] == j.get("type") and j.get("type") in ("revolute", "prismatic")
            assert root.find(f"joint[@name='{master}']/mimic") is None
            assert 0.0 < abs(float(mm.get("multiplier"))) <= 2.0
    o = Oracle(xml)
    rng = np.random.default_rng(seed)
    for _ in range(3):
        assert np.linalg.eigvalsh(o.crba(rng.uniform(-2, 2, o.n)))[0] > 1e-9


def test_generator_covers_features():
    """The named cases (plus a few seeds) really contain the tricky features."""
    xmls = [named_urdf(c) for c in CASES]
    xmls += [random_urdf(s, 12, tree=True, mimic=True) for s in range(5)]
    text = "".join(xmls)
    assert 'type="continuous"' in text and 'type="prismatic"' in text and "<mimic" in text
    found = dict(massive_fixed=False, massless_link=False, inertial_rpy=False, branches=False,
                 order_differs=False)
    for xml in xmls:
        root = ET.fromstring(xml)
        inert = {lk.get("name"): lk.find("inertial") is not None for lk in root.findall("link")}
        parents = {}
        for j in root.findall("joint"):
            parents.setdefault(j.find("parent").get("link"), []).append(j)
            if j.get("type") == "fixed" and inert[j.find("child").get("link")]:
                found["massive_fixed"] = True
        found["massless_link"] |= not all(inert.values())
        found["branches"] |= any(len(v) > 1 for v in parents.values())
        for o in root.findall("link/inertial/origin"):
            rpy = o.get("rpy")
            if rpy and any(float(x) != 0 for x in rpy.split()):
                found["inertial_rpy"] = True
        names = list(pin.buildModelFromXML(xml).names[1:])
        found["order_differs"] |= names != [n for n in tree_order(xml) if n in names]
    assert all(found.values()), found


# ---------------------------------------------------------------- oracle -------

@pytest.mark.parametrize("case", CASES)
def test_oracle_consistency(case, oracles):
    o = oracles[case]
    rng = np.random.default_rng(1)
    params = o.dynamic_parameters()
    for _ in range(4):
        q, qd, qdd = _state(rng, o.n)
        M = o.crba(q)
        assert np.allclose(M, M.T, atol=1e-12)
        assert np.linalg.eigvalsh(M)[0] > 0
        # kinetic energy of the full model at the mapped velocity
        assert math.isclose(0.5 * qd @ M @ qd, o.kinetic_energy(q, qd), rel_tol=1e-9)
        tau = o.rnea(q, qd, qdd)
        g = o.gravity(q)
        assert np.allclose(o.rnea(q, np.zeros(o.n), np.zeros(o.n)), g, atol=1e-9)
        h = o.rnea(q, qd, np.zeros(o.n))
        assert np.allclose(h, o.nonlinear(q, qd), atol=1e-9)
        assert np.allclose(tau, M @ qdd + h, atol=1e-9)
        assert np.allclose(o.coriolis_matrix(q, qd) @ qd + g, h, atol=1e-9)
        assert np.allclose(o.aba(q, qd, tau), qdd, atol=1e-7 * (1 + np.abs(qdd).max()))
        assert np.allclose(o.regressor(q, qd, qdd) @ params, tau, atol=1e-8)


@pytest.mark.parametrize("case", ["chain7", "mixed_types", "continuous_only", "mimic",
                                  "tree20_mimic"])
def test_oracle_energy_and_derivatives(case, oracles):
    """Checks against independent quantities in our coordinates (catch a wrong E or q map):
    gravity = dV/dq, power balance d(T+V)/dt = qd . tau, and RNEA derivatives by differences."""
    o = oracles[case]
    rng = np.random.default_rng(2)
    q, qd, qdd = _state(rng, o.n)
    eps = 1e-6
    I = np.eye(o.n)
    def diff(f):
        return np.array([(f(eps * e) - f(-eps * e)) / (2 * eps) for e in I]).T

    dV = diff(lambda d: o.potential_energy(q + d))
    assert np.allclose(dV, o.gravity(q), atol=1e-6)

    def energy(t):
        qt, qdt = q + qd * t + 0.5 * qdd * t * t, qd + qdd * t
        return o.kinetic_energy(qt, qdt) + o.potential_energy(qt)

    h = 1e-5
    power = (energy(h) - energy(-h)) / (2 * h)
    assert math.isclose(power, qd @ o.rnea(q, qd, qdd), rel_tol=1e-5, abs_tol=1e-6)

    dq, dqd = o.rnea_derivatives(q, qd, qdd)
    fq = diff(lambda d: o.rnea(q + d, qd, qdd))
    fqd = diff(lambda d: o.rnea(q, qd + d, qdd))
    assert np.allclose(dq, fq, atol=1e-5 * (1 + np.abs(fq).max()))
    assert np.allclose(dqd, fqd, atol=1e-5 * (1 + np.abs(fqd).max()))


@pytest.mark.parametrize("case", MIMIC_CASES)
def test_oracle_mimic_mapping(case, oracles):
    """Mimic joints follow multiplier*q_master + offset in the Pinocchio configuration, and the
    projected torque equals E^T tau_full (master collects multiplier * tau_mimic)."""
    o = oracles[case]
    xml = named_urdf(case)
    mimics = [j for j in parse_joints(xml) if j["mimic"] is not None]
    assert mimics and o.has_mimic
    rng = np.random.default_rng(3)
    q, qd, qdd = _state(rng, o.n)
    qp = o.pin_q(q)
    model = o.model
    for j in mimics:
        jm = model.joints[model.getJointId(j["name"])]
        k = o.joint_names.index(j["mimic"]["joint"])
        expect = j["mimic"]["multiplier"] * q[k] + j["mimic"]["offset"]
        assert math.isclose(qp[jm.idx_q], expect, abs_tol=1e-12)
    tau_full = pin.rnea(model, o.data, qp, o.E @ qd, o.E @ qdd)
    tau = o.rnea(q, qd, qdd).copy()

    def iv(name):
        return model.joints[model.getJointId(name)].idx_v

    for j in mimics:
        k = o.joint_names.index(j["mimic"]["joint"])
        tau[k] -= j["mimic"]["multiplier"] * tau_full[iv(j["name"])]
    for k, n in enumerate(o.joint_names):
        assert math.isclose(tau[k], tau_full[iv(n)], abs_tol=1e-9)


@pytest.mark.parametrize("case", ["chain7", "tree12", "mixed_types", "mimic", "tree20_mimic",
                                  "fixed_heavy"])
def test_oracle_locked_vs_reduced(case):
    """Locking joints in the full model == Pinocchio's buildReducedModel, and a locked joint
    at value v behaves as a controlled joint at v with zero velocity/acceleration."""
    xml = named_urdf(case)
    full = Oracle(xml)
    rng = np.random.default_rng(4)
    names = full.joint_names
    lock = [n for n in names if rng.random() < 0.4] or [names[0]]
    if len(lock) == len(names):
        lock = lock[1:]
    locked = {n: float(rng.uniform(-1, 1)) for n in lock}
    keep = [n for n in names if n not in locked][::-1]  # also a different order
    a, b = Oracle(xml, joints=keep, locked=locked), Oracle.reduced(xml, joints=keep, locked=locked)
    assert b.model.nv < full.model.nv
    for _ in range(3):
        q, qd, qdd = _state(rng, len(keep))
        for f, args in (("rnea", (q, qd, qdd)), ("gravity", (q,)), ("crba", (q,)),
                        ("coriolis_matrix", (q, qd)), ("aba", (q, qd, qdd))):
            assert np.allclose(getattr(a, f)(*args), getattr(b, f)(*args), atol=1e-8), f
        assert np.allclose(a.regressor(q, qd, qdd) @ a.dynamic_parameters(),
                           b.regressor(q, qd, qdd) @ b.dynamic_parameters(), atol=1e-8)
        qf, qdf, qddf = np.zeros(len(names)), np.zeros(len(names)), np.zeros(len(names))
        for k, n in enumerate(names):
            if n in locked:
                qf[k] = locked[n]
            else:
                i = keep.index(n)
                qf[k], qdf[k], qddf[k] = q[i], qd[i], qdd[i]
        idx = [names.index(n) for n in keep]
        assert np.allclose(full.rnea(qf, qdf, qddf)[idx], a.rnea(q, qd, qdd), atol=1e-9)
        assert np.allclose(full.crba(qf)[np.ix_(idx, idx)], a.crba(q), atol=1e-12)


def test_oracle_order_and_gravity_vector():
    xml = named_urdf("tree12")
    o = Oracle(xml)
    assert o.joint_names == default_controlled(xml)
    perm = np.random.default_rng(5).permutation(o.n)
    p = Oracle(xml, joints=[o.joint_names[i] for i in perm], gravity=(0.0, 0.0, -9.81))
    q, qd, qdd = _state(np.random.default_rng(6), o.n)
    assert np.allclose(p.rnea(q[perm], qd[perm], qdd[perm]), o.rnea(q, qd, qdd)[perm], atol=1e-10)
    assert np.allclose(p.crba(q[perm]), o.crba(q)[np.ix_(perm, perm)], atol=1e-12)
    # gravity is linear in the gravity vector; zero gravity gives zero
    g2 = Oracle(xml, gravity=(1.0, -2.0, 3.0)).gravity(q)
    gx, gy, gz = (Oracle(xml, gravity=tuple(e)).gravity(q) for e in np.eye(3))
    assert np.allclose(g2, gx - 2 * gy + 3 * gz, atol=1e-10)
    assert np.allclose(Oracle(xml, gravity=(0, 0, 0)).gravity(q), 0.0, atol=1e-14)
    with pytest.raises(ValueError):
        Oracle(xml, joints=["no_such_joint"])


def test_oracle_continuous_is_angle():
    """A continuous joint is a plain angle in our q: q and q + 2 pi give the same dynamics."""
    o = Oracle(named_urdf("continuous_only"))
    q, qd, qdd = _state(np.random.default_rng(7), o.n)
    assert o.model.nq == 2 * o.n and o.model.nv == o.n
    assert np.allclose(o.rnea(q + 2 * np.pi, qd, qdd), o.rnea(q, qd, qdd), atol=1e-9)
    assert not np.allclose(o.rnea(q + 1.0, qd, qdd), o.rnea(q, qd, qdd), atol=1e-3)


# ---------------------------------------------------------------- arm7 ---------

def test_arm7_urdf():
    xml = ARM7.read_text()
    assert "<mesh" not in xml and "filename" not in xml
    root = ET.fromstring(xml)
    assert root.get("name") == "lie_arm7"
    data_copy = ROOT / "lie_dynamics" / "data" / "arm7.urdf"
    assert data_copy.read_text() == xml
    joints = {j.get("name"): j for j in root.findall("joint")}
    movable = [n for n in tree_order(xml) if joints[n].get("type") != "fixed"]
    assert movable == [f"joint{i}" for i in range(1, 8)]
    assert sorted(_yourdfpy(xml).actuated_joint_names) == movable
    axes_world = set()
    for n in movable:
        j = joints[n]
        assert j.get("type") == "revolute"
        lim = j.find("limit")
        assert {"effort", "velocity", "lower", "upper"} <= set(lim.attrib)
        dyn = j.find("dynamics")
        assert dyn is not None and {"damping", "friction"} <= set(dyn.attrib)
        axes_world.add(j.find("axis").get("xyz"))
    assert len(axes_world) > 1, "axes should not all be written along z"
    links = {lk.get("name"): lk for lk in root.findall("link")}
    for name in ["link%d" % i for i in range(1, 8)] + ["hand"]:
        org = links[name].find("inertial/origin")
        assert any(float(x) for x in org.get("xyz").split()), name
    assert any(any(float(x) for x in links[n].find("inertial/origin").get("rpy").split())
               for n in links if links[n].find("inertial") is not None)
    assert links["flange"].find("inertial") is None
    assert joints["flange"].get("type") == "fixed"
    assert joints["flange"].find("child").get("link") == "flange"
    hand_in = links["hand"].find("inertial")
    assert 0.5 < float(hand_in.find("mass").get("value")) < 1.0
    assert any(float(x) for x in hand_in.find("origin").get("rpy").split())
    for name, _m, I in _inertials(xml):
        ev = np.linalg.eigvalsh(I)
        assert ev[0] > 0 and ev[0] + ev[1] > ev[2], name

    o = Oracle(xml)
    assert o.joint_names == movable
    # the hand (a massive fixed link) is merged into the last body
    m7 = float(links["link7"].find("inertial/mass").get("value"))
    assert math.isclose(o.model.inertias[7].mass, m7 + float(hand_in.find("mass").get("value")))
    lo = np.array([float(joints[n].find("limit").get("lower")) for n in movable])
    hi = np.array([float(joints[n].find("limit").get("upper")) for n in movable])
    effort = np.array([float(joints[n].find("limit").get("effort")) for n in movable])
    assert list(effort) == [87.0] * 4 + [12.0] * 3
    rng = np.random.default_rng(8)
    worst = np.zeros(7)
    for q in rng.uniform(lo, hi, size=(1000, 7)):
        worst = np.maximum(worst, np.abs(o.gravity(q)))
    assert np.all(worst < 0.6 * effort), worst / effort
    assert worst[1] > 10.0  # the arm is not trivially light
    # q = 0: straight up, flange pointing down above the base
    T = o.frame_pose(np.zeros(7), "tool0")
    assert T[2, 3] > 0.7 and np.allclose(T[:3, 2], [0, 0, -1], atol=1e-9)


def test_rpy_helper_matches_pinocchio():
    rpy = (0.3, -1.1, 2.5)
    assert np.allclose(rpy_to_matrix(rpy), pin.rpy.rpyToMatrix(*rpy), atol=1e-14)
