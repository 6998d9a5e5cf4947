"""`psao.Server`: a PSAO server inside an application's own process, driven from its own loop; `psao serve`
is a thin layer over it (its flags fill ServerSettings, its signals stop it).

    server = psao.Server("builtin:courtyard", ServerSettings(bake=BakeSettings(density=64)))
    server.start()                      # listens, bakes, returns once the baked grid is served
    server.move("crate", matrix)        # an instance's local-to-world transform from the next tick on
    server.set_time(t)                  # with ServerSettings.clock == "app": the scene's animations at time t
    server.add_instance("tall_block", matrix, name="block2")   # another instance of a mesh of the scene
    server.remove_instance("block2")
    server.stop()

start() binds the port, starts the websocket service (psao.server.net.service.Service) on a thread of its
own, and runs the start-up (psao.server.startup) on another: it loads the scene, bakes (a coarse first grid
first with `progressive`) and hands each grid over with its server tick
(psao.server.tick.server_tick.ServerTick); clients that connect meanwhile are told the phase in Status
messages. Clients (`psao client`, the web page, psao.Client) connect to `server.url` and see the
application's motion. Every move is checked as a client's SceneEdit is
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
import socket
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from psao.protocol.errors import EditError
from psao.protocol.session import check_edit_transform, scene_hash_bytes
from psao.server.errors import ConfigError, InstanceError
from psao.server.settings import BakeSettings, ServeSettings
from psao.server.tick.progressive import ProgressiveSettings

CLOCKS = ("wall", "app")


@dataclass
class ServerSettings:
    serve: ServeSettings = field(default_factory=lambda: ServeSettings(port=0))  # port 0: a free one
    bake: BakeSettings = field(default_factory=BakeSettings)
    animate: bool = False  # the scene's own animations (rigid paths, skins) play
    clock: str = "wall"  # "wall": the animations' time is the server's own clock; "app": set_time() gives it
    start_timeout: float = 30.0  # seconds start() waits for the port to listen, and a scene swap to be served
    # Progressive start: a coarse first grid (first_points points, one round's rays) is served at once, then
    # the full grid traced with one round's rays, refined to bake.rays by the ticks' spare budget.
    progressive: bool = False
    first_points: int = ProgressiveSettings.first_points  # points of the coarse first grid; 0: none
    tick_rays: int | None = None  # rays per point per tick round, a divisor of bake.rays; None: the default round
    tick_budget_ms: float | None = None  # ms of tracing per tick; None: the tick period's headroom
    # A baked grid without animate, progressive or allow_edits still gets a server tick that holds the scene
    # at rest, so that a move re-traces what it moves; False: such a grid is served with no tick.
    tick_at_rest: bool = True
    grid: Path | None = None  # serve this grid file (psao bake's .npz) instead of baking; no tick
    test_edits: int | None = None  # test hook: edit about this many points per tick (needs no tick)
    fast_scene_first: bool = False  # send the scene file at a fast zstd level until its strongest is ready

    def check(self, names: dict[str, str] | None = None) -> None:
        """ConfigError for settings that cannot run; `names` (a field -> what the message calls it, as
        psao serve's flags) for the refusals of a combination."""
        def n(f: str) -> str:
            return (names or {}).get(f, f)

        if self.clock not in CLOCKS:
            raise ConfigError(f"clock must be one of {', '.join(CLOCKS)}, got {self.clock!r}")
        if self.clock == "app" and not self.animate:
            raise ConfigError("clock='app' drives the scene's animations: it needs animate=True")
        if self.test_edits is not None and self.test_edits < 0:
            raise ConfigError(f"{n('test_edits')} must be >= 0, got {self.test_edits}")
        self.serve.check()
        self.bake.check()
        if self.grid is not None and self.bake.cluster is not None:
            raise ConfigError(f"{n('cluster')} traces a bake: it has nothing to do with a {n('grid')} file")
        if self.animate or self.progressive or self.serve.allow_edits:
            flag = n("animate") if self.animate else n("progressive") if self.progressive else n("allow_edits")
            if self.grid is not None:
                raise ConfigError(f"{flag} bakes the scene itself: it cannot serve a {n('grid')} file")
            if self.test_edits:
                raise ConfigError(f"{flag} and {n('test_edits')} both edit the grid: choose one")
        if self.first_points < 0:
            raise ConfigError(f"{n('first_points')} must be >= 0, got {self.first_points}")
        from psao.server.startup import budget, runs_tick

        if runs_tick(self):
            budget(self)
        elif self.tick_budget_ms is not None or self.tick_rays is not None:
            raise ConfigError(f"{n('tick_budget_ms')} and {n('tick_rays')} need {n('animate')}, {n('progressive')} "
                              f"or {n('allow_edits')} (no tick runs otherwise)")


class Server:
    """A scene served from threads of this process, moved by the application (see the module)."""

    def __init__(self, scene, settings: ServerSettings | None = None):
        """`scene`: a psao.scene Scene, or what psao.scene.load_scene takes (builtin:NAME, a .toml, a mesh
        file), which start() loads once the port listens."""
        self.settings = settings or ServerSettings()
        self.settings.check()
        self._spec = scene
        self.scene = None if isinstance(scene, str) else scene  # the scene served (loaded by start())
        self._names: dict[str, int] = {}
        self._placed: dict[str, np.ndarray] = {}  # instance name -> the transform the latest move gave it
        self._edit_lock = threading.Lock()  # a move waits for an add or remove to swap its scene in
        self._time = 0.0
        self._thread: threading.Thread | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._stop: asyncio.Event | None = None
        self._stop_requested = False
        self._failed: list[BaseException] = []
        self._full = threading.Event()  # the start-up handed the full grid over
        self._full_grid = None
        self.service = None
        self.tick = None  # the server tick of the full grid (None: served with no tick)

    # ---------------------------------------------------------------- lifecycle
    def start(self, listener=None, wait: bool = True) -> "Server":
        """Listen (on `listener`, a bound listening socket this server takes over, else on settings.serve's
        host and port), then load and bake on the start-up thread. Returns once the port listens; with `wait`
        once the full grid is served (raising what stopped the start-up, if something did)."""
        if self._thread is not None:
            raise ConfigError("this server is already started")
        from psao.server.net.service import Service, tls_context
        from psao.server.startup import grid_file, start_up
        from psao.server.tick.progressive import Startup, StartupProgress

        s = self.settings
        from_file = grid_file(s)  # a bad grid file, certificate or port fails here, before anything listens
        if s.serve.tls_cert is not None:
            tls_context(s.serve.tls_cert, s.serve.tls_key)
        sock = listener if listener is not None else bind_listener(s.serve.host, s.serve.port)
        progress = StartupProgress(f"loading {self._spec}" if isinstance(self._spec, str) else "baking")
        clock = (lambda: self._time) if s.clock == "app" else None
        self.service = Service(None, None, s.serve, progress=progress, clock=clock)
        startup = Startup(self.service, start_up(s, self._spec, from_file, self._served), self._start_up_failed,
                          progress)
        listening = threading.Event()
        self._thread = threading.Thread(target=self._serve, args=(sock, startup, listening), name="psao-server",
                                        daemon=True)
        self._thread.start()
        if not listening.wait(s.start_timeout) or self._failed:
            self._raise_after_stop(f"the server did not listen within {s.start_timeout:g} s")
        if wait:
            while not self._full.wait(0.05):
                if self._failed or not self._thread.is_alive():
                    self._raise_after_stop("the server stopped before it served its grid")
            self._wait_served(self._full_grid)
        return self

    def _raise_after_stop(self, why: str) -> None:
        failed = list(self._failed)
        try:
            self.stop()
        except BaseException:  # noqa: BLE001 - the first failure is raised below
            pass
        raise failed[0] if failed else ConfigError(why)

    def _served(self, scene, tick, grid) -> None:
        """The start-up handed the full grid of `scene` over (on the start-up thread)."""
        self.scene, self.tick, self._full_grid = scene, tick, grid
        self._names = {inst.name: i for i, inst in enumerate(scene.instances)}
        self._full.set()

    def _start_up_failed(self, exc: BaseException) -> None:
        self._failed.append(exc)
        self.request_stop()

    def _serve(self, sock, startup, listening: threading.Event) -> None:
        async def main() -> None:
            self._loop = asyncio.get_running_loop()
            self._stop = asyncio.Event()
            if self._stop_requested:
                self._stop.set()

            def ready(port: int) -> None:
                listening.set()
                startup.start()
            try:
                await self.service.run(self._stop, ready=ready, sock=sock)
            finally:
                startup.close()

        try:
            asyncio.run(main())
        except BaseException as exc:  # noqa: BLE001 - reported by start(), wait() and stop()
            self._failed.insert(0, exc)
        finally:
            listening.set()
            sock.close()
            if self.tick is not None:  # a swapped-in scene's tick (the start-up's are closed already)
                self.tick.close()

    def request_stop(self) -> None:
        """Ask the service to stop (Bye to every client); from any thread or a signal handler; wait() returns."""
        self._stop_requested = True
        if self._loop is not None and self._stop is not None:
            try:
                self._loop.call_soon_threadsafe(self._stop.set)
            except RuntimeError:  # its loop is closed: the service stopped already
                pass

    def wait(self) -> None:
        """Block until the server stopped (request_stop, or a failure, which is raised)."""
        while self._thread is not None and self._thread.is_alive():
            self._thread.join(0.5)  # in slices: the main thread's signal handlers run between them
        if self._failed:
            raise self._failed[0]

    def stop(self) -> None:
        """Say Bye to the clients, stop serving and release the tracer; raises what stopped the service, if
        something did."""
        if self._thread is None:
            return
        self.request_stop()
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
        if self.scene is None:
            raise ConfigError("the server has not loaded its scene yet (start() loads it)")
        if not self._names:
            self._names = {inst.name: i for i, inst in enumerate(self.scene.instances)}
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
            self._started()
            i = self.instance(instance)
            m = self._checked_matrix("move", matrix)
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
        if self.service is None or self._thread is None or not self._full.is_set():
            raise ConfigError("the server is not started (or has not served its grid yet)")

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
        from psao.server.startup import ticking

        scene = dataclasses.replace(self.scene, meshes=meshes, instances=instances)
        # the whole new scene baked with all its rays: a progressive start's first grids are for its first seconds
        tick = ticking(dataclasses.replace(self.settings, progressive=False), scene)
        self.service.replace_grid(tick.grid, tick, tick.transforms, final=True, close_previous=True,
                                  scene=(scene_hash_bytes(scene.content_hash()), lambda: scene_blob(scene)))
        self._wait_served(tick.grid)
        self.tick, self.scene = tick, scene
        self._names = {inst.name: i for i, inst in enumerate(scene.instances)}

    def _wait_served(self, grid) -> None:
        """Block until the service serves `grid` (it swaps a grid in at its next tick)."""
        deadline = time.perf_counter() + self.settings.start_timeout
        while self.service.grid is not grid:
            if self._failed or not self._thread.is_alive() or time.perf_counter() > deadline:
                raise self._failed[0] if self._failed else ConfigError("the service stopped before it served the new grid")
            time.sleep(0.005)

    def set_time(self, t: float) -> None:
        """The scene time (seconds) the next ticks pose the scene's animations at (ServerSettings.clock "app")."""
        if self.settings.clock != "app":
            raise ConfigError("set_time needs ServerSettings(clock='app')")
        t = float(t)
        if not math.isfinite(t):
            raise ConfigError(f"set_time: the time must be finite, got {t}")
        self._time = t


def bind_listener(host: str, port: int) -> socket.socket:
    """The listening socket, bound now (before any bake) so a busy port fails in a second, not after it."""
    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)
        family, kind, proto, _, addr = infos[0]
        sock = socket.socket(family, kind, proto)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            sock.bind(addr)
            sock.listen(128)
        except OSError:
            sock.close()
            raise
    except OSError as exc:  # the port is taken, the address is not ours, ...
        raise ConfigError(f"cannot listen on {host}:{port}: {exc.strerror or exc}") from None
    sock.setblocking(False)
    return sock


__all__ = ["Server", "ServerSettings", "bind_listener"]
