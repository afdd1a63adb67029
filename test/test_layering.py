"""Keep the layers apart: a ROS-free core, rclpy only in the node, printing only in the CLI."""

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / 'skidkin_ros'
ROS_MODULES = ('rclpy', 'sensor_msgs', 'nav_msgs', 'std_msgs', 'geometry_msgs', 'std_srvs',
               'diagnostic_msgs', 'rosgraph_msgs', 'tf2_ros', 'builtin_interfaces')
IO_MODULES = ('rosbags', 'kiss_icp')


def _imports(path):
    tree = ast.parse(path.read_text())
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                yield alias.name.split('.')[0]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            yield node.module.split('.')[0]


def _module(path):
    parts = path.relative_to(PACKAGE.parent).with_suffix('').parts
    return '.'.join(parts[:-1] if parts[-1] == '__init__' else parts)


def _files(sub):
    return sorted((PACKAGE / sub).rglob('*.py')) if sub else sorted(PACKAGE.rglob('*.py'))


def test_core_never_imports_ros_or_io_libraries():
    offenders = [(f.name, m) for f in _files('core') for m in _imports(f)
                 if m in ROS_MODULES + IO_MODULES + ('matplotlib',)]
    assert offenders == []


def test_only_the_node_imports_ros():
    offenders = [(str(f.relative_to(PACKAGE)), m) for f in _files('') for m in _imports(f)
                 if m in ROS_MODULES and f.parent.name != 'node']
    assert offenders == []


def test_library_code_does_not_print():
    offenders = []
    for f in _files(''):
        if f.parent.name in ('cli',):
            continue
        for node in ast.walk(ast.parse(f.read_text())):
            if (isinstance(node, ast.Call) and isinstance(node.func, ast.Name)
                    and node.func.id == 'print'):
                offenders.append(f'{f.relative_to(PACKAGE)}:{node.lineno}')
    assert offenders == []


# The core's folders tell the story in order: models -> what the node runs -> fitting them
# offline -> checking the result with a filter. A folder may use the ones before it, never after.
CORE_ORDER = ('kinematics', 'odometry', 'calibration', 'online', 'estimation')


def _skidkin_imports(path, names=False):
    """Yield the skidkin_ros modules a file imports.

    With ``names``, also ``module.name`` for each ``from module import name`` (a name may be a
    module).
    """
    tree = ast.parse(path.read_text())
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            if node.module.startswith('skidkin_ros'):
                yield node.module
                if names:
                    yield from (f'{node.module}.{alias.name}' for alias in node.names)
        elif isinstance(node, ast.Import):
            for alias in node.names:
                if alias.name.startswith('skidkin_ros'):
                    yield alias.name


def _core_rank(module):
    parts = module.split('.')
    if parts[:2] != ['skidkin_ros', 'core'] or len(parts) < 3:
        return None
    return CORE_ORDER.index(parts[2]) + 1 if parts[2] in CORE_ORDER else 0


def test_core_folders_only_use_earlier_folders():
    offenders = []
    for f in _files('core'):
        module = _module(f)
        rank = _core_rank(module)
        for target in _skidkin_imports(f):
            other = _core_rank(target)
            if other is None:
                if not target.startswith(('skidkin_ros.core', 'skidkin_ros.errors',
                                          'skidkin_ros.atomic')) and target != 'skidkin_ros':
                    offenders.append((module, target))
            elif other > rank:
                offenders.append((module, target))
    assert offenders == []


def test_a_cli_command_never_imports_another_command():
    """Shared CLI code lives in cli/common.py; a command is a leaf (the registry lists them)."""
    commands = {_module(f) for f in _files('cli') if f.name.startswith('cmd_')}
    offenders = [(_module(f), target) for f in _files('cli') if f.name.startswith('cmd_')
                 for target in _skidkin_imports(f, names=True)
                 if target in commands and target != _module(f)]
    assert offenders == []


def test_the_simulator_never_imports_adapters():
    """The simulator produces data; writing it as a rosbag2 is adapters.sim_writer's job."""
    offenders = [(_module(f), target) for f in _files('sim')
                 for target in _skidkin_imports(f, names=True)
                 if target.startswith(('skidkin_ros.adapters', 'skidkin_ros.cli',
                                       'skidkin_ros.node'))]
    assert offenders == []


def test_no_import_cycles():
    """Lazy and type-only imports count: a study and its report once imported each other."""
    graph = {_module(f): set(_skidkin_imports(f, names=True)) for f in _files('')}
    # A module's own packages are imported before it anyway: not an edge.
    graph = {m: {t for t in targets if t in graph and t != m and not m.startswith(t + '.')}
             for m, targets in graph.items()}
    cycles = []
    state: dict[str, int] = {}

    def visit(module, path):
        state[module] = 1
        for target in sorted(graph[module]):
            if state.get(target) == 1:
                cycles.append(path[path.index(target):] + [target])
            elif target not in state:
                visit(target, path + [target])
        state[module] = 2

    for module in sorted(graph):
        if module not in state:
            visit(module, [module])
    assert cycles == []


# The stamp convention and the lag scan are time offsets by definition: they may name it.
NAMED_ON_PURPOSE = {'recipe.py': {'time_offset'}, 'tracing.py': {'time_offset'}}


def test_generic_diagnosis_code_names_no_extension():
    """Adding an extension is a registry entry (core/kinematics/extensions.py), not an edit."""
    from skidkin_ros.core.kinematics.extensions import EXTENSION_NAMES
    offenders = []
    for f in _files('core/calibration/diagnosis'):
        allowed = NAMED_ON_PURPOSE.get(f.name, set())
        for node in ast.walk(ast.parse(f.read_text())):
            if (isinstance(node, ast.Constant) and node.value in EXTENSION_NAMES
                    and node.value not in allowed):
                offenders.append(f'{f.name}:{node.lineno} {node.value}')
    assert offenders == []


def test_the_product_never_imports_the_lab():
    """lab/ (studies, benchmarks) runs from a clone; the installed package must not need it."""
    # _imports walks the whole tree: an import inside a function counts too.
    offenders = [str(f.relative_to(PACKAGE)) for f in _files('') for m in _imports(f)
                 if m == 'lab']
    assert offenders == []


def test_setup_installs_no_lab_package():
    import re
    from setuptools import find_packages
    setup_text = (PACKAGE.parent / 'setup.py').read_text()
    exclude = ast.literal_eval(re.search(r'find_packages\(exclude=(\[[^]]*\])\)',
                                         setup_text).group(1))
    installed = find_packages(where=str(PACKAGE.parent), exclude=exclude)
    assert 'skidkin_ros' in installed
    assert [name for name in installed if name.split('.')[0] != 'skidkin_ros'] == []
