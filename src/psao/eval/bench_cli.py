"""`psao bench SCENE...`: PSAO and the methods of --methods (alias --ao) against an RTAO reference, and PSAO's stream.

For every scene:
  1. `psao bake` per density (a real process; grids cached under CACHE/grids by scene hash, N and rays);
  2. quality: PSAO from each grid and every baseline method, in one headless renderer along the camera path, against RTAO
     traced from the same G-buffer (cached under CACHE/rtao), scored with PSNR, SSIM and FLIP;
  3. stream: per density and tick rate a real `psao serve --grid FILE --density N --tick-hz H` process on a
     free 127.0.0.1 port and a real headless `psao client` for --stream-seconds after its snapshot:
     snapshot size, Mbit/s after it, and the server's milliseconds per tick from its statistics.
With `video` among the methods, PSAO is also compared with per-client video of server-rendered AO
(video_bench: equal bandwidth, latency, many clients).
Writes table.md, table.csv, results.json, runtime_error.png, bandwidth_quality.png and one side-by-side
image per scene (frame_SCENE.png) to --out. Server processes are killed (their whole process group) on
every exit path.
"""
from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import math
import re
import time
from dataclasses import dataclass
from pathlib import Path

from psao.options import comma_list, default
from psao.client.render.renderer import AO_METHODS, MethodOptions
from psao.client.render.ssao_pass import SsaoSettings
from psao.eval import video_bench
from psao.eval.video_bench import parse_list
from psao.eval.errors import EvalError
from psao.eval.reference import ReferenceSettings
from psao.eval.settings import BenchSettings
from psao.server.cli.bake import add_bake_arguments, bake_arguments, bake_settings
from psao.server.settings import BakeSettings, TickSettings

# The imports inside functions below are deferred for start-up: the renderer (OpenGL), the server's stages,
# PyTorch and matplotlib load only in the step that uses them, so `psao bench --help` and a bad option answer at once.

TICK_RAYS = default(TickSettings, "rays")  # rays per re-traced point of an animating server
DEFAULT_METHODS = BenchSettings.methods
VIDEO_METHOD = "video"  # server-rendered AO streamed per client as video (video_bench), not a client pass


def add_arguments(p: argparse.ArgumentParser) -> None:
    # A value that starts with a minus and a digit ("-1,2" for a list option) is a value, not an option,
    # so its range check gives the one-line error (argparse before 3.12.7 only takes "-1" or "-1.5"; this
    # is the pattern later versions use).
    p._negative_number_matcher = re.compile(r"-\.?\d")
    p.add_argument("scenes", nargs="+", metavar="SCENE", help="builtin:NAME, a scene .toml, or a glTF/OBJ/... file")
    p.add_argument("--densities", default=comma_list(default(BenchSettings, "densities")),
                   help="PSAO densities N, comma-separated")
    p.add_argument("--tick-hz", default=comma_list(default(BenchSettings, "tick_hz")),
                   help="server tick rates for the stream, comma-separated")
    p.add_argument("--frames", type=int, default=default(BenchSettings, "frames"),
                   help="frames along the camera path scored per scene")
    p.add_argument("--spp", type=int, default=default(ReferenceSettings, "spp"), help="RTAO reference rays per pixel")
    p.add_argument("--size", default=default(BenchSettings, "size"), metavar="WxH", help="frame size")
    p.add_argument("--ssao-samples", type=int, default=default(SsaoSettings, "samples"), help="SSAO kernel size")
    p.add_argument("--methods", "--ao", dest="methods", default=comma_list(default(BenchSettings, "methods")), metavar="LIST",
                   help=f"AO methods scored against RTAO, comma-separated: the renderer's --ao names "
                        f"({', '.join(AO_METHODS)}) and {VIDEO_METHOD} (per-client video of server-rendered AO, "
                        f"compared with PSAO at equal bandwidth, under latency and per client: see the video "
                        f"options); psao is always scored, one row per density, and every row is compared with it")
    p.add_argument("--gtao-preset", default=default(MethodOptions, "gtao_preset"), metavar="NAME",
                   help="GTAO slices x steps: speed, quality, ultra")
    p.add_argument("--mlp-steps", type=int, default=default(BenchSettings, "mlp_steps"),
                   help="Adam steps of MLP baking, trained per scene on the first density's grid")
    p.add_argument("--stream-seconds", type=float, default=default(BenchSettings, "stream_seconds"), help="seconds the client runs after its snapshot, per config")
    p.add_argument("--camera-path", default=None, metavar="NAME", help="camera path (the scene's first by default)")
    p.add_argument("--out", type=Path, default=default(BenchSettings, "out"), metavar="DIR", help="output folder")
    p.add_argument("--cache", type=Path, default=default(BenchSettings, "cache"), metavar="DIR",
                   help="cache of grids and RTAO references")
    p.add_argument("--no-stream", action="store_true", help="skip the server/client runs (quality only)")
    p.add_argument("--animate", action="store_true",
                   help="animated scenes: score each frame at its scene time (server tick in process) and stream "
                        "from `psao serve --animate` (static scenes are unaffected)")
    p.add_argument("--image-scale", type=float, default=default(BenchSettings, "image_scale"),
                   help="scale of the side-by-side PNGs")
    p.add_argument("--json", action="store_true", help="print the table's rows as one JSON array as the last line")
    add_bake_arguments(p, density=False)
    video_bench.add_arguments(p)


