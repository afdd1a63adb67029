"""The docs hold to the code: generated tables match the specs, and every link resolves."""

from pathlib import Path
import re

from lab.docs import check, GENERATED, render
import pytest
from skidkin_ros.cli.main import main

ROOT = Path(__file__).resolve().parents[1]
# docs/ and its studies/ (the lab's record behind a product page): every page is checked.
PAGES = [ROOT / 'README.md'] + sorted((ROOT / 'docs').rglob('*.md'))


def test_generated_tables_in_the_docs_match_the_specs():
    assert check(ROOT) == [], 'run `make docs`'


def test_the_node_reference_is_what_skidkin_models_node_prints(capsys):
    assert main(['models', '--node']) == 0
    out = capsys.readouterr().out.strip()
    page = (ROOT / 'docs' / 'node.md').read_text()
    assert out in page
    # Every parameter the node declares has its row (per-model ones once, as models.<model>.*).
    from skidkin_ros.core.odometry.config import parameter_schema
    for entry in parameter_schema():
        name = entry.name if not entry.name.startswith('models.') else None
        if name:
            assert f'| `{name}` |' in out, name
    assert '| `models.<model>.noise.var_x_per_m` |' in out


def test_a_stale_table_is_caught_and_a_page_without_markers_is_refused():
    command, make = GENERATED['docs/node.md']
    page = (ROOT / 'docs' / 'node.md').read_text()
    stale = page.replace('| `max_dt` | double | s | 0.5 |', '| `max_dt` | double | s | 0.7 |')
    assert stale != page and render(stale, command, make()) == page
    with pytest.raises(ValueError, match='no block for'):
        render('# a page\n', command, make())


@pytest.mark.parametrize('page', PAGES, ids=lambda p: str(p.relative_to(ROOT)))
def test_every_relative_link_resolves(page):
    text = page.read_text()
    for target in re.findall(r'\]\(([^)#\s]+)(?:#[^)]*)?\)', text):
        if '://' in target:
            continue
        assert (page.parent / target).exists(), f'{page.name}: broken link {target}'


def test_the_readme_starts_with_the_two_commands_and_stays_short():
    lines = (ROOT / 'README.md').read_text().splitlines()
    assert lines[2] == '```bash'
    assert lines[3].startswith('make demo') and lines[4].startswith('make test')
    assert len(lines) <= 200


def test_every_online_parameter_is_named_on_the_online_page():
    """A field engineer finds each ``online.*`` parameter on the page that says what it is for."""
    from skidkin_ros.core.odometry.reference import ONLINE_SPECS
    page = (ROOT / 'docs' / 'online-calibration.md').read_text()
    missing = [s.name for s in ONLINE_SPECS if f'`online.{s.name}`' not in page]
    assert missing == [], f'docs/online-calibration.md does not name online.{missing}'
