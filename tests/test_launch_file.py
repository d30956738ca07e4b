"""``launch/galvoscan.launch.py`` names only nodes, executables and parameters that exist.

launch and launch_ros are not installable from PyPI, so the launch file is read with
``ast`` and never imported: every ``Node``/``LifecycleNode`` it builds must name a package
of ``src/*/package.xml``, a console script of that package's ``setup.py``, a node of
``galvoscan.bringup.NODES`` (the graph ``galvoscan run`` starts, with the same console
script), take the ``params_file`` argument as its parameters, and be a ``LifecycleNode``
exactly when its node class is a lifecycle node. The shipped parameters YAML is read by
``galvoscan run``'s own loader and given to each node exactly as both bring-ups give it
(``--ros-args --params-file``): every key must be a parameter the node declares, with the
value the file gives. Each check is also run on a broken copy, where it must complain.
"""

from __future__ import annotations

import ast
import importlib
import re
from dataclasses import dataclass, field
from pathlib import Path

import pytest
import yaml

from galvoscan import bringup

ROOT = Path(__file__).resolve().parents[1]
LAUNCH_FILE = ROOT / 'launch' / 'galvoscan.launch.py'
#: launch_ros actions that start a node process
NODE_ACTIONS = ('Node', 'LifecycleNode')
#: the launch argument every node takes its parameters from
PARAMS_ARG = 'params_file'


@dataclass
class LaunchNode:
    """One ``Node(...)``/``LifecycleNode(...)`` call of a launch file, as written."""

    action: str
    line: int
    kwargs: dict = field(default_factory=dict)   # keyword -> ast expression

    def literal(self, key):
        """The keyword's string literal, or None when it is missing or not a literal."""
        value = self.kwargs.get(key)
        return value.value if isinstance(value, ast.Constant) and \
            isinstance(value.value, str) else None


def _call_name(call: ast.Call) -> str:
    func = call.func
    return func.id if isinstance(func, ast.Name) else \
        func.attr if isinstance(func, ast.Attribute) else ''


def _module_constants(tree: ast.Module) -> dict:
    """Module-level ``NAME = <literal>`` assignments."""
    out = {}
    for stmt in tree.body:
        if isinstance(stmt, ast.Assign) and len(stmt.targets) == 1 and \
                isinstance(stmt.targets[0], ast.Name):
            try:
                out[stmt.targets[0].id] = ast.literal_eval(stmt.value)
            except ValueError:
                continue
    return out


def _is_launch_configuration(expr, name: str) -> bool:
    """``expr`` is ``LaunchConfiguration('<name>')``."""
    return isinstance(expr, ast.Call) and _call_name(expr) == 'LaunchConfiguration' and \
        len(expr.args) == 1 and isinstance(expr.args[0], ast.Constant) and \
        expr.args[0].value == name


def console_scripts(package_dir: Path) -> dict:
    """``{script: 'module:function'}`` of a package's setup.py (read with ast)."""
    tree = ast.parse((package_dir / 'setup.py').read_text())
    out = {}
    for node in ast.walk(tree):
        if isinstance(node, ast.Dict):
            for key, value in zip(node.keys, node.values, strict=True):
                if isinstance(key, ast.Constant) and key.value == 'console_scripts':
                    for entry in ast.literal_eval(value):
                        script, target = (s.strip() for s in entry.split('=', 1))
                        out[script] = target
    return out


def ros_packages(root: Path) -> dict:
    """``{package name: its directory}`` of every ``src/*/package.xml``."""
    out = {}
    for xml in sorted(root.glob('src/*/package.xml')):
        name = re.search(r'<name>\s*([\w-]+)\s*</name>', xml.read_text())
        if name:
            out[name.group(1)] = xml.parent
    return out