@dataclass
class BenchConfig:
    scenes: list[str]
    densities: list[float]
    tick_hz: list[float]
    frames: int
    spp: int
    size: tuple[int, int]
    bake: BakeSettings  # every bake's settings but its density (one of densities)
    ssao_samples: int
    stream_seconds: float
    camera_path: str | None
    out: Path
    cache: Path
    stream: bool = True
    image_scale: float = BenchSettings.image_scale
    animate: bool = False
    methods: tuple[str, ...] = DEFAULT_METHODS
    gtao_preset: str = MethodOptions.gtao_preset
    mlp_steps: int = BenchSettings.mlp_steps
    video: video_bench.VideoBenchConfig | None = None  # set when VIDEO_METHOD is among the methods

    @property
    def render_methods(self) -> tuple[str, ...]:
        """The methods the client's renderer draws (all but the video, which the server renders)."""
        return tuple(m for m in self.methods if m != VIDEO_METHOD)

    @property
    def baselines(self) -> tuple[str, ...]:
        """The renderer's methods scored beside PSAO, in the renderer's order."""
        return tuple(m for m in self.render_methods if m != "psao")

    def method_options(self, **weights):
        from psao.client.render.renderer import MethodOptions

        return MethodOptions(ssao_samples=self.ssao_samples, gtao_preset=self.gtao_preset, **weights)


def config_from_args(args) -> BenchConfig:
    from psao.client.errors import RenderError
    from psao.client.render.output import parse_size

    try:
        size = parse_size(args.size)
    except RenderError as exc:
        raise EvalError(str(exc)) from None
    if min(size) < 8:
        raise EvalError(f"--size {args.size}: frames must be at least 8x8 pixels")
    for name, v in (("frames", args.frames), ("spp", args.spp), ("ssao-samples", args.ssao_samples),
                    ("mlp-steps", args.mlp_steps)):
        if v < 1:
            raise EvalError(f"--{name} must be >= 1, got {v}")
    if not (0.05 <= args.image_scale <= 4):
        raise EvalError(f"--image-scale must be within 0.05..4, got {args.image_scale}")
    if not (args.stream_seconds > 0 and math.isfinite(args.stream_seconds)):
        raise EvalError(f"--stream-seconds must be > 0, got {args.stream_seconds}")
    methods = parse_methods(args.methods)
    from psao.client.render.gtao_pass import GTAO_PRESETS

    if args.gtao_preset not in GTAO_PRESETS:
        raise EvalError(f"--gtao-preset {args.gtao_preset!r}: expected one of {', '.join(GTAO_PRESETS)}")
    return BenchConfig(scenes=list(args.scenes), densities=parse_list(args.densities, "densities", 1e-3, 1e7),
                       tick_hz=parse_list(args.tick_hz, "tick-hz", 5, 60), frames=args.frames, spp=args.spp,
                       size=size, bake=bake_settings(args), ssao_samples=args.ssao_samples, stream_seconds=args.stream_seconds,
                       camera_path=args.camera_path, out=args.out, cache=args.cache, stream=not args.no_stream,
                       image_scale=args.image_scale, animate=args.animate, methods=methods,
                       gtao_preset=args.gtao_preset, mlp_steps=args.mlp_steps,
                       video=video_bench.config_from_args(args, VIDEO_METHOD in methods))


