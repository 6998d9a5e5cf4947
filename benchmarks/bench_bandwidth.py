"""Bandwidth of the update stream for every codec x layout, in one run, and snapshot time.

1. Bake the scene (default builtin:courtyard at N=256) or load a baked grid (--grid). When the scene is
   animated (and it was baked here), record --animated-ticks ticks of its own animation through the real
   server tick (psao.server.tick.server_tick), with a client camera on the scene's path: the main stream.
2. Record a second stream: --ticks server ticks at --tick-hz of a moving occluder (a sphere on a loop
   through the courtyard darkens the AO of the points within its reach; points it leaves get their baked
   AO back: spatially and temporally coherent, as a moving object is) and, as a second stream, the
   random-edit test hook (AO changes, moves between cells, cells freed and allocated). Each tick's
   dirty buckets and cells (and changed transforms) are read from the grid as the server would send them.
3. Replay every stream through protocol sessions (server encodes, client decodes into a mirror) for
   every codec (none, lz4, zstd per message, zstd stream per connection; zstd at level 15, strategy lazy)
   and layout (plain = the paper's raw uint32 layout, packed = ours). Each replay starts with the
   snapshot, as a connection does; the figures count the updates only. The mirror must end bit-exact.
   Baseline: plain + zstd per message (the paper). Default: packed + zstd stream. Target: >= 2x smaller.
4. Snapshot of the whole grid to a local `psao client` process over loopback (target < 2 s).

Prints a table (bytes per changed point, per tick, per tick in steady state (after the first quarter of
the ticks), Mbit/s at the tick rate, encode and decode ms per
tick, ratio to the baseline), writes bandwidth.json and bandwidth.png to --out.

    .venv/bin/python -m benchmarks.bench_bandwidth [SCENE] [--density 256] [--rays 32] [--animated-ticks 60]
        [--ticks 120] [--random-ticks 30] [--tick-hz 60] [--grid FILE] [--out DIR] [--skip-snapshot]
"""
from __future__ import annotations

import argparse
import asyncio
import json
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from psao.protocol.codecs import Codec, codec_name
from psao.protocol.gridformat import POINTS_PER_CELL
from psao.protocol.limits import DEFAULT_LIMITS, Limits
from psao.protocol.session import ClientConfig, ClientSession, ServerConfig, ServerSession, scene_hash_bytes
from psao.protocol.updates import GridDelta, Layout, state_digest

from benchmarks.verdicts import Verdicts

TARGET_RATIO = 2.0
TARGET_SNAPSHOT_S = 2.0
BASELINE = (Codec.ZSTD, Layout.PLAIN)
DEFAULT = (Codec.ZSTD_STREAM, Layout.PACKED)
CODECS = [Codec.NONE, Codec.LZ4, Codec.ZSTD, Codec.ZSTD_STREAM]


@dataclass
class Recording:
    name: str
    snapshot: GridDelta
    updates: list[GridDelta]
    changed_points: int  # point words that changed, summed over ticks
    final_digest: str
    instances: np.ndarray
    n_buckets: int
    capacity: int


@dataclass
class Row:
    stream: str
    codec: str
    layout: str
    snapshot_bytes: int
    update_bytes: int
    bytes_per_tick: float
    bytes_per_changed_point: float
    mbit_per_s: float
    encode_ms_per_tick: float
    decode_ms_per_tick: float
    steady_bytes_per_tick: float  # mean over the ticks after the first quarter (start-up transients excluded)
    ratio_to_baseline: float = 0.0


def full_delta(grid, transforms) -> GridDelta:
    from psao.server.net.clients import changed_buckets, changed_cells, read_delta

    return read_delta(grid, transforms, np.arange(len(transforms)), changed_buckets(grid.buckets),
                      changed_cells(grid.cells))


def record(name: str, grid, transforms, tick_fn, ticks: int, tick_hz: float) -> Recording:
    """Run `ticks` ticks and keep what a client would be sent after each: the dirty buckets and cells and
    the transforms that changed. `transforms` is an array or a callable returning the current one."""
    from psao.server.net.clients import read_delta

    current = transforms if callable(transforms) else (lambda: transforms)
    grid.take_dirty()
    sent = np.array(current(), np.float32)
    snapshot = full_delta(grid, sent)
    updates, changed = [], 0
    for k in range(ticks):
        before = grid.cells.copy()
        tick_fn(grid, k / tick_hz)
        b, c = grid.take_dirty()
        n = min(len(before), len(grid.cells))
        cc = c[c < n]
        changed += int(np.count_nonzero(before[cc, :POINTS_PER_CELL] != grid.cells[cc, :POINTS_PER_CELL]))
        changed += int(np.count_nonzero(grid.cells[c[c >= n], :POINTS_PER_CELL]))
        now = np.array(current(), np.float32)
        moved = np.flatnonzero(np.any(now.reshape(len(now), -1).view(np.uint32)
                                      != sent.reshape(len(sent), -1).view(np.uint32), axis=1))
        sent = now
        updates.append(read_delta(grid, now, moved, b, c))
    digest = state_digest(grid.instances, grid.buckets, grid.cells, sent)
    return Recording(name, snapshot, updates, changed, digest, grid.instances.copy(), len(grid.buckets),
                     snapshot.cell_capacity)


