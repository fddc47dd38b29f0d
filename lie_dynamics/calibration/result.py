"""The calibration result: calibration.yaml, a calibrated model, and a corrected URDF.

calibration.yaml (format 1), every value with its standard deviation (null where the data do
not determine it alone) and its source ('identified', 'combination': determined only together
with other parameters, so it leans on the prior too, or 'prior': kept from the URDF):

    format: lie_dynamics calibration 1
    robot: {name: ..., joints: [controlled joints, in order], links: [every URDF link]}
    coulomb_velocity_epsilon: 0.05        # eps of the Coulomb term fc tanh(qd / eps)
    condition_number: ...                 # of the column-scaled base regressor of the data
    links:                                # per moving body, under its joint's child link; the
      link1:                              # values are the body's: fixed children included
        mass: {value: 3.9, std: 0.01, source: identified}
        com: {value: [x, y, z], std: [...], source: ...}            # m, in the link frame
        inertia: {value: [ixx, ixy, ixz, iyy, iyz, izz], ...}       # kg m^2, about the CoM
    joints:
      joint1:
        armature: {value: ..., std: ..., source: ...}               # kg m^2 (kg: prismatic)
        viscous: ...                                                # N m s/rad
        coulomb: ...                                                # N m
        offset: ...                                                 # N m: measured = true + offset

The robot block is what identifies the robot: a file whose links differ, or whose joints the
model does not control, describes another robot and is refused.
"""
import math
import os
from dataclasses import dataclass, field

import numpy as np

from ..laws import COULOMB_VELOCITY_EPSILON
from ..model.inertia import RTOL, violations
from . import regressor as creg

FORMAT = 'lie_dynamics calibration 1'
SOURCES = ('identified', 'combination', 'prior')
_INERTIA_KEYS = ('ixx', 'ixy', 'ixz', 'iyy', 'iyz', 'izz')


def physical(pi):
    """(mass, CoM (3,), inertia about the CoM as (ixx, ixy, ixz, iyy, iyz, izz)) of one body's
    parameters (m, m c, I about the body frame)."""
    m, h = pi[0], np.asarray(pi[1:4])
    c = h / m
    xx, xy, yy, xz, yz, zz = pi[4:]
    I = np.array([[xx, xy, xz], [xy, yy, yz], [xz, yz, zz]])
    Ic = I - m * (c @ c * np.eye(3) - np.outer(c, c))
    return float(m), c, np.array([Ic[0, 0], Ic[0, 1], Ic[0, 2], Ic[1, 1], Ic[1, 2], Ic[2, 2]])


def parameters_of(mass, com, inertia):
    """Inverse of `physical`: (10,) parameters of (mass, CoM, inertia about the CoM as 6 values)."""
    m, c = float(mass), np.asarray(com, dtype=float)
    xx, xy, xz, yy, yz, zz = inertia
    I = np.array([[xx, xy, xz], [xy, yy, yz], [xz, yz, zz]]) + m * (c @ c * np.eye(3) - np.outer(c, c))
    return np.array([m, *(m * c), I[0, 0], I[0, 1], I[1, 1], I[0, 2], I[1, 2], I[2, 2]])


def _flat(pi):
    m, c, i = physical(pi)
    return np.concatenate([[m], c, i])


