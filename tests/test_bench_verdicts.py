"""The shared benchmark verdict format: pass/fail, NaN and infinity never pass, failures counted."""

import math

import pytest

from benchmarks.verdicts import Verdicts, count_failures


def test_checks_print_one_line_each_and_set_the_exit_code(capsys):
    v = Verdicts("bench_x")
    assert v.check("ratio", 2.0, ">=", 1.5)
    assert not v.check("holes %", 0.2, "<", 0.1)
    assert v.record("grids identical", True)
    out = capsys.readouterr().out
    assert out.splitlines() == ["VERDICT PASS  bench_x  ratio: 2 >= 1.5",
                                "VERDICT FAIL  bench_x  holes %: 0.2 < 0.1",
                                "VERDICT PASS  bench_x  grids identical"]
    assert count_failures(out) == 1 and v.failures == 1 and v.exit_code() == 1


@pytest.mark.parametrize("value", [math.nan, math.inf, -math.inf])
def test_non_finite_values_fail(value, capsys):
    v = Verdicts("bench_x")
    assert not v.check("ratio", value, ">=", 1.0) and not v.check("ratio", value, "<", 1.0)
    assert v.exit_code() == 1 and count_failures(capsys.readouterr().out) == 2


def test_all_passing_exits_zero():
    v = Verdicts("bench_x")
    v.check("a", 1, "<=", 1)
    assert v.exit_code() == 0


def test_unknown_operator_is_refused():
    with pytest.raises(ValueError):
        Verdicts("bench_x").check("a", 1, "==", 1)