def is_animated(scene) -> bool:
    return any(i.animation is not None for i in scene.instances) or any(m.skin is not None for m in scene.meshes)


def record_animated(bake, ticks: int, tick_hz: float, rays: int) -> tuple[Recording, object]:
    """The scene's own animation through the real server tick (psao.server.tick.server_tick), with one client's camera
    following the scene's camera path, as `psao serve --animate` runs it. The tick traces as many rays as
    the bake did, so the bake is its first sync (no one-off re-trace of everything at tick 0). Returns
    the grid it ran on."""
    from psao.client.connection import scene_camera_feed
    from psao.server.tick.server_tick import ServerTick
    from psao.server.settings import TickSettings

    t0 = time.perf_counter()
    tick = ServerTick(bake, TickSettings(rays=rays))
    camera = scene_camera_feed(bake.scene)

    def step(grid, t):
        tick.set_cameras([camera(t)])
        tick(grid, t)

    try:
        rec = record("animated", tick.grid, tick.transforms, step, ticks, tick_hz)
    finally:
        tick.close()
    print(f"recorded {ticks} animated ticks through the server tick ({time.perf_counter() - t0:.1f} s)")
    return rec, tick.grid


def split(delta: GridDelta, limits: Limits = DEFAULT_LIMITS) -> list[GridDelta]:
    """Cut a delta into messages within the per-message limits, as the server's pending drain does."""
    n = max(1, -(-len(delta.cell_slots) // limits.max_cells_per_message),
            -(-len(delta.bucket_ids) // limits.max_buckets_per_message))
    if n == 1:
        return [delta]
    parts = []
    for i, (b, c) in enumerate(zip(np.array_split(np.arange(len(delta.bucket_ids)), n),
                                   np.array_split(np.arange(len(delta.cell_slots)), n))):
        t = slice(None) if i == 0 else slice(0, 0)
        parts.append(GridDelta(delta.cell_capacity, delta.transform_ids[t], delta.transforms[t],
                               delta.bucket_ids[b], delta.buckets[b], delta.cell_slots[c], delta.cells[c]))
    return parts


def replay(rec: Recording, codec: Codec, layout: Layout, tick_hz: float) -> Row:
    from psao.client.mirror import Mirror

    h = bytes(32)
    server = ServerSession(ServerConfig(h, codec=codec, layout=layout))
    client = ClientSession(ClientConfig(h, codecs=frozenset({codec})))
    server.receive(client.hello())
    mirror = Mirror.from_welcome(client.receive(server.welcome(1, tick_hz, rec.n_buckets, rec.capacity,
                                                               rec.instances)).welcome)
    chunks = split(rec.snapshot)
    snapshot_bytes = 0
    for i, chunk in enumerate(chunks):
        data = server.snapshot(i, len(chunks), chunk)
        mirror.apply(client.receive(data).snapshot.delta)
        snapshot_bytes += len(data)
    total, enc, dec = 0, 0.0, 0.0
    per_tick = np.zeros(len(rec.updates))
    for tick, delta in enumerate(rec.updates):
        for part in split(delta):
            t0 = time.perf_counter()
            data = server.update(tick, tick / tick_hz, part)
            t1 = time.perf_counter()
            mirror.apply(client.receive(data).update.delta)
            t2 = time.perf_counter()
            total += len(data)
            per_tick[tick] += len(data)
            enc += t1 - t0
            dec += t2 - t1
    if mirror.digest() != rec.final_digest:
        raise AssertionError(f"{rec.name} {codec_name(codec)} {layout.name}: mirror differs from the server")
    n = max(len(rec.updates), 1)
    steady = float(per_tick[len(per_tick) // 4:].mean()) if len(per_tick) else 0.0
    return Row(rec.name, codec_name(codec), layout.name.lower(), snapshot_bytes, total, total / n,
               total / max(rec.changed_points, 1), total * 8 * tick_hz / n / 1e6, 1e3 * enc / n, 1e3 * dec / n,
               steady)


def print_table(rows: list[Row], rec: Recording) -> None:
    from rich.console import Console
    from rich.table import Table

    t = Table(title=f"{rec.name}: {len(rec.updates)} ticks, {rec.changed_points:,} point changes, "
                    f"{sum(len(u.cell_slots) for u in rec.updates):,} cell and "
                    f"{sum(len(u.bucket_ids) for u in rec.updates):,} bucket updates")
    for col in ("codec", "layout", "B/changed point", "B/tick", "steady B/tick", "Mbit/s", "enc ms/tick",
                "dec ms/tick", "vs baseline", "snapshot MB"):
        t.add_column(col, justify="right")
    for r in rows:
        mark = " (baseline)" if (r.codec, r.layout) == (codec_name(BASELINE[0]), "plain") else (
            " (default)" if (r.codec, r.layout) == (codec_name(DEFAULT[0]), "packed") else "")
        t.add_row(r.codec, r.layout + mark, f"{r.bytes_per_changed_point:.2f}", f"{r.bytes_per_tick:,.0f}",
                  f"{r.steady_bytes_per_tick:,.0f}", f"{r.mbit_per_s:.2f}", f"{r.encode_ms_per_tick:.2f}", f"{r.decode_ms_per_tick:.2f}",
                  f"{r.ratio_to_baseline:.2f}x", f"{r.snapshot_bytes / 1e6:.2f}")
    Console(width=150).print(t)


def chart(results: dict[str, list[Row]], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(results), figsize=(6.5 * len(results), 4.5), squeeze=False)
    for ax, (name, rows) in zip(axes[0], results.items()):
        labels = [f"{r.codec}\n{r.layout}" for r in rows]
        vals = [r.bytes_per_tick / 1e3 for r in rows]
        colors = ["#d62728" if (r.codec, r.layout) == ("zstd", "plain") else
                  "#2ca02c" if (r.codec, r.layout) == ("zstd-stream", "packed") else "#7f7f7f" for r in rows]
        ax.bar(range(len(rows)), vals, color=colors)
        ax.set_xticks(range(len(rows)), labels, fontsize=7)
        ax.set_yscale("log")
        ax.set_ylabel("kB per tick (log)")
        ax.set_title(f"{name} stream (red: paper baseline, green: default)")
        for i, r in enumerate(rows):
            ax.text(i, vals[i], f"{r.ratio_to_baseline:.2f}x", ha="center", va="bottom", fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)


async def snapshot_to_client(grid, scene_spec: str, scene_hash: bytes, transforms: np.ndarray) -> dict:
    """Serve the grid on a free loopback port; time a real `psao client` process until its snapshot is
    complete (its own measurement: connect -> last chunk applied)."""
    from psao.server.net.service import Service, StaticTransforms
    from psao.server.settings import ServeSettings

    service = Service(grid, scene_hash, ServeSettings(port=0, tick_hz=60, stats_interval=1e9),
                      transforms=StaticTransforms(transforms))
    stop, ready = asyncio.Event(), asyncio.Event()
    task = asyncio.create_task(service.run(stop, ready=lambda port: ready.set()))
    await ready.wait()
    proc = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "psao", "client", f"ws://127.0.0.1:{service.port}", scene_spec,
        "--frames", "0", "--json", stdout=asyncio.subprocess.PIPE)
    out, _ = await proc.communicate()
    stop.set()
    await task
    if proc.returncode != 0:
        raise RuntimeError("psao client failed")
    return json.loads(out.decode().strip().splitlines()[-1])


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("scene", nargs="?", default="builtin:courtyard")
    p.add_argument("--density", type=float, default=256.0)
    p.add_argument("--rays", type=int, default=None,
                   help="AO rays per point of the bake and of the animated ticks (default: the server tick's)")
    p.add_argument("--ticks", type=int, default=120)
    p.add_argument("--tick-hz", type=float, default=60.0)
    p.add_argument("--animated-ticks", type=int, default=60,
                   help="ticks of the scene's own animation through the server tick (0: skip)")
    p.add_argument("--random-edits", type=int, default=2000, help="points per tick of the random-edit stream")
    p.add_argument("--random-ticks", type=int, default=30, help="ticks of the random-edit stream")
    p.add_argument("--grid", type=Path, default=None, help="a baked grid (.npz) instead of baking")
    p.add_argument("--out", type=Path, default=Path("out") / "bench_bandwidth")
    p.add_argument("--skip-snapshot", action="store_true")
    args = p.parse_args(argv)

    from psao.scene import load_scene
    from psao.server.bake import bake_scene
    from psao.server.settings import BakeSettings, TickSettings
    from psao.server.grid import Grid
    from psao.server.tick.testhook import MovingOccluder, RandomEdits

    args.rays = args.rays or TickSettings().rays
    scene = load_scene(args.scene)
    t0 = time.perf_counter()
    recordings = []
    if args.grid:
        grid = Grid.load(args.grid)[0]
    else:
        result = bake_scene(scene, BakeSettings(density=args.density, rays=args.rays))
        grid = result.grid
        if args.animated_ticks and is_animated(scene):
            rec, grid = record_animated(result, args.animated_ticks, args.tick_hz, args.rays)
            recordings.append(rec)
        else:
            result.tracer.close()
    transforms = np.array([i.transform for i in scene.instances], np.float32)
    print(f"grid: {len(grid.allocated_cells()):,} cells, {len(grid.buckets):,} buckets, {grid.n_points():,} points "
          f"({time.perf_counter() - t0:.1f} s)")

    t0 = time.perf_counter()
    recordings.append(record("occluder", grid, transforms, MovingOccluder(scene, grid), args.ticks, args.tick_hz))
    recordings.append(record("random", grid, transforms, RandomEdits(args.random_edits, seed=1), args.random_ticks,
                             args.tick_hz))
    print(f"recorded {args.ticks} + {args.random_ticks} ticks ({time.perf_counter() - t0:.1f} s)")

    results: dict[str, list[Row]] = {}
    for rec in recordings:
        rows = [replay(rec, c, lay, args.tick_hz) for c in CODECS for lay in (Layout.PLAIN, Layout.PACKED)]
        base = next(r for r in rows if (r.codec, r.layout) == (codec_name(BASELINE[0]), "plain"))
        for r in rows:
            r.ratio_to_baseline = base.update_bytes / max(r.update_bytes, 1)
        print_table(rows, rec)
        results[rec.name] = rows

    ratios = {name: next(r for r in rows if (r.codec, r.layout) == (codec_name(DEFAULT[0]), "packed")).ratio_to_baseline
              for name, rows in results.items()}
    target = "animated" if "animated" in ratios else "occluder"
    summary = {"scene": args.scene, "density": args.density, "ticks": args.ticks, "tick_hz": args.tick_hz,
               "target_stream": target, "default_vs_baseline": ratios, "target_ratio": TARGET_RATIO,
               "rows": {k: [asdict(r) for r in v] for k, v in results.items()}}
    v = Verdicts("bench_bandwidth")
    for name, ratio in ratios.items():
        rows = results[name]
        default = next(r for r in rows if (r.codec, r.layout) == (codec_name(DEFAULT[0]), "packed"))
        base = next(r for r in rows if (r.codec, r.layout) == (codec_name(BASELINE[0]), "plain"))
        print(f"{name} stream: default (packed + zstd stream) {default.steady_bytes_per_tick:,.0f} B/tick steady "
              f"({default.steady_bytes_per_tick * args.tick_hz * 8 / 1e6:.2f} Mbit/s at {args.tick_hz:g} Hz), "
              f"paper baseline (plain + zstd-15-lazy per message) {base.steady_bytes_per_tick:,.0f} B/tick: "
              f"{ratio:.2f}x smaller over all ticks" + ("" if name == target else " (for reference)"))
        if name == target:
            v.check(f"{name} stream ({args.rays}-ray bake and ticks) default / paper baseline bytes", ratio, ">=",
                    TARGET_RATIO)

    if not args.skip_snapshot:
        rep = asyncio.run(snapshot_to_client(grid, args.scene, scene_hash_bytes(scene.content_hash()), transforms))
        summary["snapshot"] = {k: rep[k] for k in ("snapshot_seconds", "snapshot_bytes", "mirror_cells", "codec")}
        print(f"snapshot to a local client: {rep['snapshot_seconds']:.2f} s, {rep['snapshot_bytes'] / 1e6:.2f} MB on "
              f"the wire, {rep['mirror_cells']:,} cells")
        v.check("snapshot to a local psao client, seconds", rep["snapshot_seconds"], "<", TARGET_SNAPSHOT_S)

    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "bandwidth.json").write_text(json.dumps(summary, indent=1))
    chart(results, args.out / "bandwidth.png")
    print(f"wrote {args.out / 'bandwidth.json'} and {args.out / 'bandwidth.png'}")
    return v.exit_code()


if __name__ == "__main__":
    sys.exit(main())
