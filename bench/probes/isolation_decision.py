"""What one isolation decision costs on the node's thread: contact_isolation.isolate on a weak push
(1.5x threshold) on the bundled arm's link4 whose line crosses joint 4's axis (the case of
test_contact_isolation's weak-tier test), with the default rule alone (strict_below 0), the weak
tier (strict_below 2, isolate's and the node's default) and the strict rule, beside a strong push
on the same line (3x: the default rule in every setting). Milliseconds per decision, median of
repeated calls, and the load average.

    python -m bench.probes.isolation_decision [--repeats R]
"""
import argparse
import os
import time

import numpy as np


def _case():
    import pinocchio as pin

    from lie_dynamics import default_urdf_path, load_urdf
    model = load_urdf(default_urdf_path())
    with open(default_urdf_path(), encoding='utf-8') as fh:
        pm = pin.buildModelFromXML(fh.read())
    pd = pm.createData()
    q = np.array([0.2, -0.6, 0.1, 2.0, 0.3, 1.6, 0.8])
    th = np.array([2.6] * 4 + [0.36] * 3)
    pin.computeJointJacobians(pm, pd, q)
    pin.updateFramePlacements(pm, pd)
    J4 = pin.getFrameJacobian(pm, pd, pm.getFrameId('link4'), pin.LOCAL)   # (v, w) in link4's axes
    v, w = J4[:3, 3], J4[3:, 3]
    p = np.cross(w, v) / (w @ w) + 0.03 * w / np.linalg.norm(w)   # a point on joint 4's axis
    f = np.array([1.0, 1.0, 0.0])
    r1 = J4.T @ np.concatenate([f, np.cross(p, f)])
    return model, q, th, r1 / np.max(np.abs(r1) / th)


def run(repeats=20):
    from lie_dynamics.algorithms import contact_isolation as ci
    model, q, th, unit = _case()
    rows = []
    for multiple in (1.5, 3.0):
        r = multiple * unit
        for name, kw in (('default rule (strict_below 0)', {'strict_below': 0.0}),
                         (f'weak tier (strict_below {ci.STRICT_BELOW:g}, the default)', {}),
                         ('strict rule', {'strict': True})):
            ci.isolate(model, q, r, th, **kw)
            ts = []
            for _ in range(repeats):
                t0 = time.perf_counter()
                iso = ci.isolate(model, q, r, th, **kw)
                ts.append(time.perf_counter() - t0)
            rows.append((multiple, name, float(np.median(ts)) * 1e3, iso.status, iso.link))
    print('| push | rule | ms per decision | answer |\n|---|---|---:|---|')
    for m, name, ms, status, link in rows:
        print(f'| {m:g}x threshold | {name} | {ms:.2f} | {status} {link} |')
    print(f'(load average {os.getloadavg()[0]:.1f})')
    return rows


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--repeats', type=int, default=20)
    run(ap.parse_args(argv).repeats)
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
