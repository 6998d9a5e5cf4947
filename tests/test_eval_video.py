"""The video AO streaming competitor: server render, H.264 round trip, reprojection, the bench's
the video method of `psao bench` end to end, and its bad input."""
from __future__ import annotations

import json
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from psao.eval.errors import EvalError
from psao.eval.metrics import psnr
from psao.eval.video import VideoServer, VideoSettings, decode_stream, encode_stream, reproject
from serving import HANG_S

ROOT = Path(__file__).resolve().parents[1]
SIZE = (96, 54)


@pytest.fixture(scope="module")
def cornell_frames():
    """Six client frames of the Cornell box 0.8 s apart on its camera path (the camera moves about 20
    pixels from the first to the last), with a tiny grid."""
    from psao.client.render.views import path_matrices
    from psao.eval.quality import FramePose, QualityRenderer
    from psao.scene import load_scene, scene_camera
    from psao.server.bake import bake_scene
    from psao.server.settings import BakeSettings

    scene = load_scene("builtin:cornell")
    path = scene_camera(scene)
    poses = [FramePose(i, 0.8 * i, *path_matrices(scene, path, 0.8 * i, SIZE)) for i in range(6)]
    bake = bake_scene(scene, BakeSettings(density=16, rays=4))
    with QualityRenderer(scene, SIZE) as qr:
        frames = qr.render(bake.grid, poses, timing_repeats=1)
    return scene, frames


@pytest.fixture(scope="module")
def rendered(cornell_frames):
    scene, frames = cornell_frames
    with VideoServer(scene, VideoSettings(spp=4, workers=1)) as server:
        out = [server.render(f) for f in frames]
    return [ao for ao, _ in out], [cost for _, cost in out]


def test_server_traces_every_covered_pixel(cornell_frames, rendered):
    _, frames = cornell_frames
    aos, costs = rendered
    for f, ao, cost in zip(frames, aos, costs):
        assert cost.rays == 4 * int(f.mask.sum())
        assert np.all(ao[~f.mask] == 1.0)
        covered = ao[f.mask]
        assert covered.min() >= 0 and covered.max() <= 1 and covered.std() > 0.02  # the box has real occlusion


def test_decoded_frames_match_rendered_within_codec_error(rendered):
    aos, _ = rendered
    high = encode_stream(aos, VideoSettings(bitrate_mbit=20.0, fps=60))
    decoded = decode_stream(high)
    assert len(decoded) == len(aos)
    for a, d in zip(aos, decoded):
        assert d.shape == a.shape
        # 8-bit luma: the round trip at a high bitrate is within a few code values everywhere
        assert np.abs(d - a).mean() < 2.0 / 255 and np.abs(d - a).max() < 24.0 / 255
        assert psnr(a, d) > 40.0
    low = encode_stream(aos, VideoSettings(bitrate_mbit=0.05, fps=60))
    assert low.total_bytes < high.total_bytes
    err_low = np.mean([np.abs(d - a).mean() for a, d in zip(aos, decode_stream(low))])
    err_high = np.mean([np.abs(d - a).mean() for a, d in zip(aos, decoded)])
    assert err_low > err_high


def test_odd_frame_sizes_round_trip(rendered):
    aos = [a[:53, :95] for a in rendered[0]]
    decoded = decode_stream(encode_stream(aos, VideoSettings(bitrate_mbit=20.0)))
    assert all(d.shape == (53, 95) for d in decoded)
    assert psnr(aos[0], decoded[0]) > 40.0


def test_reprojection_follows_the_surfaces(cornell_frames):
    """A pattern fixed on the surfaces, drawn for an old pose and reprojected with the new pose's depth,
    lands where the new pose sees it; shown unreprojected it does not."""
    _, frames = cornell_frames
    old, new = frames[0], frames[-1]

    def pattern(world):
        return (0.5 + 0.5 * np.sin(25.0 * world[..., 0]) * np.cos(21.0 * world[..., 1])).astype(np.float32)

    src = np.where(old.mask, pattern(old.gbuffer.world), 1.0)
    want = pattern(new.gbuffer.world)
    warped, valid = reproject(src, old.gbuffer.world, old.mask, old.pose.view, old.pose.proj,
                              new.gbuffer.world, new.mask)
    assert valid.sum() > 0.8 * new.mask.sum()
    err_warped = np.abs(warped - want)[valid].mean()
    err_plain = np.abs(src - want)[valid].mean()
    assert err_warped < 0.05 and err_plain > 2 * err_warped


@pytest.mark.parametrize("change,msg", [
    ({"codec": "mjpeg2000"}, "unknown video codec"),
    ({"bitrate_mbit": 0.0}, "bitrate must be > 0"),
    ({"bitrate_mbit": -1.0}, "bitrate must be > 0"),
    ({"spp": 0}, "rays per pixel"),
])
def test_settings_are_checked(change, msg):
    with pytest.raises(EvalError, match=msg):
        replace(VideoSettings(), **change).check()


