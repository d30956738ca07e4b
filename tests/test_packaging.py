"""The repository layout is what colcon (apt ROS) and the venv setup both expect."""

import re
import subprocess
import sys
from pathlib import Path

import pytest
from catkin_pkg.package import parse_package

ROOT = Path(__file__).resolve().parents[1]
PY_PACKAGES = ['galvoscan_common', 'galvoscan_sim', 'galvoscan_bag', 'galvo_driver',
               'stripe_extractor', 'reconstructor', 'calibration_tools', 'galvoscan']
#: packages without a ROS node or process plumbing: no rclpy among their dependencies
PURE_PACKAGES = ['galvoscan_sim']


@pytest.mark.parametrize('path', ['msgs'] + [f'src/{p}' for p in PY_PACKAGES])
def test_package_xml_parses_with_catkin_pkg(path):
    pkg = parse_package(ROOT / path / 'package.xml')
    pkg.validate()
    assert pkg.package_format == 3
    build_types = {e.content for e in pkg.exports if e.tagname == 'build_type'}
    assert build_types == ({'ament_cmake'} if path == 'msgs' else {'ament_python'})


@pytest.mark.parametrize('name', PY_PACKAGES)
def test_ament_python_layout(name):
    base = ROOT / 'src' / name
    assert (base / 'resource' / name).is_file()
    assert (base / 'setup.cfg').read_text().count(f'$base/lib/{name}') == 2
    setup_py = (base / 'setup.py').read_text()
    assert f"package_name = '{name}'" in setup_py
    # every console script points at a module that exists
    for module, func in re.findall(r"= ([\w.]+):(\w+)'", setup_py):
        path = base / (module.replace('.', '/') + '.py')
        assert path.is_file(), f'{name}: console script target {module} is missing'
        assert re.search(rf'^def {func}\(', path.read_text(), re.M), f'{module}.{func}'
    deps = {d.name for d in parse_package(base / 'package.xml').exec_depends}
    assert ('rclpy' in deps) == (name not in PURE_PACKAGES)


def test_msgs_cmake_is_plain_ament():
    text = (ROOT / 'msgs' / 'CMakeLists.txt').read_text()
    assert 'find_package(ament_cmake REQUIRED)' in text
    assert 'rosidl_generate_interfaces(${PROJECT_NAME}' in text
    assert 'ament_package()' in text
    listed = set(re.findall(r'"((?:msg|srv)/\w+\.(?:msg|srv))"', text))
    on_disk = {str(p.relative_to(ROOT / 'msgs')) for p in (ROOT / 'msgs').glob('*/*.*')
               if p.suffix in ('.msg', '.srv')}
    assert listed == on_disk
    assert '/opt/' not in text and 'venv' not in text


def test_interfaces_import_without_environment():
    """Inside the venv, with no environment variables set, the interfaces import."""
    out = subprocess.run(
        [sys.executable, '-c',
         'import galvoscan_msgs.msg, galvoscan_msgs.srv; '
         'print(galvoscan_msgs.msg.GalvoState().STATUS_FAULT)'],
        env={}, cwd='/', capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == '2'


def test_every_interface_field_documents_its_unit():
    """Each field line of every .msg/.srv carries a comment (the unit lives there)."""
    for path in (ROOT / 'msgs').glob('*/*.*'):
        for line in path.read_text().splitlines():
            code = line.split('#')[0].strip()
            if code and code != '---' and '=' not in code:
                assert '#' in line, f'{path.name}: field without a comment: {line!r}'
