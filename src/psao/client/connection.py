"""`MirrorClient`: connect, handshake, receive the snapshot and updates into a Mirror, reconnect.

Thin around psao.protocol.session.ClientSession (which decides what bytes mean). Another module drives it by
`await MirrorClient(...).run(frames=...)` and plugs in callbacks:

    on_connect(mirror)                      a new connection's fresh mirror (after Welcome)
    on_snapshot(mirror)                     the snapshot is complete: the mirror equals the server
    on_update(mirror, transforms, tick)     after every Update is applied
    on_frame(mirror)                        at frame_hz, the client's own rate, from the snapshot on
                                            (a renderer draws the latest state and transforms)
    on_scene(scene, scene_hash)             with it, every connection first asks for the server's scene
                                            (SceneRequest with the hash of the one held): a server that
                                            changed its scene (instances added or removed) sends the new
                                            one, which goes here before the Hello names it

After a dropped connection it reconnects with growing pauses and resyncs from a fresh snapshot into a
fresh mirror; a server that refuses it (Error message: wrong token, other scene) is not retried. A server
that replaced its grid (close code GRID_REPLACED_CLOSE) is reconnected to at once, also with reconnect=False.

A server that is still starting: one that does not accept connections yet (refused, or no opening
handshake) is tried again for up to `start_wait` seconds, also with reconnect=False, saying so once in the
log; one that answers while it loads and bakes sends Status messages (phase, progress, text), which go to
`on_status(status)` and, when they change, to the log (`log(line)`: stderr by default).
"""
from __future__ import annotations

import asyncio
import dataclasses
import errno
import json
import socket
import ssl
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from websockets.asyncio.client import connect
from websockets.exceptions import ConnectionClosed, ConnectionClosedOK, InvalidHandshake, InvalidURI
from websockets.uri import parse_uri

from psao.protocol import messages as m
from psao.protocol.codecs import Codec, codec_name
from psao.protocol.errors import ProtocolError
from psao.protocol.limits import DEFAULT_LIMITS, Limits
from psao.protocol.session import (
    ByeReceived,
    ClientConfig,
    ClientSession,
    ClientState,
    RemoteError,
    SceneReceived,
    SnapshotReceived,
    StatusReceived,
    UpdateReceived,
    Welcomed,
    reconnect_at_once,
)

from psao.client.errors import ClientError, ConnectError
from psao.client.mirror import Mirror
from psao.client.settings import ConnectSettings

OnMirror = Callable[[Mirror], None]
OnUpdate = Callable[[Mirror, np.ndarray, int], None]
CameraFeed = Callable[[float], tuple[np.ndarray, np.ndarray]]  # seconds -> (view, projection)
READ_AHEAD = 4  # messages the websocket library queues before it stops reading (websockets' max_queue)
QUIET_END_S = 5.0  # run(frames): seconds without any Update after the snapshot that end it (a static server)
START_POLL_S = 0.2  # seconds between tries at a server that does not accept connections yet
START_WAIT_S = 15.0  # seconds a client waits for a server that does not accept connections yet (start_wait)
STATUS_LOG_STEP = 0.1  # progress (of 1) a Status must move by to be logged again with the same phase and text


@dataclass
class ClientStats:
    bytes_received: int = 0  # websocket message bytes, all connections
    messages: int = 0
    snapshot_bytes: int = 0
    updates: int = 0
    # seconds from the first Update received to the latest, all connections (connecting and snapshots
    # before the first not counted): (updates - 1) / stream_seconds is the rate Updates came at
    stream_seconds: float = 0.0
    reconnects: int = 0
    grid_replacements: int = 0  # connections the server closed because it replaced its grid (reconnected at once)
    scenes: int = 0  # new scenes received on reconnecting (with on_scene: the server changed its scene)
    frames: int = 0  # on_frame calls (frames rendered), all connections
    snapshot_seconds: float | None = None  # last connection: connect -> snapshot complete
    connection_id: int = 0
    codec: str = ""
    quiet_end: bool = False  # run(frames) ended because no Update followed the snapshot (a static server)
    status_messages: int = 0  # Status messages received (a starting server's), all connections
    status: str = ""  # the last Status received: "phase progress% text" ("" when none came)


class _Lost(Exception):
    """The connection ended without an Error message: worth reconnecting."""


