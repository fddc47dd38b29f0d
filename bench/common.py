"""Shared benchmark helpers: interleaved timing, benchmark robots, errors, tables and charts.

Timing. The machine is shared and noisy, so every benchmark times its candidates in
interleaved rounds (each round runs each candidate once) and reports medians over rounds;
ratios are medians of per-round ratios, so both sides of a ratio saw the same load.

References: bench/reference.py (the same algorithms in numpy.longdouble and other dtypes);
rel_err and boundary here measure against them.
"""
import argparse
import csv
import gc
import json
import os
import time
import xml.etree.ElementTree as ET

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
EPS64 = float(np.finfo(np.float64).eps)
EPS32 = float(np.finfo(np.float32).eps)


# ------------------------------------------------------------------ timing
def calibrate(fn, target):
    """Calls per measurement so that one measurement takes about `target` seconds. The first call
    is not timed: it may build or load a kernel (a kernel cache at its size bound evicts and
    rebuilds), and a calibration on it measured one call per round."""
    fn()
    t0 = time.perf_counter()
    fn()
    dt = time.perf_counter() - t0
    number = 1
    while dt * number < target and number < 1_000_000:
        number *= 2
    return number


def time_interleaved(fns, rounds, target, rotate=False, pause_gc=False, numbers=None):
    """{key: callable} -> {key: array of seconds per call, one entry per round}.

    Every round times every callable once (interleaved), so slow phases of a shared machine
    hit all candidates alike; report medians and medians of per-round ratios. rotate: the
    order turns by one each round (no candidate always runs first); pause_gc: the cyclic
    garbage collector is off during a measurement (as timeit does); numbers: a dict that
    receives the calls per measurement.
    """
    keys = list(fns)
    calls = {k: calibrate(fns[k], target) for k in keys}
    if numbers is not None:
        numbers.update(calls)
    out = {k: np.empty(rounds) for k in keys}
    enabled = gc.isenabled()
    for r in range(rounds):
        s = r % len(keys) if rotate else 0
        for k in keys[s:] + keys[:s]:
            f, n = fns[k], calls[k]
            if pause_gc:
                gc.disable()
            try:
                t0 = time.perf_counter()
                for _ in range(n):
                    f()
                dt = time.perf_counter() - t0
            finally:
                if pause_gc and enabled:
                    gc.enable()
            out[k][r] = dt / n
    return out


def slope(ns, ts, fit_from=16):
    """Log-log slope of ts against ns over ns >= fit_from (fixed per-call costs dominate below)."""
    ns, ts = np.asarray(ns, float), np.asarray(ts, float)
    sel = (ns >= fit_from) & np.isfinite(ts) & (ts > 0)
    if sel.sum() < 2:
        return float('nan')
    return float(np.polyfit(np.log(ns[sel]), np.log(ts[sel]), 1)[0])


# ------------------------------------------------------------------ robots
def default_urdf():
    """The bundled arm (config/arm7.urdf), else the package's embedded copy."""
    path = os.path.join(ROOT, 'config', 'arm7.urdf')
    if os.path.isfile(path):
        return path
    from lie_dynamics import default_urdf_path
    return default_urdf_path()


def arm_xml():
    with open(default_urdf(), encoding='utf-8') as fh:
        return fh.read()


def robot_urdf(n, tree=False, seed=0, mass_ratio=1.0):
    """A random revolute robot with n joints (random axes, offsets, CoMs, inertias).

    tree=False: a serial chain. tree=True: a binary tree (body i hangs off body (i-1)//2, depth
    log2 n), the opposite extreme of branching. Masses and inertias fall geometrically along the
    chain so that the last body is `mass_ratio` times the first (ill-conditioned M when small).
    Joint names are zero-padded so that Pinocchio's alphabetical child order is file order.
    """
    rng = np.random.default_rng(seed)

    def f(v):
        return ' '.join(repr(float(x)) for x in np.atleast_1d(v))
    parts = [f'<robot name="{"tree" if tree else "chain"}{n}">', '<link name="l0"/>']
    for i in range(1, n + 1):
        parent = (i - 1) // 2 if tree and i > 1 else i - 1
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        xyz, rpy = rng.uniform(-0.2, 0.2, 3), rng.uniform(-1, 1, 3)
        s = mass_ratio ** ((i - 1) / max(1, n - 1))
        m = rng.uniform(0.5, 3.0)
        d = rng.uniform(0.05, 0.2, 3)
        I = m / 12 * np.array([d[1] ** 2 + d[2] ** 2, d[0] ** 2 + d[2] ** 2, d[0] ** 2 + d[1] ** 2]) * s
        c = rng.uniform(-0.1, 0.1, 3)
        parts.append(f'<joint name="j{i:03d}" type="revolute"><parent link="l{parent}"/><child link="l{i}"/>'
                     f'<origin xyz="{f(xyz)}" rpy="{f(rpy)}"/><axis xyz="{f(axis)}"/>'
                     '<limit effort="50" velocity="2" lower="-3" upper="3"/></joint>')
        parts.append(f'<link name="l{i}"><inertial><origin xyz="{f(c)}"/><mass value="{f(m * s)}"/>'
                     f'<inertia ixx="{f(I[0])}" ixy="0" ixz="0" iyy="{f(I[1])}" iyz="0" izz="{f(I[2])}"/>'
                     '</inertial></link>')
    parts.append('</robot>')
    return '\n'.join(parts)


