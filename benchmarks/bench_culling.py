"""Per-client culling of sends: `python -m benchmarks.bench_culling [--density 64] [--seconds 20]`.

The animated courtyard through the real server tick (time-budgeted, as `psao serve --animate` runs it)
and the websocket service in this process, with three real MirrorClients on loopback: two stand at the
courtyard's centre looking in opposite directions along `--axis` (each is sent the cells in its extended
view, the rest wait), the third sends no camera, so it is sent every change, as every client was before
culling: the baseline, on the same ticks in the same window. The tick re-traces what the two cameras see.

After the window the animation holds still; once everything in view has been sent, each culled
client's mirror must equal the server on every bucket, every transform and every cell not pending for
it (everything it has been sent), while the cells pending for it are cells it lacks. Then both turn
around: once the server has the turned cameras and each is quiet, no cell pending for it lies in its new
view (what it was kept back has arrived) and its mirror is again exact on everything it was sent. Cells
outside both directions may still wait (the time-budgeted tick refines points outside every view when
it has time left). Last, both step back to a camera that sees the whole courtyard: once nothing is
pending their mirrors must equal the server's whole state.

Verdicts: bytes of each culled client / bytes of the baseline client <= 0.6 over the window; both
mirror checks exact. Only bytes are judged (no speed): run it niced, without the benchmark lock.
"""
from __future__ import annotations

import argparse
import asyncio
import sys
import time

import numpy as np

from benchmarks.verdicts import Verdicts
from psao.server.tick.base import Tick

PATIENCE = 600.0  # seconds to wait for an event before giving up (a loaded machine is slow)


class Holdable(Tick):
    """The server tick, which stops ticking (the scene holds still, nothing changes) once `hold` is set."""
    threaded = places_instances = True

    def __init__(self, tick):
        self.tick = tick
        self.hold = False
        self.set_cameras, self.transforms = tick.set_cameras, tick.transforms

    def prepare(self, t: float):
        return None if self.hold else self.tick.prepare(t)

    def apply(self, plan):
        return None if plan is None else self.tick.apply(plan)


async def until(condition, what: str) -> None:
    t0 = time.perf_counter()
    while not condition():
        if time.perf_counter() - t0 > PATIENCE:
            raise TimeoutError(f"bench_culling: never happened: {what}")
        await asyncio.sleep(0.02)


def exact_where_sent(grid, transforms, mirror, pending: np.ndarray) -> tuple[bool, int]:
    """(mirror equals the server on all buckets, transforms and the cells not pending; pending cells the
    mirror lacks)."""
    kept = np.zeros(len(grid.cells), bool)
    kept[pending] = True
    same = (mirror.buckets.tobytes() == grid.buckets.tobytes()
            and mirror.transforms.tobytes() == np.ascontiguousarray(transforms, np.float32).tobytes()
            and len(mirror.cells) == len(grid.cells)
            and mirror.cells[~kept].tobytes() == grid.cells[~kept].tobytes())
    lacking = int(np.any(mirror.cells[pending] != grid.cells[pending], axis=1).sum())
    return same, lacking