@dataclass
class CalibrationResult:
    """A calibration: parameters in regressor.parameter_names order for the robot it names.

    robot: name; joint_names: the controlled joints; link_names: every URDF link;
    body_links: the link of each body (the values are the body's, fixed children included).
    parameters, std (NaN: not determined alone), source: per calibration parameter. eps: the
    Coulomb velocity scale. condition_number, base (regressor.BaseParameters), residual_rms:
    what the fit reported (None when loaded from a file). std_physical / covariance: optional.
    """
    robot: str
    joint_names: list
    link_names: list
    body_links: list
    parameters: np.ndarray
    std: np.ndarray
    source: list
    eps: float = COULOMB_VELOCITY_EPSILON
    condition_number: float = math.nan
    base: object = None
    residual_rms: object = None
    physical_std: dict = field(default_factory=dict)
    report: dict = field(default_factory=dict)

    @property
    def inertial(self):
        """(bodies, 10) inertial parameters."""
        return np.asarray(self.parameters[:10 * len(self.body_links)]).reshape(-1, 10)

    def _joint(self, k):
        return np.asarray(self.parameters[10 * len(self.body_links):]).reshape(-1, 4)[:, k].copy()

    armature = property(lambda self: self._joint(0), doc='(n,) armature per joint')
    viscous = property(lambda self: self._joint(1), doc='(n,) viscous friction per joint')
    coulomb = property(lambda self: self._joint(2), doc='(n,) Coulomb friction per joint')
    offset = property(lambda self: self._joint(3), doc='(n,) effort offset per joint')

    def as_dict(self):
        """The calibration.yaml content (module docstring) as plain Python values."""
        def num(x):
            return None if not np.isfinite(x) else float(x)

        def entry(values, stds, sources, vector):
            src = _worst(sources)
            if vector:
                return {'value': [float(v) for v in values], 'std': [num(s) for s in stds], 'source': src}
            return {'value': float(values[0]), 'std': num(stds[0]), 'source': src}

        links = {}
        for b, link in enumerate(self.body_links):
            sl = slice(10 * b, 10 * b + 10)
            flat = _flat(self.parameters[sl])
            src = self.source[sl]
            std = self.physical_std.get(link, _physical_std(self.parameters[sl], self.std[sl]))
            links[link] = {'mass': entry(flat[:1], std[:1], src[:1], False),
                           'com': entry(flat[1:4], std[1:4], src[:4], True),
                           'inertia': entry(flat[4:], std[4:], src, True)}
        joints = {}
        ni = 10 * len(self.body_links)
        for j, name in enumerate(self.joint_names):
            joints[name] = {t: {'value': float(self.parameters[ni + 4 * j + k]), 'std': num(self.std[ni + 4 * j + k]),
                                'source': self.source[ni + 4 * j + k]} for k, t in enumerate(creg.JOINT_TERMS)}
        return {'format': FORMAT,
                'robot': {'name': self.robot, 'joints': list(self.joint_names), 'links': list(self.link_names)},
                'coulomb_velocity_epsilon': float(self.eps),
                'condition_number': num(self.condition_number),
                'links': links, 'joints': joints}

    def save(self, path):
        """Write calibration.yaml (module docstring) to `path`; returns path."""
        import yaml   # PyYAML: imported where it is used

        text = yaml.safe_dump(self.as_dict(), sort_keys=False, default_flow_style=None, width=120)
        with open(path, 'w') as fh:
            fh.write('# lie_dynamics calibration: identified inertial parameters, friction, armature and effort\n'
                     '# offsets (measured effort = true effort + offset). Load it with load_calibration or\n'
                     "# the node's calibration_file parameter.\n" + text)
        return path


def _worst(sources):
    for s in ('prior', 'combination'):
        if s in sources:
            return s if all(x == s for x in sources) or s == 'combination' else 'combination'
    return 'identified'


def _physical_std(pi, std):
    """First-order std of (mass, CoM, inertia about the CoM) from the parameters' std (treated
    as independent); NaN where a parameter it depends on has none."""
    J = np.empty((10, 10))
    h = 1e-7 * max(abs(pi[0]), 1e-3)
    for k in range(10):
        d = np.zeros(10)
        d[k] = h * max(1.0, abs(pi[k]) / max(abs(pi[0]), 1e-12))
        J[:, k] = (_flat(pi + d) - _flat(pi - d)) / (2 * d[k])
    dep = np.abs(J) > 1e-12 * np.abs(J).max()
    s = np.sqrt((J ** 2) @ np.nan_to_num(std ** 2))
    s[(dep & np.isnan(std)[None, :]).any(axis=1)] = np.nan
    return s


def from_fit(model, fitted):
    """CalibrationResult of a fit.FitResult on `model`."""
    return CalibrationResult(robot=model.name, joint_names=list(model.joint_names), link_names=list(model.link_frames),
                             body_links=list(model.body_link_names), parameters=np.asarray(fitted.parameters),
                             std=np.asarray(fitted.std), source=list(fitted.source), eps=fitted.eps,
                             condition_number=fitted.base.condition_number, base=fitted.base,
                             residual_rms=fitted.residual_rms)


