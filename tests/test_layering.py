"""The package layout's rules, checked on every import of every module in src/.

Every import counts: module level and inside functions, ``import a.b``, ``from a import b``
and relative imports. ``from pkg import name`` is an import of ``pkg.name`` where that is a
module, and of ``pkg`` otherwise (a parent package is imported implicitly by every
submodule, so it is not an edge of its own). README's "Layout" section draws the rules.
"""

from __future__ import annotations

import ast
import collections
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[1] / 'src'

#: Layers, top to bottom: a package imports only packages of lower layers (and itself).
LAYERS = (
    ('galvoscan',),
    ('calibration_tools', 'galvo_driver', 'galvoscan_view'),
    ('reconstructor', 'stripe_extractor', 'galvoscan_sim', 'galvoscan_bag'),
    ('galvoscan_common',),
)
ROS = ('rclpy', 'rosidl', 'rosbags', 'rcl_interfaces', 'lifecycle_msgs')

#: Modules allowed to import rclpy (and ROS message packages), with the reason.
RCLPY_ALLOWED = {
    'galvoscan_common.executor': 'the spin loop and run_node of every node process',
    'galvoscan_bag.ros_messages': 'turns rclpy messages into bag records for record/replay',
    'galvoscan_bag.record_node': 'the `galvoscan record` node',
    'galvoscan_bag.replay_node': 'the `galvoscan replay` node',
}


def _is_node_module(module: str) -> bool:
    return module.endswith('_node') or module.split('.')[0] == 'galvoscan'


def module_files(src: Path) -> dict[str, Path]:
    """Module name -> file, for every package under ``src/<pkg>/<pkg>/`` (no tests)."""
    out = {}
    for path in sorted(src.glob('*/*/**/*.py')):
        parts = path.relative_to(src).parts[1:]
        if 'test' in parts or parts[-1] == 'setup.py':
            continue
        name = '.'.join(parts)[:-3]
        out[name.removesuffix('.__init__')] = path
    return out


def imports_of(name: str, path: Path, modules) -> list[tuple[str, int]]:
    """``(imported name, line)`` of every import in a module, resolved to modules where known."""
    package = name if path.name == '__init__.py' else name.rpartition('.')[0]
    found = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            found += [(a.name, node.lineno) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split('.')[:len(package.split('.')) - node.level + 1]
                mod = '.'.join(base + ([node.module] if node.module else []))
            else:
                mod = node.module
            for alias in node.names:
                sub = f'{mod}.{alias.name}'
                found.append((sub if sub in modules else mod, node.lineno))
    return found


def import_graph(src: Path = SRC):
    """``{module: [(imported, line), ...]}`` and the module files."""
    modules = module_files(src)
    return {m: imports_of(m, p, modules) for m, p in modules.items()}, modules


def cycles(graph, modules) -> list[list[str]]:
    """Strongly connected components of more than one module (Tarjan)."""
    edges = {m: {t for t, _ in imps if t in modules and t != m} for m, imps in graph.items()}
    index, low, stack, on_stack, out = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in edges.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(edges):
        if v not in index:
            visit(v)
    return out


def violations(graph, modules, rule) -> list[str]:
    """``file:line imported`` for every import where ``rule(module, top_of_import)`` fails."""
    out = []
    for module, imps in sorted(graph.items()):
        for target, line in imps:
            if not rule(module, target.split('.')[0], target):
                out.append(f'{modules[module]}:{line} {module} imports {target}')
    return out


def _layer(pkg):
    for i, layer in enumerate(LAYERS):
        if pkg in layer:
            return i
    return None


def _is_ros(top):
    return top in ROS or top.startswith(ROS) or top.endswith('_msgs')


RULES = {
    'calibration_tools imports neither the simulator, nor the app, nor the driver':
        lambda m, top, t: not (m.startswith('calibration_tools')
                               and top in ('galvoscan_sim', 'galvoscan', 'galvo_driver')),
    'galvoscan_sim imports neither the model, nor calibration, nor ROS, nor bags':
        lambda m, top, t: not (m.split('.')[0] == 'galvoscan_sim' and (
            top in ('reconstructor', 'calibration_tools', 'galvoscan', 'galvo_driver',
                    'galvoscan_bag', 'stripe_extractor') or _is_ros(top))),
    'only galvoscan imports galvoscan':
        lambda m, top, t: top != 'galvoscan' or m.split('.')[0] == 'galvoscan',
    'imports run down the layers':
        lambda m, top, t: _layer(top) is None or top == m.split('.')[0]
        or _layer(top) > _layer(m.split('.')[0]),
    'rclpy only in nodes, the executor helper, bag record/replay and the app':
        lambda m, top, t: top != 'rclpy' or _is_node_module(m) or m in RCLPY_ALLOWED,
}


@pytest.fixture(scope='module')
def graph():
    return import_graph()


@pytest.mark.parametrize('rule', list(RULES))
def test_rule(graph, rule):
    bad = violations(*graph, RULES[rule])
    assert not bad, f'{rule}:\n' + '\n'.join(bad)


def test_no_import_cycles(graph):
    found = cycles(*graph)
    assert not found, 'import cycles:\n' + '\n'.join(' <-> '.join(c) for c in found)


def test_every_package_is_in_a_layer(graph):
    _, modules = graph
    assert {m.split('.')[0] for m in modules} == {p for layer in LAYERS for p in layer}


def test_the_checker_finds_what_it_must(tmp_path):
    """A fake tree with a cycle (through a function-level and a relative import), a
    forbidden import and rclpy in a library module: each is reported."""
    files = {
        'galvoscan_sim/galvoscan_sim/__init__.py': '',
        'galvoscan_sim/galvoscan_sim/a.py': 'def f():\n    from . import b\n',
        'galvoscan_sim/galvoscan_sim/b.py': 'from galvoscan_sim.a import f\n',
        'galvoscan_sim/galvoscan_sim/c.py': 'import reconstructor.model\n',
        'reconstructor/reconstructor/__init__.py': '',
        'reconstructor/reconstructor/model.py': 'def g():\n    import rclpy\n',
        'reconstructor/reconstructor/x_node.py': 'import rclpy\n',
        'reconstructor/test/test_x.py': 'import galvoscan\n',
    }
    for rel, text in files.items():
        (tmp_path / rel).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / rel).write_text(text)
    g, modules = import_graph(tmp_path)
    assert 'reconstructor.test_x' not in modules  # tests are not checked
    assert cycles(g, modules) == [['galvoscan_sim.a', 'galvoscan_sim.b']]
    sim_rule = RULES['galvoscan_sim imports neither the model, nor calibration, nor ROS, nor bags']
    assert [v.split()[-1] for v in violations(g, modules, sim_rule)] == ['reconstructor.model']
    layer_rule = RULES['imports run down the layers']
    assert len(violations(g, modules, layer_rule)) == 1
    rclpy_rule = RULES['rclpy only in nodes, the executor helper, bag record/replay and the app']
    assert [v.split()[1] for v in violations(g, modules, rclpy_rule)] == ['reconstructor.model']
    assert collections.Counter(t for _, imps in g.items() for t, _ in imps)['rclpy'] == 2
