"""docs/fault-matrix.md is a real index: every row names tests, and every test named exists."""

import ast
from pathlib import Path
import re

ROOT = Path(__file__).resolve().parents[1]
MATRIX = ROOT / 'docs' / 'fault-matrix.md'
ROW = re.compile(r'^\|\s*([A-Z]+[0-9]+)\s*\|')
TEST_REF = re.compile(r'`(test_[a-z0-9_]+\.py)::(test_[A-Za-z0-9_]+)`')


def _rows():
    rows = {}
    for line in MATRIX.read_text(encoding='utf-8').splitlines():
        match = ROW.match(line)
        if match:
            rows[match.group(1)] = TEST_REF.findall(line)
    return rows


def _tests_in(file_name):
    tree = ast.parse((ROOT / 'test' / file_name).read_text(encoding='utf-8'))
    return {node.name for node in ast.walk(tree)
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef))
            and node.name.startswith('test_')}


def test_every_row_names_a_test():
    rows = _rows()
    assert len(rows) >= 42  # N1-N22 and C1-C20 at least
    assert [row for row, tests in rows.items() if not tests] == []


def test_every_named_test_exists():
    missing = []
    for row, tests in _rows().items():
        for file_name, test_name in tests:
            path = ROOT / 'test' / file_name
            if not path.is_file() or test_name not in _tests_in(file_name):
                missing.append(f'{row}: {file_name}::{test_name}')
    assert missing == []


def test_row_ids_are_unique():
    ids = [ROW.match(line).group(1)
           for line in MATRIX.read_text(encoding='utf-8').splitlines() if ROW.match(line)]
    assert len(ids) == len(set(ids))
