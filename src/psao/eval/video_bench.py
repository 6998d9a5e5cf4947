"""`psao bench --methods ...,video` (or `--ao video`): PSAO against per-client video of server-rendered AO, on the same frames.

For every scene and every scored frame (the bench's frames, time t on the camera path):
  * video: the server renders a clip of `clip` frames plus the largest latency's frames at `fps`, ending
    at t (each frame for the pose, and with --animate the scene, at its own time; the camera runs its
    path `camera_speed` times faster before t; traced, accumulated and denoised by video.VideoServer),
    encodes it at each bitrate and decodes it. With latency L the client shows the newest frame
    rendered for a time <= t - L, as it is ("plain") and reprojected to the pose at t with the client's
    depth ("reprojected"). Mbit/s: the encoded bytes of every clip over their duration.
  * PSAO: the client draws the pose at t from the latest grid. A static scene's grid does not change,
    so latency changes nothing; with --animate the grid is the server's tick at t - L - 1/tick_hz (one
    tick old), ticked in this process, while the client draws the scene at t (its own clock).
    Mbit/s: Update bytes of ticks 1/tick_hz apart (zstd stream, packed layout, as `psao serve` sends).
Both are scored against the RTAO reference at t (the bench's cached references). Server costs are
measured per client and per tick; totals for many clients are modelled from them (`client_costs`).
"""
from __future__ import annotations

import argparse
import math
import time
from dataclasses import dataclass, replace

import numpy as np

from psao.options import comma_list, default
from psao.eval.errors import EvalError
from psao.eval.settings import VideoSweepSettings
from psao.eval.video import CODECS, VideoSettings, check_latency, decode_stream, encode_stream, reproject
from psao.server.settings import BakeSettings, TickSettings

# The imports inside functions below are deferred for start-up: the renderer (OpenGL), the server's tick and
# the metrics' libraries load only when the video comparison runs, not when the bench reads its options.


@dataclass
class VideoBenchConfig:
    bitrates: list[float]  # Mbit/s targets of the sweep
    latencies_ms: list[float]  # from pose to display
    clients: list[int]  # client counts of the server-cost model
    settings: VideoSettings  # codec, fps, spp, filters (bitrate replaced per sweep point)
    clip: int = 30  # frames streamed before each scored frame's earliest shown frame (rate control, GOP)
    camera_speed: float = 1.0  # the camera runs its path this many times faster around each scored pose


def add_arguments(p: argparse.ArgumentParser) -> None:
    d = VideoSettings()
    g = p.add_argument_group("video AO streaming competitor (the method video of --methods / --ao)")
    g.add_argument("--video-bitrates", default=comma_list(default(VideoSweepSettings, "bitrates")), metavar="MBITS",
                   help="video bitrates in Mbit/s, comma-separated")
    g.add_argument("--video-codec", default=d.codec, help=f"video codec: {', '.join(CODECS)}")
    g.add_argument("--video-fps", type=float, default=d.fps, help=f"video frames per second")
    g.add_argument("--video-spp", type=int, default=d.spp, help=f"AO rays per pixel per video frame")
    g.add_argument("--video-clip", type=int, default=default(VideoBenchConfig, "clip"), help="frames streamed before each scored frame")
    g.add_argument("--video-accumulate", type=float, default=d.accumulate,
                   help="temporal accumulation: weight of the reprojected history, 0 = off")
    g.add_argument("--video-denoise", type=float, default=d.denoise_px, metavar="SIGMA",
                   help=f"depth-aware Gaussian over the traced AO, sigma in pixels, 0 = off")
    g.add_argument("--camera-speed", type=float, default=default(VideoBenchConfig, "camera_speed"),
                   help="before each scored frame the camera runs its path this many times faster (fast motion; "
                        "the scored poses stay the bench's)")
    g.add_argument("--latency-ms", default=comma_list(default(VideoSweepSettings, "latencies_ms")),
                   help="latencies in ms, comma-separated")
    g.add_argument("--clients", default=comma_list(default(VideoSweepSettings, "clients")),
                   help="client counts of the server-cost table")