class MirrorClient:
    def __init__(self, url: str, scene_hash: bytes, *, token: str = "", codecs=frozenset(Codec),
                 camera: CameraFeed | None = None, on_connect: OnMirror | None = None,
                 on_snapshot: OnMirror | None = None, on_update: OnUpdate | None = None,
                 read_delay: float = 0.0, digest_log: Path | None = None, reconnect: bool = True,
                 reconnect_timeout: float = 10.0, camera_hz: float = 30.0, recv_buffer: int | None = None,
                 limits: Limits = DEFAULT_LIMITS, on_frame: OnMirror | None = None, frame_hz: float = 30.0,
                 tls_ca: Path | None = None, digest_every: int = ConnectSettings.digest_every,
                 digest_if: Callable[[int, int], bool] | None = None, open_timeout: float = 5.0,
                 start_wait: float = START_WAIT_S, on_status: Callable[[m.Status], None] | None = None,
                 log: Callable[[str], None] | None = None, on_scene: Callable | None = None):
        self.url = url
        self.config = ClientConfig(scene_hash, token, frozenset(codecs), limits)
        self.on_scene = on_scene
        self.camera = camera
        self.on_connect, self.on_snapshot, self.on_update = on_connect, on_snapshot, on_update
        self.on_frame = on_frame
        if not frame_hz > 0:
            raise ClientError(f"frame rate must be > 0, got {frame_hz}")
        if not open_timeout > 0:
            raise ClientError(f"open timeout must be > 0 seconds, got {open_timeout}")
        if not start_wait >= 0:
            raise ClientError(f"start wait must be >= 0 seconds, got {start_wait}")
        # seconds to keep trying a server that does not accept connections yet, before "cannot connect"
        self.start_wait = start_wait
        self.on_status = on_status
        self.status_log = StatusLog(url, log)
        self.frame_period = 1.0 / frame_hz
        self.read_delay = read_delay
        self.digest_log = digest_log
        if digest_every < 1:
            raise ClientError(f"digest every must be >= 1 Updates, got {digest_every}")
        # (connection id, message index) -> whether to log this Snapshot/Update's digest (each hashes the
        # whole mirror); by default after every Snapshot chunk and the first Update, then every
        # digest_every-th Update applied
        self.digest_if = digest_if or (
            lambda _conn, _seq: self.stats.updates <= 1 or self.stats.updates % digest_every == 0)
        self.reconnect = reconnect
        self.reconnect_timeout = reconnect_timeout
        # seconds for a connection's opening handshake; a busy server's is slow, and each retry throws away
        # the work it had done on the abandoned one
        self.open_timeout = open_timeout
        self.camera_period = 1.0 / camera_hz
        self.recv_buffer = recv_buffer  # small: the server feels a slow reader at once (tests, slow links)
        # wss://: the system's trusted certificates, or only those in tls_ca (a self-signed server)
        self.tls = ssl.create_default_context(cafile=str(tls_ca)) if tls_ca is not None else None
        self.mirror: Mirror | None = None
        self.stats = ClientStats()
        self._first_update_at: float | None = None  # time.perf_counter() at the first Update received
        self._stop = asyncio.Event()
        self._open: tuple | None = None  # (websocket, session) of the connection being received, for stop()
        self._closing: asyncio.Task | None = None
        self._start = 0.0

    def clock(self) -> float:
        """Seconds since run() started: the time of the camera poses this client sends."""
        return time.perf_counter() - self._start

    def stop(self) -> None:
        """Ask run() to say Bye and return after the message being handled, or at once when none comes (a
        server with nothing to change sends nothing). Call it on run()'s event loop."""
        self._stop.set()
        if self._open is not None:
            ws, session = self._open
            self._open = None
            self._closing = asyncio.get_running_loop().create_task(_say_bye(ws, session))

    async def run(self, frames: int | None = None) -> ClientStats:
        """Receive until the snapshot and then `frames` Updates have been applied (a server that sends no
        Update after the snapshot: see _quiet_limit), or with on_frame, until `frames` frames were rendered
        (None: until stop())."""
        self._start = self._last_ok = time.perf_counter()
        pause = 0.1
        digests = open(self.digest_log, "a", buffering=1) if self.digest_log else None
        try:
            while True:
                try:
                    await self._connection(frames, digests)
                    return self.stats
                except RemoteError as exc:
                    raise ConnectError(f"{self.url}: server refused: {exc.text}") from None
                except ProtocolError as exc:
                    raise ConnectError(f"{self.url}: bad data from the server: {exc}") from None
                except (_Lost, ConnectionClosed, OSError, asyncio.TimeoutError, InvalidHandshake) as exc:
                    if isinstance(exc, ConnectionClosed) and exc.rcvd is not None and reconnect_at_once(exc.rcvd.code):
                        self.stats.grid_replacements += 1  # not a loss: the new grid is there now
                        self._last_ok = time.perf_counter()
                        continue
                    answered = self.stats.messages or self.stats.status_messages
                    if not answered and not_up_yet(exc) and time.perf_counter() - self._start < self.start_wait:
                        self.status_log.waiting(_why(exc), self.start_wait)  # (once)
                        await asyncio.sleep(START_POLL_S)
                        continue
                    if not self.reconnect or time.perf_counter() - self._last_ok > self.reconnect_timeout:
                        if not answered:
                            tried = (f"; tried for {time.perf_counter() - self._start:.0f} s"
                                     if not_up_yet(exc) and self.start_wait else "")
                            raise ConnectError(f"{self.url}: cannot connect ({_why(exc)}{tried})") from None
                        raise ConnectError(f"{self.url}: connection lost ({_why(exc)}){self.status_log.unfinished()}, "
                                           "not reconnecting") from None
                    pause = 0.1 if time.perf_counter() - self._last_ok < 1.0 else min(2 * pause, 2.0)
                    await asyncio.sleep(pause)
                    self.stats.reconnects += 1
        except InvalidURI as exc:
            raise ConnectError(f"bad server URL: {exc}") from None
        finally:
            if digests:
                digests.close()

    async def _connection(self, frames: int | None, digests) -> None:
        limits = self.config.limits
        # following the server's scene: the session takes the hash the server names, the request the one held
        session = ClientSession(dataclasses.replace(self.config, scene_hash=None) if self.on_scene else self.config)
        t0 = time.perf_counter()
        cameras: asyncio.Task | None = None
        renders: asyncio.Task | None = None
        # Messages the websocket library may read ahead of the mirror: few, as it answers the server's pings as
        # it reads, and the server sends a client more only when those answers show it has read enough
        # (read-ahead is lag the server cannot see)
        extra = ({"sock": await self._small_buffer_socket(), "max_queue": 1} if self.recv_buffer
                 else {"max_queue": READ_AHEAD})
        if self.tls is not None and self.url.startswith("wss:"):
            extra["ssl"] = self.tls
        async with connect(self.url, compression=None, max_size=limits.server_message_bytes,
                           open_timeout=self.open_timeout, **extra) as ws:
            await ws.send(session.scene_request(self.config.scene_hash) if self.on_scene else session.hello())
            seq = 0
            updates_here = 0  # Updates on this connection
            self._open = (ws, session)
            try:
                while True:
                    try:
                        data = await asyncio.wait_for(ws.recv(), self._quiet_limit(session, frames, updates_here))
                    except ConnectionClosedOK:
                        break
                    except asyncio.TimeoutError:  # a server with nothing to change: its ticks passed anyway
                        self.stats.quiet_end = True
                        await ws.send(session.bye())
                        await _discard_until_closed(ws, timeout=2.0)
                        return
                    if isinstance(data, str):
                        raise ProtocolError("text message from the server")
                    if session.state == ClientState.CLOSED:  # the render task said Bye: drop what is in flight
                        continue
                    event = session.receive(data)
                    self._last_ok = time.perf_counter()
                    if isinstance(event, StatusReceived):  # a starting server's state: no message of the stream
                        self._status(event.status, len(data))
                        continue
                    if event is None or isinstance(event, SceneReceived):  # following the server's scene
                        self.stats.bytes_received += len(data)
                        if event is not None:
                            self._new_scene(event)
                            await ws.send(session.hello())
                        continue
                    self.stats.messages += 1
                    self.stats.bytes_received += len(data)
                    self._apply(event, len(data), t0)
                    updates_here += isinstance(event, UpdateReceived)
                    if isinstance(event, Welcomed) and self.camera is not None:
                        cameras = asyncio.create_task(self._send_cameras(ws, session))
                    if isinstance(event, SnapshotReceived) and event.complete and self.on_frame is not None:
                        await _cancel(renders)
                        renders = asyncio.create_task(self._render_frames(ws, session, frames))
                    if (digests and isinstance(event, (SnapshotReceived, UpdateReceived))
                            and self.digest_if(self.stats.connection_id, seq)):
                        # the whole mirror hashed on a worker thread (sha256 lets go of the GIL): meanwhile
                        # the loop reads ahead (up to the library's queue), answers the server's pings and
                        # sends cameras; nothing writes the mirror until the digest is back
                        digest = await asyncio.to_thread(self.mirror.digest)
                        # t: wall-clock seconds (time.time()) once applied and hashed, comparable with the server's logs
                        digests.write(json.dumps({"conn": self.stats.connection_id, "seq": seq, "tick": self.mirror.tick,
                                                  "digest": digest, "t": time.time()}) + "\n")
                    seq += 1
                    done = (frames is not None and self.on_frame is None and session.state == ClientState.STREAMING
                            and self.stats.updates >= frames)
                    if (self._stop.is_set() or done) and self._open is not None:
                        self._open = None
                        await _cancel(cameras)
                        await _cancel(renders)
                        await ws.send(session.bye())
                        await _discard_until_closed(ws, timeout=2.0)
                        return
                    if self.read_delay:
                        await asyncio.sleep(self.read_delay)
            finally:
                self._open = None
                await _cancel(cameras)
                await _cancel(renders)
        if self._closing is not None:
            await self._closing
        if self._stop.is_set():  # stop() or the render task said Bye and closed: done, not lost
            return
        raise _Lost("server closed the connection")

    async def _render_frames(self, ws, session: ClientSession, frames: int | None) -> None:
        """on_frame at the client's own rate with whatever the mirror holds by then; Updates are applied
        between frames. After `frames` frames: Bye, and close, which ends the receive loop."""
        next_t = time.perf_counter()
        while True:
            if frames is not None and self.stats.frames >= frames:
                self._stop.set()
                await ws.send(session.bye())
                await ws.close()
                return
            self.on_frame(self.mirror)
            self.stats.frames += 1
            next_t = max(next_t + self.frame_period, time.perf_counter() - self.frame_period)  # no catch-up bursts
            await asyncio.sleep(max(0.0, next_t - time.perf_counter()))

    async def _small_buffer_socket(self) -> socket.socket:
        uri = parse_uri(self.url)
        sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, self.recv_buffer)
        sock.setblocking(False)
        try:
            await asyncio.wait_for(asyncio.get_running_loop().sock_connect(sock, (uri.host, uri.port)), self.open_timeout)
        except BaseException:
            sock.close()
            raise
        return sock

    def _quiet_limit(self, session: ClientSession, frames: int | None, updates_here: int) -> float | None:
        """Seconds to wait for the next message. A server sends an Update only when something changed, so
        a static one sends nothing after the snapshot: run(frames) then ends after `frames` server tick
        periods (at least QUIET_END_S) without an Update on this connection. Once Updates flow, no limit."""
        if (frames is None or self.on_frame is not None or session.state != ClientState.STREAMING
                or updates_here):
            return None
        return max(max(frames, 1) / session.welcome.tick_hz, QUIET_END_S)

    def _status(self, status: m.Status, nbytes: int) -> None:
        self.stats.status_messages += 1
        self.stats.bytes_received += nbytes
        self.stats.status = describe_status(status)
        self.status_log(status)
        if self.on_status is not None:
            self.on_status(status)

    def _apply(self, event, nbytes: int, t0: float) -> None:
        """One received event into the mirror and the statistics; callbacks run here."""
        if isinstance(event, Welcomed):
            self._welcomed(event)
            return
        if self.mirror is not None:
            self.mirror.received(nbytes)
        if isinstance(event, SnapshotReceived):
            self.mirror.apply(event.snapshot.delta)
            self.stats.snapshot_bytes += nbytes
            if event.complete:
                self.mirror.complete()
                self.stats.snapshot_seconds = time.perf_counter() - t0
                if self.on_snapshot:
                    self.on_snapshot(self.mirror)
        elif isinstance(event, UpdateReceived):
            self.mirror.apply(event.update.delta)
            self.mirror.tick = event.update.tick
            self.mirror.server_time = float(event.update.server_time)
            self.stats.updates += 1
            now = time.perf_counter()
            if self._first_update_at is None:
                self._first_update_at = now
            self.stats.stream_seconds = now - self._first_update_at
            if self.on_update:
                self.on_update(self.mirror, self.mirror.transforms, event.update.tick)
        elif isinstance(event, ByeReceived):
            raise _Lost("server said Bye")

    async def _send_cameras(self, ws, session: ClientSession) -> None:
        """The camera pose at camera_hz, whether or not updates arrive (the server selects by it)."""
        while True:
            view, proj = self.camera(self.clock())
            await ws.send(session.camera(view, proj))
            await asyncio.sleep(self.camera_period)

    def _new_scene(self, event: SceneReceived) -> None:
        """The server's scene, answering this connection's SceneRequest: a new one goes to on_scene."""
        if event.scene is None:  # the one held is current
            return
        from psao.client.scene_import import scene_from_file  # (trimesh: imported once there is a scene)

        self.on_scene(scene_from_file(event.scene, f"{self.url} scene"), event.scene_hash)
        self.config = dataclasses.replace(self.config, scene_hash=event.scene_hash)
        self.stats.scenes += 1

    def _welcomed(self, event: Welcomed) -> None:
        w = event.welcome
        self.mirror = Mirror.from_welcome(w, self.config.limits)
        self.stats.connection_id = w.connection_id
        self.stats.codec = codec_name(w.codec)
        if self.on_connect:
            self.on_connect(self.mirror)


