"""`psao.Server`: a PSAO server inside an application's own process, driven from its own loop.

    server = psao.Server("builtin:courtyard", ServerSettings(bake=BakeSettings(density=64)))
    server.start()                      # bakes, then serves on a thread of its own; returns when it listens
    server.move("crate", matrix)        # an instance's local-to-world transform from the next tick on
    server.set_time(t)                  # with ServerSettings.clock == "app": the scene's animations at time t
    server.stop()

It is the same service, tick and bake as `psao serve` (psao.server.net.service.Service,
psao.server.tick.server_tick.ServerTick): clients (`psao client`, the web page, psao.Client) connect to
`server.url` and see the application's motion. Every move is checked as a client's SceneEdit is
(psao.protocol.session.check_edit_transform) and raises EditError at the call when it is out of range;
the server keeps serving.
"""
from __future__ import annotations

import asyncio
import math
import threading
from dataclasses import dataclass, field

import numpy as np

from psao.protocol.errors import EditError
from psao.protocol.session import check_edit_transform, scene_hash_bytes
from psao.server.errors import ConfigError
from psao.server.settings import BakeSettings, ServeSettings, TickSettings
from psao.server.tick.budget import BudgetSettings, fitting_round_rays

CLOCKS = ("wall", "app")


@dataclass
class ServerSettings:
    serve: ServeSettings = field(default_factory=lambda: ServeSettings(port=0))  # port 0: a free one
    bake: BakeSettings = field(default_factory=BakeSettings)
    animate: bool = False  # the scene's own animations (rigid paths, skins) play
    clock: str = "wall"  # "wall": the animations' time is the server's own clock; "app": set_time() gives it
    start_timeout: float = 30.0  # seconds start() waits for the service to listen once the bake is done

    def check(self) -> None:
        if self.clock not in CLOCKS:
            raise ConfigError(f"clock must be one of {', '.join(CLOCKS)}, got {self.clock!r}")
        if self.clock == "app" and not self.animate:
            raise ConfigError("clock='app' drives the scene's animations: it needs animate=True")
        self.serve.check()
        self.bake.check()


