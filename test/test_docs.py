"""The documentation says what the code does: the README's library example runs as pasted and
prints what its comment says, every node parameter is documented in docs/node.md, the README's
demo table has the columns the demo prints, and every relative link points to a file."""
import os
import re
import subprocess
import sys

from lie_dynamics.ros.core.params import PARAMS
from lie_dynamics.sim.demo import scenarios

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
DOCS = ('README.md', 'docs/node.md', 'docs/library.md', 'docs/architecture.md', 'docs/benchmarks.md')


def _read(name):
    with open(os.path.join(ROOT, name), encoding='utf-8') as fh:
        return fh.read()


def test_readme_library_example_runs_as_pasted(tmp_path):
    readme = _read('README.md')
    code = re.search(r'```python\n(.*?)```', readme, re.S).group(1)
    assert re.search(r'^q = ', code, re.M) and re.search(r'^qd = ', code, re.M) and re.search(r'^qdd = ', code, re.M)
    # run from another folder, as a user would paste it
    r = subprocess.run([sys.executable, '-W', 'error', '-c', code], cwd=tmp_path, capture_output=True, text=True,
                       timeout=120)
    assert r.returncode == 0, r.stderr
    promised = re.search(r'^print\(np\.round\(tau, 3\)\.tolist\(\)\)\s+# (\[.*\])$', code, re.M).group(1)
    assert r.stdout.splitlines()[-1] == promised, (r.stdout, promised)


def test_every_node_parameter_is_documented():
    node = _read('docs/node.md')
    missing = [p.name for p in PARAMS if f'`{p.name}`' not in node]
    assert not missing, missing


def test_readme_demo_table_has_the_columns_the_demo_prints():
    readme = _read('README.md')
    header = next(line for line in readme.splitlines() if line.startswith('| scenario |'))
    columns = [c.strip() for c in header.strip('|').split('|')]
    demo = _read('lie_dynamics/sim/demo.py')
    printed = re.search(r"print\(f\"\\n\{'scenario':24s\} (.*?)\"\n\s+f\"(.*?)\"\)", demo, re.S)
    assert printed, 'the table header print in lie_dynamics/sim/demo.py changed: update this test and the README'
    names = ['scenario'] + re.findall(r"\{'([^']+)':>\d+s\}", printed.group(1) + printed.group(2))
    assert columns == names
    lines = readme.splitlines()
    rows = []
    for line in lines[lines.index(header) + 2:]:
        if not line.startswith('|'):
            break
        rows.append(line.split('|')[1].strip())
    assert rows == list(scenarios())   # every scenario, in the order the demo runs them


def test_relative_links_point_to_files():
    for name in DOCS:
        for target in re.findall(r'\]\(([^)#:]+)(?:#[^)]*)?\)', _read(name)):
            path = os.path.normpath(os.path.join(ROOT, os.path.dirname(name), target))
            assert os.path.exists(path), (name, target)
