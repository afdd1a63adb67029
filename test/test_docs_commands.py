"""What the docs tell a user to type exists: commands, flags, make targets, parameters, paths."""

import argparse
from pathlib import Path
import re

import pytest
from skidkin_ros.cli.main import build_parser
from skidkin_ros.core.odometry.config import parameter_schema

ROOT = Path(__file__).resolve().parents[1]
# docs/ and its studies/ (the lab's record behind a product page): every page is checked.
PAGES = [ROOT / 'README.md'] + sorted((ROOT / 'docs').rglob('*.md'))
# Folders a path named in the docs starts from (the package's own folders are named without it).
OWN_FOLDERS = ('skidkin_ros', 'core', 'adapters', 'node', 'cli', 'report', 'sim', 'lab', 'test',
               'config', 'launch', 'data', 'docs')


def _subcommands() -> dict[str, argparse.ArgumentParser]:
    for action in build_parser()._actions:
        if isinstance(action, argparse._SubParsersAction):
            return dict(action.choices)
    raise AssertionError('skidkin has no subcommands')


def _text(page: Path) -> str:
    return page.read_text(encoding='utf-8').replace('\\\n', ' ')  # join continued lines


def _skidkin_commands(text: str):
    """Yield (subcommand, the rest of its line) for every `skidkin SUB ...` a page shows."""
    for match in re.finditer(r'\bskidkin ([a-z]+)([^\n`|]*)', text):
        yield match.group(1), match.group(2).split('#')[0]


def _flags(parser: argparse.ArgumentParser) -> set[str]:
    return {flag for action in parser._actions for flag in action.option_strings}


def _command_problems(text: str) -> list[str]:
    """Return what is wrong with the `skidkin` command lines of a page's text."""
    commands, problems = _subcommands(), []
    for sub, rest in _skidkin_commands(text):
        if sub not in commands:
            # prose such as "skidkin reads"; a command line has an option or a file after it
            if re.match(r'\s+(--|\S+\.(csv|bag|mcap|db3|yaml)\b)', rest):
                problems.append(f'skidkin has no subcommand {sub!r}')
            continue
        flags = _flags(commands[sub])
        problems += [f'skidkin {sub} has no {flag}'
                     for flag in re.findall(r'(?<![\w-])(--[a-z][\w-]*)', rest)
                     if flag not in flags]
    return problems


def _path_problems(text: str, folder: Path) -> list[str]:
    """Return the repository paths a page's text names in backticks that do not exist."""
    problems = []
    for path in re.findall(r'`([\w./-]+/[\w.-]+\.(?:py|yaml|csv|md|png))`', text):
        if path.split('/')[0] not in OWN_FOLDERS:
            continue
        if not any(c.exists() for c in (ROOT / path, ROOT / 'skidkin_ros' / path, folder / path)):
            problems.append(f'no file {path}')
    return problems


@pytest.mark.parametrize('page', PAGES, ids=lambda p: str(p.relative_to(ROOT)))
def test_every_skidkin_command_in_the_docs_has_the_flags_shown(page):
    assert _command_problems(_text(page)) == [], page.name


def test_every_make_target_in_the_docs_exists():
    targets = set(re.findall(r'^([a-z][\w-]*):', (ROOT / 'Makefile').read_text(), re.M))
    for page in PAGES:
        for block in re.findall(r'```[a-z]*\n(.*?)```', page.read_text(encoding='utf-8'), re.S):
            for target in re.findall(r'^make (?:[A-Z_]+=\S* )*([a-z][\w-]*)', block, re.M):
                assert target in targets, f'{page.name}: the Makefile has no target {target}'


def test_every_node_parameter_set_on_a_command_line_in_the_docs_exists():
    names = {entry.name for entry in parameter_schema()}
    launch = (ROOT / 'launch' / 'odom_node.launch.py').read_text()
    arguments = set(re.findall(r"'(\w+_topic)':", launch))
    arguments |= {'params_file', 'use_sim_time', 'namespace'}
    for page in PAGES:
        text = _text(page)
        for name in re.findall(r'-p ([\w.]+):=', text):
            assert name in names, f'{page.name}: the node has no parameter {name}'
        for line in re.findall(r'ros2 launch skidkin_ros odom_node\.launch\.py([^\n`]*)', text):
            for argument in re.findall(r'(\w+):=', line):
                assert argument in arguments, f'{page.name}: the launch file has no {argument}'


@pytest.mark.parametrize('page', PAGES, ids=lambda p: str(p.relative_to(ROOT)))
def test_every_path_the_docs_name_exists(page):
    assert _path_problems(page.read_text(encoding='utf-8'), page.parent) == [], page.name


def test_the_checks_catch_a_wrong_subcommand_flag_and_path():
    text = ('skidkin calibrate t.csv --out p.yaml --splitby x  # --not-this\n'
            'skidkin calibrat t.csv --out p.yaml\nskidkin reads bags\n'
            '`core/calibration/segments.py`, `core/calibration/segmentation.py`, `rosdep/x.yaml`')
    assert _command_problems(text) == ['skidkin calibrate has no --splitby',
                                       "skidkin has no subcommand 'calibrat'"]
    assert _path_problems(text, ROOT / 'docs') == ['no file core/calibration/segmentation.py']