def parse_methods(text: str) -> tuple[str, ...]:
    """The renderer's methods named (psao always among them), in its order, then VIDEO_METHOD if named."""
    from psao.client.errors import RenderError
    from psao.client.render.renderer import parse_ao_modes

    names = [t.strip().lower() for t in str(text).split(",") if t.strip()]
    client = ["psao", *(n for n in names if n != VIDEO_METHOD)]
    try:
        methods = parse_ao_modes(",".join(client))
    except RenderError as exc:
        raise EvalError(f"--methods: {exc}, or {VIDEO_METHOD}") from None
    return methods + ((VIDEO_METHOD,) if VIDEO_METHOD in names else ())


def ensure_writable(folder: Path, what: str) -> Path:
    """Create the folder and prove a file can be written there, or fail with one line."""
    folder = Path(folder)
    try:
        folder.mkdir(parents=True, exist_ok=True)
        probe = folder / ".psao-write-test"
        probe.write_text("ok")
        probe.unlink()
    except OSError as exc:
        raise EvalError(f"{what} {folder} cannot be written: {exc.strerror or exc}") from None
    return folder


class Log:
    """Step lines on stderr with the elapsed time (rich when stderr is a terminal)."""

    def __init__(self):
        from rich.console import Console

        self.console = Console(stderr=True, highlight=False)
        self.t0 = time.perf_counter()

    def __call__(self, text: str) -> None:
        self.console.print(f"[{time.perf_counter() - self.t0:6.1f} s] {text}", markup=False, soft_wrap=True)


def grid_path(cache: Path, scene, settings: BakeSettings) -> Path:
    """Cache entry of a bake: named by scene, N and rays, and by a digest of the other bake options when
    they are not the defaults."""
    options = bake_arguments(dataclasses.replace(settings, density=BakeSettings.density, rays=BakeSettings.rays,
                                                 workers=BakeSettings.workers))
    extra = "" if options == bake_arguments(BakeSettings()) else "-" + hashlib.sha256(" ".join(options).encode()).hexdigest()[:8]
    return cache / "grids" / f"{scene.name}-{scene.content_hash()[:12]}-N{settings.density:g}-R{settings.rays}{extra}.npz"


def bake_cached(spec: str, scene, settings: BakeSettings, cache: Path, log: Log) -> tuple[Path, dict]:
    from psao.client.render.gridfile import load_grid_file
    from psao.eval.processes import bake_grid

    density, rays = settings.density, settings.rays
    path = grid_path(cache, scene, settings)
    if path.is_file():
        try:
            return path, dict(load_grid_file(path).meta)
        except Exception:  # noqa: BLE001 - a damaged cache entry is simply baked again
            pass
    log(f"{scene.name}: psao bake N={density:g}, {rays} rays")
    tmp = path.with_name(path.stem + ".partial.npz")
    tmp.parent.mkdir(parents=True, exist_ok=True)
    stats = bake_grid(spec, settings, tmp)
    tmp.replace(path)
    log(f"{scene.name}: baked {stats.get('points_kept', 0):,} points in {stats.get('seconds_trace', 0):.1f} s of tracing")
    return path, stats


def method_name(density: float) -> str:
    return f"PSAO-{density:g}"


def bench_scene(spec: str, cfg: BenchConfig, log: Log) -> tuple[list[dict], dict, tuple | None]:
    """All rows of one scene, the data of its side-by-side image and, with the video method, the video
    comparison's rows and image."""
    from psao.eval.quality import frame_poses
    from psao.scene import load_scene

    scene = load_scene(spec)
    if not scene.camera_paths and cfg.camera_path is None:
        log(f"warning: scene '{scene.name}' has no camera path: using an orbit around its bounds")
    poses = frame_poses(scene, cfg.frames, cfg.size, cfg.camera_path)
    grids = {d: bake_cached(spec, scene, dataclasses.replace(cfg.bake, density=d), cfg.cache, log) for d in cfg.densities}
    baseline_rows, quality, image = score_scene(scene, poses, grids, cfg, log)
    rows = list(baseline_rows)
    for d in cfg.densities:
        base = {"scene": scene.name, "method": method_name(d), "density": d, **quality[d]}
        if not cfg.stream:
            rows.append({**base, "tick_hz": None})
            continue
        for hz in cfg.tick_hz:
            rows.append({**base, "tick_hz": hz, **stream_run(spec, scene, grids[d][0], d, hz, cfg, log)})
    video = video_bench.compare_scene(spec, scene, poses, grids, cfg, cfg.video, log) if cfg.video else None
    return rows, image, video