# ---------------------------------------------------------------------------------------------- load

def load_calibration(path):
    """CalibrationResult from calibration.yaml; ValueError naming what is malformed or invalid
    (non-finite or missing values, a mass <= 0, an inertia that is not physically valid,
    negative friction or armature, eps <= 0, an unknown source)."""
    import yaml

    try:
        with open(path) as fh:   # libyaml's safe loader where built in: a tenth of the time
            data = yaml.load(fh, Loader=getattr(yaml, 'CSafeLoader', yaml.SafeLoader))
    except yaml.YAMLError as exc:
        raise ValueError(f'{path}: not YAML: {" ".join(str(exc).split())}') from None
    where = os.fspath(path)
    if not isinstance(data, dict) or data.get('format') != FORMAT:
        raise ValueError(f"{where}: not a calibration file (no 'format: {FORMAT}')")
    robot = _get(data, 'robot', dict, where)
    name = _get(robot, 'name', str, f'{where}: robot')
    joints = _names(_get(robot, 'joints', list, f'{where}: robot'), f'{where}: robot.joints')
    links = _names(_get(robot, 'links', list, f'{where}: robot'), f'{where}: robot.links')
    eps = _number(data.get('coulomb_velocity_epsilon'), f'{where}: coulomb_velocity_epsilon')
    if eps <= 0:
        raise ValueError(f'{where}: coulomb_velocity_epsilon must be > 0, got {eps}')
    cond = data.get('condition_number')
    cond = math.nan if cond is None else _number(cond, f'{where}: condition_number')
    body = _get(data, 'links', dict, where)
    jt = _get(data, 'joints', dict, where)
    for ln in body:
        if ln not in links:
            raise ValueError(f"{where}: link '{ln}' is not among robot.links")
    for jn in jt:
        if jn not in joints:
            raise ValueError(f"{where}: joint '{jn}' is not among robot.joints")
    params, std, source, pstd = [], [], [], {}
    body_links = list(body)
    for ln in body_links:
        entry = _get(body, ln, dict, f'{where}: links')
        ctx = f"{where}: link '{ln}'"
        m, ms, msrc = _value(entry, 'mass', 1, ctx)
        c, cs, csrc = _value(entry, 'com', 3, ctx)
        i, is_, isrc = _value(entry, 'inertia', 6, ctx)
        if not m[0] > 0:
            raise ValueError(f'{ctx}: mass must be > 0, got {m[0]}')
        xx, xy, xz, yy, yz, zz = i
        I = np.array([[xx, xy, xz], [xy, yy, yz], [xz, yz, zz]])
        bad = violations(m[0], I, RTOL * max(0.5 * abs(np.trace(I)), 1e-12))
        if bad:
            raise ValueError(f'{ctx}: inertia is not physically valid: ' + '; '.join(f'{r}: {d}' for r, d in bad))
        params.append(parameters_of(m[0], c, i))
        pstd[ln] = np.concatenate([ms, cs, is_])
        std += [math.nan] * 10                  # the file holds the physical values' std (pstd)
        source += [msrc] * 4 + [isrc] * 6
    for jn in jt:
        entry = _get(jt, jn, dict, f'{where}: joints')
        ctx = f"{where}: joint '{jn}'"
        for t in creg.JOINT_TERMS:
            v, s, src = _value(entry, t, 1, ctx)
            if t != 'offset' and v[0] < 0:
                raise ValueError(f'{ctx}: {t} must be >= 0, got {v[0]}')
            params.append([v[0]])
            std.append(s[0])
            source.append(src)
    ni = 10 * len(body_links)
    flat = np.concatenate([np.ravel(p) for p in params]) if params else np.zeros(0)
    joint_part = flat[ni:].reshape(-1, 4)
    # joints the file lists, in robot.joints order: a missing one keeps no value (NaN)
    full = np.full((len(joints), 4), np.nan)
    fstd = np.full((len(joints), 4), np.nan)
    fsrc = [['prior'] * 4 for _ in joints]
    for k, jn in enumerate(jt):
        r = joints.index(jn)
        full[r] = joint_part[k]
        fstd[r] = std[ni + 4 * k: ni + 4 * k + 4]
        fsrc[r] = source[ni + 4 * k: ni + 4 * k + 4]
    return CalibrationResult(robot=name, joint_names=joints, link_names=links, body_links=body_links,
                             parameters=np.concatenate([flat[:ni], full.reshape(-1)]),
                             std=np.concatenate([np.array(std[:ni], dtype=float), fstd.reshape(-1)]),
                             source=source[:ni] + [s for row in fsrc for s in row], eps=eps,
                             condition_number=cond, physical_std=pstd)