class Server:
    """A baked scene served from a thread of this process, moved by the application (see the module)."""

    def __init__(self, scene, settings: ServerSettings | None = None):
        """`scene`: a psao.scene Scene, or what psao.scene.load_scene takes (builtin:NAME, a .toml, a mesh file)."""
        from psao.scene import load_scene

        self.settings = settings or ServerSettings()
        self.settings.check()
        self.scene = load_scene(scene) if isinstance(scene, str) else scene
        self._names = {inst.name: i for i, inst in enumerate(self.scene.instances)}
        self._time = 0.0
        self._thread: threading.Thread | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._stop: asyncio.Event | None = None
        self._failed: list[BaseException] = []
        self.service = None
        self.tick = None

    # ---------------------------------------------------------------- lifecycle
    def start(self) -> "Server":
        """Bake the scene (here, in the calling thread) and serve it; returns once the service listens."""
        if self._thread is not None:
            raise ConfigError("this server is already started")
        from psao.server.bake import bake_scene
        from psao.server.net.scene_export import scene_blob
        from psao.server.net.service import Service
        from psao.server.tick.server_tick import AtRest, ServerTick

        s = self.settings
        bake = bake_scene(self.scene, s.bake)
        budget = BudgetSettings(round_rays=fitting_round_rays(s.bake.rays))
        budget.check(s.bake.rays)
        tick_settings = TickSettings(rays=s.bake.rays, seed=s.bake.seed, budget=budget, selection=True,
                                     tracer=s.bake.tracer, workers=s.bake.workers)
        self.tick = ServerTick(bake, tick_settings, close_bake_tracer=True, tick_hz=s.serve.tick_hz)
        clock = (lambda: self._time) if s.clock == "app" else None
        driven = self.tick if s.animate else AtRest(self.tick)
        self.service = Service(self.tick.grid, scene_hash_bytes(self.scene.content_hash()), s.serve, tick=driven,
                               transforms=self.tick.transforms, on_scene_edit=self.tick.edit,
                               scene_blob=lambda: scene_blob(self.scene), clock=clock)
        listening = threading.Event()
        self._thread = threading.Thread(target=self._serve, args=(listening,), name="psao-server", daemon=True)
        self._thread.start()
        if not listening.wait(s.start_timeout) or self._failed:
            self.stop()
            raise self._failed[0] if self._failed else ConfigError(
                f"the server did not listen within {s.start_timeout:g} s")
        return self

    def _serve(self, listening: threading.Event) -> None:
        async def main() -> None:
            self._loop = asyncio.get_running_loop()
            self._stop = asyncio.Event()
            await self.service.run(self._stop, ready=lambda port: listening.set())

        try:
            asyncio.run(main())
        except BaseException as exc:  # noqa: BLE001 - reported by start() and stop()
            self._failed.append(exc)
        finally:
            listening.set()
            self.tick.close()

    def stop(self) -> None:
        """Say Bye to the clients, stop serving and release the tracer; raises what stopped the service, if
        something did."""
        if self._thread is None:
            return
        if self._loop is not None and self._stop is not None:
            self._loop.call_soon_threadsafe(self._stop.set)
        self._thread.join()
        self._thread = None
        if self._failed:
            raise self._failed[0]

    def __enter__(self) -> "Server":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    # ---------------------------------------------------------------- where clients connect
    @property
    def port(self) -> int:
        if self.service is None or self.service.port is None:
            raise ConfigError("the server is not started")
        return self.service.port

    @property
    def url(self) -> str:
        scheme = "wss" if self.settings.serve.tls_cert else "ws"
        return f"{scheme}://{self.settings.serve.host}:{self.port}"

    @property
    def ticks(self) -> int:
        """Ticks served so far."""
        return self.service.tick if self.service is not None else 0

    # ---------------------------------------------------------------- the application's motion
    def instance(self, instance: int | str) -> int:
        """The index of `instance` (its index or its name); EditError for one the scene does not have."""
        n = len(self.scene.instances)
        if isinstance(instance, str):
            if instance not in self._names:
                known = ", ".join(list(self._names)[:8]) + (", ..." if n > 8 else "")
                raise EditError(f"no instance named {instance!r} (the scene has {n}: {known})")
            return self._names[instance]
        if isinstance(instance, (bool, np.bool_)) or not isinstance(instance, (int, np.integer)) or not 0 <= instance < n:
            raise EditError(f"no instance {instance!r} (the scene has {n}, indices 0..{n - 1})")
        return int(instance)

    def move(self, instance: int | str, matrix) -> None:
        """Place `instance` (index or name) at the 4x4 local-to-world `matrix` from the next tick on: the tick
        re-traces what it moves and touches and every client gets its new transform. EditError for an unknown
        instance or a matrix that is not finite, not affine, singular or out of the limits of a SceneEdit."""
        i = self.instance(instance)
        m = np.asarray(matrix, dtype=np.float64)
        if m.shape != (4, 4):
            raise EditError(f"move: the matrix must be 4x4, got shape {m.shape}")
        if not np.isfinite(m).all():
            raise EditError("move: the matrix holds NaN or infinity")
        check_edit_transform(m, self.settings.serve.limits)
        if self.service is None:
            raise ConfigError("the server is not started")
        self.service.scene_edit(i, m)

    def set_time(self, t: float) -> None:
        """The scene time (seconds) the next ticks pose the scene's animations at (ServerSettings.clock "app")."""
        if self.settings.clock != "app":
            raise ConfigError("set_time needs ServerSettings(clock='app')")
        t = float(t)
        if not math.isfinite(t):
            raise ConfigError(f"set_time: the time must be finite, got {t}")
        self._time = t


__all__ = ["Server", "ServerSettings"]
