"""Every benchmark in one go (`make bench`), each with its default settings, in one process after another.

Each script measures its own ratio against a baseline in the same run, prints one `VERDICT PASS|FAIL`
line per target (benchmarks.verdicts) and exits 1 on a miss; this runner keeps going after a miss or a
crash, ends with one line per benchmark (its exit status and how many `VERDICT FAIL` lines it printed)
and exits non-zero if any benchmark failed, crashed or missed a target. `--only bake,tick` picks some; `--quick` passes each script the small settings
listed in QUICK_ARGS (minutes instead of about an hour on a 2-core machine). A benchmark that cannot run here
(bench_web without chromium, playwright or the page's npm packages) prints one `SKIPPED` line naming
what is missing and exits 0.

`--out DIR` gives every benchmark that writes files (TAKES_OUT) `--out DIR/NAME` and writes DIR/run_all.json
after each benchmark: the commit, and per benchmark its command, exit status and verdicts
(benchmarks.verdicts.parse_lines), which benchmarks.report renders into docs/results.md.

    .venv/bin/python -m benchmarks.run_all [--only NAMES] [--quick] [--out DIR]
"""

from __future__ import annotations

import argparse
import importlib
import io
import json
import shlex
import sys
import time
from contextlib import redirect_stdout
from pathlib import Path

from benchmarks.verdicts import count_failures, parse_lines
from psao.eval.bench_cli import source_commit

# Order: cheapest first, so a broken install shows up early. Each name is benchmarks.bench_NAME, or the
# module MODULES names.
BENCHMARKS = ("fuzz", "points", "bake", "bandwidth", "render", "tick", "static_hits", "quality", "culling", "clients", "web",
              "three", "denoise", "video", "realtime", "dask", "progressive", "scenes", "objects", "densify",
              "baselines", "soak", "links")
MODULES = {"fuzz": "benchmarks.fuzz"}
# The benchmarks whose parser takes --out DIR (where they write their JSON, tables and charts).
TAKES_OUT = ("points", "bake", "bandwidth", "tick", "quality", "clients", "web", "three", "video", "realtime", "dask",
             "progressive", "scenes", "objects", "baselines", "soak", "links")

# Small settings per benchmark for --quick: same code paths, fewer points, frames and ticks.
QUICK_ARGS = {
    "fuzz": ["--inputs", "2000"],
    "points": ["--points", "200000", "--pcu-samples", "50000"],
    "bake": ["--densities", "64", "--probes", "4000", "--probe-rays", "256"],
    "bandwidth": ["--density", "64", "--animated-ticks", "20", "--ticks", "30", "--random-ticks", "10"],
    "render": ["--densities", "64,256", "--frames", "2"],
    "tick": ["--density", "64", "--ticks", "10", "--ticks-off", "2", "--sweep", ""],
    "static_hits": ["--density", "16", "--repeats", "1"],
    "quality": ["--densities", "512", "--frames", "2", "--spp", "64"],
    "web": ["--density", "16", "--updates", "10", "--frames", "3", "--codecs", "zstd-stream"],
    "three": ["--density", "16", "--updates", "5", "--frames", "3", "--rounds", "2"],
    "denoise": ["--scenes", "builtin:robots", "--frames", "1", "--repeats", "3"],
    "video": ["--scenes", "builtin:robots", "--densities", "32,64", "--size", "160x90", "--frames", "2", "--spp", "32",
              "--clip", "8", "--bitrates", "0.25,1,4,20"],
    "realtime": ["--parts", "tracer,grid", "--tracer-density", "32", "--bake-points", "20000", "--bake-rays", "16",
                 "--tick-points", "4000", "--repeats", "2", "--skinned-points", "10000", "--grid-ticks", "5"],
    "dask": ["--density", "64", "--repeats", "1", "--large", "builtin:courtyard-3x3", "--rate-points", "30000"],
    "culling": ["--seconds", "8", "--warmup", "1"],
    "clients": ["--counts", "1,10", "--density", "32", "--seconds", "5"],
    "scenes": ["--scenes", "builtin:cornell", "--scales", "1", "--probes", "2000", "--probe-rays", "64", "--spp", "16",
               "--frames", "1"],
    "objects": ["--probes", "1000"],
    "densify": ["--scene", "builtin:cornell", "--frames", "1", "--rounds", "2", "--probes", "2000", "--size", "160x90"],
    "baselines": ["--methods", "ssao,gtao,psao", "--frames", "1", "--spp", "32", "--no-stream", "--sponza-density", "64"],
    "progressive": ["--scenes", "courtyard", "--rays", "32", "--marks", "1,3,5", "--probes", "4000", "--ref-rays", "256"],
    "links": ["--quick", "--density", "64", "--seconds", "5"],
    "soak": ["--minutes", "1.5", "--clients", "4", "--event-seconds", "4", "--host-kill-seconds", "30"],
}