def _get(d, key, kind, ctx):
    if key not in d:
        raise ValueError(f"{ctx}: '{key}' is missing")
    v = d[key]
    if not isinstance(v, kind):
        raise ValueError(f"{ctx}: '{key}' must be a {kind.__name__}, got {type(v).__name__}")
    return v


def _names(v, ctx):
    if not all(isinstance(x, str) for x in v) or len(set(v)) != len(v):
        raise ValueError(f'{ctx}: must be distinct names')
    return list(v)


def _number(x, ctx):
    if isinstance(x, bool) or not isinstance(x, (int, float)) or not math.isfinite(x):
        raise ValueError(f'{ctx}: must be a finite number, got {x!r}')
    return float(x)


def _value(entry, key, size, ctx):
    """(values (size,), std (size,) with NaN for null, source) of one entry."""
    e = _get(entry, key, dict, ctx)
    v = e.get('value')
    vals = [v] if size == 1 else v
    if not isinstance(vals, list) or len(vals) != size:
        raise ValueError(f'{ctx}: {key}.value must be {"a number" if size == 1 else f"{size} numbers"}, got {v!r}')
    vals = np.array([_number(x, f'{ctx}: {key}.value') for x in vals])
    s = e.get('std')
    sl = [s] if size == 1 else (s if s is not None else [None] * size)
    if not isinstance(sl, list) or len(sl) != size:
        raise ValueError(f'{ctx}: {key}.std must match its value, got {s!r}')
    stds = np.array([math.nan if x is None else _number(x, f'{ctx}: {key}.std') for x in sl])
    if np.any(stds < 0):
        raise ValueError(f'{ctx}: {key}.std must be >= 0')
    src = e.get('source')
    if src not in SOURCES:
        raise ValueError(f'{ctx}: {key}.source must be one of {", ".join(SOURCES)}, got {src!r}')
    return vals, stds, src


# ---------------------------------------------------------------------------------------------- apply

def check_robot(model, c):
    """ValueError naming what differs when calibration `c` describes another robot than `model`:
    links that differ, joints the model does not control, body links that are not the model's."""
    mine = set(model.link_frames)
    theirs = set(c.link_names)
    if mine != theirs:
        extra, missing = sorted(theirs - mine), sorted(mine - theirs)
        parts = ([f'not in the model: {", ".join(extra)}'] if extra else []) + (
            [f'not in the calibration: {", ".join(missing)}'] if missing else [])
        raise ValueError(f"the calibration describes another robot ('{c.robot}'): links " + '; '.join(parts))
    unknown = [j for j in c.joint_names if j not in model.joint_names]
    if unknown:
        raise ValueError(f'the calibration names joints the model does not control: {", ".join(unknown)}')
    bad = [ln for ln in c.body_links if ln not in model.body_link_names]
    if bad:
        raise ValueError(f'the calibration gives inertias for links that are not a moving body of the model: '
                         f'{", ".join(bad)}')


