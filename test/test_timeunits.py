"""Time units have one home (core/timeunits.py) and one rounding rule: nearest, halves to even."""

import io
from pathlib import Path
import tokenize

import numpy as np
import pytest
from skidkin_ros.core.timeunits import NS_PER_S, ns_to_s, s_to_ns, s_to_ns_array

PACKAGE = Path(__file__).resolve().parents[1] / 'skidkin_ros'
HOME = PACKAGE / 'core' / 'timeunits.py'


def test_one_second_is_a_billion_integer_nanoseconds():
    assert NS_PER_S == 1_000_000_000 and isinstance(NS_PER_S, int)


@pytest.mark.parametrize('seconds, expected', [
    (0.5e-9, 0),             # half a nanosecond: to the even neighbour, 0
    (1.5e-9, 2),             # and here to 2
    (2.5e-9, 2),             # and back to 2: ties go to even, not up
    (-0.5e-9, 0),
    (-1.5e-9, -2),
    (-2.5e-9, -2),
    (1.001, 1_001_000_000),  # the product is 1000999999.9999999: truncation would lose 1 ns
    (-1.001, -1_001_000_000),
    (0.0, 0),
    (3, 3 * NS_PER_S),       # an integer number of seconds stays exact
])
def test_seconds_become_the_nearest_nanosecond_ties_to_even(seconds, expected):
    ns = s_to_ns(seconds)
    assert ns == expected and type(ns) is int


def test_large_values_keep_integer_nanoseconds():
    # Ten years in seconds: the product is exact, and so is the integer.
    assert s_to_ns(315_576_000.0) == 315_576_000 * NS_PER_S
    # An absolute Unix time in float seconds: the nearest float product, not more.
    assert s_to_ns(1.7e9) == 1_700_000_000 * NS_PER_S
    assert s_to_ns(np.float64(0.25)) == 250_000_000


def test_non_finite_seconds_are_refused():
    with pytest.raises(ValueError):
        s_to_ns(float('nan'))
    with pytest.raises(OverflowError):
        s_to_ns(float('inf'))


def test_arrays_follow_the_same_rule_as_scalars():
    seconds = np.array([0.5e-9, 1.5e-9, 2.5e-9, -0.5e-9, -1.5e-9, 1.001, -1.001, 1.7e9,
                        12.3456789])
    ns = s_to_ns_array(seconds)
    assert ns.dtype == np.int64
    assert ns.tolist() == [s_to_ns(float(x)) for x in seconds]
    assert s_to_ns_array([0.001, 0.002]).tolist() == [1_000_000, 2_000_000]


def test_nanoseconds_become_seconds_as_the_integrator_computes_them():
    assert ns_to_s(1_500_000_000) == 1.5
    assert ns_to_s(-250_000_000) == -0.25
    t_ns = np.array([0, 10_000_000, 1_000_000_001], dtype=np.int64)
    np.testing.assert_array_equal(ns_to_s(t_ns), t_ns * 1e-9)   # the same bits
    assert ns_to_s(s_to_ns(0.123456789)) == pytest.approx(0.123456789, rel=1e-15)  # 1 ulp


def _product_files():
    for path in sorted(PACKAGE.rglob('*.py')):
        relative = path.relative_to(PACKAGE).as_posix()
        if path != HOME:
            yield relative, path


def _is_billion(token):
    if token.type != tokenize.NUMBER:
        return False
    try:
        return float(token.string.replace('_', '')) == 1e9
    except ValueError:
        return False


def _inline_conversions(source):
    """Yield (line, text) where code scales by a literal 1e9 or defines NS_PER_S.

    Strings and comments are skipped: a docstring may say ``sec * 1e9``.
    """
    tokens = [t for t in tokenize.generate_tokens(io.StringIO(source).readline)
              if t.type not in (tokenize.COMMENT, tokenize.NL, tokenize.NEWLINE, tokenize.INDENT,
                                tokenize.DEDENT, tokenize.STRING)]
    for i, token in enumerate(tokens):
        before = tokens[i - 1].string if i > 0 else ''
        after = tokens[i + 1].string if i + 1 < len(tokens) else ''
        if _is_billion(token) and ('*' in (before, after) or '/' in (before, after)):
            yield token.start[0], token.line.strip()
        elif (token.string == '10' and after == '**' and i + 2 < len(tokens)
              and tokens[i + 2].string == '9'):
            yield token.start[0], token.line.strip()
        elif token.string == 'NS_PER_S' and token.start[1] == 0 and after in ('=', ':'):
            yield token.start[0], token.line.strip()


def test_no_product_module_converts_seconds_inline_or_defines_ns_per_s():
    offenders = [f'{relative}:{line}: {text}' for relative, path in _product_files()
                 for line, text in _inline_conversions(path.read_text())]
    assert offenders == [], 'use skidkin_ros.core.timeunits:\n' + '\n'.join(offenders)


@pytest.mark.parametrize('code', ['t_ns = int(t_s * 1e9)\n', 't = 2 * 1_000_000_000\n',
                                  'x = 1e9 / rate\n', 'y = 600 * 10**9\n',
                                  'NS_PER_S = 1_000_000_000\n'])
def test_the_scan_sees_each_inline_form(code):
    assert len(list(_inline_conversions(code))) == 1


def test_the_scan_ignores_strings_and_other_uses_of_a_billion():
    code = ("LIMIT_M = 1e9\n'''sec * 1e9 + nanosec'''\nf = 'round(t * 1e9)'  # t * 1e9\n"
            't = sec * NS_PER_S + nanosec\n')
    assert list(_inline_conversions(code)) == []
