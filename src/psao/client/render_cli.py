"""`psao render SCENE --grid FILE`: render frames offline from a baked grid, no server.

Writes numbered PNGs (composite and AO per mode) along a camera path; with --json the last stdout line
is a JSON object with the per-frame GPU time of every pass (timer queries) and the wall time.
"""
from __future__ import annotations

import json
import sys
import time
from pathlib import Path

from psao.options import default
from psao.client.render.stream_render import add_frame_arguments
from psao.client.settings import FrameSettings


def add_arguments(parser) -> None:
    parser.add_argument("scene", metavar="SCENE", help="builtin:NAME, a .toml scene or a mesh file")
    parser.add_argument("--grid", required=True, metavar="FILE", help="baked grid (.npz from psao bake)")
    parser.add_argument("--frames", type=int, default=default(FrameSettings, "frames"), metavar="N",
                        help="frames spread over the path")
    add_frame_arguments(parser)
    parser.add_argument("--out", default=default(FrameSettings, "out"), metavar="DIR", help="output folder")
    parser.add_argument("--json", action="store_true", help="print per-frame pass times as JSON (last line)")


def run(args) -> int:
    from psao.client.errors import RenderError
    from psao.client.render.gridfile import check_scene, load_grid_file
    from psao.client.render.output import parse_size, save_frame
    from psao.client.render.renderer import FrameRenderer, MethodOptions
    from psao.client.render.views import path_matrices, path_times
    from psao.scene import load_scene, scene_camera

    size = parse_size(args.size)
    if args.frames < 1:
        raise RenderError(f"--frames must be >= 1, got {args.frames}")
    grid = load_grid_file(args.grid)
    scene = load_scene(args.scene)
    check_scene(grid, scene, args.grid)
    try:
        path = scene_camera(scene, args.camera_path)
    except KeyError as exc:
        raise RenderError(str(exc.args[0])) from None
    out = Path(args.out)
    records = []
    with FrameRenderer(scene, size, args.ao, window=args.window,
                       options=MethodOptions.from_args(args)) as renderer:
        renderer.upload_grid(grid.instances, grid.buckets, grid.cells)
        for i, t in enumerate(_progress(path_times(path, args.frames), quiet=args.json)):
            view, proj = path_matrices(scene, path, float(t), size)
            start = time.perf_counter()
            frame = renderer.render(view, proj, read_gbuffer=False)
            wall_ms = (time.perf_counter() - start) * 1e3
            save_frame(frame, out, i)
            records.append({"frame": i, "time": float(t), "gpu_ms": frame.gpu_ms, "wall_ms": wall_ms})
        gl_renderer = renderer.ctx.info.get("GL_RENDERER", "")
    if args.json:
        print(json.dumps({"scene": scene.name, "size": list(size), "ao": args.ao, "gl_renderer": gl_renderer,
                          "out": str(out), "frames": records}))
    else:
        print(f"wrote {len(records)} frame(s) to {out}/", file=sys.stderr)
    return 0


def _progress(times, quiet: bool):
    if quiet or len(times) < 2:
        return times
    from rich.progress import track

    return track(times, description="rendering", transient=True, console=_stderr_console())


def _stderr_console():
    from rich.console import Console

    return Console(stderr=True)
