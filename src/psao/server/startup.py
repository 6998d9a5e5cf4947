"""What a server does between listening and serving its full grid: psao.Server.start (so also `psao serve`).

The service listens first; this work then runs on the start-up thread (psao.server.tick.progressive.Startup)
and hands the service what it has as it comes, while waiting clients are told the phase in Status messages:

    load the scene                -> its hash and scene file (a fast zstd level first, when asked)
    progressive start: a coarse first grid traced with a round's rays (its own tick with `animate`)
    the full grid                 -> with the server tick (`animate`, `progressive`, `allow_edits` or
                                     `tick_at_rest`), or baked, or read from a grid file, with no tick

Every choice here comes from `s`, a psao.server.embed.ServerSettings (not imported: embed imports this module).
"""
from __future__ import annotations

import concurrent.futures
import contextlib
import dataclasses
import logging
from typing import Callable

import numpy as np

from psao.server.errors import ConfigError
from psao.server.settings import TickSettings
from psao.server.tick.budget import BudgetSettings, fitting_round_rays
from psao.server.tick.progressive import ProgressiveSettings

log = logging.getLogger("psao.serve")


def budget(s) -> BudgetSettings:
    """The tick's time budget from the tick rate, `tick_budget_ms` and `tick_rays` (without it the default
    round, or the largest divisor of the bake's rays below it), checked against the bake's rays (ConfigError)."""
    round_rays = s.tick_rays if s.tick_rays is not None else fitting_round_rays(s.bake.rays)
    b = BudgetSettings(budget_ms=s.tick_budget_ms, round_rays=round_rays)
    b.check_rate(s.serve.tick_hz)
    b.check(s.bake.rays)
    return b


def runs_tick(s) -> bool:
    """Whether the full grid is served with the server tick; else it stands still or the test hook edits it
    (`tick_at_rest` gives a baked grid a tick that holds the scene at rest and re-traces what a move moves)."""
    return s.animate or s.progressive or s.serve.allow_edits or (s.tick_at_rest and s.grid is None and not s.test_edits)


def ticking(s, scene, report=None):
    """The server tick on a fresh bake of `scene` (it needs the bake's point sets): animating the scene with
    `animate`, refining a first few-ray grid with `progressive`, re-tracing what the application's moves and
    the clients' edits move. `report(fraction, text)`: the bake's progress."""
    from psao.server.bake import bake_scene
    from psao.server.tick.server_tick import AtRest, ServerTick

    b = budget(s)
    # The bake's AO counts as that many rays of every point's history: with all the rays it is converged,
    # with `progressive` the ticks' spare budget refines it.
    bake_rays = b.round_rays if s.progressive else s.bake.rays
    bake = bake_scene(scene, dataclasses.replace(s.bake, rays=bake_rays), report=report)
    refiner = None
    if s.progressive:  # the bake's tracer (a cluster's, or local worker processes) refines beside the ticks
        from psao.server.tick.refine import BackgroundTracer, ClusterRefiner
        refiner = ClusterRefiner(bake.tracer if s.bake.cluster is not None else BackgroundTracer(bake.tracer))
    # closes the bake's tracer (unless the refiner keeps it), starts its own
    tick = ServerTick(bake, TickSettings.serving(s.bake, b), close_bake_tracer=refiner is None, refiner=refiner,
                      tick_hz=s.serve.tick_hz)
    log.info("baked %s at N=%g with %d rays: %d points; server tick on (%d rays per point per round, up to %d)",
             scene.name, bake.stats["density"], bake_rays, bake.stats["points_kept"], b.round_rays, s.bake.rays)
    return tick if s.animate else AtRest(tick)


def coarse_first(s, scene, report=None):
    """(coarse first grid, its tick or None) when the progressive start makes one
    (psao.server.tick.progressive), else None. With `animate` a server tick of its own poses and traces the
    movers on it from the first tick; without, the coarse grid stands still until the full one comes."""
    from psao.server.bake import bake_scene
    from psao.server.tick.progressive import coarse_bake_settings, wants_coarse_grid
    from psao.server.tick.server_tick import ServerTick
    from psao.server.tracer.embree import numpy_rays

    if not s.progressive or s.serve.allow_edits or s.bake.cluster is not None:
        return None
    b = budget(s)
    if not wants_coarse_grid(scene, s.bake, ProgressiveSettings(first_points=s.first_points)):
        return None
    with numpy_rays():  # its few rays stay in this process and thread (workers=1): no worker processes to start
        coarse = bake_scene(scene, coarse_bake_settings(s.bake, s.first_points, b.round_rays), report=report)
    log.info("coarse first grid of %s: %d points with %d rays in %.1f s; the full grid (N=%s) is baked behind it",
             scene.name, coarse.stats["points_kept"], b.round_rays,
             sum(v for k, v in coarse.stats.items() if k.startswith("seconds_")),
             f"{s.bake.density:g}" if s.bake.density else "default")
    if not s.animate:
        coarse.tracer.close()
        return coarse.grid, None
    tick = ServerTick(coarse, TickSettings.serving(s.bake, b), close_bake_tracer=True)
    return tick.grid, tick


