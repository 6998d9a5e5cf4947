"""`psao.Client`: a headless PSAO client inside an application's own process.

    client = psao.Client(server_url, on_update=lambda mirror, transforms, tick: ...)
    client.start()                   # fetches the server's scene, connects, returns once the snapshot is in
    client.set_camera(view, proj)    # the pose it sends (default: the scene's camera path)
    client.mirror                    # the grid as the server holds it (exact after every Update)
    client.wait_for_updates(10)
    client.stop()

It is psao.client.connection's MirrorClient (the code `psao client` runs) on a thread of its own: it
reconnects and resyncs as `psao client` does, and follows the server's scene: when the server adds or
removes an instance (psao.Server.add_instance), the client receives the new scene (`scene`, `scene_hash`,
`on_scene`) and then a snapshot of the new grid. Callbacks run on that thread.
"""
from __future__ import annotations

import asyncio
import threading
from collections.abc import Callable

import numpy as np

from psao.client.connection import MirrorClient, OnUpdate, fetch_scene, scene_camera_feed
from psao.client.errors import ClientError, ConnectError
from psao.client.mirror import Mirror


class Client:
    """A mirror of a server's grid, kept on a thread of its own (see the module)."""

    def __init__(self, url: str, *, token: str = "", on_update: OnUpdate | None = None,
                 on_snapshot: Callable[[Mirror], None] | None = None, on_scene: Callable | None = None,
                 digest_log=None, start_wait: float = 15.0, camera_hz: float = 30.0):
        self.url, self.token = url, token
        self.on_update, self.on_snapshot, self.on_scene = on_update, on_snapshot, on_scene
        self.digest_log, self.start_wait, self.camera_hz = digest_log, start_wait, camera_hz
        self.scene = None
        self.scene_hash: bytes | None = None
        self.mirror: Mirror | None = None
        self._camera: tuple[np.ndarray, np.ndarray] | None = None
        self._path_feed = None
        self._client: MirrorClient | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread: threading.Thread | None = None
        self._changed = threading.Condition()
        self._snapshots = 0
        self._updates = 0
        self._failed: list[BaseException] = []
        self._done = False

    # ---------------------------------------------------------------- lifecycle
    def start(self, timeout: float = 60.0) -> "Client":
        """Connect and return once the first snapshot is complete (ConnectError if it fails, or after `timeout` s)."""
        if self._thread is not None:
            raise ClientError("this client is already started")
        self._thread = threading.Thread(target=self._run, name="psao-client", daemon=True)
        self._thread.start()
        self.wait_for(lambda: self._snapshots >= 1, timeout, "the first snapshot")
        return self

    def _run(self) -> None:
        async def main() -> None:
            self._loop = asyncio.get_running_loop()
            self.scene, self.scene_hash, _ = await fetch_scene(self.url, self.token, start_wait=self.start_wait)
            self._path_feed = scene_camera_feed(self.scene)
            self._client = MirrorClient(self.url, self.scene_hash, token=self.token, camera=self._camera_at,
                                        on_snapshot=self._snapshot, on_update=self._update, digest_log=self.digest_log,
                                        start_wait=self.start_wait, camera_hz=self.camera_hz, on_scene=self._new_scene)
            await self._client.run()

        try:
            asyncio.run(main())
        except BaseException as exc:  # noqa: BLE001 - raised by the waits and stop()
            self._failed.append(exc)
        finally:
            with self._changed:
                self._done = True
                self._changed.notify_all()

    def stop(self) -> None:
        """Say Bye to the server and stop; raises what ended the client early, if something did."""
        if self._thread is None:
            return
        try:
            if self._loop is not None and self._client is not None:
                self._loop.call_soon_threadsafe(self._client.stop)
            elif self._loop is not None:  # still fetching the scene
                for task in asyncio.all_tasks(self._loop):
                    self._loop.call_soon_threadsafe(task.cancel)
        except RuntimeError:  # its loop is closed: the client ended already (the server went, or refused it)
            pass
        self._thread.join()
        self._thread = None
        failed = [e for e in self._failed if not isinstance(e, asyncio.CancelledError)]
        if failed:
            raise failed[0]

    def __enter__(self) -> "Client":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    # ---------------------------------------------------------------- state
    @property
    def updates(self) -> int:
        """Updates applied so far, all connections."""
        return self._updates

    @property
    def stats(self):
        """psao.client.connection.ClientStats (bytes, updates, reconnects, ...)."""
        return self._client.stats if self._client is not None else None

    def digest(self) -> str:
        """The mirror's state digest (equal to the server's state digest after the same message)."""
        if self.mirror is None:
            raise ClientError("no snapshot yet")
        return self.mirror.digest()

    def set_camera(self, view, proj) -> None:
        """The camera this client sends from now on: 4x4 row-major view and projection (None: the scene's path)."""
        if view is None:
            self._camera = None
            return
        v, p = (np.asarray(a, dtype=np.float32) for a in (view, proj))
        if v.shape != (4, 4) or p.shape != (4, 4) or not (np.isfinite(v).all() and np.isfinite(p).all()):
            raise ClientError("set_camera: view and proj must be finite 4x4 matrices")
        self._camera = (v, p)

    def _camera_at(self, t: float):
        return self._camera if self._camera is not None else self._path_feed(t)

    # ---------------------------------------------------------------- waiting
    def wait_for(self, predicate: Callable[[], bool], timeout: float, what: str) -> None:
        """Block until `predicate()` holds after a snapshot or Update; ConnectError when the client ended
        first, ClientError after `timeout` seconds."""
        with self._changed:
            if not self._changed.wait_for(lambda: predicate() or self._done, timeout):
                raise ClientError(f"{self.url}: no {what} within {timeout:g} s")
            if not predicate():
                failed = [e for e in self._failed if not isinstance(e, asyncio.CancelledError)]
                if failed and isinstance(failed[0], (ConnectError, ClientError)):
                    raise failed[0]
                raise ConnectError(f"{self.url}: the client stopped before {what}") from (failed[0] if failed else None)

    def wait_for_updates(self, n: int, timeout: float = 60.0) -> None:
        """Block until `n` more Updates have been applied."""
        target = self._updates + n
        self.wait_for(lambda: self._updates >= target, timeout, f"{n} Updates")

    def _new_scene(self, scene, scene_hash: bytes) -> None:
        """The server changed its scene: the new one, before the Hello that names it."""
        self.scene, self.scene_hash = scene, scene_hash
        self._path_feed = scene_camera_feed(scene)
        if self.on_scene is not None:
            self.on_scene(scene, scene_hash)

    @property
    def snapshots(self) -> int:
        """Snapshots completed so far, one per connection (a changed scene brings a new one)."""
        return self._snapshots

    def _snapshot(self, mirror: Mirror) -> None:
        self.mirror = mirror
        if self.on_snapshot is not None:
            self.on_snapshot(mirror)
        with self._changed:
            self._snapshots += 1
            self._changed.notify_all()

    def _update(self, mirror: Mirror, transforms: np.ndarray, tick: int) -> None:
        self.mirror = mirror
        if self.on_update is not None:
            self.on_update(mirror, transforms, tick)
        with self._changed:
            self._updates += 1
            self._changed.notify_all()