async def run(args) -> int:
    from psao.protocol.session import scene_hash_bytes
    from psao.protocol.updates import state_digest
    from psao.client.connection import MirrorClient
    from psao.scene import load_scene
    from psao.scene.camera import look_at, perspective
    from psao.server.bake import bake_scene
    from psao.server.tick.budget import BudgetSettings
    from psao.server.net.service import Service
    from psao.server.settings import BakeSettings, ServeSettings, TickSettings
    from psao.server.tick.server_tick import ServerTick

    scene = load_scene(args.scene)
    t0 = time.perf_counter()
    bake = bake_scene(scene, BakeSettings(density=args.density, rays=args.rays))
    tick = Holdable(ServerTick(bake, TickSettings(rays=args.rays, budget=BudgetSettings()), tick_hz=args.tick_hz))
    print(f"baked {scene.name} at N={args.density:g}: {bake.stats['points_kept']:,} points "
          f"({time.perf_counter() - t0:.0f} s)", flush=True)
    service = Service(tick.tick.grid, scene_hash_bytes(scene.content_hash()),
                      ServeSettings(port=0, tick_hz=args.tick_hz, stats_interval=1e9), tick=tick,
                      transforms=tick.transforms)
    stop, ready = asyncio.Event(), asyncio.Event()
    served = asyncio.create_task(service.run(stop, ready=lambda port: ready.set()))
    await ready.wait()
    url = f"ws://127.0.0.1:{service.port}"
    lo, hi = scene.world_bounds()
    eye = np.array([(lo[0] + hi[0]) / 2, lo[1] + args.eye_height, (lo[2] + hi[2]) / 2])
    axis = np.eye(3)[{"x": 0, "z": 2}[args.axis]]
    far = 4.0 * float(np.linalg.norm(hi - lo))
    proj = perspective(60.0, 16 / 9, 0.05, far).astype(np.float32)
    facing = {"a": 1.0, "b": -1.0}
    overview = {"a": False, "b": False}  # step back: the whole courtyard in view
    centre = (lo + hi) / 2
    far_eye = centre + np.array([0.0, 1.0, 1.5]) * float(np.linalg.norm(hi - lo))

    def pose(name) -> np.ndarray:
        if overview[name]:
            return look_at(far_eye, centre).astype(np.float32)
        return look_at(eye, eye + facing[name] * axis).astype(np.float32)

    def camera(name):
        return lambda t: (pose(name), proj)

    hash_ = scene_hash_bytes(scene.content_hash())
    clients = {"a": MirrorClient(url, hash_, camera=camera("a")), "b": MirrorClient(url, hash_, camera=camera("b")),
               "all": MirrorClient(url, hash_)}
    tasks = [asyncio.create_task(c.run()) for c in clients.values()]
    v = Verdicts("bench_culling")
    try:
        await until(lambda: all(c.stats.snapshot_seconds is not None for c in clients.values())
                    and len(service.registry) == 3, "every snapshot")
        await asyncio.sleep(args.warmup)
        before = {k: c.stats.bytes_received for k, c in clients.items()}
        ticks0, t_start = service.tick, time.perf_counter()
        await asyncio.sleep(args.seconds)
        got = {k: c.stats.bytes_received - before[k] for k, c in clients.items()}
        ticks = service.tick - ticks0
        wall = time.perf_counter() - t_start
        print(f"window: {wall:.1f} s, {ticks} ticks; bytes received: " +
              ", ".join(f"{k} {n / 1e3:.1f} kB" for k, n in got.items()), flush=True)
        for k in ("a", "b"):
            v.check(f"{args.scene} N={args.density:g} client looking {'+' if facing[k] > 0 else '-'}{args.axis}: "
                    f"bytes / every-change client's bytes", got[k] / max(got["all"], 1), "<=", args.target)
        tick.hold = True
        by_id = {c.stats.connection_id: (k, c) for k, c in clients.items()}
        server_side = {by_id[s.id][0]: s for s in service.registry if s.id in by_id}

        def quiet(keys):
            return all(not server_side[k].busy and not server_side[k].outbox and not server_side[k].in_flight
                       and not (server_side[k].wake.is_set() and not server_side[k].on_parts)
                       and clients[k].stats.messages == server_side[k].messages_sent for k in keys)

        held = service.tick
        await until(lambda: service.tick >= held + 2 and quiet(clients), "the held scene's last changes sent")
        for k in ("a", "b"):
            pending = np.flatnonzero(server_side[k].pending_cells)
            same, lacking = exact_where_sent(service.grid, service.transforms(), clients[k].mirror, pending)
            print(f"client {k}: {len(pending)} cells pending (outside its view), {lacking} of them differ from "
                  f"its mirror", flush=True)
            v.record(f"client {k}'s mirror equals the server on everything it was sent", same,
                     f"{len(pending)} cells kept back")
        facing["a"], facing["b"] = -facing["a"], -facing["b"]

        def seen_by_server(k) -> bool:  # the server holds the client's latest pose
            cam = server_side[k].camera
            return cam is not None and np.array_equal(cam[0], pose(k))

        def in_new_view(k) -> int:
            pending = np.flatnonzero(server_side[k].pending_cells)
            view = service.fanout.in_view(server_side[k], service.grid, service.transforms())
            return int(view(pending).sum()) if view is not None and len(pending) else 0

        held = service.tick
        await until(lambda: all(seen_by_server(k) for k in ("a", "b")) and service.tick >= held + 2
                    and quiet(("a", "b")) and not any(in_new_view(k) for k in ("a", "b")),
                    "the turned clients sent what their new views hold")
        for k in ("a", "b"):
            pending = np.flatnonzero(server_side[k].pending_cells)
            same, _ = exact_where_sent(service.grid, service.transforms(), clients[k].mirror, pending)
            print(f"client {k} turned around: {len(pending)} cells still pending (outside both directions)", flush=True)
            v.record(f"client {k} turned around: every kept-back cell its new view holds arrived, mirror exact "
                     f"where sent", same, f"{len(pending)} outside both directions")
        overview["a"] = overview["b"] = True
        await until(lambda: all(seen_by_server(k) for k in ("a", "b")) and quiet(("a", "b"))
                    and not any(server_side[k].pending_anything() for k in ("a", "b")), "the stepped-back clients drained")
        g = service.grid
        want = state_digest(g.instances, g.buckets, g.cells, service.transforms())
        for k in ("a", "b"):
            m = clients[k].mirror
            v.record(f"client {k}'s mirror equals the whole server state once its view holds the whole courtyard",
                     state_digest(m.instances, m.buckets, m.cells, m.transforms) == want)
    finally:
        for c in clients.values():
            c.stop()
        # stop() acts at the client's next message, and a held scene sends none: cancel whoever still waits
        _, waiting = await asyncio.wait(tasks, timeout=5.0)
        for task in waiting:
            task.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
        stop.set()
        await served
        tick.tick.close()
    return v.exit_code()


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.bench_culling", description=__doc__.splitlines()[0])
    p.add_argument("--scene", default="builtin:courtyard")
    p.add_argument("--density", type=float, default=64.0)
    p.add_argument("--rays", type=int, default=32, help="AO rays per point of the bake and the ticks")
    p.add_argument("--tick-hz", type=float, default=30.0)
    p.add_argument("--seconds", type=float, default=20.0, help="measured window")
    p.add_argument("--warmup", type=float, default=2.0, help="seconds after the snapshots before the window")
    p.add_argument("--axis", choices=("x", "z"), default="x", help="the two clients look along +axis and -axis")
    p.add_argument("--eye-height", type=float, default=1.7, help="above the scene's lowest point (world units)")
    p.add_argument("--target", type=float, default=0.6, help="bytes of a culled client / every-change client")
    args = p.parse_args(argv)
    return asyncio.run(run(args))


if __name__ == "__main__":
    sys.exit(main())