def render_scene(scene, poses, grids: dict, cfg: BenchConfig, log: Log) -> tuple[dict, dict, str, bool]:
    """Frames per density (PSAO and the baselines in one renderer), in-process tick ms per density
    (animated scenes with --animate), the GL renderer's name and whether the frames are animated."""
    from psao.client.render.gridfile import load_grid_file
    from psao.eval.dynamic import is_animated
    from psao.eval.quality import QualityRenderer

    log(f"{scene.name}: rendering {len(poses)} frame(s) at {cfg.size[0]}x{cfg.size[1]}, PSAO at "
        f"{len(grids)} densities and {', '.join(m.upper() for m in cfg.baselines) or 'no baseline'}")
    frames, tick_ms = {}, {}
    animate = cfg.animate and is_animated(scene)
    weights = learned_weights(scene, grids, cfg, log)
    with QualityRenderer(scene, cfg.size, methods=cfg.render_methods,
                         options=cfg.method_options(**{f"{m}_weights": str(w["path"]) for m, w in weights.items()})) as qr:
        for d, (path, _) in grids.items():
            if animate:
                frames[d], tick_ms[d] = animated_frames(qr, scene, d, poses, cfg, log)
            else:
                frames[d] = qr.render(load_grid_file(path), poses)
        return frames, tick_ms, qr.gl_renderer, animate, weights


def learned_weights(scene, grids: dict, cfg: BenchConfig, log: Log) -> dict[str, dict]:
    """method -> {path, bytes, train_s, trained_on} for the learned methods among cfg.methods."""
    out = {}
    if "mlp" in cfg.methods:
        out["mlp"] = mlp_cached(scene, grids[cfg.densities[0]][0], cfg, log)
    for method in ("nnao", "aogan"):
        if method in cfg.methods:
            out[method] = shipped_weights(method, scene)
    return out


def shipped_weights(method: str, scene) -> dict:
    """The shipped weights of a learned screen-space method; refuses a scene they were trained on."""
    from psao.client.errors import RenderError
    from psao.client.render.aogan_net import DEFAULT_AOGAN_WEIGHTS
    from psao.client.render.nnao_net import DEFAULT_NNAO_WEIGHTS
    from psao.client.render.weights import load_weights, weight_bytes

    path = {"nnao": DEFAULT_NNAO_WEIGHTS, "aogan": DEFAULT_AOGAN_WEIGHTS}[method]
    try:
        arrays, header = load_weights(path, method)
    except RenderError as exc:
        raise EvalError(str(exc)) from None
    trained_on = list(header.get("trained_on", []))
    if scene.name in trained_on:
        raise EvalError(f"{method.upper()} weights {path.name} were trained on {scene.name}: the benchmark scores a "
                        "learned method only on scenes it was not trained on")
    return {"path": path, "bytes": weight_bytes(arrays), "train_s": header.get("train_s"),
            "trained_on": "+".join(trained_on)}


def mlp_cached(scene, grid_file: Path, cfg: BenchConfig, log: Log) -> dict:
    """MLP baking weights of this scene, trained on its grid (a bake, like PSAO's: trained on the scene it
    shows, scored on RTAO pixels it never saw); cached beside the grids."""
    from psao.client.render.gridfile import load_grid_file
    from psao.client.render.weights import load_weights, save_weights, weight_bytes
    from psao.eval.learn.mlp_train import MlpTrainSettings, train_mlp

    settings = MlpTrainSettings(steps=cfg.mlp_steps)
    path = cfg.cache / "mlp" / f"{grid_file.stem}-S{settings.steps}-P{settings.points}-seed{settings.seed}.npz"
    if path.is_file():
        try:
            arrays, header = load_weights(path, "mlp")
            return {"path": path, "bytes": weight_bytes(arrays), "train_s": header.get("train_s"),
                    "trained_on": scene.name}
        except Exception:  # noqa: BLE001 - a damaged cache entry is trained again
            pass
    log(f"{scene.name}: psao train mlp ({settings.steps} steps, {len(scene.instances)} object(s))")
    result = train_mlp(load_grid_file(grid_file), settings)
    nbytes = save_weights(path, "mlp", result.arrays, {"scene_hash": scene.content_hash(), "hidden": list(settings.hidden),
                                                       "train_s": result.seconds})
    log(f"{scene.name}: MLP trained in {result.seconds:.1f} s, loss {result.losses[0]:.4f} -> {result.losses[-1]:.4f}")
    return {"path": path, "bytes": nbytes, "train_s": result.seconds, "trained_on": scene.name}


