"""benchmarks.run_all reaches every kept benchmark, each with quick settings its own parser accepts."""
from pathlib import Path

import pytest

from benchmarks import run_all

BENCH_DIR = Path(run_all.__file__).parent


def test_every_benchmark_script_is_in_run_all():
    scripts = {p.stem.removeprefix("bench_") for p in BENCH_DIR.glob("bench_*.py")} | {"fuzz"}
    assert scripts == set(run_all.BENCHMARKS)
    assert set(run_all.QUICK_ARGS) == set(run_all.BENCHMARKS)


@pytest.mark.parametrize("name", ["culling", "soak", "clients", "fuzz"])
def test_unknown_option_is_refused_in_the_verdict_format(name, capsys):
    """A benchmark run from run_all that cannot start counts as failed (exit 2), not as passed."""
    rc, fails, _ = run_all.run_one(name, ["--no-such-option"])
    assert rc == 2 and fails == 0
