"""Start-up of `psao serve`: it listens first, then loads and bakes on a thread of its own (Startup),
serving a coarse first grid at once and the full grid behind it (progressive start, the default).

The full bake of a large scene (points at the target density, a first trace with the tick's round of
rays, the server tick's set-up) takes tens of seconds. So the server first bakes a coarse grid of about
`first_points` points (uniform random points, no elimination and no buried-surface test: they cost more
than the preview gains), traced with the same few rays, and streams it as soon as it is baked; with
--animate a server tick of its own poses and traces the movers on it from its first tick. The full bake
runs on the same thread behind it (its tracing in the tracer's worker processes); when it is done the
service swaps the full grid in (Service.replace_grid), every client reconnects to it (close code
GRID_REPLACED_CLOSE), and the server tick refines it to the target rays in its spare budget. Until then the
service tells connected clients what the start-up is doing (StartupProgress, in Status messages).
"""
from __future__ import annotations

import dataclasses
import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

from psao.server.settings import BakeSettings, GapFillSettings

if TYPE_CHECKING:  # psao.scene imports trimesh (a second): `psao serve --help` does without it
    from psao.scene.model import Scene

log = logging.getLogger("psao.serve")


@dataclass
class ProgressiveSettings:
    first_points: int = 12_000  # points of the coarse first grid; 0: no coarse grid, the full grid comes first
    # The coarse grid is worth it only when the full grid is this many times larger (else it comes soon anyway).
    min_ratio: float = 4.0


def coarse_bake_settings(full: BakeSettings, first_points: int, rays: int) -> BakeSettings:
    """The coarse first grid's bake: a total of `first_points`, spawned uniformly (no detail levels: at so few
    points nearly every triangle would be one) and kept as spawned (no
    elimination), no buried-surface test, no gap fill, `rays` rays, traced in this process (starting worker
    processes would cost more than its few rays)."""
    return dataclasses.replace(full, density=None, points=float(first_points), detail_factor=1, rays=rays,
                               spawn_ratio=1.0, skip_buried=False, gap_fill=GapFillSettings(passes=0), workers=1)


def wants_coarse_grid(scene: Scene, full: BakeSettings, settings: ProgressiveSettings) -> bool:
    """True when the full bake's estimated points exceed the coarse grid's by settings.min_ratio (ConfigError
    here, before anything is baked, when the full bake is over its point limit)."""
    from psao.server.points.sampling import resolve_density

    if settings.first_points <= 0:
        return False
    estimate = resolve_density(scene, full.sampling(), full.min_points).estimate
    return estimate >= settings.min_ratio * settings.first_points


class StartupProgress:
    """What the start-up is doing: the fraction done of its current step (0..1) and a line of text, set by
    the start-up thread and read by the service for its Status messages (one tuple, replaced whole)."""

    def __init__(self, text: str = "starting"):
        self._now = (0.0, text)
        self.started = time.perf_counter()

    def set(self, fraction: float, text: str) -> None:
        self._now = (min(max(float(fraction), 0.0), 1.0), text)

    def __call__(self) -> tuple[float, str]:
        return self._now


class Stopped(Exception):
    """The server stopped while the start-up ran: what it made is closed and the thread ends."""


class Startup:
    """`work(startup)` on a daemon thread once the service listens: it loads the scene and bakes, and hands
    the service what it has as it comes: `scene(...)` (the scene hash and blob), `serve(...)` (a coarse first
    grid, then the full one), `step(...)` (progress for the Status messages). A failure goes to
    `on_error(exc)` (the server stops with it). close() (the server stopped) closes every tick it handed
    over, and one that arrives afterwards; the work then ends at its next hand-over (Stopped)."""

    def __init__(self, service, work: Callable[["Startup"], None], on_error: Callable[[BaseException], None],
                 progress: StartupProgress | None = None):
        self.service, self._work, self._on_error = service, work, on_error
        self.progress = progress or StartupProgress()
        self._lock = threading.Lock()
        self._closed = False
        self._ticks: list = []  # the ticks handed to the service
        self.seconds: dict[str, float] = {}  # seconds from start() to each grid served ("coarse", "full")
        self._t0 = 0.0
        self._thread = threading.Thread(target=self._run, name="psao start-up", daemon=True)

    def start(self) -> None:
        self._t0 = time.perf_counter()
        self._thread.start()

    def _run(self) -> None:
        try:
            self._work(self)
        except Stopped:
            return
        except BaseException as exc:  # noqa: BLE001 - reported to the service, which stops
            if not self._closed:
                self._on_error(exc)

    def step(self, fraction: float, text: str) -> None:
        """Progress of the current step (Stopped once the server stopped)."""
        if self._closed:
            raise Stopped()
        self.progress.set(fraction, text)

    def scene(self, scene_hash: bytes, scene_blob) -> None:
        if self._closed:
            raise Stopped()
        self.service.set_scene(scene_hash, scene_blob)

    def scene_blob(self, scene_blob: bytes) -> None:
        """The scene file compressed anew (a stronger level): sent from now on."""
        if not self._closed:
            self.service.set_scene_blob(scene_blob)

    def serve(self, grid, tick, transforms, final: bool) -> None:
        """Hand the service a grid with its tick and transforms (the coarse one: final False); the tick
        served before is closed once it is replaced."""
        with self._lock:
            if self._closed:
                if tick is not None:
                    tick.close()
                raise Stopped()
            if tick is not None:
                self._ticks.append(tick)
            self.service.replace_grid(grid, tick, transforms, final=final, close_previous=True)
        self.seconds["full" if final else "coarse"] = time.perf_counter() - self._t0

    def close(self) -> None:
        with self._lock:
            self._closed = True
            ticks, self._ticks = self._ticks, []
        for tick in ticks:
            tick.close()


class BackgroundBake:
    """`build()` -> (grid, tick) in a daemon thread; `on_ready(grid, tick)` hears the result, `on_error(exc)`
    a failure. close() closes the tick if it arrives after the server stopped (or closes it now)."""

    def __init__(self, build: Callable[[], tuple], on_ready: Callable, on_error: Callable[[BaseException], None]):
        self._build, self._on_ready, self._on_error = build, on_ready, on_error
        self._lock = threading.Lock()
        self._closed = False
        self.tick = None
        self.seconds: float | None = None  # how long the full bake took
        self._thread = threading.Thread(target=self._run, name="full bake", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def _run(self) -> None:
        t0 = time.perf_counter()
        try:
            grid, tick = self._build()
        except BaseException as exc:  # noqa: BLE001 - reported to the service, which stops
            self._on_error(exc)
            return
        self.seconds = time.perf_counter() - t0
        with self._lock:
            if self._closed:  # the server stopped meanwhile
                tick.close()
                return
            self.tick = tick
        self._on_ready(grid, tick)

    def close(self) -> None:
        with self._lock:
            self._closed = True
            if self.tick is not None:
                self.tick.close()
                self.tick = None
