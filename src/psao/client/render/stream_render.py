"""Rendering while streaming: `psao client URL --render OUTDIR` calls this at its own frame rate (--fps).

    callback = make_render_callback(scene, args)   # args: render, camera_path, size, ao, ssao_samples
    callback(mirror, transforms, tick)             # renders one frame of the mirror's latest state
    callback.close()                               # releases the GL context

The first call uploads the whole mirror; later calls upload only the buckets and cells the mirror
marked dirty since (Mirror.take_dirty), growing or cutting the cell table with the mirror's capacity.
The camera follows the scene's path at the time the client passes (camera_time=...), or at
tick / tick_rate seconds when it passes none. Each frame also gets a line in OUTDIR/frames.jsonl (frame,
tick, camera time, wall time when written, server time, instance transforms): what it takes to draw the same frame again, e.g.
to score it against a ray-traced reference (psao.eval.client_frames).
"""
from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from psao.options import default
from psao.client.errors import RenderError
from psao.client.render.gtao_pass import GTAO_PRESETS
from psao.client.render.renderer import MethodOptions
from psao.client.settings import FrameSettings


class StreamRenderer:
    def __init__(self, scene, out_dir, size: tuple[int, int] | None = None, ao_mode: str = FrameSettings.ao,
                 camera_path=None, ssao_samples: int = MethodOptions.ssao_samples,
                 tick_rate: float = FrameSettings.tick_rate, ctx=None, window: bool = False, options=None):
        """size: (width, height) in pixels, FrameSettings.size without it."""
        from psao.client.render.output import parse_size
        from psao.client.render.renderer import FrameRenderer
        from psao.scene import scene_camera

        try:
            self.path = scene_camera(scene, camera_path)
        except KeyError as exc:
            raise RenderError(str(exc.args[0])) from None
        if not tick_rate > 0:
            raise RenderError(f"tick rate must be > 0, got {tick_rate}")
        self.scene = scene
        self.out_dir = Path(out_dir)
        self.size = parse_size(FrameSettings.size) if size is None else tuple(size)
        self.tick_rate = float(tick_rate)
        self.renderer = FrameRenderer(scene, self.size, ao_mode, ssao_samples=ssao_samples, ctx=ctx, window=window,
                                      options=options)
        self._uploaded_instances: np.ndarray | None = None
        self.frames = 0
        self.records: list[dict] = []  # per frame: tick, camera time, GPU ms per pass
        (self.out_dir / "frames.jsonl").unlink(missing_ok=True)  # frames are numbered from 0 again

    def __call__(self, mirror, transforms, tick: int, camera_time: float | None = None) -> dict:
        from psao.client.render.output import save_frame
        from psao.client.render.views import path_matrices

        self._sync(mirror)
        self.renderer.set_transforms(transforms)
        self.renderer.set_skin_time(mirror.server_time)
        t = float(tick) / self.tick_rate if camera_time is None else float(camera_time)
        view, proj = path_matrices(self.scene, self.path, t, self.size)
        frame = self.renderer.render(view, proj, read_gbuffer=False)
        save_frame(frame, self.out_dir, self.frames)
        record = {"frame": self.frames, "tick": int(tick), "time": t, "gpu_ms": frame.gpu_ms}
        self.records.append(record)
        self._log(record, mirror, transforms)
        self.frames += 1
        return record

    def _log(self, record: dict, mirror, transforms) -> None:
        """One line per frame, appended as it is written (a killed client keeps the lines before)."""
        line = dict(record, wall=time.time(), camera_path=self.path.name, size=list(self.size),
                    server_time=mirror.server_time, skin_time=self.renderer.skin_time,
                    transforms=np.asarray(transforms, np.float64).reshape(-1, 16).tolist())
        with open(self.out_dir / "frames.jsonl", "a", encoding="utf-8") as f:
            f.write(json.dumps(line) + "\n")

    def _sync(self, mirror) -> None:
        """Full upload the first time (or when the instance table changed), dirty rows after that."""
        if self._uploaded_instances is None or not np.array_equal(self._uploaded_instances, mirror.instances):
            mirror.take_dirty()  # everything goes up now
            self.renderer.upload_grid(mirror.instances, mirror.buckets, mirror.cells)
            self._uploaded_instances = np.array(mirror.instances, copy=True)
            return
        buckets, cells = mirror.take_dirty()
        self.renderer.update_grid(buckets, mirror.buckets[buckets], cells, mirror.cells[cells], len(mirror.cells))

    def close(self) -> None:
        self.renderer.release()

    def __enter__(self) -> "StreamRenderer":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def make_render_callback(scene, args) -> StreamRenderer:
    """From the client's parsed arguments: args.render (OUTDIR), args.camera_path, args.size ('WxH'),
    args.ao (methods, see parse_ao_modes); optional args.ssao_samples and args.tick_rate."""
    from psao.client.render.output import parse_size
    from psao.client.render.renderer import MethodOptions

    return StreamRenderer(
        scene,
        args.render,
        size=parse_size(getattr(args, "size", FrameSettings.size)),
        ao_mode=getattr(args, "ao", FrameSettings.ao),
        camera_path=getattr(args, "camera_path", None),
        ssao_samples=int(getattr(args, "ssao_samples", MethodOptions.ssao_samples)),
        tick_rate=float(getattr(args, "tick_rate", None) or FrameSettings.tick_rate),
        window=bool(getattr(args, "window", False)),
        options=MethodOptions.from_args(args),
    )


def add_frame_arguments(parser) -> None:
    """The options of the frames themselves, the same on every sub-command that renders (client, render)."""
    parser.add_argument("--camera-path", metavar="NAME", default=None, help="camera path of the scene (its first by default)")
    parser.add_argument("--size", default=default(FrameSettings, "size"), metavar="WxH", help="frame size in pixels")
    parser.add_argument("--ao", default=default(FrameSettings, "ao"), metavar="METHODS",
                        help="AO method(s) to render: psao, ssao, gtao, nnao, mlp, aogan, comma-separated, or both (= psao,ssao)")
    parser.add_argument("--ssao-samples", type=int, default=default(MethodOptions, "ssao_samples"), metavar="K",
                        help="SSAO kernel size")
    parser.add_argument("--gtao-preset", default=default(MethodOptions, "gtao_preset"), metavar="NAME",
                        help=f"GTAO slices x steps: {', '.join(GTAO_PRESETS)}")
    parser.add_argument("--mlp-weights", default=None, metavar="FILE", help="MLP baking weights (psao train mlp) for --ao mlp")
    parser.add_argument("--nnao-weights", default=None, metavar="FILE",
                        help="NNAO weights (psao train nnao; the shipped ones without it)")
    parser.add_argument("--nnao-samples", type=int, default=default(MethodOptions, "nnao_samples"), metavar="K",
                        help="NNAO first-layer cells per pixel: 64, 128, 256 or 961")
    parser.add_argument("--aogan-weights", default=None, metavar="FILE",
                        help="AOGAN weights (psao train aogan; the shipped ones without it)")
    parser.add_argument("--window", action="store_true",
                        help="also show the frames in a window (needs a display and the 'glfw' package: pip install glfw)")


def add_render_arguments(parser) -> None:
    """The options `psao client` needs for --render."""
    parser.add_argument("--render", metavar="OUTDIR", default=None, help="render frames (PNG) into OUTDIR")
    add_frame_arguments(parser)
    parser.add_argument("--fps", type=float, default=default(FrameSettings, "fps"), metavar="F",
                        help="frames per second to render at, the client's own rate, whatever the server's tick rate "
                             "(a slow GPU renders as fast as it can)")
