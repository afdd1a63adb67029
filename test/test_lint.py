"""ament's linters, as in every ROS 2 package: flake8 (ROS settings) and pep257."""

from ament_flake8.main import main_with_errors as flake8_main
from ament_pep257.main import main as pep257_main
import pytest

PATHS = ['skidkin_ros', 'test', 'lab', 'launch', 'setup.py']


@pytest.mark.linter
def test_flake8():
    rc, errors = flake8_main(argv=PATHS)
    assert rc == 0, 'flake8 found %d error(s):\n' % len(errors) + '\n'.join(errors)


@pytest.mark.linter
def test_pep257():
    # House docstring style: the summary sits on the first line (D212), not the second.
    rc = pep257_main(argv=PATHS + ['--add-ignore', 'D213'])
    assert rc == 0, 'pep257 found code style errors / warnings (see output above)'