def parse_list(text: str, what: str, low: float, high: float) -> list[float]:
    """Sorted distinct numbers of a comma-separated option (`what`: its name), each within low..high
    (the bench's and the video comparison's list options; here, the lower of the two modules)."""
    try:
        values = [float(t) for t in str(text).split(",") if t.strip()]
    except ValueError:
        raise EvalError(f"--{what}: expected comma-separated numbers, got {text!r}") from None
    if not values:
        raise EvalError(f"--{what}: no values given")
    bad = [v for v in values if not (math.isfinite(v) and low <= v <= high)]
    if bad:
        raise EvalError(f"--{what}: {bad[0]:g} is outside {low:g}..{high:g}")
    return sorted(set(values))


def _numbers(text: str, what: str) -> list[float]:
    """Sorted distinct finite numbers; each option checks its own range with its own message."""
    return parse_list(text, what, -math.inf, math.inf)


def config_from_args(args, enabled: bool) -> VideoBenchConfig | None:
    """The video comparison's settings, or None when the video is not among the bench's methods (its
    options are still checked)."""
    settings = VideoSettings(codec=args.video_codec, fps=args.video_fps, spp=args.video_spp,
                             accumulate=args.video_accumulate, denoise_px=args.video_denoise)
    settings.check()
    bitrates = _numbers(args.video_bitrates, "video-bitrates")
    for b in bitrates:
        replace(settings, bitrate_mbit=b).check()
    latencies = [check_latency(v) for v in _numbers(args.latency_ms, "latency-ms")]
    clients = _numbers(args.clients, "clients")
    if any(c < 1 or c != int(c) for c in clients):
        raise EvalError(f"--clients: client counts must be whole numbers >= 1, got {args.clients!r}")
    if args.video_clip < 1:
        raise EvalError(f"--video-clip must be >= 1, got {args.video_clip}")
    if not (math.isfinite(args.camera_speed) and 0 < args.camera_speed <= 100):
        raise EvalError(f"--camera-speed must be within 0..100, got {args.camera_speed:g}")
    if not enabled:
        return None
    return VideoBenchConfig(bitrates, latencies, [int(c) for c in clients], settings, args.video_clip,
                            args.camera_speed)


def video_name(bitrate: float) -> str:
    return f"Video-{bitrate:g}M"


# ------------------------------------------------------------------------------------ the experiment
def _transforms_at(scene, t: float) -> np.ndarray:
    from psao.scene.rigid import instance_transform

    return np.stack([instance_transform(scene, i, t) for i in range(len(scene.instances))]) \
        if scene.instances else np.zeros((0, 4, 4))


def _lag_frames(latency_ms: float, fps: float) -> int:
    """Frames back from t of the newest frame rendered for a time <= t - latency."""
    return int(math.ceil(latency_ms * fps / 1000.0 - 1e-9))


@dataclass
class ShownSource:
    """What the client keeps of a decoded-or-raw frame it may show: the frame's view and depth."""
    view: np.ndarray
    proj: np.ndarray
    world: np.ndarray
    mask: np.ndarray


def video_clips(scene, qr, grid, poses, vcfg: VideoBenchConfig, camera_path, animate: bool, log):
    """Per scored frame: the server's AO images of its clip, the clip's shown-frame sources per lag
    (frames back from t), and the per-frame costs."""
    from psao.client.render.views import path_matrices
    from psao.eval.quality import FramePose
    from psao.eval.video import VideoServer
    from psao.scene import scene_camera

    s = vcfg.settings
    path = scene_camera(scene, camera_path)
    lags = sorted({_lag_frames(L, s.fps) for L in vcfg.latencies_ms})
    n = vcfg.clip + max(lags)
    clips, costs = [], []
    before = (lambda pose: (grid, _transforms_at(scene, pose.time))) if animate else None
    with VideoServer(scene, s) as server:
        for i, p in enumerate(poses):
            back = [j / s.fps for j in range(n - 1, -1, -1)]  # seconds before the scored frame
            clip_poses = [FramePose(k, p.time - dt, *path_matrices(scene, path, p.time - vcfg.camera_speed * dt, qr.size))
                          for k, dt in enumerate(back)]
            clip_poses[-1] = p  # the scored frame is the bench's own pose (same reference cache key)
            server.reset()  # each clip streams from scratch
            aos, sources = [], {}
            for k, (cp, f) in enumerate(zip(clip_poses, qr.render(grid, clip_poses, timing_repeats=1,
                                                                  before_frame=before))):
                ao, cost = server.render(f)
                aos.append(ao)
                costs.append(cost)
                lag = n - 1 - k
                if lag in lags:
                    sources[lag] = ShownSource(cp.view, cp.proj, np.asarray(f.gbuffer.world), f.mask)
            clips.append((aos, sources))
            log(f"{scene.name}: video clip {i + 1}/{len(poses)}: {n} frames at {s.fps:g} fps, {s.spp} spp, "
                f"{np.mean([c.trace_seconds for c in costs[-n:]]) * 1e3:.0f} ms tracing per frame")
    return clips, costs