async def _cancel(task: asyncio.Task | None) -> None:
    """Cancel `task` and wait for it; one that already ended on the closed connection (a camera send the
    server's close met) has its exception taken, so it is not reported as never retrieved."""
    if task is not None and task.done() and not task.cancelled() and isinstance(task.exception(), ConnectionClosed):
        return
    if task is not None and not task.done():
        task.cancel()
        try:
            await task
        except (asyncio.CancelledError, ConnectionClosed):
            pass


async def _say_bye(ws, session: ClientSession) -> None:
    """Bye and close (stop()): the receive loop then ends at the close."""
    try:
        await ws.send(session.bye())
        await ws.close()
    except (ConnectionClosed, OSError):
        pass


async def _discard_until_closed(ws, timeout: float) -> None:
    """After Bye, read (and drop) what the server still had in flight, so its close frame gets through
    even when reading was paused by flow control."""
    try:
        async with asyncio.timeout(timeout):
            async for _ in ws:
                pass
    except (TimeoutError, ConnectionClosed):
        pass


async def fetch_scene(url: str, token: str = "", limits: Limits = DEFAULT_LIMITS, timeout: float = 60.0,
                      start_wait: float = START_WAIT_S, log: Callable[[str], None] | None = None):
    """The server's scene: (psao.scene Scene, scene hash bytes, compressed bytes received), over one short
    connection (SceneRequest, SceneData chunks, Bye). A server that does not accept connections yet is
    tried again for up to `start_wait` seconds; one that is loading its scene sends Status messages (to the
    log, as MirrorClient's) until it sends the scene. `timeout`: seconds without any message."""
    status_log = StatusLog(url, log)
    start = time.perf_counter()
    while True:
        try:
            return await _fetch_scene_once(url, token, limits, timeout, status_log)
        except InvalidURI as exc:
            raise ConnectError(f"bad server URL: {exc}") from None
        except RemoteError as exc:
            raise ConnectError(f"{url}: server refused: {exc.text}") from None
        except ProtocolError as exc:
            raise ConnectError(f"{url}: bad scene data from the server: {exc}") from None
        except (ConnectionClosed, OSError, TimeoutError, InvalidHandshake) as exc:
            if status_log.status is None and not_up_yet(exc) and time.perf_counter() - start < start_wait:
                status_log.waiting(_why(exc), start_wait)
                await asyncio.sleep(START_POLL_S)
                continue
            tried = f"; tried for {time.perf_counter() - start:.0f} s" if not_up_yet(exc) and start_wait else ""
            raise ConnectError(f"{url}: cannot fetch the scene ({_why(exc)}{tried}){status_log.unfinished()}") from None