def read_launch_file(path: Path):
    """(tree, module constants, node calls, ``{argument: default expression}``)."""
    tree = ast.parse(path.read_text(), filename=str(path))
    nodes, arguments = [], {}
    for node in ast.walk(tree):
        if not isinstance(node, ast.Call):
            continue
        name = _call_name(node)
        if name in NODE_ACTIONS:
            nodes.append(LaunchNode(name, node.lineno, {k.arg: k.value for k in node.keywords}))
        elif name == 'DeclareLaunchArgument' and node.args and \
                isinstance(node.args[0], ast.Constant):
            arguments[node.args[0].value] = {k.arg: k.value for k in node.keywords}.get(
                'default_value')
    return tree, _module_constants(tree), sorted(nodes, key=lambda n: n.line), arguments


def _check_node(node: LaunchNode, packages: dict) -> list[str]:
    """What is wrong with one node action (empty: nothing)."""
    where = f'line {node.line}'
    package, executable, name = (node.literal(k) for k in ('package', 'executable', 'name'))
    if None in (package, executable, name):
        return [f'{where}: package, executable and name must be string literals']
    problems = []
    if package not in packages:
        problems.append(f'{where}: no package {package!r} in src/*/package.xml')
    elif executable not in console_scripts(packages[package]):
        problems.append(f'{where}: {executable!r} is not a console script of {package}')
    if name not in bringup.NODES:
        problems.append(f'{where}: node {name!r} is not one of galvoscan.bringup.NODES')
    else:
        script, target = bringup.NODES[name]
        if script != executable or target.split('.')[0] != package:
            problems.append(f'{where}: {name} runs {package}/{executable}, galvoscan run '
                            f'runs {target.split(".")[0]}/{script}')
        from rclpy.lifecycle import Node as RclpyLifecycleNode

        lifecycle = issubclass(bringup.node_class(name), RclpyLifecycleNode)
        if lifecycle != (node.action == 'LifecycleNode'):
            problems.append(f'{where}: {name} is {"a" if lifecycle else "no"} lifecycle node '
                            f'but started with {node.action}')
    params = node.kwargs.get('parameters')
    if not (isinstance(params, ast.List) and len(params.elts) == 1
            and _is_launch_configuration(params.elts[0], PARAMS_ARG)):
        problems.append(f"{where}: {name}: parameters must be [LaunchConfiguration('"
                        f"{PARAMS_ARG}')], the file galvoscan run --params takes")
    return problems


def _check_arguments(path: Path, constants: dict, arguments: dict, tree) -> list[str]:
    """The launch arguments: declared, used, and their defaults those of galvoscan run."""
    problems = []
    used = {n.args[0].value for n in ast.walk(tree) if isinstance(n, ast.Call)
            and _call_name(n) == 'LaunchConfiguration' and n.args
            and isinstance(n.args[0], ast.Constant)}
    problems += [f'LaunchConfiguration({a!r}) has no DeclareLaunchArgument'
                 for a in sorted(used - set(arguments))]
    default = arguments.get(PARAMS_ARG)
    # default_value=str(Path(__file__).with_name(NAME)): the file beside the launch file
    with_name = [n for n in ast.walk(default) if isinstance(n, ast.Call)
                 and _call_name(n) == 'with_name'] if default is not None else []
    if len(with_name) != 1 or not isinstance(with_name[0].args[0], ast.Name):
        problems.append(f'{PARAMS_ARG}: default must be Path(__file__).with_name(CONSTANT)')
    else:
        params = path.with_name(str(constants.get(with_name[0].args[0].id)))
        if not params.is_file():
            problems.append(f'{PARAMS_ARG}: default {params} does not exist')
    nodes = arguments.get('nodes')
    value = constants.get(nodes.id) if isinstance(nodes, ast.Name) else \
        nodes.value if isinstance(nodes, ast.Constant) else None
    if value != ','.join(bringup.DEFAULT_NODES):
        problems.append(f'nodes: default {value!r} is not galvoscan run\'s '
                        f'{",".join(bringup.DEFAULT_NODES)!r}')
    return problems