def _show(ao: np.ndarray, src: ShownSource, now, reprojected: bool) -> np.ndarray:
    from psao.eval.metrics import composite_ao

    if reprojected:
        ao, _ = reproject(ao, src.world, src.mask, src.view, src.proj, now.gbuffer.world, now.mask)
    return composite_ao(ao, now.mask)


def score_video(scene_name: str, clips, frames, refs, vcfg: VideoBenchConfig, log) -> tuple[list[dict], dict]:
    """Rows per bitrate (and uncompressed), latency and plain/reprojected; the shown images of the middle
    frame for the side-by-side picture."""
    from psao.eval.metrics import psnr, score

    s = vcfg.settings
    rows, shown_images = [], {}
    pick = len(frames) // 2
    sweep = [*vcfg.bitrates, None]  # None: the server's AO images before encoding
    for b in sweep:
        decoded, mbit, enc_ms, codec_psnr = [], None, None, None
        if b is None:
            decoded = [aos for aos, _ in clips]
        else:
            streams = [encode_stream(aos, replace(s, bitrate_mbit=b)) for aos, _ in clips]
            decoded = [decode_stream(st) for st in streams]
            total = sum(st.total_bytes for st in streams)
            mbit = 8e-6 * total * s.fps / sum(len(st.packets) for st in streams)
            enc_ms = 1e3 * float(np.mean([x for st in streams for x in st.encode_seconds]))
            codec_psnr = float(np.mean([psnr(a, d) for (aos, _), dec in zip(clips, decoded) for a, d in zip(aos, dec)]))
        for L in vcfg.latencies_ms:
            lag = _lag_frames(L, s.fps)
            for rep in ((False, True) if lag > 0 else (False,)):
                per = []
                for i, ((aos, sources), dec, now, ref) in enumerate(zip(clips, decoded, frames, refs)):
                    img = _show(dec[len(dec) - 1 - lag], sources[lag], now, rep)
                    sc, fmap = score(ref, img)
                    per.append(sc)
                    if i == pick:
                        shown_images[(b, L, rep)] = (img, fmap, sc.as_dict())
                rows.append({"scene": scene_name, "kind": "video",
                             "method": video_name(b) if b is not None else "Video-raw",
                             "bitrate": b, "mbit_s": mbit, "latency_ms": L, "reprojected": rep,
                             "encode_ms_frame": enc_ms, "codec_psnr": codec_psnr, **_mean(per)})
        if b is not None:
            r0 = next(r for r in rows if r["bitrate"] == b and not r["reprojected"])
            log(f"{scene_name}: {video_name(b)}: {mbit:.2f} Mbit/s measured, PSNR {r0['psnr']:.2f} dB at "
                f"{vcfg.latencies_ms[0]:g} ms, decoded vs rendered {codec_psnr:.1f} dB, encode {enc_ms:.1f} ms/frame")
    return rows, shown_images


def _mean_or_nan(values) -> float:
    return float(np.mean(values)) if len(values) else float("nan")


def _mean(scores) -> dict:
    return {k: float(np.mean([getattr(x, k) for x in scores])) for k in ("psnr", "ssim", "flip", "bias")}


