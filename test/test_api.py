"""The public API: what skidkin_ros exports, and the example of docs/api.md run as it stands."""

import importlib
from pathlib import Path
import pkgutil
import re

import numpy as np
import skidkin_ros

ROOT = Path(__file__).resolve().parents[1]


def test_the_example_of_the_api_page_runs_and_checks_itself(monkeypatch, capsys):
    page = (ROOT / 'docs' / 'api.md').read_text()
    blocks = re.findall(r'```python\n(.*?)```', page, flags=re.S)
    assert len(blocks) == 1
    monkeypatch.chdir(ROOT)  # the example reads config/odom_node.yaml
    namespace = {}
    exec(compile(blocks[0], 'docs/api.md', 'exec'), namespace)  # noqa: S102 (our own page)
    out = capsys.readouterr().out
    assert 'after 5 s: x ' in out and 'position sigma (m):' in out
    # The example's own check held (exec raises otherwise); and the arc turns left.
    assert namespace['yaw'] > 0 and np.all(np.isfinite(namespace['cov']))


def test_the_package_exports_what_its_all_names():
    assert len(skidkin_ros.__all__) == len(set(skidkin_ros.__all__))
    for name in skidkin_ros.__all__:
        assert hasattr(skidkin_ros, name), name
    config = skidkin_ros.load_parameters(ROOT / 'config' / 'odom_node.yaml')
    assert isinstance(config, skidkin_ros.OdometryConfig)
    assert isinstance(skidkin_ros.Odometer.from_config(config), skidkin_ros.Odometer)


def test_every_package_declares_its_all():
    missing = []
    for info in pkgutil.walk_packages(skidkin_ros.__path__, 'skidkin_ros.'):
        if not info.ispkg:
            continue
        module = importlib.import_module(info.name)
        names = getattr(module, '__all__', None)
        if names is None:
            missing.append(info.name)
            continue
        for name in names:  # a listed submodule or a re-exported name
            assert hasattr(module, name) or importlib.util.find_spec(
                f'{info.name}.{name}') is not None, f'{info.name}.{name}'
    assert missing == []