def _check_imports(tree) -> list[str]:
    """Names the launch file imports from this project's packages exist."""
    problems = []
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module and \
                node.module.split('.')[0] in {p.name for p in ROOT.glob('src/*')}:
            module = importlib.import_module(node.module)
            problems += [f'line {node.lineno}: {node.module} has no {a.name}'
                         for a in node.names if not hasattr(module, a.name)]
    return problems


def launch_file_problems(path: Path, root: Path = ROOT) -> list[str]:
    """Everything the launch file at ``path`` names that does not exist (empty: all fine)."""
    tree, constants, nodes, arguments = read_launch_file(path)
    problems = []
    if not any(isinstance(f, ast.FunctionDef) and f.name == 'generate_launch_description'
               for f in tree.body):
        problems.append('no generate_launch_description()')
    packages = ros_packages(root)
    for node in nodes:
        problems += _check_node(node, packages)
    names = [n.literal('name') for n in nodes]
    missing = [n for n in bringup.NODES if n not in names]
    if missing:
        problems.append(f'nodes galvoscan run can start are missing: {", ".join(missing)}')
    # the table the `nodes` argument selects from: its keys are the node names
    for dict_node in (n for n in ast.walk(tree) if isinstance(n, ast.Dict)):
        for key, value in zip(dict_node.keys, dict_node.values, strict=True):
            if isinstance(value, ast.Call) and _call_name(value) in NODE_ACTIONS:
                name = next((k.value.value for k in value.keywords if k.arg == 'name'
                             and isinstance(k.value, ast.Constant)), None)
                if not isinstance(key, ast.Constant) or key.value != name:
                    problems.append(f'line {value.lineno}: selected as '
                                    f'{ast.unparse(key) if key else "**"} but named {name!r}')
    problems += _check_arguments(path, constants, arguments, tree)
    problems += _check_imports(tree)
    return problems


def parameter_problems(params_file: Path) -> list[str]:
    """Keys of a parameters file that its nodes do not declare, or declare otherwise.

    Each node of the file is built in-process with ``--ros-args --params-file
    params_file``, the arguments both ``galvoscan run`` and launch_ros give it.
    """
    import rclpy

    params = bringup.load_params(params_file)
    problems = [f'{name}: not a node of galvoscan.bringup.NODES' for name in params
                if name not in bringup.NODES]
    ctx = rclpy.Context()
    rclpy.init(context=ctx, args=['--ros-args', '--params-file', str(params_file)])
    try:
        for name in (n for n in params if n in bringup.NODES):
            try:
                node = bringup.node_class(name)(context=ctx)
            except Exception as exc:  # noqa: BLE001 - the complaint is the result
                problems.append(f'{name}: not built with this file: {exc!r}')
                continue
            try:
                for key, value in params[name]['ros__parameters'].items():
                    if not node.has_parameter(key):
                        problems.append(f'{name}: declares no parameter {key!r}')
                    elif node.get_parameter(key).value != value:
                        problems.append(f'{name}.{key}: {node.get_parameter(key).value!r} '
                                        f'instead of {value!r}')
            finally:
                if hasattr(node, 'make_safe'):
                    node.make_safe()
                node.destroy_node()
    finally:
        rclpy.try_shutdown(context=ctx)
    return problems


def _default_params_file() -> Path:
    _, constants, _, _ = read_launch_file(LAUNCH_FILE)
    return LAUNCH_FILE.with_name(constants['PARAMS_FILE'])


# ---- the shipped files ------------------------------------------------------------------

def test_launch_file_names_only_what_exists():
    assert launch_file_problems(LAUNCH_FILE) == []


def test_launch_file_starts_each_node_of_galvoscan_run_once():
    _, _, nodes, _ = read_launch_file(LAUNCH_FILE)
    assert sorted(n.literal('name') for n in nodes) == sorted(bringup.NODES)