def scale_chain_masses(xml, ratio):
    """The URDF with the mass and inertia of the k-th movable body of a serial chain scaled by
    ratio^(k/(n-1)), links welded to a body by fixed joints included (CoMs unchanged)."""
    root = ET.fromstring(xml)
    children = {}
    for j in root.findall('joint'):
        children.setdefault(j.find('parent').get('link'), []).append(j)
    links = {lk.get('name'): lk for lk in root.findall('link')}
    child_names = {j.find('child').get('link') for j in root.findall('joint')}
    base = next(name for name in links if name not in child_names)
    factor = {}

    def walk(link, k):
        for j in children.get(link, []):
            kk = k + (j.get('type') != 'fixed')
            factor[j.find('child').get('link')] = kk
            walk(j.find('child').get('link'), kk)
    walk(base, 0)
    ratio = float(ratio)
    n = max(factor.values())
    for name, k in factor.items():
        if k == 0:
            continue
        s = ratio ** ((k - 1) / max(1, n - 1))
        inertial = links[name].find('inertial')
        if inertial is None:
            continue
        mass = inertial.find('mass')
        mass.set('value', repr(float(mass.get('value')) * s))
        inertia = inertial.find('inertia')
        for key in ('ixx', 'ixy', 'ixz', 'iyy', 'iyz', 'izz'):
            if inertia.get(key) is not None:
                inertia.set(key, repr(float(inertia.get(key)) * s))
    return ET.tostring(root, encoding='unicode')


def near_coaxial_urdf(tilt):
    """A 3-joint arm whose last two joints are coaxial up to `tilt` (rad), with a massless link
    between them: both joints turn the last link about (almost) the same line, so M is
    ill-conditioned by geometry (cond ~ 1/tilt^2), not by scale; tilt = 0 makes it singular."""
    def link(name, mass):
        if mass is None:
            return f'<link name="{name}"/>'
        return (f'<link name="{name}"><inertial><origin xyz="0.1 0.02 0.05"/><mass value="{mass}"/>'
                '<inertia ixx="0.01" ixy="0" ixz="0" iyy="0.02" iyz="0" izz="0.015"/></inertial></link>')

    def joint(name, parent, child, xyz, axis):
        return (f'<joint name="{name}" type="revolute"><parent link="{parent}"/><child link="{child}"/>'
                f'<origin xyz="{xyz}"/><axis xyz="{axis}"/>'
                '<limit effort="10" velocity="1" lower="-3" upper="3"/></joint>')
    return ''.join(['<robot name="near_coaxial">', link('l0', None), joint('j1', 'l0', 'l1', '0 0 0.1', '0 1 0'),
                    link('l1', 1.0), joint('j2', 'l1', 'l2', '0 0 0.3', '0 0 1'), link('l2', None),
                    joint('j3', 'l2', 'l3', '0 0 0.2', f'{float(np.sin(tilt))!r} 0 {float(np.cos(tilt))!r}'),
                    link('l3', 1.0),
                    '</robot>'])


def python_kernels(model):
    """A copy of the model that runs the Python kernels only (the native column's peer)."""
    import copy
    from lie_dynamics.codegen import runtime
    py = copy.deepcopy(model)
    runtime.use_native(py, False)
    return py


def random_states(model, N, seed=0):
    """(q, qd, qdd) of N states, positions inside the joint limits."""
    rng = np.random.default_rng(seed)
    lo = np.where(np.isfinite(model.position_lower), model.position_lower, -np.pi)
    hi = np.where(np.isfinite(model.position_upper), model.position_upper, np.pi)
    return rng.uniform(lo, hi, (N, model.n)), rng.uniform(-1.5, 1.5, (N, model.n)), rng.uniform(-3, 3, (N, model.n))


# ------------------------------------------------------------------ Pinocchio and Modern Robotics
def pinocchio_model(xml, model):
    """(pin, model, data) from the same URDF text, with our gravity."""
    import pinocchio as pin
    pm = pin.buildModelFromXML(xml)
    pm.gravity.linear = model.gravity_vector
    if pm.nq != model.n or pm.nv != model.n:
        raise ValueError('benchmark robots need one revolute/prismatic Pinocchio joint per joint')
    return pin, pm, pm.createData()