def bench(tmp_path: Path, *extra: str) -> list[str]:
    return [sys.executable, "-m", "psao.cli", "bench", "builtin:cornell", "--cache", str(tmp_path / "cache"),
            "--out", str(tmp_path / "out"), "--size", "96x54", "--spp", "8", "--frames", "2", "--no-stream",
            "--densities", "64", "--tick-hz", "60", *extra]


@pytest.mark.parametrize("args,msg", [
    (["--video-codec", "mjpeg2000"], "unknown video codec 'mjpeg2000'"),
    (["--video-bitrates", "0"], "bitrate must be > 0"),
    (["--video-bitrates", "1,-2"], "bitrate must be > 0"),
    (["--video-bitrates", "-1,2"], "bitrate must be > 0"),
    (["--latency-ms", "-50,0"], "latency must be >= 0"),
    (["--latency-ms", "-50"], "latency must be >= 0"),
])
def test_bad_video_arguments_are_one_line(tmp_path, capsys, args, msg):
    from psao.cli import main  # the CLI dispatcher in this process: argument errors need no subprocess

    rc = main(bench(tmp_path, "--ao", "video", *args)[3:])
    err = capsys.readouterr().err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert rc == 2 and len(lines) == 1 and msg in lines[0], err


def test_bench_video_end_to_end(tmp_path):
    r = subprocess.run(bench(tmp_path, "--ao", "video", "--video-bitrates", "0.5,4", "--video-spp", "2",
                             "--video-clip", "3", "--latency-ms", "0,50", "--clients", "1,10"),
                       cwd=ROOT, capture_output=True, text=True, timeout=HANG_S)
    assert r.returncode == 0, r.stderr[-2000:]
    out = tmp_path / "out"
    for name in ("video_table.md", "video_results.json", "video_bandwidth_quality.png", "video_latency.png",
                 "video_clients.png", "frame_video_cornell.png", "table.md"):
        assert (out / name).is_file() and (out / name).stat().st_size > 0, name
    data = json.loads((out / "video_results.json").read_text())
    rows = data["rows"]
    video = {(r["method"], r["latency_ms"], r["reprojected"]): r for r in rows if r["kind"] == "video"}
    assert set(video) == {(m, L, rep) for m in ("Video-0.5M", "Video-4M", "Video-raw")
                          for L, rep in ((0.0, False), (50.0, False), (50.0, True))}
    assert video[("Video-4M", 0.0, False)]["mbit_s"] > video[("Video-0.5M", 0.0, False)]["mbit_s"] > 0
    psao = [r for r in rows if r["kind"] == "psao"]
    assert {r["latency_ms"] for r in psao} == {0.0, 50.0}
    # a static scene's grid is the same at every latency
    assert psao[0]["psnr"] == psao[1]["psnr"]
    costs = {(c["method"], c["clients"]): c for c in data["clients"]}
    v1, v10 = costs[("Video-4M", 1)], costs[("Video-4M", 10)]
    assert v10["ms_total"] == pytest.approx(10 * v1["ms_total"]) and v1["ms_per_client"] > 0
    assert "Video-4M" in (out / "table.md").read_text()


def _row(kind, method, L, rep=False, **kw):
    return {"scene": "s", "kind": kind, "method": method, "latency_ms": L, "reprojected": rep, **kw}


def test_bench_video_verdicts(capsys):
    from benchmarks.bench_video import check

    rows = []
    for b, mbit, cp in ((0.5, 0.6, 30.0), (2.0, 2.2, 38.0), (20.0, 19.0, 45.0)):
        rows.append(_row("video", f"Video-{b:g}M", 0.0, bitrate=b, mbit_s=mbit, codec_psnr=cp, psnr=30.0))
        rows.append(_row("video", f"Video-{b:g}M", 100.0, bitrate=b, mbit_s=mbit, codec_psnr=cp, psnr=28.0))
    rows += [_row("psao", "PSAO-64", 0.0, animated=True, mbit_s=1.0, psnr=29.0),
             _row("psao", "PSAO-128", 0.0, animated=True, mbit_s=40.0, psnr=30.0)]
    assert check(rows).exit_code() == 0
    assert capsys.readouterr().out.count("VERDICT PASS") == 4
    rows[-1]["mbit_s"] = rows[-2]["mbit_s"] = 50.0  # no PSAO density inside the video's Mbit/s range
    rows[4]["codec_psnr"] = 35.0  # the highest bitrate's round trip is too lossy
    assert check(rows).exit_code() != 0
    assert capsys.readouterr().out.count("VERDICT FAIL") == 2