async def _fetch_scene_once(url: str, token: str, limits: Limits, timeout: float, status_log: "StatusLog"):
    session = ClientSession(ClientConfig(None, token, frozenset(Codec), limits))
    async with connect(url, compression=None, max_size=limits.server_message_bytes, open_timeout=5.0) as ws:
        await ws.send(session.scene_request())
        while True:
            try:
                data = await asyncio.wait_for(ws.recv(), timeout)
            except ConnectionClosedOK:
                break
            if isinstance(data, str):
                raise ProtocolError("text message from the server")
            event = session.receive(data)
            if isinstance(event, StatusReceived):
                status_log(event.status)
            elif isinstance(event, ByeReceived):
                break
            elif isinstance(event, SceneReceived):
                from psao.client.scene_import import scene_from_file  # (trimesh: imported once there is a scene)

                await ws.send(session.bye())
                return scene_from_file(event.scene, f"{url} scene"), event.scene_hash, event.blob_bytes
    raise ConnectError(f"{url}: the server closed the connection before sending its scene{status_log.unfinished()}")


def describe_status(status: m.Status) -> str:
    """'baking 40%: text', as the log shows a Status."""
    head = f"{status.phase.name.lower()} {100 * status.progress:.0f}%"
    return f"{head}: {status.text}" if status.text else head


