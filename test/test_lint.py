"""The linter (ruff, configured in ruff.toml) passes on the whole repository, and the math core
imports no ROS package."""
import ast
import os
import subprocess
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
PACKAGE = os.path.join(ROOT, 'lie_dynamics')
# ROS packages (and the test oracle) the math core must not pull in
FORBIDDEN = ('rclpy', 'rosidl_runtime_py', 'pinocchio')
# The math core: every module outside ros/ and sim/, except the two `python -m` shims of ROS entry
# points kept at their documented paths; inside sim/, the simulator's physics.
ROS_PARTS = ('ros', 'sim')
ROS_SHIMS = ('dynamics_node', 'demo')
SIM_PHYSICS = ('sim.arm', 'sim.integrators')


def test_ruff_is_clean():
    r = subprocess.run([sys.executable, '-m', 'ruff', 'check', '--no-cache', '.'], cwd=ROOT, capture_output=True,
                       text=True, timeout=300)
    assert r.returncode == 0, r.stdout[-5000:] + r.stderr[-2000:]


def _module_names():
    """Dotted names (below lie_dynamics) of every module file of the package."""
    out = []
    for folder, dirs, files in os.walk(PACKAGE):
        dirs[:] = [d for d in dirs if d != '__pycache__']
        rel = os.path.relpath(folder, PACKAGE)
        prefix = '' if rel == '.' else rel.replace(os.sep, '.') + '.'
        out += [prefix + f[:-3] for f in files if f.endswith('.py')]
    return sorted(out)


def _claims_no_rclpy(name):
    """Does the module's docstring promise plain Python ('no rclpy import')?"""
    with open(os.path.join(PACKAGE, *name.split('.')) + '.py') as fh:
        doc = ast.get_docstring(ast.parse(fh.read())) or ''
    return 'no rclpy' in ' '.join(doc.split())


def _ros_free_modules():
    names = []
    for name in _module_names():
        top = name.split('.')[0]
        if (top not in ROS_PARTS and name not in ROS_SHIMS) or name in SIM_PHYSICS or _claims_no_rclpy(name):
            names.append('lie_dynamics' if name == '__init__' else
                         'lie_dynamics.' + name.removesuffix('.__init__'))
    return names


def test_math_core_imports_no_ros_package():
    """Every module of the math core, and every module whose docstring says 'no rclpy import',
    imports without a ROS package (found by walking the package: a new module is checked too)."""
    names = _ros_free_modules()
    core = [n for n in names if n.split('.')[1:2] not in (['ros'], ['sim'])]
    assert len(core) >= 30 and 'lie_dynamics.algorithms.rnea' in core and 'lie_dynamics.laws' in core, core
    assert {'lie_dynamics.ros.core.compensator', 'lie_dynamics.ros.core.params'} <= set(names)
    code = ('import importlib, sys\n'
            'for name in sys.argv[1:]:\n'
            '    importlib.import_module(name)\n'
            f'    bad = sorted({{m.split(".")[0] for m in sys.modules}} & set({FORBIDDEN!r}))\n'
            '    if bad:\n'
            '        sys.exit(f"{name} imports {bad}")\n')
    # one interpreter per module is slow (numpy each time): batch per top-level part, which still
    # names the first module that brings a ROS package in
    groups = {}
    for name in names:
        groups.setdefault('.'.join(name.split('.')[:2]), []).append(name)
    for group in groups.values():
        r = subprocess.run([sys.executable, '-c', code, *group], cwd=ROOT, capture_output=True, text=True,
                           timeout=120)
        assert r.returncode == 0, r.stdout + r.stderr


def _imports(name):
    """The lie_dynamics modules (dotted, below lie_dynamics) module `name` imports anywhere in its
    code, relative imports resolved."""
    path = os.path.join(PACKAGE, *name.split('.')) + '.py'
    with open(path) as fh:
        tree = ast.parse(fh.read())
    package = name.split('.')[:-1]
    known = {n.removesuffix('.__init__') for n in _module_names()}
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package[:len(package) - (node.level - 1)] if node.level > 1 else package
                stem = '.'.join(['lie_dynamics'] + base + ([node.module] if node.module else []))
            else:
                stem = node.module or ''
            # `from . import x` may name a module (counted) or a name in the package's __init__
            targets = [stem] + [f'{stem}.{a.name}' for a in node.names]
        else:
            continue
        out |= {t.removeprefix('lie_dynamics.') for t in targets if t.startswith('lie_dynamics.')}
    return out & known


# (modules under this prefix, what they must not import, why) - docs/architecture.md, "Layers"
LAYERS = (
    ('ros.core.', ('ros.',), ('ros.core',), 'ros/core is the bottom of the node'),
    ('codegen.', ('algorithms',), (), 'codegen lies below algorithms: every algorithm calls its runtime'),
)


def _under(target, prefixes):
    return any(target == p.rstrip('.') or target.startswith(p if p.endswith('.') else p + '.') for p in prefixes)


def test_layers_only_point_down():
    """Imports found by parsing every module, at module level or inside a function (a new module
    is checked too): ros/core imports nothing else of ros/ (loading, trajectories, features, the
    shell), codegen nothing of algorithms, the math core nothing of ros/ or sim/."""
    names = _module_names()
    bad = []
    for prefix, forbidden, allowed, why in LAYERS:
        checked = [n for n in names if n.startswith(prefix)]
        assert len(checked) >= 5, (prefix, checked)
        for name in checked:
            for t in sorted(_imports(name)):
                if _under(t, forbidden) and not _under(t, allowed):
                    bad.append(f'{name} imports {t} ({why})')
    math_core = [n for n in names if n.split('.')[0] not in ROS_PARTS and n not in ROS_SHIMS]
    assert 'algorithms.rnea' in math_core and 'laws' in math_core
    for name in math_core:
        bad += [f'{name} imports {t} (the math core knows no node)' for t in sorted(_imports(name))
                if _under(t, ROS_PARTS)]
    assert not bad, '\n'.join(bad)


def test_the_import_parser_sees_relative_imports():
    assert 'ros.core.descriptions' in _imports('ros.loading.build_process')
    assert 'ros.core.pipe' in _imports('ros.trajectories.process')
    assert 'codegen.thresholds' in _imports('codegen.traced.aba')
    assert {'ros.core', 'ros.core.watchdog'} & _imports('ros.features.gravity_source')