# ----------------------------------------------------------------------------------------------- PSAO
class UpdateMeter:
    """Bytes and encode time of the Update a `psao serve` connection would send after a tick (zstd
    stream, packed layout: the service's defaults), for one client that sees everything."""

    def __init__(self, scene, grid):
        from psao.protocol.session import ClientConfig, ClientSession, ServerConfig, ServerSession, scene_hash_bytes
        from psao.server.settings import ServeSettings

        st = ServeSettings()
        h = scene_hash_bytes(scene.content_hash())
        self.session = ServerSession(ServerConfig(h, codec=st.codec, layout=st.layout, zstd=st.zstd, limits=st.limits))
        self.session.receive(ClientSession(ClientConfig(h)).hello())
        self.settings = st
        self.tick = 0
        self.last_transforms = None
        self.snapshot_bytes, self.snapshot_s = self._snapshot(grid)

    def _snapshot(self, grid) -> tuple[int, float]:
        from psao.server.net.clients import SnapshotPlan, read_delta

        plan = SnapshotPlan.of(grid, self.settings.limits, self.settings.snapshot_cells_per_chunk)
        tf = np.zeros((len(grid.instances), 4, 4))
        total, t0 = 0, time.perf_counter()
        for i in range(len(plan)):
            delta = read_delta(grid, tf, np.arange(len(tf)), plan.bucket_chunks[i], plan.cell_chunks[i])
            total += len(self.session.snapshot(i, len(plan), delta))
        return total, time.perf_counter() - t0

    def update(self, grid, transforms: np.ndarray, server_time: float) -> tuple[int, float]:
        from psao.server.net.clients import read_delta

        b, c = grid.take_dirty()
        if self.last_transforms is None or self.last_transforms.shape != transforms.shape:
            tids = np.arange(len(transforms))
        else:
            tids = np.flatnonzero(np.any(self.last_transforms != transforms, axis=(1, 2)))
        self.last_transforms = transforms.copy()
        self.tick += 1
        t0 = time.perf_counter()
        data = self.session.update(self.tick, server_time, read_delta(grid, transforms, tids, b, c))
        return len(data), time.perf_counter() - t0


def psao_static(scene, qr, grid_file, poses) -> tuple[list, dict]:
    """Frames of a static scene (the same at every latency) and the stream's figures."""
    from psao.client.render.gridfile import load_grid_file

    g = load_grid_file(grid_file)
    frames = qr.render(g, poses, timing_repeats=1)
    meter = UpdateMeter(scene, g)
    return frames, {"mbit_s": 0.0, "snapshot_mb": meter.snapshot_bytes / 1e6, "server_ms_tick": 0.0,
                    "send_ms_tick": 0.0, "snapshot_encode_s": meter.snapshot_s}


