"""Calibration never places its own targets: no module of calibration_tools calls a
simulator service (``sim/...``) or names the simulator's scene service type; a real rig has
neither. Targets reach the scene only through the operator (a person, a robot program or
the application's simulated operator)."""

import ast
from pathlib import Path

SRC = Path(__file__).resolve().parents[1] / 'src' / 'calibration_tools' / 'calibration_tools'


def _offences(path: Path) -> list[str]:
    out = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Constant) and isinstance(node.value, str) and \
                node.value.lstrip('/').startswith('sim/'):
            out.append(f'{path.name}:{node.lineno} string {node.value!r}')
        elif isinstance(node, (ast.Name, ast.Attribute)) and \
                (getattr(node, 'id', None) or getattr(node, 'attr', None)) == 'SetScene':
            out.append(f'{path.name}:{node.lineno} SetScene')
        elif isinstance(node, ast.alias) and node.name.split('.')[-1] == 'SetScene':
            out.append(f'{path.name}:{node.lineno} imports SetScene')
    return out


def test_calibration_tools_makes_no_sim_call():
    files = sorted(SRC.rglob('*.py'))
    assert len(files) > 20
    offences = [o for f in files for o in _offences(f)]
    assert not offences, 'calibration_tools calls the simulator:\n' + '\n'.join(offences)


def test_the_check_finds_a_sim_call(tmp_path):
    bad = tmp_path / 'bad.py'
    bad.write_text("from galvoscan_msgs.srv import SetScene\n"
                   "def f(node):\n    return node.create_client(SetScene, 'sim/set_scene')\n")
    assert len(_offences(bad)) == 3  # the import, the type and the service name
