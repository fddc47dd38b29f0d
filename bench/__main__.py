"""All benchmarks in one command: tables (Markdown + CSV/JSON) and PNG charts in one folder.

    python -m bench [--quick] [--out DIR] [--only core,calls,lagrangian,accuracy,scaling,stability,robots,node,payload,
                     observer,contact,jacobian,compile,signals,calibration,excitation] [--docs-img DIR]
    make bench ARGS="--quick"

Sections (each writes its own files into DIR, default bench/out/):
  core        inverse dynamics and gravity against Pinocchio and Modern Robotics (bench/core.py)
  calls       one call (allocating, out=, the ufunc floor) and batches per state (threads, against a
              Pinocchio loop and rneaInParallel) on UR5, xArm7, the Talos arm and the Panda (bench/calls.py)
  lagrangian  mass matrix, Coriolis, forward dynamics, derivatives (bench/lagrangian.py)
  accuracy    speed against accuracy, every method, arm and 30-joint chain (bench/accuracy.py)
  scaling     time against number of joints, chains and trees, fitted slopes (bench/scaling.py)
  stability   where methods fail: exp/log, chain length, ill-conditioned M, FD step, energy
              drift (bench/stability.py)
  robots      real vendor robots (example-robot-data) beside Pinocchio; the locked-finger Panda
              (fingers folded) beside the fixed-finger Panda (bench/robots.py)
  node        the ROS node: trajectory effort fill against a Pinocchio loop, and joint_states ->
              effort latency in gravity and feedforward modes beside a bare echo node (real
              processes over DDS; bench/feedforward.py, bench/node_latency.py)
  payload     payload identification error against torque noise and recording length, through
              the node's recording and fit (bench/payload.py)
  observer    external-torque observer: estimate error against gain, detection delay against
              threshold, the node's cost per message with the observer beside without it
              (bench/observer.py)
  contact     contact isolation and the external wrench: random pushes on the bundled arm, Panda and
              UR5 through the observer and the node's decision logic; tool wrench; the node's cost
              with isolation beside without it (bench/contact.py)
  jacobian    frame Jacobians and J̇q̇ in the three frames beside pin.computeFrameJacobian and
              getFrameClassicalAcceleration, one state and batches (bench/jacobian.py)
  compile     native kernels: compile time of each family at first use, load time from the
              cache, call time cut into parts against one function (bench/compile.py)
  signals     calibration signals: q̇, q̈ and effort error against the low-pass cutoff, a
              dropout's length and the distance from a segment's end (bench/signals.py)
  calibration identify_dynamics: held-out torque prediction error against effort noise, recording
              length and decimation, gated at 3 % with 2 % noise; the identify_dynamics command's
              run time on a 60 s, 1 kHz recording (bench/calibration.py)
  excitation  calibration excitation: condition number of the optimised excitation against the
              random one, bundled arm and UR5 at 10, 20 and 60 s (bench/calibration_excitation.py)
--quick shortens everything (a smoke test runs it); the full run takes a few minutes.
--docs-img copies the PNG charts, palette-compressed, to DIR (docs/img: the copies docs/benchmarks.md shows).
A failing section is reported and the others still run; the exit status is then 1.
"""
import argparse
import glob
import importlib
import os
import shutil
import sys
import time
import traceback

HERE = os.path.dirname(os.path.abspath(__file__))
SECTIONS = ('core', 'calls', 'lagrangian', 'accuracy', 'scaling', 'stability', 'robots', 'node', 'payload', 'observer',
            'contact', 'jacobian', 'compile', 'signals', 'calibration', 'excitation')


def _section(module):
    """The section that is bench.<module>.run(quick=..., out=...): it prints and writes its own tables."""
    def runner(quick, out):
        importlib.import_module(f'bench.{module}').run(quick=quick, out=out)
    runner.__name__ = f'_{module}'
    return runner


def _core(quick, out):
    from bench import core
    res = core.run(quick=quick)
    core.write(res, out)


def _node(quick, out):
    from bench import feedforward, node_latency
    feedforward.run(quick=quick, out=out)
    # the round trip beside bare echo nodes under both executors, 1 and 2 kHz (prints its table)
    node_latency.run(quick=quick, out=out)