def psao_animated(scene, qr, bake: BakeSettings, poses, latencies_ms: list[float], tick_hz: float,
                  log) -> tuple[dict, dict]:
    """Frames per latency: the grid of the tick at t - L - 1/tick_hz (ticked here), the scene drawn at t;
    Update bytes and server ms of the ticks that follow 1/tick_hz of motion (ticks clamped to the scene's
    start, t = 0, do not count: they cover less motion)."""
    from psao.eval.dynamic import AnimatedServer, AnimatedSettings

    frames = {L: [] for L in latencies_ms}
    sizes, tick_s, send_s = [], [], []
    log(f"{scene.name}: PSAO-{bake.density:g} animated: in-process bake, ticks at t - latency - 1/{tick_hz:g} s")
    with AnimatedServer(scene, AnimatedSettings(bake, tick_rays=TickSettings.rays, tick_hz=tick_hz)) as server:
        meter = UpdateMeter(scene, server.grid)
        for p in poses:
            for L in sorted(latencies_ms, reverse=True):  # ticks go forward in time
                t_grid = p.time - L / 1000.0 - 1.0 / tick_hz
                server.tick.set_cameras([(p.view, p.proj)])
                server.tick(server.grid, max(0.0, t_grid - 1.0 / tick_hz))  # catches up with the jump
                meter.update(server.grid, np.asarray(server.tick.transforms(), np.float64), t_grid)
                t0 = time.perf_counter()
                server.tick(server.grid, max(0.0, t_grid))
                tick_seconds = time.perf_counter() - t0
                n, s = meter.update(server.grid, np.asarray(server.tick.transforms(), np.float64), t_grid)
                if t_grid - 1.0 / tick_hz >= 0:  # both ticks after the scene's start: 1/tick_hz of motion
                    sizes.append(n)
                    send_s.append(s)
                    tick_s.append(tick_seconds)
                grid = server.grid
                frames[L] += qr.render(grid, [p], timing_repeats=1,
                                       before_frame=lambda pose: (grid, _transforms_at(scene, pose.time)))
        points = server.points
    if not sizes:
        log(f"{scene.name}: PSAO-{bake.density:g}: no scored frame late enough for two ticks after t = 0: no Mbit/s")
    return frames, {"mbit_s": 8e-6 * _mean_or_nan(sizes) * tick_hz, "snapshot_mb": meter.snapshot_bytes / 1e6,
                    "server_ms_tick": 1e3 * _mean_or_nan(tick_s), "send_ms_tick": 1e3 * _mean_or_nan(send_s),
                    "snapshot_encode_s": meter.snapshot_s, "points": points}


# ----------------------------------------------------------------------------------------- per scene
def compare_scene(spec: str, scene, poses, grids: dict, cfg, vcfg: VideoBenchConfig, log) -> tuple[list[dict], dict]:
    """All video and PSAO rows of one scene (quality per latency, bandwidth, server cost) and its
    side-by-side picture."""
    from psao.client.render.gridfile import load_grid_file
    from psao.eval.dynamic import is_animated
    from psao.eval.metrics import score
    from psao.eval.quality import QualityRenderer, reference_images
    from psao.eval.reference import ReferenceSettings

    animate = cfg.animate and is_animated(scene)
    hz = max(cfg.tick_hz)
    s = vcfg.settings
    with QualityRenderer(scene, cfg.size, methods=("psao",)) as qr:
        psao_rows, psao_frames = [], {}
        for d, (path, meta) in grids.items():
            if animate:
                fr, info = psao_animated(scene, qr, replace(cfg.bake, density=d), poses, vcfg.latencies_ms, hz, log)
            else:
                f0, info = psao_static(scene, qr, path, poses)
                fr = {L: f0 for L in vcfg.latencies_ms}
                info["points"] = meta.get("points_kept")
            psao_frames[d] = (fr, info)
        base = load_grid_file(grids[min(grids)][0])
        client = psao_frames[min(grids)][0][0.0 if 0.0 in vcfg.latencies_ms else vcfg.latencies_ms[0]]
        log(f"{scene.name}: video server: {s.spp} spp, {s.fps:g} fps, clips of {vcfg.clip} frames + latency")
        clips, costs = video_clips(scene, qr, base, poses, vcfg, cfg.camera_path, animate, log)
    log(f"{scene.name}: RTAO reference, {cfg.spp} spp (cached in {cfg.cache / 'rtao'})")
    refs = reference_images(scene, client, ReferenceSettings(spp=cfg.spp, cache_dir=cfg.cache / "rtao"))
    rows, shown = score_video(scene.name, clips, client, refs, vcfg, log)
    trace_ms = 1e3 * float(np.mean([c.trace_seconds for c in costs]))
    filter_ms = 1e3 * float(np.mean([c.filter_seconds for c in costs]))
    rays = float(np.mean([c.rays for c in costs]))
    for r in rows:
        r.update(rays_per_frame=rays, trace_ms_frame=trace_ms, filter_ms_frame=filter_ms, fps=s.fps, spp=s.spp,
                 codec=s.codec, animated=animate)
    pick = len(client) // 2
    psao_panels = {}
    for d, (fr, info) in psao_frames.items():
        for L in vcfg.latencies_ms:
            per = [score(ref, f.ao["psao"]) for f, ref in zip(fr[L], refs)]
            rows.append({"scene": scene.name, "kind": "psao", "method": f"PSAO-{d:g}", "density": d,
                         "latency_ms": L, "reprojected": False, "tick_hz": hz, "animated": animate, **info,
                         **_mean([sc for sc, _ in per])})
            psao_panels[(d, L)] = (fr[L][pick].ao["psao"], per[pick][1], per[pick][0].as_dict())
    image = side_by_side_data(scene.name, refs[pick], psao_panels, shown, grids, vcfg, rows)
    return rows, image


