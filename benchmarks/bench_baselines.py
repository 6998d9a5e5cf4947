"""PSAO against the baselines users would pick instead (GTAO, NNAO, MLP baking, AOGAN), via `psao bench`.

Targets: on every built-in scene GTAO has a higher PSNR than SSAO; on every scene PSAO (N = 512; Sponza at
--sponza-density) has a higher PSNR and a lower FLIP than GTAO. Sponza (../shared/scenes/sponza) is scored
too when present, in a second `psao bench` run (its own table and chart under OUT/sponza). The table's
client ms are a speed figure: run it unniced under the shared benchmark lock.
The learned methods are rows of the table (NNAO and AOGAN were trained on scenes/pavilion.toml and
scenes/playground.toml, kept out of this benchmark; MLP baking is trained per scene on its own grid).

    python -m benchmarks.bench_baselines [--methods ssao,gtao,nnao,mlp,aogan,psao] [--frames 3] [--spp 512]
        [--sponza-density 512] [--mlp-steps 1500] [--no-stream]
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from benchmarks.verdicts import Verdicts

BUILTINS = ("builtin:cornell", "builtin:courtyard", "builtin:space", "builtin:robots")
SPONZA = Path(__file__).resolve().parents[1].parent / "shared" / "scenes" / "sponza" / "sponza_s_lod4.glb"
TARGET_N = 512.0


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--methods", default="ssao,gtao,nnao,mlp,aogan,psao")
    p.add_argument("--frames", type=int, default=3)
    p.add_argument("--spp", type=int, default=512)
    p.add_argument("--tick-hz", default="60")
    p.add_argument("--sponza-density", type=float, default=TARGET_N,
                   help="PSAO density N for Sponza (its N = 512 bake is about 3 M points)")
    p.add_argument("--mlp-steps", type=int, default=1500, help="Adam steps of MLP baking per scene")
    p.add_argument("--no-stream", action="store_true", help="skip the server/client runs (quality and client ms only)")
    p.add_argument("--image-scale", type=float, default=1.0, help="scale of the side-by-side PNGs")
    p.add_argument("--out", type=Path, default=Path("out") / "bench_baselines")
    a = p.parse_args(argv)
    from psao.cli import main as psao_main

    runs = [(list(BUILTINS), TARGET_N, a.out)]
    if SPONZA.is_file():
        runs.append(([str(SPONZA)], a.sponza_density, a.out / "sponza"))
    else:
        print(f"Sponza not found at {SPONZA}: built-in scenes only")
    rows, densities = [], {}
    for scenes, density, out in runs:
        rc = psao_main(["bench", *scenes, "--densities", f"{density:g}", "--tick-hz", a.tick_hz, "--frames",
                        str(a.frames), "--spp", str(a.spp), "--methods", a.methods, "--mlp-steps", str(a.mlp_steps),
                        "--image-scale", str(a.image_scale), "--out", str(out)] + (["--no-stream"] if a.no_stream else []))
        if rc != 0:
            return rc
        run_rows = json.loads((out / "results.json").read_text())
        rows += run_rows
        densities.update({r["scene"]: density for r in run_rows})
    return check_targets(rows, densities).exit_code()


def check_targets(rows: list[dict], densities: dict[str, float] | None = None) -> Verdicts:
    """Verdicts on `psao bench` rows; `densities` maps scene -> the PSAO density compared (default 512)."""
    v = Verdicts("bench_baselines")
    builtin_names = {b.split(":", 1)[1] for b in BUILTINS}
    for scene in sorted({r["scene"] for r in rows}):
        by = {r["method"]: r for r in rows if r["scene"] == scene}
        density = (densities or {}).get(scene, TARGET_N)
        gtao, ssao, psao = by.get("GTAO"), by.get("SSAO"), by.get(f"PSAO-{density:g}")
        if gtao and ssao and scene in builtin_names:
            v.check(f"{scene} GTAO PSNR minus SSAO's ({gtao['psnr']:.2f} vs {ssao['psnr']:.2f} dB)",
                    gtao["psnr"] - ssao["psnr"], ">", 0)
        if gtao and psao:
            v.check(f"{scene} PSAO-{density:g} PSNR minus GTAO's ({psao['psnr']:.2f} vs {gtao['psnr']:.2f} dB)",
                    psao["psnr"] - gtao["psnr"], ">", 0)
            v.check(f"{scene} PSAO-{density:g} FLIP minus GTAO's ({psao['flip']:.3f} vs {gtao['flip']:.3f})",
                    psao["flip"] - gtao["flip"], "<", 0)
    return v


if __name__ == "__main__":
    sys.exit(main())