def modern_robotics_lists(model):
    """(Mlist, Glist, Slist) of Modern Robotics for a serial chain model.

    MR puts link frame {i} at the centre of mass with G_i = diag(I_c, m 1) there, Mlist the
    home poses of {i} in {i-1} (plus an end frame), Slist the space-frame screws (w, v).
    """
    from lie_dynamics import spatial as se3
    if np.any(model.parent != np.arange(-1, model.nb - 1)) or not np.array_equal(model.E, np.eye(model.n)) \
            or np.any(model.e0 != 0):
        raise ValueError('Modern Robotics needs a serial chain without mimic or locked joints')
    T = np.eye(4)
    frames, G, S = [], [], []
    for b in range(model.nb):
        T = T @ model.M[b]                      # body frame at q = 0
        J = model.J[b]
        m = J[3, 3]
        c = np.array([J[2, 4], J[0, 5], J[1, 3]]) / m if m > 0 else np.zeros(3)  # J[:3, 3:] = m[c]
        C = T @ se3.transform(p=c)              # CoM frame, body orientation
        Ic = J[:3, :3] + m * se3.hat3(c) @ se3.hat3(c)
        G.append(np.block([[Ic, np.zeros((3, 3))], [np.zeros((3, 3)), m * np.eye(3)]]))
        S.append(se3.Ad(T) @ model.S[b])
        frames.append(C)
    Mlist = [frames[0]] + [se3.inv(frames[i - 1]) @ frames[i] for i in range(1, model.nb)] + [np.eye(4)]
    return np.array(Mlist), np.array(G), np.array(S).T


# ------------------------------------------------------------------ dtype-generic dynamics
def rel_err(x, ref, axis=None):
    """max |x - ref| / max |ref| (max norm), in float; inf when x is not finite."""
    x = np.asarray(x)
    ref = np.asarray(ref)
    if axis is None:
        if not np.all(np.isfinite(x)):
            return float('inf')
        return float(np.max(np.abs(x.astype(ref.dtype) - ref)) / max(np.max(np.abs(ref)), np.finfo(float).tiny))
    num = np.max(np.abs(x.astype(ref.dtype) - ref), axis=axis)
    den = np.maximum(np.max(np.abs(ref), axis=axis), np.finfo(float).tiny)
    out = (num / den).astype(float)
    bad = ~np.all(np.isfinite(x), axis=axis)
    out[bad] = np.inf
    return out


def boundary(xs, errs, tol):
    """Failure region on a grid: (smallest, largest) x where err > tol (or not finite), else None."""
    xs, errs = np.asarray(xs, float), np.asarray(errs, float)
    bad = ~(errs <= tol)
    if not bad.any():
        return None
    return float(xs[bad].min()), float(xs[bad].max())


def cell(row, key, fmt):
    """A table cell: row[key] formatted with fmt, or '–' where the row has no value."""
    return '–' if row.get(key) is None else format(row[key], fmt)


def write_tables(out, name, md, data, rows=None, fields=None):
    """A section's files in `out`: name.md (md), name.json (data) and, given rows (dicts),
    name.csv with columns `fields` (default: the first row's keys; other keys are left out)."""
    os.makedirs(out, exist_ok=True)
    with open(os.path.join(out, f'{name}.md'), 'w', encoding='utf-8') as fh:
        fh.write(md)
    if rows is not None:
        rows = list(rows)
        with open(os.path.join(out, f'{name}.csv'), 'w', newline='', encoding='utf-8') as fh:
            w = csv.DictWriter(fh, fieldnames=fields or list(rows[0]), extrasaction='ignore')
            w.writeheader()
            w.writerows(rows)
    with open(os.path.join(out, f'{name}.json'), 'w', encoding='utf-8') as fh:
        json.dump(data, fh, indent=1)


def write_rows(out, name, head, line, rows):
    """write_tables for a table of one line per row dict: head, then line(row) for each; the
    CSV's fields every key of the rows, in first-seen order."""
    md = head + '\n' + '\n'.join(line(r) for r in rows) + '\n'
    write_tables(out, name, md, dict(rows=rows), rows, fields=list(dict.fromkeys(k for r in rows for k in r)))


def savefig(fig, path):
    """PNG at ~100 dpi (small enough to commit copies)."""
    fig.savefig(path, dpi=100)
    import matplotlib.pyplot as plt
    plt.close(fig)


def setup_matplotlib():
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    return plt


def section_main(argv, doc, run, markdown):
    """The command line of a benchmark section: --quick, --out DIR; runs it and prints its tables."""
    ap = argparse.ArgumentParser(description=doc.split('\n')[0])
    ap.add_argument('--quick', action='store_true')
    ap.add_argument('--out', default=os.path.join(HERE, 'out'))
    args = ap.parse_args(argv)
    print(markdown(run(args.quick, args.out)))
    return 0


def rows_main(argv, doc, name, head, line, measure, robots, families='', options=()):
    """The command line of a table of one line per (robot, family) row: --robots, --families,
    --rounds, --out DIR and `options` ((flag, argparse keywords), ...); prints head, then
    measure(args) prints and returns the rows; with --out writes them (write_rows, as `name`)."""
    ap = argparse.ArgumentParser(description=doc.splitlines()[0])
    ap.add_argument('--robots', default=robots)
    ap.add_argument('--families', default=families)
    for flag, kw in options:
        ap.add_argument(flag, **kw)
    ap.add_argument('--rounds', type=int, default=7)
    ap.add_argument('--out', default=None)
    a = ap.parse_args(argv)
    a.robots, a.families = a.robots.split(','), [f for f in a.families.split(',') if f]
    print(head)
    rows = measure(a)
    if a.out:
        write_rows(a.out, name, head, line, rows)
    return 0
