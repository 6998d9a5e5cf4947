"""`psao.Server`: a PSAO server inside an application's own process, driven from its own loop.

    server = psao.Server("builtin:courtyard", ServerSettings(bake=BakeSettings(density=64)))
    server.start()                      # bakes, then serves on a thread of its own; returns when it listens
    server.move("crate", matrix)        # an instance's local-to-world transform from the next tick on
    server.set_time(t)                  # with ServerSettings.clock == "app": the scene's animations at time t
    server.add_instance("tall_block", matrix, name="block2")   # another instance of a mesh of the scene
    server.remove_instance("block2")
    server.stop()

It is the same service, tick and bake as `psao serve` (psao.server.net.service.Service,
psao.server.tick.server_tick.ServerTick): clients (`psao client`, the web page, psao.Client) connect to
`server.url` and see the application's motion. Every move is checked as a client's SceneEdit is
(psao.protocol.session.check_edit_transform) and raises EditError at the call when it is out of range;
the server keeps serving.

Adding or removing an instance changes the scene: the server bakes the new scene (every instance at its
current pose) in the calling thread while it goes on serving the old one, then swaps the new scene and grid
in as the progressive start swaps its full grid in (Service.replace_grid with the new scene): every client
is closed with GRID_REPLACED_CLOSE, asks for the scene again (SceneRequest with the hash of the one it
holds), receives the new one and a snapshot of the new grid. A bad call raises InstanceError before any
of that.
"""
from __future__ import annotations

import asyncio
import dataclasses
import math
import threading
import time
from dataclasses import dataclass, field

import numpy as np