def _jacobian(quick, out):
    from bench import jacobian
    print(jacobian.run(quick=quick, out=out))


def _calibration(quick, out):
    from bench import calibration
    rows, status, ok = calibration.run(quick=quick, out=out)
    print(calibration.markdown(rows, status))
    text, _ = calibration.identify_time(repeats=1 if quick else 3)
    print(text)
    with open(os.path.join(out, 'calibration.md'), 'a', encoding='utf-8') as fh:
        fh.write('\n' + text + '\n')
    if not ok:
        raise RuntimeError(status)


def _small_copy(src, dst):
    """Copy a chart for committing: a 128-colour palette PNG is ~3x smaller and looks the same."""
    try:
        from PIL import Image
    except ImportError:
        shutil.copy(src, dst)
        return
    with Image.open(src) as im:
        im.convert('RGB').quantize(colors=128, method=Image.Quantize.MEDIANCUT,
                                   dither=Image.Dither.NONE).save(dst, optimize=True)


# section -> runner; most are bench.<module>.run (the module named beside them in the docstring)
RUNNERS = {'core': _core, 'node': _node, 'jacobian': _jacobian, 'calibration': _calibration,
           **{name: _section(module) for name, module in (
               ('calls', 'calls'), ('lagrangian', 'lagrangian'), ('accuracy', 'accuracy'), ('scaling', 'scaling'),
               ('stability', 'stability'), ('robots', 'robots'), ('payload', 'payload'), ('observer', 'observer'),
               ('contact', 'contact'), ('compile', 'compile'), ('signals', 'signals'),
               ('excitation', 'calibration_excitation'))}}
assert set(RUNNERS) == set(SECTIONS)


def main(argv=None):
    ap = argparse.ArgumentParser(prog='python -m bench', description=__doc__.split('\n')[0])
    ap.add_argument('--quick', action='store_true', help='short runs (seconds per section)')
    ap.add_argument('--out', default=os.path.join(HERE, 'out'), help='output folder (default bench/out)')
    ap.add_argument('--only', default=','.join(SECTIONS), help='comma-separated sections to run')
    ap.add_argument('--docs-img', metavar='DIR', help='also copy the PNG charts to DIR')
    args = ap.parse_args(argv)
    sections = [s.strip() for s in args.only.split(',') if s.strip()]
    unknown = [s for s in sections if s not in RUNNERS]
    if unknown:
        ap.error(f'unknown section(s) {unknown}; choose from {list(SECTIONS)}')
    os.makedirs(args.out, exist_ok=True)
    status = {}
    for name in sections:
        t0 = time.perf_counter()
        print(f'[bench] {name} ...', flush=True)
        try:
            RUNNERS[name](args.quick, args.out)
            status[name] = f'ok ({time.perf_counter() - t0:.0f} s)'
        except Exception:   # keep going: one broken section must not hide the others' results
            traceback.print_exc()
            status[name] = f'FAILED ({time.perf_counter() - t0:.0f} s)'
        print(f'[bench] {name}: {status[name]}', flush=True)
    files = sorted(os.path.basename(p) for p in glob.glob(os.path.join(args.out, '*'))
                   if p.endswith(('.md', '.csv', '.json', '.png')) and not p.endswith('index.md'))
    with open(os.path.join(args.out, 'index.md'), 'w', encoding='utf-8') as fh:
        fh.write('# Benchmark outputs\n\n' + ('Quick run (short, noisy).\n\n' if args.quick else '') +
                 ''.join(f'- {k}: {v}\n' for k, v in status.items()) + '\n' +
                 ''.join(f'- [{f}]({f})\n' for f in files))
    if args.docs_img:
        os.makedirs(args.docs_img, exist_ok=True)
        for p in glob.glob(os.path.join(args.out, '*.png')):
            _small_copy(p, os.path.join(args.docs_img, os.path.basename(p)))
    print(f'[bench] outputs in {args.out}')
    return 1 if any(v.startswith('FAILED') for v in status.values()) else 0


if __name__ == '__main__':
    sys.exit(main())
