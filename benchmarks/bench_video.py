"""PSAO against per-client video of server-rendered AO (H.264 through PyAV), via `psao bench --methods psao,video`.

Runs the bench on an animated and a static built-in scene with PSAO at several densities and the video
at several bitrates, 0 / 50 / 100 ms of latency, the camera run `--camera-speed` times faster before
each scored frame, and prints the video tables. Targets (VERDICT lines):
  * the codec round trip: decoded frames against the server's rendered AO at the highest bitrate,
    PSNR >= 40 dB (what the client shows is what the server rendered, up to the codec);
  * rate control: no stream overshoots its target bitrate by more than 1.5x (targets >= 0.5 Mbit/s;
    below a target the encoder may stop at its finest quantiser: small AO frames need less);
  * equal bandwidth: on the animated scene, the PSAO densities' Mbit/s lie inside the video sweep's
    range (fraction of densities >= 0.5), so the two curves can be read at equal Mbit/s;
  * latency: the video's PSNR drops from 0 ms to the largest latency on the moving camera (> 0 dB).
No target says which method wins: the tables and charts show that, per scene.

    .venv/bin/python -m benchmarks.bench_video [--scenes builtin:robots,builtin:cornell] [--size 320x180] ...

Quality and bytes do not depend on the machine's load, milliseconds do: `--report DIR... --costs DIR...`
merges the results of several runs (quality runs, e.g. one scene each) with the server costs of short
runs made under the benchmark lock (same scenes, densities and bitrates), and writes the tables, charts
and verdicts of the whole to --out:

    .venv/bin/python -m benchmarks.bench_video --report out/bv_a out/bv_b --costs out/bvc_a out/bvc_b --out out/bv_all
"""
from __future__ import annotations

import argparse
import json
import shutil
import sys
from pathlib import Path

from benchmarks.verdicts import Verdicts


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scenes", default="builtin:robots,builtin:cornell", help="comma-separated scenes")
    p.add_argument("--densities", default="32,64,128,256")
    p.add_argument("--bitrates", default="0.25,0.5,1,2,4,8,20", help="video Mbit/s; the last is the round-trip check's")
    p.add_argument("--size", default="320x180")
    p.add_argument("--frames", type=int, default=2)
    p.add_argument("--spp", type=int, default=128, help="RTAO reference rays per pixel")
    p.add_argument("--video-spp", type=int, default=8)
    p.add_argument("--clip", type=int, default=20, help="video frames streamed before each scored frame")
    p.add_argument("--camera-speed", type=float, default=4.0)
    p.add_argument("--latency-ms", default="0,50,100", help="latencies in ms, comma-separated")
    p.add_argument("--out", type=Path, default=Path("out") / "bench_video")
    p.add_argument("--cache", type=Path, default=Path("out") / ".cache")
    p.add_argument("--report", type=Path, nargs="+", metavar="DIR",
                   help="merge the results in these output folders instead of running")
    p.add_argument("--costs", type=Path, nargs="+", metavar="DIR",
                   help="with --report: take the server costs from these (locked) runs' results")
    a = p.parse_args(argv)
    if a.report:
        return report(a.report, a.costs or [], a.out)
    if a.costs:
        p.error("--costs needs --report")
    from psao.cli import main as psao_main

    rc = psao_main(["bench", *a.scenes.split(","), "--densities", a.densities, "--tick-hz", "60",
                    "--frames", str(a.frames), "--spp", str(a.spp), "--size", a.size, "--no-stream", "--animate",
                    "--out", str(a.out), "--cache", str(a.cache), "--methods", "psao,video", "--video-bitrates", a.bitrates,
                    "--video-spp", str(a.video_spp), "--video-clip", str(a.clip), "--camera-speed",
                    str(a.camera_speed), "--latency-ms", a.latency_ms])
    if rc != 0:
        return rc
    print((a.out / "video_table.md").read_text())
    return check(json.loads((a.out / "video_results.json").read_text())["rows"]).exit_code()


def report(folders: list[Path], cost_folders: list[Path], out: Path) -> int:
    """Tables, charts and verdicts of several runs' rows, with the costs of the cost runs when given;
    the runs' side-by-side frames are copied along."""
    from psao.eval import video_report
    from psao.eval.errors import EvalError
    from psao.eval.video_bench import client_costs

    try:
        rows = [r for f in folders for r in video_report.read_results(f)["rows"]]
        if cost_folders:
            cost_rows = [r for f in cost_folders for r in video_report.read_results(f)["rows"]]
            rows = video_report.merge_costs(rows, cost_rows, " ".join(map(str, cost_folders)))
    except EvalError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    out.mkdir(parents=True, exist_ok=True)
    clients = sorted({c["clients"] for f in folders for c in video_report.read_results(f)["clients"]})
    video_report.write_outputs(rows, [], client_costs(rows, clients), out)
    for f in folders:
        for png in Path(f).glob("frame_video_*.png"):
            shutil.copy(png, out / png.name)
    print((out / "video_table.md").read_text())
    return check(rows).exit_code()


def check(rows: list[dict]) -> Verdicts:
    v = Verdicts("bench_video")
    L0, L1 = min(r["latency_ms"] for r in rows), max(r["latency_ms"] for r in rows)
    for scene in sorted({r["scene"] for r in rows}):
        video = [r for r in rows if r["scene"] == scene and r["kind"] == "video" and r["bitrate"] is not None
                 and not r["reprojected"]]
        at0 = [r for r in video if r["latency_ms"] == L0]
        top = max(at0, key=lambda r: r["bitrate"])
        v.check(f"{scene} decoded vs rendered PSNR dB at {top['bitrate']:g} Mbit/s", top["codec_psnr"], ">=", 40.0)
        ratios = [r["mbit_s"] / r["bitrate"] for r in at0 if r["bitrate"] >= 0.5]
        v.check(f"{scene} measured / target Mbit/s, highest", max(ratios), "<=", 1.5)
        psao = [r for r in rows if r["scene"] == scene and r["kind"] == "psao" and r["latency_ms"] == L0]
        if any(r["animated"] for r in psao):
            lo, hi = min(r["mbit_s"] for r in at0), max(r["mbit_s"] for r in at0)
            inside = sum(lo <= r["mbit_s"] <= hi for r in psao) / len(psao)
            v.check(f"{scene} PSAO densities inside the video's Mbit/s range (fraction)", inside, ">=", 0.5)
        if L1 > L0:
            mid = sorted(at0, key=lambda r: r["bitrate"])[len(at0) // 2]
            late = next(r for r in video if r["bitrate"] == mid["bitrate"] and r["latency_ms"] == L1)
            v.check(f"{scene} {mid['method']} PSNR loss from {L0:g} to {L1:g} ms (dB)", mid["psnr"] - late["psnr"],
                    ">", 0.0)
    return v


if __name__ == "__main__":
    sys.exit(main())
