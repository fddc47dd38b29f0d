"""Compare two benchmark output folders row by row: time / Pinocchio before and after a change.

    python -m bench.compare BEFORE_DIR AFTER_DIR [BEFORE_DIR AFTER_DIR ...] [--threshold 5]

Reads the core, lagrangian and robots sections (core.json, lagrangian.json, robots.json) that
`python -m bench --only core,lagrangian,robots --out DIR` writes, pairs the rows by name, and
prints each ratio to Pinocchio before and after with the change in percent. Both ratios are
measured against Pinocchio in their own run, so machine load mostly cancels; rows slower by more
than --threshold percent are marked.

Several pairs (each run back to back, before then after) give each row's median over the
pairs of its ratios and of its change: one pair on a shared machine moves single-state rows by
10-20 %, and the median of three or more pairs separates a real regression from a busy minute.
"""
import argparse
import json
import os
import statistics
import sys


def rows(folder):
    """{row label: time / Pinocchio} of every section present in `folder`."""
    out = {}

    def load(name):
        path = os.path.join(folder, f'{name}.json')
        if not os.path.isfile(path):
            return None
        with open(path, encoding='utf-8') as fh:
            return json.load(fh)

    core = load('core')
    for r in (core or {}).get('rows', []):
        if r['impl'] == 'lie_dynamics':
            out[f"core: {r['op']}, N = {r['N']}"] = r['ratio_to_pinocchio']
    lag = load('lagrangian')
    for r in ((lag or {}).get('arm') or {}).get('rows', []):
        out[f"lagrangian: {r['name']}, one state"] = r['single_ratio']
        out[f"lagrangian: {r['name']}, batch"] = r['batch_ratio']
    for r in (load('robots') or {}).get('rows', []):
        out[f"robots: {r['robot']}, {r['op']}"] = r['ratio_median']
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(prog='python -m bench.compare', description=__doc__.split('\n')[0])
    ap.add_argument('folders', nargs='+', metavar='BEFORE AFTER', help='pairs of output folders')
    ap.add_argument('--threshold', type=float, default=5.0, help='mark rows slower by more than this, %%')
    args = ap.parse_args(argv)
    if len(args.folders) % 2:
        ap.error('give the folders in pairs: BEFORE AFTER [BEFORE AFTER ...]')
    runs = [rows(f) for f in args.folders]
    befores, afters = runs[0::2], runs[1::2]
    common = [k for k in befores[0] if all(k in r for r in runs)]
    if not common:
        ap.error('no benchmark rows in common (run python -m bench --only core,lagrangian,robots --out DIR)')
    pairs = len(befores)
    what = 'median of %d pairs, ' % pairs if pairs > 1 else ''
    print(f'| row | before (× Pinocchio) | after (× Pinocchio) | change ({what}%) |')
    print('|---|---:|---:|---:|')
    slower = 0
    for k in common:
        b = statistics.median(r[k] for r in befores)
        a = statistics.median(r[k] for r in afters)
        change = statistics.median(100.0 * (ra[k] / rb[k] - 1.0) for rb, ra in zip(befores, afters, strict=True))
        mark = ' **slower**' if change > args.threshold else ''
        slower += bool(mark)
        print(f'| {k} | {b:.3g} | {a:.3g} | {change:+.1f} %{mark} |')
    print(f'\n{len(common)} rows, {slower} slower by more than {args.threshold:g} %')
    return 0


if __name__ == '__main__':
    sys.exit(main())
