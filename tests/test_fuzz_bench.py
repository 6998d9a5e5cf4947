"""A bounded run of the kept fuzzers (python -m benchmarks.fuzz): no crash, every digest exact."""
from __future__ import annotations

from benchmarks import fuzz


def test_bounded_fuzz_run(capsys):
    assert fuzz.main(["--inputs", "200", "--seed", "3"]) == 0
    out = capsys.readouterr().out
    assert "0 crashes" in out and out.count("VERDICT PASS") == 3 and "VERDICT FAIL" not in out


def test_an_unexpected_error_counts_as_a_crash():
    t = fuzz.Tally()
    t.run("parse", lambda: int("x"))  # ValueError: not one of the ends' own errors
    t.run("parse", lambda: None)
    assert len(t.crashes) == 1 and "ValueError" in t.crashes[0] and t.parsed == 1