def score_scene(scene, poses, grids: dict, cfg: BenchConfig, log: Log) -> tuple[list[dict], dict, dict]:
    """(baseline rows, PSAO quality per density, side-by-side image data) against the RTAO reference."""
    from psao.eval.quality import mean_scores, reference_images, score_frames

    frames, tick_ms, gl_renderer, animate, weights = render_scene(scene, poses, grids, cfg, log)
    first = frames[cfg.densities[0]]  # every density draws the same G-buffers
    log(f"{scene.name}: RTAO reference, {cfg.spp} spp, {len(first)} frame(s) (cached in {cfg.cache / 'rtao'})")
    refs = reference_images(scene, first, ReferenceSettings(spp=cfg.spp, cache_dir=cfg.cache / "rtao"))
    common = {"frames": len(first), "spp": cfg.spp, "animated": animate, "gl_renderer": gl_renderer}

    pick = len(first) // 2  # the side-by-side frame
    baseline_rows, baseline_panels = [], []
    for m in cfg.baselines:
        sc = score_frames(first, refs, methods=(m,))
        s = mean_scores(sc, m)
        baseline_rows.append({"scene": scene.name, "method": m.upper(), "density": None, "tick_hz": None,
                              **s.as_dict(), **common, "client_ms_frame": _median([f.gpu_ms[m] for f in first]),
                              "weight_bytes": weights.get(m, {}).get("bytes"), "train_s": weights.get(m, {}).get("train_s"),
                              "trained_on": weights.get(m, {}).get("trained_on")})
        baseline_panels.append((m.upper(), first[pick].ao[m], sc[pick].flip_map, sc[pick].scores.as_dict()))
        log(f"{scene.name}: {m.upper()} PSNR {s.psnr:.2f} dB, FLIP {s.flip:.3f}")
    panels, quality = [], {}
    for d in cfg.densities:
        sc = score_frames(frames[d], refs, methods=("psao",))
        meta = grids[d][1]
        quality[d] = {**mean_scores(sc, "psao").as_dict(), **common,
                      "client_ms_frame": _median([f.gpu_ms["psao"] for f in frames[d]]),
                      "points": meta.get("points_kept"), "bake_trace_s": meta.get("seconds_trace"),
                      "holes": float(sum(f.holes for f in frames[d]) / len(frames[d])), "anim_tick_ms": tick_ms.get(d)}
        panels.append((method_name(d), frames[d][pick].ao["psao"], sc[pick].flip_map, sc[pick].scores.as_dict()))
        log(f"{scene.name}: {method_name(d)} PSNR {quality[d]['psnr']:.2f} dB, FLIP {quality[d]['flip']:.3f}")
    return baseline_rows, quality, {"scene": scene.name, "reference": refs[pick], "panels": panels + baseline_panels}


def animated_frames(qr, scene, density: float, poses, cfg: BenchConfig, log: Log):
    """Frames of the animated scene at their own times: the server's tick in this process (see dynamic.py)."""
    from psao.eval.dynamic import AnimatedServer, AnimatedSettings

    hz = max(cfg.tick_hz)
    log(f"{scene.name}: animated, N={density:g}: in-process bake and server ticks at {hz:g} Hz up to each frame")
    with AnimatedServer(scene, AnimatedSettings(bake=dataclasses.replace(cfg.bake, density=density),
                                                tick_rays=TICK_RAYS, tick_hz=hz)) as server:
        frames = qr.render(server.grid, poses, before_frame=server.frame_state)
        return frames, server.mean_tick_ms()


