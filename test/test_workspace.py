"""The package in a ROS workspace: package.xml agrees with setup.py, and the launch file holds.

rosdep installs what package.xml declares, pip what setup.py requires: the two lists must name
the same things (by the rosdep key that exists for each, see rosdistro's rosdep/python.yaml), and
what has no key is said in package.xml and in docs/field-recordings.md. The launch packages have
no wheel here, so the launch file is not run: it is parsed and checked against what setup.py
installs and what the node subscribes to.
"""

import ast
from pathlib import Path
import re
import runpy
import xml.etree.ElementTree as ElementTree

import pytest
import setuptools

ROOT = Path(__file__).resolve().parents[1]
LAUNCH = ROOT / 'launch' / 'odom_node.launch.py'
# setup.py requirement -> its rosdep key (rosdistro master, rosdep/python.yaml).
ROSDEP_KEYS = {
    'setuptools': 'python3-setuptools',
    'numpy': 'python3-numpy',
    'scipy': 'python3-scipy',
    'matplotlib': 'python3-matplotlib',
    'PyYAML': 'python3-yaml',
    'tqdm': 'python3-tqdm',
    'rosbags': 'python3-rosbags-pip',
}
# No rosdep key exists for these (checked in rosdep/python.yaml and jazzy/distribution.yaml).
NO_ROSDEP_KEY = ('kiss-icp', 'threadpoolctl', 'apsw')
ROS_IMPORT = re.compile(
    r'^(rclpy|rcl_interfaces|builtin_interfaces|tf2_ros|[a-z0-9_]+_(msgs|srvs))$')


@pytest.fixture(scope='module')
def setup_kwargs():
    """Return the keyword arguments setup.py passes to setuptools.setup."""
    captured = {}
    original = setuptools.setup
    setuptools.setup = lambda **kwargs: captured.update(kwargs)
    try:
        runpy.run_path(str(ROOT / 'setup.py'), run_name='not_main')
    finally:
        setuptools.setup = original
    return captured


def _requirement_names(kwargs):
    return [re.split(r'[<>=!~;\[ ]', item, maxsplit=1)[0] for item in kwargs['install_requires']]


def _declared(kinds=('depend', 'exec_depend', 'build_export_depend', 'buildtool_depend')):
    root = ElementTree.parse(ROOT / 'package.xml').getroot()
    return {element.text.strip() for kind in kinds for element in root.iter(kind)}


def test_package_xml_declares_every_requirement_by_its_rosdep_key(setup_kwargs):
    names = _requirement_names(setup_kwargs)
    unknown = [n for n in names if n not in ROSDEP_KEYS and n not in NO_ROSDEP_KEY]
    assert unknown == [], 'add the rosdep key (or its absence) of these requirements'
    declared = _declared()
    missing = [ROSDEP_KEYS[n] for n in names if n in ROSDEP_KEYS
               and ROSDEP_KEYS[n] not in declared]
    assert missing == []
    # Nothing python3-* in package.xml that setup.py does not require (a stale or made-up key).
    stale = sorted(key for key in declared if key.startswith('python3-')
                   and key not in {ROSDEP_KEYS[n] for n in names if n in ROSDEP_KEYS})
    assert stale == []
    xml_text = (ROOT / 'package.xml').read_text()
    docs = (ROOT / 'docs' / 'field-recordings.md').read_text()
    for name in NO_ROSDEP_KEY:
        assert name in names
        assert name in xml_text, f'package.xml should say {name} has no rosdep key'
        assert re.search(rf'pip install [^\n]*{re.escape(name)}', docs), name


def test_package_xml_declares_every_ros_package_the_code_imports():
    imported = set()
    for path in (ROOT / 'skidkin_ros').rglob('*.py'):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                imported.update(alias.name.split('.')[0] for alias in node.names)
            elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                imported.add(node.module.split('.')[0])
    ros = {name for name in imported if ROS_IMPORT.match(name)}
    assert {'rclpy', 'nav_msgs', 'tf2_ros'} <= ros
    assert sorted(ros - _declared()) == []
    launch_imports = {node.module.split('.')[0] for node in ast.walk(ast.parse(LAUNCH.read_text()))
                      if isinstance(node, ast.ImportFrom) and node.module}
    assert {'launch', 'launch_ros'} <= launch_imports
    assert sorted(launch_imports - {'ament_index_python'} - _declared()) == []


def _launch_constants():
    tree = ast.parse(LAUNCH.read_text())
    constants = {}
    for node in tree.body:
        if isinstance(node, ast.Assign) and isinstance(node.targets[0], ast.Name):
            constants[node.targets[0].id] = ast.literal_eval(node.value)
    return tree, constants


def _installed(kwargs):
    return {f'{folder}/{Path(item).name}': item for folder, items in kwargs['data_files']
            for item in items}


def test_the_launch_file_names_the_installed_executable_config_and_topics(setup_kwargs):
    tree, constants = _launch_constants()
    package = setup_kwargs['name']
    assert constants['PACKAGE'] == package
    scripts = {line.split('=')[0].strip(): line.split('=')[1].strip()
               for line in setup_kwargs['entry_points']['console_scripts']}
    assert scripts[constants['EXECUTABLE']] == 'skidkin_ros.node.odom_node:main'
    installed = _installed(setup_kwargs)
    config = '/'.join(constants['DEFAULT_PARAMS'])
    assert installed[f'share/{package}/{config}'] == config and (ROOT / config).is_file()
    assert installed[f'share/{package}/launch/{LAUNCH.name}'] == f'launch/{LAUNCH.name}'
    # Every remap names a topic the node really uses (a typo would remap nothing).
    node_files = (ROOT / 'skidkin_ros' / 'node').glob('*.py')
    node_source = '\n'.join(path.read_text() for path in node_files
                            if path.name != 'replay.py')   # replay drives the node from outside
    used = set(re.findall(r"create_(?:subscription|publisher)\(\s*\w+, '([^']+)'", node_source))
    assert set(constants['REMAPS'].values()) == used - {'~/set_pose', '/diagnostics'}
    declared = {call.args[0].value for call in ast.walk(tree)
                if isinstance(call, ast.Call)
                and getattr(call.func, 'id', '') == 'DeclareLaunchArgument'
                and isinstance(call.args[0], ast.Constant)}
    assert {'params_file', 'use_sim_time', 'namespace'} <= declared
    # The comprehension declares one argument per remap.
    assert any(isinstance(c, ast.ListComp) for c in ast.walk(tree))
    node_call = next(call for call in ast.walk(tree) if isinstance(call, ast.Call)
                     and getattr(call.func, 'id', '') == 'Node')
    keywords = {k.arg for k in node_call.keywords}
    assert {'package', 'executable', 'namespace', 'parameters', 'remappings'} <= keywords