def test_denoise_keeps_depth_edges_and_background():
    from psao.eval.video import masked_gaussian

    rng = np.random.default_rng(1)
    h, w = 40, 60
    depth = np.where(np.arange(w)[None, :] < 30, 2.0, 4.0) * np.ones((h, 1))  # a near and a far wall
    truth = np.where(np.arange(w)[None, :] < 30, 0.3, 0.9) * np.ones((h, 1))
    mask = np.ones((h, w), bool)
    mask[:5] = False  # background rows are not blended in and stay as they were
    noisy = np.where(mask, truth + rng.normal(0, 0.1, (h, w)), 1.0).astype(np.float32)
    out = masked_gaussian(noisy, mask, depth, 1.5)
    assert np.array_equal(out[~mask], noisy[~mask])
    assert np.abs(out - truth)[mask].mean() < 0.5 * np.abs(noisy - truth)[mask].mean()
    # the columns beside the edge keep their own wall's AO
    assert abs(out[5:, 29].mean() - 0.3) < 0.03 and abs(out[5:, 30].mean() - 0.9) < 0.03


@pytest.mark.parametrize("sigma", [0.7, 1.0, 2.0])
def test_denoise_equals_the_layered_gaussian(sigma):
    """The offset-sum denoise gives the per-layer masked Gaussian's values: on a ramp of depths (many
    layers, a floor-like slope), a step, holes in the coverage and the image's edges."""
    from benchmarks.bench_denoise import layered_gaussian
    from psao.eval.video import masked_gaussian

    rng = np.random.default_rng(7)
    h, w = 37, 52
    yy, xx = np.mgrid[0:h, 0:w]
    depth = np.where(xx < 20, 1.0 + 0.08 * yy, 6.0 - 0.03 * xx).astype(np.float32)  # ~40 layers
    mask = rng.random((h, w)) > 0.15
    ao = rng.random((h, w)).astype(np.float32)
    got = masked_gaussian(np.where(mask, ao, 1.0), mask, depth, sigma)
    want = layered_gaussian(np.where(mask, ao, 1.0), mask, depth, sigma)
    assert len(np.unique(np.floor(np.log(depth[mask]) / 0.05))) > 20
    np.testing.assert_allclose(got, want, atol=2e-6)
    assert np.array_equal(got[~mask], np.ones((~mask).sum(), np.float32))


def _result_rows(trace_ms: float, tick_ms: float, psnr: float) -> list[dict]:
    common = {"psnr": psnr, "ssim": 0.9, "flip": 0.05, "bias": 0.0}
    video = {"kind": "video", "method": "Video-2M", "bitrate": 2.0, "mbit_s": 1.9, "codec_psnr": 45.0,
             "rays_per_frame": 1000.0, "trace_ms_frame": trace_ms, "filter_ms_frame": 1.0, "encode_ms_frame": 2.0,
             "fps": 60.0, **common}
    psao = {"kind": "psao", "method": "PSAO-64", "density": 64.0, "mbit_s": 1.5, "animated": True,
            "server_ms_tick": tick_ms, "send_ms_tick": 0.5, "snapshot_encode_s": 0.1, "snapshot_mb": 0.2, **common}
    return [_row(**video, L=L) for L in (0.0, 100.0)] + [_row(**psao, L=L) for L in (0.0, 100.0)]


def test_report_merges_runs_with_locked_costs(tmp_path):
    """`bench_video --report RUNS --costs LOCKED`: quality and Mbit/s from the runs, every server cost from
    the locked run of the same scene and method, and the client table computed from those."""
    from benchmarks.bench_video import main

    for name, trace, tick, q in (("run", 900.0, 800.0, 31.0), ("locked", 90.0, 80.0, 12.0)):
        (tmp_path / name).mkdir()
        (tmp_path / name / "video_results.json").write_text(
            json.dumps({"rows": _result_rows(trace, tick, q), "clients": [{"clients": 1}, {"clients": 10}]}))
    out = tmp_path / "all"
    main(["--report", str(tmp_path / "run"), "--costs", str(tmp_path / "locked"), "--out", str(out)])
    data = json.loads((out / "video_results.json").read_text())
    by = {(r["method"], r["latency_ms"]): r for r in data["rows"]}
    assert by[("Video-2M", 0.0)]["psnr"] == 31.0 and by[("Video-2M", 0.0)]["trace_ms_frame"] == 90.0
    assert by[("PSAO-64", 100.0)]["server_ms_tick"] == 80.0 and by[("PSAO-64", 0.0)]["costs_from"]
    costs = {(c["method"], c["clients"]): c["ms_per_client"] for c in data["clients"]}
    assert costs[("Video-2M", 10)] == pytest.approx(90.0 + 1.0 + 2.0)
    assert costs[("PSAO-64", 10)] == pytest.approx(80.0 / 10 + 0.5)
    for name in ("video_table.md", "video_bandwidth_quality.png", "video_latency.png", "video_clients.png"):
        assert (out / name).stat().st_size > 0


def test_report_of_a_folder_without_results_is_one_line(tmp_path, capsys):
    from benchmarks.bench_video import main

    assert main(["--report", str(tmp_path / "nothing"), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "not a video benchmark result" in err[0]
