"""Frame Jacobians and J̇q̇ beside Pinocchio: one state, and per state of a batch.

    python -m bench.jacobian [--quick] [--out DIR]

Robots: the bundled arm (tool0), the Panda controlled by its 7 arm joints (fingers locked and
folded; Pinocchio's model reduced with the fingers locked; panda_hand_tcp) and the UR5 (tool0)
from example-robot-data. Peers, each the single call that goes from q to the same numbers:
  * model.jacobian(q, link, frame) beside pin.computeFrameJacobian(model, data, q, frame_id,
    reference) (forward kinematics and the frame's Jacobian in one call);
  * model.jacobian_dot_times_qd(q, qd, link, frame) beside pin.forwardKinematics(q, v, 0) then
    pin.getFrameClassicalAcceleration(frame_id, reference).vector.
Frames 'world_aligned', 'local', 'world' = LOCAL_WORLD_ALIGNED, LOCAL, WORLD. Batches: one
lie_dynamics call on (N, n), Pinocchio in a Python loop (it has no batch API). Every pair is
checked to agree before it is timed. Medians of interleaved rounds; ratio = median of
per-round ratios ours / Pinocchio (p10-p90). Ours: the native C kernels where a C compiler
works; beside them the same model with the native backend off (the Python kernels; N = 1000
batches route to numpy rows). Writes bench/out/jacobian.{md,csv,json}.
"""
import os
import sys
import warnings

import numpy as np

from bench import common
from bench.robots import PANDA_ARM, FINGERS, robot_dir

FRAMES = ('world_aligned', 'local', 'world')


def _cases():
    """(label, xml, model, Pinocchio model, link)."""
    import pinocchio as pin
    from lie_dynamics import load_urdf

    arm = common.arm_xml()
    out = [('arm7 (bundled)', load_urdf(arm), pin.buildModelFromXML(arm), 'tool0')]
    try:
        root = robot_dir()
    except RuntimeError:
        return out
    with open(os.path.join(root, 'panda_description/urdf/panda.urdf'), encoding='utf-8') as fh:
        panda = fh.read()
    full = pin.buildModelFromXML(panda)
    reduced = pin.buildReducedModel(full, [full.getJointId(j) for j in FINGERS], pin.neutral(full))
    out.append(('panda, fingers locked', load_urdf(panda, joints=PANDA_ARM), reduced, 'panda_hand_tcp'))
    with open(os.path.join(root, 'ur_description/urdf/ur5_robot.urdf'), encoding='utf-8') as fh:
        ur5 = fh.read()
    with warnings.catch_warnings():
        warnings.simplefilter('ignore')
        out.append(('ur5', load_urdf(ur5), pin.buildModelFromXML(ur5), 'tool0'))
    return out


def _pairs(model, py, pm, link, frame, q, qd):
    """{call: (ours, ours with the Python kernels, Pinocchio)} for a batch q, qd (N, n) (N = 1:
    the single-state calls)."""
    import pinocchio as pin

    pd = pm.createData()
    fid = pm.getFrameId(link)
    rf = {'world_aligned': pin.LOCAL_WORLD_ALIGNED, 'local': pin.LOCAL, 'world': pin.WORLD}[frame]
    a0 = np.zeros(model.n)
    if len(q) == 1:
        x, v = q[0], qd[0]
        return {'jacobian': (lambda: model.jacobian(x, link, frame), lambda: py.jacobian(x, link, frame),
                             lambda: pin.computeFrameJacobian(pm, pd, x, fid, rf)),
                'J̇q̇': (lambda: model.jacobian_dot_times_qd(x, v, link, frame),
                        lambda: py.jacobian_dot_times_qd(x, v, link, frame),
                        lambda: (pin.forwardKinematics(pm, pd, x, v, a0),
                                 pin.getFrameClassicalAcceleration(pm, pd, fid, rf).vector)[1])}

    def pin_jacobians():
        return [pin.computeFrameJacobian(pm, pd, x, fid, rf) for x in q]

    def pin_drifts():
        out = []
        for x, v in zip(q, qd):
            pin.forwardKinematics(pm, pd, x, v, a0)
            out.append(pin.getFrameClassicalAcceleration(pm, pd, fid, rf).vector)
        return out
    return {'jacobian': (lambda: model.jacobian(q, link, frame), lambda: py.jacobian(q, link, frame), pin_jacobians),
            'J̇q̇': (lambda: model.jacobian_dot_times_qd(q, qd, link, frame),
                    lambda: py.jacobian_dot_times_qd(q, qd, link, frame), pin_drifts)}


