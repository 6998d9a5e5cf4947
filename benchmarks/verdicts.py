"""The one verdict format every benchmark prints, and the exit status that follows from it.

A benchmark makes one `Verdicts`, calls `check()` once per target and returns `exit_code()` from its
`main()`. Each check prints one line:

    VERDICT PASS  bench_tick  courtyard N=256 traced-points ratio: 61.8 >= 10
    VERDICT FAIL  bench_bake  courtyard holes %: 0.19 < 0.1

A value that is NaN or infinite never passes (a ratio over zero measured work is not a result).
`benchmarks.run_all` counts the `VERDICT FAIL` lines of every script it runs.
"""

from __future__ import annotations

import math
import operator
import re

_OPS = {"<": operator.lt, "<=": operator.le, ">": operator.gt, ">=": operator.ge}

# What run_all and tests match: the marker, the outcome, then free text.
LINE_PATTERN = re.compile(r"^VERDICT (PASS|FAIL)\s", re.MULTILINE)


def count_failures(text: str) -> int:
    """Number of `VERDICT FAIL` lines in a benchmark's output."""
    return sum(1 for m in LINE_PATTERN.finditer(text) if m.group(1) == "FAIL")


# One whole line as Verdicts prints it: outcome, bench, what, then `value OP target` or a free detail.
_WHOLE_LINE = re.compile(r"^VERDICT (PASS|FAIL)  (\S+)  (.*)$", re.MULTILINE)
_COMPARISON = re.compile(r"^(\S+) (<=|>=|<|>) (\S+)$")


def parse_lines(text: str) -> list[dict]:
    """Every verdict line of a benchmark's output as {"outcome", "bench", "what", "value", "op", "target"}
    (a `check`) or {"outcome", "bench", "what", "detail"} (a `record`); values as printed."""
    found = []
    for m in _WHOLE_LINE.finditer(text):
        outcome, bench, rest = m.groups()
        what, sep, tail = rest.rpartition(": ")
        cmp = _COMPARISON.match(tail) if sep else None
        if cmp:
            found.append({"outcome": outcome, "bench": bench, "what": what, "value": cmp.group(1),
                          "op": cmp.group(2), "target": cmp.group(3)})
        elif sep:
            found.append({"outcome": outcome, "bench": bench, "what": what, "detail": tail})
        else:
            found.append({"outcome": outcome, "bench": bench, "what": rest, "detail": ""})
    return found


def format_value(value: float) -> str:
    """Three significant figures, plain notation for ordinary magnitudes."""
    if not math.isfinite(value):
        return str(value)
    return f"{value:.3g}" if abs(value) < 1e6 else f"{value:.3e}"


class Verdicts:
    """Collects the targets of one benchmark run."""

    def __init__(self, bench: str):
        self.bench = bench
        self.results: list[tuple[str, bool]] = []

    def check(self, what: str, value: float, op: str, target: float) -> bool:
        """Print one verdict line for `value OP target` and remember it; returns whether it passed."""
        if op not in _OPS:
            raise ValueError(f"unknown comparison {op!r}; use one of {', '.join(_OPS)}")
        value = float(value)
        ok = math.isfinite(value) and bool(_OPS[op](value, target))
        print(f"VERDICT {'PASS' if ok else 'FAIL'}  {self.bench}  {what}: {format_value(value)} {op} "
              f"{format_value(float(target))}", flush=True)
        self.results.append((what, ok))
        return ok

    def record(self, what: str, ok: bool, detail: str = "") -> bool:
        """A yes/no target (e.g. grids identical byte for byte)."""
        print(f"VERDICT {'PASS' if ok else 'FAIL'}  {self.bench}  {what}" + (f": {detail}" if detail else ""),
              flush=True)
        self.results.append((what, bool(ok)))
        return bool(ok)

    @property
    def failures(self) -> int:
        return sum(1 for _, ok in self.results if not ok)

    def exit_code(self) -> int:
        """0 when every target passed, 1 on any miss."""
        return 1 if self.failures else 0
