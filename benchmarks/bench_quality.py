"""PSAO versus SSAO against the RTAO reference on every built-in scene, via `psao bench`.

Target: on every built-in scene PSAO at N = 512 has a higher PSNR and a lower FLIP than SSAO.
Prints the table and two verdict lines per scene (PSNR, FLIP); exits 1 when a scene misses the target.

    .venv/bin/python -m benchmarks.bench_quality [--densities 256,512] [--frames 4] [--spp 512] [--animate] [--out DIR]
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from benchmarks.verdicts import Verdicts

BUILTINS = ("builtin:cornell", "builtin:courtyard", "builtin:space", "builtin:robots")
TARGET_N = 512.0


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--densities", default="256,512")
    p.add_argument("--tick-hz", default="60")
    p.add_argument("--frames", type=int, default=4)
    p.add_argument("--spp", type=int, default=512)
    p.add_argument("--out", type=Path, default=Path("out") / "bench_quality")
    p.add_argument("--animate", action="store_true", help="score animated scenes at their frame times (psao bench --animate)")
    a = p.parse_args(argv)
    from psao.cli import main as psao_main

    rc = psao_main(["bench", *BUILTINS, "--densities", a.densities, "--tick-hz", a.tick_hz, "--frames", str(a.frames),
                    "--spp", str(a.spp), "--out", str(a.out), *(["--animate"] if a.animate else [])])
    if rc != 0:
        return rc
    return check_target(json.loads((a.out / "results.json").read_text())).exit_code()


def check_target(rows: list[dict], density: float = TARGET_N) -> Verdicts:
    """Per scene: PSAO's PSNR minus SSAO's > 0 dB and PSAO's FLIP minus SSAO's < 0."""
    v = Verdicts("bench_quality")
    for scene in sorted({r["scene"] for r in rows}):
        ssao = next(r for r in rows if r["scene"] == scene and r["method"] == "SSAO")
        psao = [r for r in rows if r["scene"] == scene and r.get("density") == density]
        if not psao:
            v.record(f"{scene} PSAO-{density:g} row present", False)
            continue
        v.check(f"{scene} PSAO-{density:g} PSNR minus SSAO's ({psao[0]['psnr']:.2f} vs {ssao['psnr']:.2f} dB)",
                psao[0]["psnr"] - ssao["psnr"], ">", 0.0)
        v.check(f"{scene} PSAO-{density:g} FLIP minus SSAO's ({psao[0]['flip']:.3f} vs {ssao['flip']:.3f})",
                psao[0]["flip"] - ssao["flip"], "<", 0.0)
    return v


if __name__ == "__main__":
    sys.exit(main())