def run(quick=False, out=None, rounds=None):
    rounds = rounds or (3 if quick else 15)
    target = 0.002 if quick else 0.02
    batch = 100 if quick else 1000
    rows, worst = [], 0.0
    for label, model, pm, link in _cases():
        pm.gravity.linear = model.gravity_vector
        py = common.python_kernels(model)
        for N in (1, batch):
            q, qd, _ = common.random_states(model, N, seed=3)
            for frame in FRAMES if N == 1 else FRAMES[:1]:
                for call, (ours, python, peer) in _pairs(model, py, pm, link, frame, q, qd).items():
                    b = np.array(peer()).reshape(N, -1)
                    for fn in (ours, python):
                        a = np.asarray(fn()).reshape(N, -1)
                        err = float(np.max(np.abs(a - b)) / max(1.0, np.max(np.abs(b))))
                        if err > 1e-9:
                            raise AssertionError(f'{label} {call} {frame}: {err:.1e} from Pinocchio')
                        worst = max(worst, err)
                    t = common.time_interleaved({'ours': ours, 'python': python, 'pin': peer}, rounds, target,
                                                rotate=True)
                    ratio = t['ours'] / t['pin']
                    py_ratio = t['python'] / t['pin']
                    rows.append(dict(robot=label, n=model.n, call=call, frame=frame, N=N,
                                     ours_us=float(np.median(t['ours'])) / N * 1e6,
                                     pin_us=float(np.median(t['pin'])) / N * 1e6,
                                     ratio_median=float(np.median(ratio)), ratio_p10=float(np.percentile(ratio, 10)),
                                     ratio_p90=float(np.percentile(ratio, 90)),
                                     python_us=float(np.median(t['python'])) / N * 1e6,
                                     python_ratio_median=float(np.median(py_ratio)), native=native_on(model, link)))
    md = markdown(rows, rounds, worst)
    if out:
        common.write_tables(out, 'jacobian', md, dict(rows=rows, rounds=rounds, max_relative_error=worst), rows)
    return md


def native_on(model, link):
    """True when the link's Jacobian runs as a native C kernel."""
    from lie_dynamics.codegen import runtime
    from lie_dynamics.codegen.traced import jacobian as traced
    return runtime.native(model, traced.spec('jacobian', 'world_aligned', model.link_frames[link][0])) is not None


def markdown(rows, rounds, worst):
    import pinocchio as pin
    lines = ['# Frame Jacobians beside Pinocchio', '',
             f'Median of {rounds} interleaved rounds; ratio = ours / Pinocchio per round (p10-p90). Peers: '
             'pin.computeFrameJacobian; pin.forwardKinematics(q, v, 0) + getFrameClassicalAcceleration. '
             f'Batches: one call beside a Pinocchio loop. Pinocchio {pin.__version__}, numpy {np.__version__}. '
             f'Largest difference to Pinocchio (relative): {worst:.1e}. Ours: the native C kernels '
             f'(native: {all(r["native"] for r in rows)}); Python kernels: the same model with the native '
             'backend off.', '',
             '| robot | n | call | frame | N | ours µs/state | Pinocchio µs/state | ratio (p10-p90) | '
             'Python kernels µs/state | Python / Pinocchio |',
             '|---|---|---|---|---|---:|---:|---|---:|---:|']
    for r in rows:
        lines.append(f"| {r['robot']} | {r['n']} | {r['call']} | {r['frame']} | {r['N']} | {r['ours_us']:.2f} | "
                     f"{r['pin_us']:.2f} | {r['ratio_median']:.2f} ({r['ratio_p10']:.2f}-{r['ratio_p90']:.2f}) | "
                     f"{r['python_us']:.2f} | {r['python_ratio_median']:.2f} |")
    return '\n'.join(lines) + '\n'


def _run(quick, out):
    return run(quick=quick, out=out)


if __name__ == '__main__':
    sys.exit(common.section_main(None, __doc__, _run, lambda md: md))