def side_by_side_data(scene_name, reference, psao_panels, shown, grids, vcfg, rows) -> dict:
    """RTAO, the densest PSAO, then the video at the bitrate nearest PSAO's Mbit/s (or the middle one):
    at the first latency, and at the last latency plain and reprojected."""
    d = max(grids)
    L0, L1 = vcfg.latencies_ms[0], vcfg.latencies_ms[-1]
    psao_mbit = next((r["mbit_s"] for r in rows if r["kind"] == "psao" and r["density"] == d), 0.0)
    b = min(vcfg.bitrates, key=lambda x: abs(math.log(x) - math.log(max(psao_mbit, 1e-3)))) if psao_mbit > 0 \
        else vcfg.bitrates[len(vcfg.bitrates) // 2]
    panels = []
    for L in (L0, L1) if L1 != L0 else (L0,):
        ao, fmap, sc = psao_panels[(d, L)]
        panels.append((f"PSAO-{d:g} {L:g} ms", ao, fmap, sc))
    for key, label in (((b, L0, False), f"{video_name(b)} {L0:g} ms"), ((b, L1, False), f"{video_name(b)} {L1:g} ms"),
                       ((b, L1, True), f"{video_name(b)} {L1:g} ms reproj.")):
        if key in shown and (key[1] != L0 or key == (b, L0, False)):
            img, fmap, sc = shown[key]
            panels.append((label, img, fmap, sc))
    return {"scene": scene_name, "reference": reference, "panels": panels}


# ------------------------------------------------------------------------------------ many clients
def client_costs(rows: list[dict], clients: list[int]) -> list[dict]:
    """Server milliseconds per client per frame (video) or per tick (PSAO) at each client count, from the
    measured per-client and per-tick costs (one machine): video = trace + filter + encode per client per
    frame, the same for every client; PSAO = the shared tick / clients + one Update encode per client.
    Totals = per client x clients (modelled, not run with that many clients)."""
    out = []
    for scene in sorted({r["scene"] for r in rows}):
        sel = [r for r in rows if r["scene"] == scene and r["latency_ms"] == min(x["latency_ms"] for x in rows)
               and not r["reprojected"]]
        for r in sel:
            if r["kind"] == "video" and r["bitrate"] is not None:
                per = r["trace_ms_frame"] + r["filter_ms_frame"] + r["encode_ms_frame"]
                shared = 0.0
            elif r["kind"] == "psao":
                per, shared = r["send_ms_tick"], r["server_ms_tick"]
            else:
                continue
            for n in clients:
                out.append({"scene": scene, "method": r["method"], "kind": r["kind"], "clients": n,
                            "ms_per_client": shared / n + per, "ms_total": shared + n * per,
                            "mbit_s": r["mbit_s"], "psnr": r["psnr"]})
    return out


def table1_rows(rows: list[dict]) -> list[dict]:
    """The video rows of the bench's Table 1 (smallest latency, encoded bitrates): quality and Mbit/s
    at the video's frame rate."""
    L0 = min(r["latency_ms"] for r in rows)
    return [{"scene": r["scene"], "method": r["method"], "density": None, "tick_hz": r["fps"], "video": True,
             "stream_mbit_s": r["mbit_s"], "psnr": r["psnr"], "ssim": r["ssim"], "flip": r["flip"],
             "bias": r["bias"], "server_ms_tick": r["trace_ms_frame"] + r["filter_ms_frame"] + r["encode_ms_frame"]}
            for r in rows if r["kind"] == "video" and r["bitrate"] is not None and r["latency_ms"] == L0
            and not r["reprojected"]]