def with_calibration(model, c):
    """A copy of `model` with the calibration's inertial parameters on its bodies and its friction
    as Model.damping (viscous) and Model.friction (Coulomb), and its armature as Model.armature
    (set_armature). The effort offsets belong to the sensor and stay in the calibration.
    `c`: a CalibrationResult or the path of a calibration.yaml. ValueError when it describes
    another robot (check_robot) or holds invalid values."""
    if not isinstance(c, CalibrationResult):
        c = load_calibration(c)
    check_robot(model, c)
    pi = model.inertial_parameters().reshape(model.nb, 10).copy()
    for b, ln in enumerate(c.body_links):
        pi[model.body_link_names.index(ln)] = c.inertial[b]
    new = model.with_inertial_parameters(pi.reshape(-1), check=True)
    damping, friction = np.array(model.damping, dtype=float), np.array(model.friction, dtype=float)
    armature = np.array(model.armature, dtype=float)
    for j, name in enumerate(c.joint_names):
        k = model.joint_names.index(name)
        if np.isfinite(c.viscous[j]):
            damping[k] = c.viscous[j]
        if np.isfinite(c.coulomb[j]):
            friction[k] = c.coulomb[j]
        if np.isfinite(c.armature[j]):
            armature[k] = c.armature[j]
    new.set_armature(armature)
    damping.flags.writeable = friction.flags.writeable = False
    new.damping, new.friction = damping, friction
    new.calibration = c
    return new


# ---------------------------------------------------------------------------------------------- URDF

def rewrite_urdf(urdf_text, model, c):
    """The URDF text with the calibration written in: each calibrated body's <inertial> (mass, CoM
    as origin xyz, inertia about the CoM in link axes) and each calibrated joint's <dynamics
    damping friction>. A body's value covers the fixed links merged into it: their own
    <inertial> is kept and subtracted from the body's link where that leaves a valid inertia,
    else the body's total goes to its link and theirs are removed. Armature and offsets have no
    URDF element: they stay in calibration.yaml."""
    import xml.etree.ElementTree as ET

    from ..model.inertia import inertia_to_parameters, link_inertia, parameter_consistency

    check_robot(model, c)
    root = ET.fromstring(urdf_text)
    links = {ln.get('name'): ln for ln in root.iter('link')}
    for b, ln in enumerate(c.body_links):
        body = model.body_link_names.index(ln)
        total = c.inertial[b].copy()
        merged = [other for other, (bb, _) in model.link_frames.items()
                  if bb == body and other != ln and links[other].find('inertial') is not None]
        own = total.copy()
        for other in merged:
            T = model.link_frames[other][1]
            own -= inertia_to_parameters(link_inertia(T, _read_inertial(links[other]))[None])[0]
        if own[0] > 0 and parameter_consistency(own[None])[0][0]:
            _write_inertial(links[ln], own, ET)
        else:
            _write_inertial(links[ln], total, ET)
            for other in merged:
                links[other].remove(links[other].find('inertial'))
    for j, name in enumerate(c.joint_names):
        for jt in root.iter('joint'):
            if jt.get('name') == name:
                d = jt.find('dynamics')
                if d is None:
                    d = ET.SubElement(jt, 'dynamics')
                d.set('damping', repr(float(c.viscous[j])))
                d.set('friction', repr(float(c.coulomb[j])))
    return ET.tostring(root, encoding='unicode')


def _read_inertial(link):
    """(mass, CoM, inertia about the CoM) of a link's <inertial>, in the link frame."""
    from ..spatial import rpy_to_matrix

    el = link.find('inertial')
    o = el.find('origin')
    xyz = np.array([float(v) for v in (o.get('xyz', '0 0 0') if o is not None else '0 0 0').split()])
    rpy = np.array([float(v) for v in (o.get('rpy', '0 0 0') if o is not None else '0 0 0').split()])
    m = float(el.find('mass').get('value'))
    i = el.find('inertia')
    xx, xy, xz, yy, yz, zz = (float(i.get(k, 0.0)) for k in _INERTIA_KEYS)
    I = np.array([[xx, xy, xz], [xy, yy, yz], [xz, yz, zz]])
    R = rpy_to_matrix(rpy)
    return m, xyz, R @ I @ R.T


def _write_inertial(link, pi, ET):
    m, com, inertia = physical(pi)
    old = link.find('inertial')
    if old is not None:
        link.remove(old)
    el = ET.SubElement(link, 'inertial')
    ET.SubElement(el, 'origin', xyz=' '.join(repr(float(v)) for v in com), rpy='0 0 0')
    ET.SubElement(el, 'mass', value=repr(m))
    ET.SubElement(el, 'inertia', **{k: repr(float(v)) for k, v in zip(_INERTIA_KEYS, inertia)})