def grid_file(s):
    """(grid, scene hash) of the `grid` file, read before the server listens (a bad file fails at once), or None."""
    from psao.server.grid import Grid

    if s.grid is None:
        return None
    grid, scene_hash, _meta = Grid.load(s.grid)
    return grid, scene_hash


def still_grid(s, scene, from_file=None, report=None):
    """The grid served with no tick: `from_file` (grid_file's) checked against the scene, else a bake's."""
    from psao.server.bake import bake_scene

    if from_file is not None:
        grid, scene_hash = from_file
        if scene_hash and scene_hash != scene.content_hash():
            raise ConfigError(f"{s.grid} was baked from another scene than {scene.name}")
        if len(grid.instances) != len(scene.instances):
            raise ConfigError(f"{s.grid} has {len(grid.instances)} instances, {scene.name} has {len(scene.instances)}")
        return grid
    result = bake_scene(scene, s.bake, report=report)
    result.tracer.close()
    log.info("baked %s at N=%g: %d points in %d cells", scene.name, result.stats["density"],
             result.stats["points_kept"], result.stats["cells"])
    return result.grid


def _import_bake_modules() -> None:
    """Import what the bake needs (scipy, Embree, the tracer) ahead of it. A failure is left to the bake's
    own import, which raises it where it is reported."""
    with contextlib.suppress(Exception):
        import psao.server.bake  # noqa: F401
        import psao.server.tick.server_tick  # noqa: F401
        import psao.server.tracer.embree  # noqa: F401


def _warn_failed(what: str):
    """A done-callback for a background future: its failure (not Stopped) as one warning line."""
    def done(future) -> None:
        exc = future.exception()
        if exc is not None and type(exc).__name__ != "Stopped":
            log.warning("%s failed: %s", what, exc)
    return done


def start_up(s, scene, from_file, on_served: Callable) -> Callable:
    """The start-up's work (progressive.Startup), on its own thread once the service listens: load `scene`
    (a Scene, or what load_scene takes) and hand its hash and blob over, serve a coarse first grid when the
    progressive start makes one, then the full grid; `on_served(scene, tick or None, grid)` hears the full
    grid handed over."""
    def work(startup) -> None:
        from psao.protocol.session import scene_hash_bytes
        from psao.scene import load_scene
        from psao.server.net.scene_export import SceneExportSettings, scene_blob
        from psao.server.net.service import StaticTransforms
        from psao.server.tick.testhook import RandomEdits

        background = concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="psao-startup")
        loaded = scene
        if isinstance(scene, str):
            background.submit(_import_bake_modules)  # beside the scene's loading
            startup.step(0.0, f"loading {scene}")
            loaded = load_scene(scene)
        scene_hash = scene_hash_bytes(loaded.content_hash())
        if s.fast_scene_first:
            # Clients that ask for the scene now get it compressed fast; its strongest zstd level, which takes a
            # while on a large scene, is compressed after the coarse grid, beside the full bake, and sent from then on.
            startup.scene(scene_hash, scene_blob(loaded, level=SceneExportSettings.first_zstd_level))
        else:
            startup.scene(scene_hash, lambda: scene_blob(loaded))
        resting = StaticTransforms(np.array([i.transform for i in loaded.instances], dtype=np.float32))
        startup.step(0.0, "baking the coarse first grid")
        coarse = coarse_first(s, loaded, lambda f, text: startup.step(f, f"coarse grid {text}"))
        if coarse is not None:
            grid, tick = coarse
            startup.serve(grid, tick, tick.transforms if tick is not None else resting, final=False)
        if s.fast_scene_first:
            strong = background.submit(lambda: startup.scene_blob(scene_blob(loaded)))
            strong.add_done_callback(_warn_failed("compressing the scene file at its strongest level"))
        background.shutdown(wait=False)
        startup.step(0.0, "baking the full grid")
        report = lambda f, text: startup.step(f, f"full grid {text}")  # noqa: E731
        if runs_tick(s):
            tick = ticking(s, loaded, report)
            startup.serve(tick.grid, tick, tick.transforms, final=True)
            on_served(loaded, tick, tick.grid)
        else:
            grid = still_grid(s, loaded, from_file, report)
            tick = RandomEdits(s.test_edits, seed=s.bake.seed) if s.test_edits else None
            startup.serve(grid, tick, resting, final=True)
            on_served(loaded, None, grid)
    return work
