"""package.xml as rosdep reads it: every key resolves on Jazzy, every import is declared.

No network: the keys are checked against test/data/rosdep_keys_jazzy.txt, a snapshot of
ros/rosdistro (made by test/data/rosdep_keys_jazzy.py).
"""
from __future__ import annotations

import ast
import re
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
DEPEND_TAGS = ('depend', 'exec_depend', 'build_depend', 'buildtool_depend', 'test_depend', 'build_export_depend')
#: Python modules -> the rosdep key that brings them; None: no key on Jazzy, installed by pip
#: (README "On a ROS 2 Jazzy install"; setup.py install_requires or an extra).
PYTHON_KEYS = {
    'numpy': 'python3-numpy', 'scipy': 'python3-scipy', 'cv2': 'python3-opencv', 'yaml': 'python3-yaml',
    'matplotlib': 'python3-matplotlib', 'tqdm': 'python3-tqdm', 'rosbags': 'python3-rosbags-pip',
    'mcap': None, 'gtsam': None, 'evo': None, 'vqf': None,
}


def _keys() -> dict[str, str]:
    root = ET.parse(REPO / 'package.xml').getroot()
    return {el.text.strip(): el.tag for tag in DEPEND_TAGS for el in root.iter(tag)}


def _known() -> set[str]:
    lines = (REPO / 'test' / 'data' / 'rosdep_keys_jazzy.txt').read_text().splitlines()
    return {line.strip() for line in lines if line.strip() and not line.startswith('#')}


def _imports() -> set[str]:
    """Top-level module names imported anywhere in ar_tracking/ and launch/."""
    names: set[str] = set()
    for path in list((REPO / 'ar_tracking').rglob('*.py')) + list((REPO / 'launch').glob('*.py')):
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                names.update(a.name.split('.')[0] for a in node.names)
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names.add(node.module.split('.')[0])
    return names


def test_every_package_xml_key_resolves_on_jazzy():
    known = _keys()
    missing = sorted(k for k in known if k not in _known())
    assert not missing, f'not rosdep keys on Jazzy: {missing}'


def test_the_snapshot_knows_what_a_bad_key_is():
    known = _known()
    assert 'python3-numpy' in known and 'launch_ros' in known and 'tf2_msgs' in known
    assert 'python3-gtsam-pip' not in known and 'python3-mcap-pip' not in known


def test_every_ros_import_is_declared():
    keys = _keys()
    known = _known()
    stdlib = set(sys.stdlib_module_names)
    # Jazzy package names (rclpy, *_msgs, launch_ros, ...); system keys such as zlib aside.
    ros = sorted(m for m in _imports() if m in known and m not in stdlib and m not in PYTHON_KEYS)
    assert 'rclpy' in ros and 'launch_ros' in ros and 'ament_index_python' in ros
    undeclared = [m for m in ros if m not in keys]
    assert not undeclared, f'imported but not in package.xml: {undeclared}'


def test_every_third_party_import_is_a_key_or_a_documented_pip_install():
    keys = _keys()
    setup = (REPO / 'setup.py').read_text()
    readme = (REPO / 'README.md').read_text()
    stdlib = set(sys.stdlib_module_names) | {'ar_tracking'}
    known = _known()
    third = sorted(m for m in _imports() if m not in stdlib and (m in PYTHON_KEYS or m not in known))
    for module in third:
        if module in PYTHON_KEYS and PYTHON_KEYS[module] is not None:
            assert PYTHON_KEYS[module] in keys, f'{module}: add <exec_depend>{PYTHON_KEYS[module]}</exec_depend>'
        elif module in PYTHON_KEYS:
            assert re.search(rf'pip install [^\n`]*\b{module}\b', readme), f'{module}: no rosdep key; the README must say pip install it'
            assert f"'{module}" in setup, f'{module}: not in setup.py'
        else:
            # Optional peers (benchmarks, other backends): a setup.py extra must name them.
            assert re.search(rf"'{re.escape(module)}[\w\-\[\]]*[<>=~']", setup), \
                f'{module} is imported but neither in PYTHON_KEYS nor in setup.py'
