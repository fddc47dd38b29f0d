"""Compare two benchmark output folders row by row: time / Pinocchio before and after a change.

    python -m bench.compare BEFORE_DIR AFTER_DIR [--threshold 5]

Reads the core, lagrangian and robots sections (core.json, lagrangian.json, robots.json) that
`python -m bench --only core,lagrangian,robots --out DIR` writes, pairs the rows by name, and
prints each ratio to Pinocchio before and after with the change in percent. Both ratios are
measured against Pinocchio in their own run, so machine load mostly cancels; rows slower by more
than --threshold percent are marked.
"""
import argparse
import json
import os
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
    ap.add_argument('before')
    ap.add_argument('after')
    ap.add_argument('--threshold', type=float, default=5.0, help='mark rows slower by more than this, %%')
    args = ap.parse_args(argv)
    before, after = rows(args.before), rows(args.after)
    common = [k for k in before if k in after]
    if not common:
        ap.error('no benchmark rows in common (run python -m bench --only core,lagrangian,robots --out DIR)')
    print('| row | before (× Pinocchio) | after (× Pinocchio) | change |')
    print('|---|---:|---:|---:|')
    slower = 0
    for k in common:
        change = 100.0 * (after[k] / before[k] - 1.0)
        mark = ' **slower**' if change > args.threshold else ''
        slower += bool(mark)
        print(f'| {k} | {before[k]:.3g} | {after[k]:.3g} | {change:+.1f} %{mark} |')
    print(f'\n{len(common)} rows, {slower} slower by more than {args.threshold:g} %')
    return 0


if __name__ == '__main__':
    sys.exit(main())