def test_default_parameters_file_works_for_galvoscan_run_too(tmp_path):
    """The launch file's default YAML is one galvoscan run reads and starts nodes with."""
    params_file = _default_params_file()
    params = bringup.load_params(params_file)
    assert set(params) == set(bringup.NODES)
    start = bringup.with_sim_starting_calibration(params_file, list(bringup.NODES), tmp_path)
    assert bringup.load_params(start)['galvo_driver'] == params['galvo_driver']
    sup = bringup.Supervisor(list(bringup.NODES), params_file)
    for child in sup.children:
        assert child.argv[-2:] == ['--params-file', str(params_file)]


def test_default_parameters_are_declared_by_their_nodes(ros_env):
    assert parameter_problems(_default_params_file()) == []


# ---- the checks complain about broken copies ----------------------------------------------

BROKEN = {
    'package': ("package='reconstructor'", "package='reconstructer'", 'no package'),
    'executable': ("executable='stripe_extractor'", "executable='extractor'",
                   'not a console script'),
    'node name': ("name='reconstructor'", "name='reconstruct'", 'bringup.NODES'),
    'lifecycle': ("'galvo_driver': LifecycleNode(", "'galvo_driver': Node(",
                  'lifecycle node'),
    'no lifecycle': ("'reconstructor': Node(", "'reconstructor': LifecycleNode(",
                     'lifecycle node'),
    'parameters': ("name='calibration',\n            parameters=[LaunchConfiguration(",
                   "name='calibration',\n            parameters=[{'quick': True}, (",
                   'parameters must be'),
    'default nodes': ("DEFAULT_NODES = 'galvo_driver,",
                      "DEFAULT_NODES = 'galvo_driver,calibration,", 'nodes: default'),
    'default params': ("PARAMS_FILE = 'galvoscan.params.yaml'",
                       "PARAMS_FILE = 'galvoscan_params.yaml'", 'does not exist'),
    'undeclared argument': ("LaunchConfiguration('nodes').perform",
                            "LaunchConfiguration('node_names').perform",
                            'no DeclareLaunchArgument'),
    'import': ('import ENV, PROFILE_VARS, child_env', 'import ENV, PROFILE_VARIABLES, child_env',
               'has no PROFILE_VARIABLES'),
    'selection key': ("'stripe_extractor': Node(", "'extractor': Node(", 'selected as'),
}


@pytest.mark.parametrize('case', BROKEN, ids=list(BROKEN))
def test_checker_finds_a_broken_launch_file(tmp_path, case):
    old, new, complaint = BROKEN[case]
    text = LAUNCH_FILE.read_text()
    assert text.count(old) == 1, f'{case}: the launch file changed; update this case'
    broken = tmp_path / LAUNCH_FILE.name
    broken.write_text(text.replace(old, new))
    (tmp_path / 'galvoscan.params.yaml').write_text(_default_params_file().read_text())
    problems = launch_file_problems(broken)
    assert any(complaint in p for p in problems), problems


@pytest.mark.parametrize('node, key, value, complaint', [
    ('galvo_driver', 'frame_rte', 500.0, "declares no parameter 'frame_rte'"),
    ('galvo_driver', 'frame_rate', 'fast', 'not built with this file'),
    ('reconstructor', 'scan_end_timeout', 100.0, 'not built with this file'),
    ('stripe_extractor', 'line_width', 4.7, "declares no parameter 'line_width'"),
])
def test_checker_finds_a_broken_parameters_file(tmp_path, ros_env, node, key, value, complaint):
    params = bringup.load_params(_default_params_file())
    section = {n: s for n, s in params.items() if n == node}
    section[node]['ros__parameters'][key] = value
    broken = tmp_path / 'params.yaml'
    broken.write_text(yaml.safe_dump(section))
    problems = parameter_problems(broken)
    assert any(complaint in p for p in problems), problems