from psao.protocol.errors import EditError
from psao.protocol.session import check_edit_transform, scene_hash_bytes
from psao.server.errors import ConfigError, InstanceError
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
        self._placed: dict[str, np.ndarray] = {}  # instance name -> the transform the latest move gave it
        self._edit_lock = threading.Lock()  # a move waits for an add or remove to swap its scene in
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
        from psao.server.net.scene_export import scene_blob
        from psao.server.net.service import Service

        s = self.settings
        self.tick, driven = self._baked(self.scene)
        clock = (lambda: self._time) if s.clock == "app" else None
        scene = self.scene
        self.service = Service(self.tick.grid, scene_hash_bytes(scene.content_hash()), s.serve, tick=driven,
                               transforms=self.tick.transforms, on_scene_edit=self.tick.edit,
                               scene_blob=lambda: scene_blob(scene), clock=clock)
        listening = threading.Event()
        self._thread = threading.Thread(target=self._serve, args=(listening,), name="psao-server", daemon=True)
        self._thread.start()
        if not listening.wait(s.start_timeout) or self._failed:
            self.stop()
            raise self._failed[0] if self._failed else ConfigError(
                f"the server did not listen within {s.start_timeout:g} s")
        return self

    def _baked(self, scene):
        """(server tick, what the service ticks) of a fresh bake of `scene`."""
        from psao.server.bake import bake_scene
        from psao.server.tick.server_tick import AtRest, ServerTick

        s = self.settings
        bake = bake_scene(scene, s.bake)
        budget = BudgetSettings(round_rays=fitting_round_rays(s.bake.rays))
        budget.check(s.bake.rays)
        tick = ServerTick(bake, TickSettings.serving(s.bake, budget), close_bake_tracer=True, tick_hz=s.serve.tick_hz)
        return tick, (tick if s.animate else AtRest(tick))

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
        with self._edit_lock:
            i = self.instance(instance)
            m = self._checked_matrix("move", matrix)
            self._started()
            self.service.scene_edit(i, m)
            self._placed[self.scene.instances[i].name] = m

    def _checked_matrix(self, what: str, matrix) -> np.ndarray:
        """`matrix` as a float64 4x4 local-to-world transform, checked as a SceneEdit's (EditError)."""
        m = np.asarray(matrix, dtype=np.float64)
        if m.shape != (4, 4):
            raise EditError(f"{what}: the matrix must be 4x4, got shape {m.shape}")
        if not np.isfinite(m).all():
            raise EditError(f"{what}: the matrix holds NaN or infinity")
        check_edit_transform(m, self.settings.serve.limits)
        return m

    def _started(self) -> None:
        if self.service is None or self._thread is None:
            raise ConfigError("the server is not started")

    # ---------------------------------------------------------------- adding and removing instances
    def add_instance(self, mesh, matrix, name: str) -> int:
        """Add an instance named `name` of `mesh` (the index or name of a mesh of the scene, or a psao.scene
        Mesh, which joins the scene) at the 4x4 local-to-world `matrix`; returns its index. Bakes the new scene
        here and swaps it in (see the module): the new instance's points are traced, and so are its
        neighbours', which it now occludes. InstanceError for an unknown mesh, a name that is empty or taken,
        or a matrix a move would refuse; the server goes on serving."""
        from psao.scene.model import Instance, Mesh

        with self._edit_lock:
            self._started()
            if not isinstance(name, str) or not name.strip():
                raise InstanceError(f"add_instance: the name must be a non-empty string, got {name!r}")
            if name in self._names:
                raise InstanceError(f"add_instance: the scene already has an instance named {name!r}")
            limit = self.settings.serve.limits.max_instances
            if len(self.scene.instances) >= limit:
                raise InstanceError(f"add_instance: the scene has {limit} instances, the most a client takes")
            try:
                m = self._checked_matrix("add_instance", matrix)
            except EditError as exc:
                raise InstanceError(str(exc)) from None
            meshes = list(self.scene.meshes)
            if isinstance(mesh, Mesh):
                meshes.append(mesh)
                index = len(meshes) - 1
            else:
                index = self._mesh(mesh)
            self._swap_scene(meshes, [*self._posed_instances(), Instance(name, index, m)])
            return len(self.scene.instances) - 1

    def remove_instance(self, instance: int | str) -> None:
        """Remove `instance` (index or name): bakes the scene without it here and swaps it in (see the
        module); its cells and its occlusion of the others are gone, and the instances after it move one index
        down. InstanceError for an unknown instance or the scene's last one; the server goes on serving."""
        with self._edit_lock:
            self._started()
            try:
                i = self.instance(instance)
            except EditError as exc:
                raise InstanceError(f"remove_instance: {exc}") from None
            if len(self.scene.instances) == 1:
                raise InstanceError("remove_instance: a scene keeps at least one instance")
            instances = self._posed_instances()
            self._placed.pop(instances[i].name, None)
            self._swap_scene(list(self.scene.meshes), instances[:i] + instances[i + 1:])

    def _mesh(self, mesh: int | str) -> int:
        meshes = self.scene.meshes
        if isinstance(mesh, str):
            found = [i for i, m in enumerate(meshes) if m.name == mesh]
            if len(found) != 1:
                known = ", ".join(m.name for m in meshes[:8]) + (", ..." if len(meshes) > 8 else "")
                why = "several meshes are" if found else "no mesh is"
                raise InstanceError(f"add_instance: {why} named {mesh!r} (the scene has {len(meshes)}: {known})")
            return found[0]
        if isinstance(mesh, (bool, np.bool_)) or not isinstance(mesh, (int, np.integer)) or not 0 <= mesh < len(meshes):
            raise InstanceError(f"add_instance: no mesh {mesh!r} (the scene has {len(meshes)}, indices 0..{len(meshes) - 1})")
        return int(mesh)

    def _posed_instances(self) -> list:
        """The scene's instances, each one the application moved at its latest move's transform."""
        return [dataclasses.replace(inst, transform=self._placed[inst.name]) if inst.name in self._placed else inst
                for inst in self.scene.instances]

    def _swap_scene(self, meshes: list, instances: list) -> None:
        """Bake the scene with `meshes` and `instances` and serve it from the next tick on; returns once the
        service serves it."""
        from psao.server.net.scene_export import scene_blob

        scene = dataclasses.replace(self.scene, meshes=meshes, instances=instances)
        tick, driven = self._baked(scene)
        self.service.replace_grid(tick.grid, driven, tick.transforms, final=True, close_previous=True,
                                  scene=(scene_hash_bytes(scene.content_hash()), lambda: scene_blob(scene)))
        deadline = time.perf_counter() + self.settings.start_timeout
        while self.service.grid is not tick.grid:  # the swap happens at the service's next tick
            if self._failed or not self._thread.is_alive() or time.perf_counter() > deadline:
                raise self._failed[0] if self._failed else ConfigError("the service stopped before the new scene was served")
            time.sleep(0.005)
        self.tick, self.scene = tick, scene
        self._names = {inst.name: i for i, inst in enumerate(scene.instances)}

    def set_time(self, t: float) -> None:
        """The scene time (seconds) the next ticks pose the scene's animations at (ServerSettings.clock "app")."""
        if self.settings.clock != "app":
            raise ConfigError("set_time needs ServerSettings(clock='app')")
        t = float(t)
        if not math.isfinite(t):
            raise ConfigError(f"set_time: the time must be finite, got {t}")
        self._time = t


__all__ = ["Server", "ServerSettings"]