class _Tee(io.TextIOBase):
    """Writes through to the terminal and keeps a copy, so the verdicts can be counted afterwards."""

    def __init__(self, out):
        self.out, self.copy = out, io.StringIO()

    def write(self, text: str) -> int:
        self.copy.write(text)
        return self.out.write(text)

    def flush(self) -> None:
        self.out.flush()


def module_name(name: str) -> str:
    """The module that runs benchmark `name`."""
    return MODULES.get(name, f"benchmarks.bench_{name}")


def run_one(name: str, args: list[str], printed: list[str] | None = None) -> tuple[int, int, float]:
    """Run benchmarks.bench_NAME.main(args) (or MODULES[NAME].main); returns (exit code, FAIL verdicts printed, wall seconds).
    A crash counts as exit code 2. `printed`, when given, gets what the benchmark printed."""
    start = time.perf_counter()
    tee = _Tee(sys.stdout)
    try:
        with redirect_stdout(tee):
            module = importlib.import_module(module_name(name))
            rc = int(module.main(args) or 0)
    except SystemExit as exc:  # argparse errors and scripts that call sys.exit
        rc = exc.code if isinstance(exc.code, int) else 1
    except Exception as exc:  # keep going: one broken benchmark must not hide the others' figures
        print(f"run_all: bench_{name} failed: {type(exc).__name__}: {exc}", file=sys.stderr)
        rc = 2
    fails = count_failures(tee.copy.getvalue())
    if printed is not None:
        printed.append(tee.copy.getvalue())
    return rc, fails, time.perf_counter() - start


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", default=",".join(BENCHMARKS), help="comma list of: " + ", ".join(BENCHMARKS))
    ap.add_argument("--quick", action="store_true", help="small settings (QUICK_ARGS) for a smoke run")
    ap.add_argument("--out", type=Path, help="give each benchmark --out OUT/NAME; write OUT/run_all.json")
    a = ap.parse_args(argv)
    names = [n.strip() for n in a.only.split(",") if n.strip()]
    unknown = [n for n in names if n not in BENCHMARKS]
    if unknown:
        ap.error(f"unknown benchmark(s): {', '.join(unknown)}")

    results, record = [], {"quick": a.quick, "commit": source_commit(), "benchmarks": []}
    for name in names:
        print(f"\n=== bench_{name} ===", flush=True)
        args = list(QUICK_ARGS[name] if a.quick else [])
        if a.out is not None and name in TAKES_OUT:
            args += ["--out", str(a.out / name)]
        printed: list[str] = []
        rc, fails, seconds = run_one(name, args, printed)
        results.append((name, rc, fails, seconds))
        if a.out is not None:
            record["benchmarks"].append({"name": name, "command": shlex.join(["python", "-m", module_name(name), *args]),
                                         "rc": rc, "verdicts": parse_lines(printed[0])})
            a.out.mkdir(parents=True, exist_ok=True)
            (a.out / "run_all.json").write_text(json.dumps(record, indent=1) + "\n")

    print("\n=== summary ===")
    for name, rc, fails, seconds in results:
        verdict = f"exit {rc}" + (f", {fails} FAIL verdict(s)" if fails else ", no FAIL verdict")
        print(f"bench_{name:<10} {seconds:8.1f} s  {verdict}")
    return 0 if all(rc == 0 and fails == 0 for _, rc, fails, _ in results) else 1


if __name__ == "__main__":
    sys.exit(main())
