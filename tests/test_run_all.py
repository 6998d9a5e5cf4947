"""benchmarks.run_all reaches every kept benchmark, each with quick settings its own parser accepts."""
import json
from pathlib import Path

import pytest

from benchmarks import run_all
from benchmarks.verdicts import Verdicts, parse_lines
from support.benchmarks import help_options

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


@pytest.mark.parametrize("name", run_all.BENCHMARKS)
def test_quick_settings_and_out_are_options_of_the_benchmark(name):
    """Every option QUICK_ARGS passes is one the benchmark's parser lists, and run_all gives --out exactly to
    the benchmarks that take it."""
    options = help_options(run_all.module_name(name))
    passed = {a for a in run_all.QUICK_ARGS[name] if a.startswith("--")}
    assert passed <= options, f"bench_{name} has no option {sorted(passed - options)}"
    assert ("--out" in options) == (name in run_all.TAKES_OUT)


def test_run_all_json_records_each_benchmark_and_its_verdicts(tmp_path, capsys):
    """run_all --out writes the command it ran, the exit status and the verdicts printed, as parsed back."""
    assert run_all.main(["--only", "fuzz", "--quick", "--out", str(tmp_path)]) == 0
    record = json.loads((tmp_path / "run_all.json").read_text())
    (entry,) = record["benchmarks"]
    assert entry["name"] == "fuzz" and entry["rc"] == 0
    assert entry["command"] == "python -m benchmarks.fuzz " + " ".join(run_all.QUICK_ARGS["fuzz"])
    printed = capsys.readouterr().out
    assert entry["verdicts"] == parse_lines(printed) and len(entry["verdicts"]) == printed.count("VERDICT ")


def test_parse_lines_reads_back_what_verdicts_print(capsys):
    v = Verdicts("bench_x")
    v.check("courtyard holes %: at N=64", 0.19, "<", 0.1)
    v.record("grids identical", True, "3 of 3")
    v.record("mirror exact", True)
    parsed = parse_lines(capsys.readouterr().out)
    assert parsed == [
        {"outcome": "FAIL", "bench": "bench_x", "what": "courtyard holes %: at N=64", "value": "0.19", "op": "<",
         "target": "0.1"},
        {"outcome": "PASS", "bench": "bench_x", "what": "grids identical", "detail": "3 of 3"},
        {"outcome": "PASS", "bench": "bench_x", "what": "mirror exact", "detail": ""}]