def _stderr_line(line: str) -> None:
    print(f"psao client: {line}", file=sys.stderr, flush=True)


class StatusLog:
    """The log's lines about a server that is still starting (`log(line)`, stderr by default): a Status
    whose phase or text changed or whose progress moved by STATUS_LOG_STEP since the last line, and once
    the notice that no server accepts connections yet."""

    def __init__(self, url: str, log: Callable[[str], None] | None = None):
        self.url = url
        self.log = log or _stderr_line
        self.status: m.Status | None = None  # the last Status received
        self._logged: tuple | None = None  # (phase, text, progress) of the last Status logged
        self._said_waiting = False

    def __call__(self, status: m.Status) -> None:
        self.status = status
        last = self._logged
        if last is None or (status.phase, status.text) != last[:2] or abs(status.progress - last[2]) >= STATUS_LOG_STEP:
            self._logged = (status.phase, status.text, status.progress)
            self.log(f"{self.url}: server {describe_status(status)}")

    def waiting(self, why: str, seconds: float) -> None:
        if not self._said_waiting:
            self._said_waiting = True
            self.log(f"{self.url}: no server accepts connections yet ({why}); waiting up to {seconds:g} s for it to start")

    def unfinished(self) -> str:
        """' while the server was baking 40%: ...' when the last Status was not READY, else ''."""
        st = self.status
        return "" if st is None or st.phase == m.StatusPhase.READY else f" while the server was {describe_status(st)}"