def stream_run(spec: str, scene, grid: Path, density: float, hz: float, cfg: BenchConfig, log: Log) -> dict:
    from psao.eval.dynamic import is_animated
    from psao.eval.processes import ServerProcess, run_client, stream_rates, welcome_bytes

    name = scene.name
    welcome = welcome_bytes(scene)
    animate = cfg.animate and is_animated(scene)
    # An animating server bakes the scene itself (its tick needs the point sets) with the tick's ray count:
    # a bake with other rays makes the first tick re-trace every visible point (seconds here), which
    # would be measured as the stream. A static server serves the benchmark's grid.
    if animate:
        source = ["--animate", *bake_arguments(dataclasses.replace(cfg.bake, density=density, rays=TICK_RAYS)),
                  "--tick-rays", str(TICK_RAYS)]
        log(f"{name}: psao serve --animate N={density:g} @{hz:g} Hz, {TICK_RAYS} rays (the server bakes first)")
    else:
        source = ["--grid", str(grid), *bake_arguments(dataclasses.replace(cfg.bake, density=density))]
    with ServerProcess(spec, [*source, "--tick-hz", f"{hz:g}"],
                       start_timeout=1800.0) as server:
        stats = run_client(server.url, spec, cfg.stream_seconds)
        rates = stream_rates(stats, welcome)
        rates["server_ms_tick"] = server.tick_ms()
        rates["stream_animated"] = animate
        if not server.alive():
            raise EvalError(f"psao serve {spec} died during the run")
    log(f"{name}: N={density:g} @{hz:g} Hz{' animated' if animate else ''}: snapshot {rates['snapshot_mb']:.2f} MB "
        f"in {rates['snapshot_s']:.1f} s, then {rates['stream_mbit_s']:.3f} Mbit/s ({rates['updates_per_s']:.1f} "
        f"updates/s), server {rates['server_ms_tick']:.2f} ms/tick")
    return rates


def _median(values) -> float:
    import numpy as np

    return float(np.median(values)) if len(values) else float("nan")


def write_outputs(rows: list[dict], images: list[dict], out: Path, image_scale: float = 1.0) -> list[Path]:
    from psao.eval import report

    written = [out / "table.md", out / "table.csv", out / "results.json", out / "run.json", out / "runtime_error.png",
               out / "bandwidth_quality.png"]
    (out / "table.md").write_text(report.markdown_table(rows))
    (out / "run.json").write_text(json.dumps({"commit": source_commit()}) + "\n")  # benchmarks.report names it
    report.write_csv(rows, out / "table.csv")
    (out / "results.json").write_text(json.dumps(rows, indent=1, default=_json_default))
    report.runtime_chart(rows, out / "runtime_error.png")
    report.bandwidth_chart(rows, out / "bandwidth_quality.png")
    for im in images:
        path = out / f"frame_{im['scene']}.png"
        report.side_by_side(im["reference"], im["panels"], path, scale=image_scale)
        written.append(path)
    return written


def source_commit() -> str:
    """The git commit of the psao source that runs ("+local changes" if its tree differs), or "unknown"
    for an install that is not a git checkout."""
    import subprocess

    here = Path(__file__).resolve().parent

    def git(*args):
        return subprocess.run(["git", *args], cwd=here, capture_output=True, text=True, check=True).stdout.strip()

    try:
        head = git("rev-parse", "--short", "HEAD")
        return head + ("+local changes" if git("status", "--porcelain", "--untracked-files=no") else "")
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def _json_default(v):
    if hasattr(v, "item"):
        return v.item()
    raise TypeError(f"not JSON serialisable: {type(v)}")


def run(args) -> int:
    from psao.eval.processes import interrupt_on_sigterm

    with interrupt_on_sigterm():
        return _run(args)


def _run(args) -> int:
    from psao.eval import report
    from psao.eval.metrics import LPIPS_NOTE

    cfg = config_from_args(args)
    ensure_writable(cfg.out, "output folder")
    ensure_writable(cfg.cache, "cache folder")
    log = Log()
    rows, images, video_rows, video_images = [], [], [], []
    for spec in cfg.scenes:
        scene_rows, image, video = bench_scene(spec, cfg, log)
        rows += scene_rows
        images.append(image)
        if video:
            rows += video_bench.table1_rows(video[0])
            video_rows += video[0]
            video_images.append(video[1])
    written = write_outputs(rows, images, cfg.out, cfg.image_scale)
    if cfg.video:
        from psao.eval import video_report

        costs = video_bench.client_costs(video_rows, cfg.video.clients)
        written += video_report.write_outputs(video_rows, video_images, costs, cfg.out, cfg.image_scale)
        print(video_report.table1_markdown(video_rows))
    print(report.markdown_table(rows))
    print(LPIPS_NOTE)
    for p in written:
        print(p)
    if args.json:
        print(json.dumps(rows, default=_json_default))
    log("done")
    return 0