def not_up_yet(exc: BaseException) -> bool:
    """Whether a failed connection attempt looks like a server that is not accepting connections yet: the
    connection refused, or no answer to the opening handshake (a server busy starting)."""
    if isinstance(exc, (ConnectionRefusedError, TimeoutError, asyncio.TimeoutError)):
        return True
    return isinstance(exc, OSError) and exc.errno == errno.ECONNREFUSED and not isinstance(exc, ssl.SSLError)


def _why(exc: BaseException) -> str:
    if isinstance(exc, ConnectionRefusedError):
        return "connection refused"
    if isinstance(exc, ConnectionClosed):
        rcvd = exc.rcvd
        return f"close code {rcvd.code}" if rcvd else "no close frame"
    return str(exc) or type(exc).__name__


def scene_camera_feed(scene, aspect: float = 16 / 9, path_name: str | None = None) -> CameraFeed:
    """Camera poses along the scene's camera path (the named one, its first, or the default orbit), as
    float32 matrices."""
    from psao.scene.camera import look_at, path_sampler, perspective, scene_camera

    try:
        path = scene_camera(scene, path_name)
    except KeyError as exc:
        raise ClientError(str(exc.args[0])) from None
    lo, hi = scene.world_bounds()
    far = 4.0 * float(np.linalg.norm(hi - lo)) + 1.0
    proj = perspective(path.fov_y, aspect, far * 1e-4, far).astype(np.float32)
    camera_at = path_sampler(path)

    def feed(t: float) -> tuple[np.ndarray, np.ndarray]:
        eye, target = camera_at(t)
        return look_at(eye, target).astype(np.float32), proj

    return feed
