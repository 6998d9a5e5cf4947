"""The websocket service: a tick loop that edits the grid, and one sender and one reader per client.

Thin by design: protocol decisions live in psao.protocol.session (sans-I/O), streaming state in
psao.server.net.clients, who gets what in psao.server.net.fanout. The service knows nothing about what a tick
does: it calls `tick(grid, t)` at the tick rate (psao.server.tick.server_tick.ServerTick, or a test hook of
psao.server.tick.testhook), takes the grid's dirty sets and hands them to the fan-out, which encodes one
shared Update for the clients in sync and marks the changes pending for the others. Each client's sender
sends the snapshot, then the shared Updates in its outbox, or (off the shared stream) one Update of its
own at a time with what is pending in its view: while a message is being written (a slow reader), ticks
only accumulate in that client's pending sets (or, on the shared stream, at most a few in its outbox).

`replace_grid` swaps in another grid (and its tick) at the next tick: every connection is closed with
GRID_REPLACED_CLOSE and its client reconnects to the new grid (`psao serve` serves a coarse first grid
while the full one is baked).

A service may start without a scene and a grid (`psao serve` listens before it loads and bakes):
`set_scene` and the first `replace_grid` come later, from the start-up thread. Connections are accepted
meanwhile: the first message is read and its token checked at once, a Hello's scene hash once the scene is
known, and each waits (SceneRequest for the scene, Hello for a grid) while Status messages tell it the
phase (LOADING, BAKING, COARSE, READY), the progress and a line of text: at once, then whenever that
changes (at most STATUS_HZ a second), to every connection that arrived before the full grid was served.

The same port answers plain HTTP GETs with the web client's page (psao.server.net.webpage, an allow-list);
before Hello a connection may ask for the scene (SceneRequest), answered from `scene_blob`.
"""
from __future__ import annotations

import asyncio
import dataclasses
import json
import logging
import socket
import ssl
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from websockets.asyncio.server import ServerConnection, serve
from websockets.datastructures import Headers
from websockets.exceptions import ConnectionClosed
from websockets.http11 import Request, Response

from psao.protocol import messages as m
from psao.protocol.codecs import Codec, codec_name
from psao.protocol.errors import EditError, HeaderError, ProtocolError
from psao.protocol.session import (
    ByeReceived,
    CameraReceived,
    HelloAccepted,
    RefusedError,
    SceneEditReceived,
    SceneRequested,
    ServerConfig,
    ServerSession,
    GRID_REPLACED_CLOSE,
    GRID_REPLACED_REASON,
    error_reply,
)
from psao.protocol.updates import state_digest

from psao.server.net import webpage
from psao.server.net.clients import Client, Registry, SnapshotPlan, read_delta
from psao.server.errors import ConfigError
from psao.server.net.fanout import Fanout, Parts
from psao.server.net.rate import pace_rate
from psao.server.settings import ServeSettings
from psao.server.tick.base import Tick, as_tick
from psao.server.tick.summary import TickSummary

log = logging.getLogger("psao.serve")

STATUS_HZ = 4.0  # Status messages a second at most, per connection, while a server starts


class StaticTransforms:
    """Instance transforms of a server without animation: they change only by SceneEdit."""

    def __init__(self, transforms: np.ndarray):
        self.array = np.ascontiguousarray(transforms, dtype=np.float32).reshape(-1, 4, 4)

    def __call__(self) -> np.ndarray:
        return self.array

    def edit(self, instance: int, transform: np.ndarray) -> None:
        if not 0 <= instance < len(self.array):
            raise EditError(f"SceneEdit: no instance {instance} (the scene has {len(self.array)})")
        self.array = self.array.copy()
        self.array[instance] = transform


def served_tick(tick: Tick | Callable | None, tick_hz: float) -> Tick | None:
    """`tick` as a Tick (as_tick) told the service's rate, or None."""
    tick = as_tick(tick)
    if tick is not None:
        tick.set_tick_rate(tick_hz)
    return tick


def scene_editor(tick: Tick | None, transforms) -> Callable[[int, np.ndarray], None] | None:
    """What applies SceneEdits: the tick when it does, else the service's own StaticTransforms; None: nothing."""
    if tick is not None and tick.applies_edits:
        return tick.edit
    return transforms.edit if isinstance(transforms, StaticTransforms) else None


@dataclass
class Counters:
    ticks: int = 0
    bytes_out: int = 0
    messages_out: int = 0
    updates_out: int = 0  # Update messages sent, all clients
    connections: int = 0
    rejected: int = 0
    cameras: int = 0  # Camera messages received
    camera_merges: int = 0  # times the clients' cameras were handed to the tick (at most once per tick)
    edits: int = 0  # SceneEdits applied
    paced_seconds: float = 0.0  # seconds messages were held back by the clients' rate cap, all clients
    tick_seconds: float = 0.0
    encode_seconds: float = 0.0
    cells_sent: int = 0  # cell rows in Updates, all clients
    buckets_sent: int = 0  # bucket rows in Updates, all clients
    last: dict = field(default_factory=dict)
    at_last_record: dict = field(default_factory=dict)  # the totals at the previous tick record


class Service:
    """`tick` (a psao.server.tick.base.Tick; a bare function `fn(grid, t)` is wrapped as one) runs at the tick
    rate: `tick(grid, t)` on the loop, or for a threaded tick (the server tick of psao.server.tick.server_tick)
    its prepare in a worker thread (it writes no grid, so senders keep reading the grid meanwhile) and its
    apply on the loop. The prepare runs on a thread of its own and
    the shared Updates' encodes on another (the next tick's prepare goes on meanwhile), so a tick never
    queues behind the clients' own encodes (which run on the loop's default executor, one per client). `transforms()` gives the instance
    transforms to send; `on_cameras([(view, proj), ...])` (default: the tick's `set_cameras`) hears the
    connected clients' latest camera poses whenever one changes. `scene_blob` (scene_export.scene_blob, or a
    function giving it, called on a worker thread at the first SceneRequest: compressing a scene takes a while)
    answers SceneRequest; without it a SceneRequest is refused.

    grid None (and scene_hash None): a starting service (see the module); `progress()` -> (fraction 0..1,
    text) says what the start-up is doing, for the Status messages."""

    def __init__(self, grid, scene_hash: bytes | None, settings: ServeSettings, tick: Tick | Callable | None = None,
                 transforms: Callable[[], np.ndarray] | None = None,
                 on_scene_edit: Callable[[int, np.ndarray], None] | None = None,
                 on_cameras: Callable[[list], None] | None = None,
                 scene_blob: bytes | Callable[[], bytes] | None = None,
                 progress: Callable[[], tuple[float, str]] | None = None,
                 clock: Callable[[], float] | None = None):
        settings.check()
        self.clock = clock  # the scene time each tick runs at (seconds); None: seconds since the service started
        if grid is not None and scene_hash is None:
            raise ConfigError("a service with a grid needs its scene's hash")
        self.scene_blob = scene_blob
        self.grid = grid
        self.settings = settings
        self.tick_fn = tick = served_tick(tick, settings.tick_hz)
        if transforms is None and grid is not None:
            transforms = StaticTransforms(np.tile(np.eye(4, dtype=np.float32), (len(grid.instances), 1, 1)))
        self.transforms = transforms
        self.on_scene_edit = on_scene_edit or scene_editor(tick, transforms)
        if settings.allow_edits and self.on_scene_edit is None and grid is not None:
            raise ConfigError("edits are allowed but nothing applies them")
        self.on_cameras = on_cameras or (tick.set_cameras if tick is not None else None)
        # the config of sessions made before the scene is known: tokens, codecs, limits, no scene hash yet
        self._early_config = ServerConfig(None, settings.token, settings.edit_token if settings.allow_edits else "",
                                          settings.codec, settings.layout, settings.zstd, settings.limits)
        self.config: ServerConfig | None = None
        self.fanout: Fanout | None = None
        self._scene_known = asyncio.Event()  # set_scene (or a scene hash given here)
        self._grid_ready = asyncio.Event()  # a grid is served
        self._final = grid is not None  # the grid served is the full one (not a coarse first grid)
        self.progress = progress
        self._loop: asyncio.AbstractEventLoop | None = None
        self._watchers: dict = {}  # connection -> _Watch: the connections Status messages go to
        self._closing: list = []  # closes of replaced ticks (close_previous), on worker threads
        if scene_hash is not None:
            self._set_scene(scene_hash, scene_blob)
        if grid is not None:
            self._grid_ready.set()
        self._cameras_changed_since_tick = False
        self._digest_of: tuple | None = None  # (tick, edits) and the state digest then
        self._open = 0  # connections being served, handshake included
        self.registry = Registry()
        self.counters = Counters()
        self.tick = 0
        self.time = 0.0
        self.port: int | None = None
        self._connections: set[ServerConnection] = set()
        self._digests = open(settings.digest_log, "a", buffering=1) if settings.digest_log else None
        self._stats_out = open(settings.stats_json, "a", buffering=1) if settings.stats_json else None
        self.last_tick_stats: dict = {}
        self.summary = TickSummary()  # the whole run's per-tick statistics (psao serve --json)
        self._replacement: tuple | None = None  # (grid, tick, transforms, final, close previous, scene) from the next tick on
        self._live: dict[int, tuple] = {}  # client id -> (reader, writer) tasks of a client being served
        self._replaced: set[int] = set()  # clients whose connection ends because the grid was replaced
        self.grids_replaced = 0
        self._tick_thread: ThreadPoolExecutor | None = None  # the tick's prepare (run)
        self._encode_thread: ThreadPoolExecutor | None = None  # the shared Updates' encodes, one tick after another
        self._delivery: asyncio.Task | None = None  # the last tick's encode and delivery

    # ---------------------------------------------------------------- lifecycle
    async def run(self, stop: asyncio.Event, ready: Callable[[int], None] | None = None,
                  sock: socket.socket | None = None) -> None:
        """Serve until `stop` is set; on `sock` (already bound and listening) or on settings.host:port."""
        s = self.settings
        self._loop = asyncio.get_running_loop()
        # The user-space write buffer is bounded like the kernel's: a slow reader blocks our send early.
        write_limit = min(32 * 1024, s.send_buffer) if s.send_buffer else 32 * 1024
        where = {"sock": sock} if sock is not None else {"host": s.host, "port": s.port}
        if s.tls_cert is not None:
            where["ssl"] = tls_context(s.tls_cert, s.tls_key)
        async with serve(self._handler, compression=None, write_limit=write_limit,
                         max_size=4 * s.limits.client_message_bytes, max_queue=16,
                         process_request=self._http, **where) as server:
            self.port = server.sockets[0].getsockname()[1]
            ws_scheme, http_scheme = ("wss", "https") if s.tls_cert else ("ws", "http")
            log.info("listening on %s://%s:%d, web client on %s://%s:%d/ (codec %s, layout %s, %g Hz%s)",
                     ws_scheme, s.host, self.port, http_scheme, s.host, self.port,
                     codec_name(s.codec), s.layout.name.lower(), s.tick_hz, ", token required" if s.token else "")
            if ready:
                ready(self.port)
            self._tick_thread = ThreadPoolExecutor(1, thread_name_prefix="psao-tick")
            self._encode_thread = ThreadPoolExecutor(1, thread_name_prefix="psao-encode")
            ticker = asyncio.create_task(self._tick_loop(stop))
            statuses = asyncio.create_task(self._status_loop())
            stopper = asyncio.create_task(stop.wait())
            await asyncio.wait({ticker, stopper}, return_when=asyncio.FIRST_COMPLETED)
            stopper.cancel()
            statuses.cancel()
            if ticker.done():
                ticker.result()  # a tick that raised is a bug: let it out
            ticker.cancel()
            if self._delivery is not None:
                self._delivery.cancel()
            self._tick_thread.shutdown(wait=False, cancel_futures=True)
            self._encode_thread.shutdown(wait=False, cancel_futures=True)
            await self._say_goodbye()
        if self._closing:
            await asyncio.gather(*self._closing, return_exceptions=True)
        if self._digests:
            self._digests.close()
        if self._stats_out:
            self._stats_out.close()

    async def _say_goodbye(self) -> None:
        """Bye to every client and to every connection still waiting for the server to start."""
        for ws in list(self._connections | set(self._watchers)):
            try:
                await asyncio.wait_for(ws.send(m.encode(m.Bye())), 1.0)
                await asyncio.wait_for(ws.close(1001, "server shutting down"), 2.0)
            except (ConnectionClosed, asyncio.TimeoutError, OSError):
                pass

    # ---------------------------------------------------------------- start-up and grid replacement
    @property
    def open_connections(self) -> int:
        """Connections being served now, those still in their handshake included."""
        return self._open

    def set_scene(self, scene_hash: bytes, scene_blob: bytes | Callable[[], bytes] | None = None) -> None:
        """The scene is loaded: its hash (a Hello is checked against it) and its blob (SceneRequest);
        callable from any thread."""
        self._on_loop(self._set_scene, scene_hash, scene_blob)

    def set_scene_blob(self, scene_blob: bytes) -> None:
        """Send `scene_blob` (the same scene file, compressed anew) to the SceneRequests from now on;
        callable from any thread."""
        self._on_loop(setattr, self, "scene_blob", scene_blob)

    def _set_scene(self, scene_hash: bytes, scene_blob) -> None:
        self.config = dataclasses.replace(self._early_config, scene_hash=scene_hash)
        if scene_blob is not None:
            self.scene_blob = scene_blob
        self.fanout = Fanout(self.config, self.settings.fanout)
        self._scene_known.set()

    def _on_loop(self, fn, *args) -> None:
        """fn(*args) on the event loop (at once when the service is not running yet)."""
        if self._loop is None:
            fn(*args)
        else:
            self._loop.call_soon_threadsafe(fn, *args)

    def replace_grid(self, grid, tick: Tick | Callable | None = None, transforms: Callable[[], np.ndarray] | None = None,
                     final: bool = True, close_previous: bool = False,
                     scene: tuple[bytes, bytes | Callable[[], bytes]] | None = None) -> None:
        """Serve `grid` (ticked by `tick`, instances placed by `transforms`, by default the tick's) from the
        next tick on; callable from any thread. Connections open then are closed with GRID_REPLACED_CLOSE
        (after a Status READY when `final`). `final` False: a coarse first grid (Status phase COARSE);
        `close_previous`: the tick served until then is closed (on a worker thread) once it is replaced.
        `scene` (hash, blob): the grid is of another scene (instances added or removed), served from the same
        tick on; a client that reconnects asks for it with SceneRequest (its cached scene's hash), and one
        still in its handshake with the previous scene is closed with GRID_REPLACED_CLOSE too."""
        if scene is None and self.grid is not None and len(grid.instances) != len(self.grid.instances):
            raise ConfigError(f"a replacement grid has {len(grid.instances)} instances, the served one {len(self.grid.instances)}")
        tick = served_tick(tick, self.settings.tick_hz)
        if transforms is None and tick is not None and tick.places_instances:
            transforms = tick.transforms
        self._replacement = (grid, tick, transforms, final, close_previous, scene)

    def _swap_grid(self) -> None:
        """Between ticks, on the loop (nothing else runs meanwhile): the new grid, tick and transforms in,
        the clients of the old grid out of the registry and their senders and readers cancelled, so that
        nothing reads the new grid for a client whose mirror holds the old one; _serve_client then closes
        each connection with GRID_REPLACED_CLOSE."""
        grid, tick, transforms, final, close_previous, scene = self._replacement
        self._replacement = None
        counters = self.fanout.counters
        if scene is not None:
            self._set_scene(*scene)
        first = self.grid is None
        previous = self.tick_fn
        self.grid, self.tick_fn, self._final = grid, tick, final
        if transforms is None:
            transforms = StaticTransforms(self.transforms() if self.transforms is not None else
                                          np.tile(np.eye(4, dtype=np.float32), (len(grid.instances), 1, 1)))
        self.transforms = transforms
        self.on_scene_edit = scene_editor(tick, transforms)
        self.on_cameras = tick.set_cameras if tick is not None else None
        self.fanout = Fanout(self.config, self.settings.fanout)
        self.fanout.counters = counters
        self._digest_of = None
        grid.take_dirty()  # all of it goes out in the snapshots
        for client_id, (client, tasks) in list(self._live.items()):
            self._replaced.add(client_id)
            self.registry.remove(client)
            for task in tasks:
                task.cancel()
        if close_previous and previous is not None:
            self._closing.append(asyncio.ensure_future(asyncio.to_thread(previous.close)))
        self._cameras_changed()
        self._grid_ready.set()
        kind = "full" if final else "coarse"
        if first:
            log.info("serving the %s grid (%d cells in use)%s", kind, int(len(grid.allocated_cells())),
                     f"; {len(self._watchers)} connections were waiting for it" if self._watchers else "")
            return
        self.grids_replaced += 1
        log.info("grid replaced by the %s grid (%d cells in use): %d clients reconnect to it", kind,
                 int(len(grid.allocated_cells())), len(self._replaced))

    # ---------------------------------------------------------------- ticking
    async def _tick_loop(self, stop: asyncio.Event) -> None:
        period = 1.0 / self.settings.tick_hz
        start = time.perf_counter()
        next_at = start
        last_stats = start
        # the last tick's seconds besides its stages (hand-offs, fan-out, records), and when it asked the loop
        # to come back: how late the loop came back counts too (the clients' tasks ran)
        own_s, due = None, 0.0
        while not stop.is_set():
            self.time = self.clock() if self.clock is not None else time.perf_counter() - start
            t0 = time.perf_counter()
            if own_s is not None and self.tick_fn is not None:
                self.tick_fn.observe_service(own_s + max(t0 - due, 0.0))
            if self._replacement is not None and self.config is not None:
                self._swap_grid()
            if self.grid is None:  # starting: nothing to tick yet
                next_at, own_s = time.perf_counter() + period, None
                await asyncio.sleep(period)
                continue
            self._merge_cameras()
            stats = None
            if self.tick_fn is not None and self.tick_fn.threaded:
                plan = await self._on_tick_thread(self.tick_fn.prepare, self.time)
                stats = self.tick_fn.apply(plan)
            elif self.tick_fn is not None:
                stats = self.tick_fn(self.grid, self.time)
            self.tick += 1
            self.counters.ticks += 1
            b, c = self.grid.take_dirty()
            await self._fan_out(b, c)
            self.counters.tick_seconds += time.perf_counter() - t0
            self._record_tick(stats, len(b), len(c), time.perf_counter() - t0)
            now = time.perf_counter()
            if now - last_stats >= self.settings.stats_interval:
                self._log_stats(now - last_stats)
                last_stats = now
            # a tick late by up to a period is made up for by the next one starting at once (ticks of uneven
            # length keep the rate on average); later than that, the schedule restarts from then (no burst)
            next_at = max(next_at + period, now - period)
            own_s, due = now - t0 - (stats.seconds_total if stats is not None else 0.0), max(next_at, now)
            await asyncio.sleep(max(next_at - now, 0.0))

    async def _fan_out(self, bucket_ids: np.ndarray, cell_slots: np.ndarray) -> None:
        """The tick's changes: one Update encoded once for the clients on the shared stream, Updates of
        shared parts for the clients off it (when several are), pending for the rest. The plan reads the
        grid now; the encode runs on the encode thread while the next tick goes on, and the Updates reach
        the outboxes in tick order (a receiver sends nothing of its own meanwhile: Client.in_flight)."""
        if self._delivery is not None and self._delivery.done():
            self._delivery.result()  # an encode that raised is a bug: let it out
        transforms = self.transforms()
        share, parted = self.fanout.plan(list(self.registry), self.grid, bucket_ids, cell_slots, transforms,
                                         self.tick, self.time, time.perf_counter())
        parts = (self.fanout.plan_parts(parted, self.grid, bucket_ids, cell_slots, transforms, self.tick, self.time)
                 if parted else None)
        if share is None and parts is None:
            return
        drained = (share is not None and any(not c.pending_anything() for c in share.members)) or (
            parts is not None and any(r.drained for r in parts.recipes))
        # the state the Updates bring them to, hashed on the encode thread (a whole-grid sha256 takes
        # milliseconds: on the loop it would hold up the next tick)
        digest = self._digest_later() if self._digests and drained else None
        receivers = (share.members if share else []) + ([r.client for r in parts.recipes] if parts else [])
        for c in receivers:
            c.in_flight += 1

        def encode():
            t0 = time.perf_counter()
            out = (share.encode() if share else None, parts.encode() if parts else None)
            seconds = time.perf_counter() - t0
            return out, seconds, digest() if digest is not None else None

        encoded = asyncio.get_running_loop().run_in_executor(self._encode_thread, encode)
        self._delivery = asyncio.create_task(self._deliver(self._delivery, encoded, share, parts,
                                                           len(bucket_ids), len(cell_slots)))

    async def _deliver(self, previous, encoded, share, parts, n_buckets: int, n_cells: int) -> None:
        """Put one tick's encoded Updates in the receivers' outboxes, after the previous tick's."""
        if previous is not None:
            await previous
        (data, frames), seconds, digest = await encoded
        self.counters.encode_seconds += seconds
        if share is not None:
            for client in share.members:
                client.in_flight -= 1
            for client, seq in self.fanout.deliver(share, data):
                self.counters.cells_sent += n_cells
                self.counters.buckets_sent += n_buckets
                if digest is not None and not client.pending_anything():
                    self._write_digest(client, seq, digest)
        if parts is not None:
            for recipe in parts.recipes:
                recipe.client.in_flight -= 1
            for recipe, seq in self.fanout.deliver_parts(parts, frames):
                self.counters.cells_sent += recipe.cells(parts)
                self.counters.buckets_sent += len((recipe.own_head or parts.head).bucket_ids)
                if digest is not None and recipe.drained:
                    self._write_digest(recipe.client, seq, digest)

    async def _on_tick_thread(self, fn, *args):
        return await asyncio.get_running_loop().run_in_executor(self._tick_thread, fn, *args)

    def _record_tick(self, stats, buckets_dirty: int, cells_dirty: int, seconds: float) -> None:
        """Keep the tick's own statistics (the server tick's TickStats) for the live line and the jsonl.
        Sends run on each client's own task, so what was sent (bytes, cell and bucket rows, encode time,
        all clients) is counted since the previous tick record: the sends of the previous tick's changes."""
        c = self.counters
        totals = {"bytes_out": c.bytes_out, "cells_sent": c.cells_sent, "buckets_sent": c.buckets_sent,
                  "seconds_encode": c.encode_seconds}
        since = {k: v - c.at_last_record.get(k, 0) for k, v in totals.items()}
        c.at_last_record = totals
        record = stats.to_dict() if stats is not None else {}
        # wall: wall-clock seconds (time.time()) once the tick is applied, comparable with a client's digest log
        record.update(service_tick=self.tick, time=self.time, wall=time.time(), buckets_dirty=buckets_dirty, cells_dirty=cells_dirty,
                      seconds_tick=seconds, bytes_sent=since["bytes_out"], cells_sent=since["cells_sent"],
                      buckets_sent=since["buckets_sent"], seconds_encode=since["seconds_encode"],
                      bytes_out=c.bytes_out, seconds_encode_total=c.encode_seconds, clients=len(self.registry),
                      shared_members=sum(cl.shared for cl in self.registry),
                      shared_updates=self.fanout.counters.shared_updates,
                      shared_sends=self.fanout.counters.shared_sends,
                      part_updates=self.fanout.counters.part_updates, parts_encoded=self.fanout.counters.parts_encoded,
                      parts_sent=self.fanout.counters.parts_sent)
        self.last_tick_stats = record
        self.summary.add(record)
        if self._stats_out:
            self._stats_out.write(json.dumps(record) + "\n")

    def _log_stats(self, dt: float) -> None:
        c, last = self.counters, self.counters.last
        rate = (c.bytes_out - last.get("bytes", 0)) / dt
        ticks = (c.ticks - last.get("ticks", 0)) / dt
        busy = (c.tick_seconds - last.get("tick_s", 0.0)) / dt
        encode = (c.encode_seconds - last.get("encode_s", 0.0)) / max(c.ticks - last.get("ticks", 0), 1)
        pending = max((cl.cells_pending.count for cl in self.registry), default=0)
        s = self.last_tick_stats
        work = ""
        if "traced" in s:  # the server tick's split of the last tick
            work = (f" | last tick: {s['traced']}/{s['considered']} points traced, {s['changed']} changed, "
                    f"{s['cells_dirty']} cells | ms animate {1e3 * s['seconds_animate']:.1f} select "
                    f"{1e3 * s['seconds_select']:.1f} trace {1e3 * s['seconds_trace']:.1f} grid "
                    f"{1e3 * s['seconds_grid']:.1f} encode {1e3 * encode:.1f}")
            if s.get("budget_ms"):  # the time-budgeted tick: its queue and how much of its budget it used
                work += (f" | queue {s['queue']} (oldest {s['queue_oldest_ms']:.0f} ms), budget "
                         f"{s['budget_ms']:.1f} ms, used {100 * s['budget_used']:.0f}%")
        shared = sum(cl.shared for cl in self.registry)
        log.info("tick %d | %.1f ticks/s | tick load %.0f%% | %d clients (%d on the shared stream) | out %.1f kB/s | "
                 "most pending cells %d%s", self.tick, ticks, 100 * busy, len(self.registry), shared, rate / 1e3,
                 pending, work)
        c.last = {"bytes": c.bytes_out, "ticks": c.ticks, "tick_s": c.tick_seconds, "encode_s": c.encode_seconds}

    # ---------------------------------------------------------------- connections
    async def _handler(self, ws: ServerConnection) -> None:
        peer = "%s:%s" % tuple(ws.remote_address[:2]) if ws.remote_address else "?"
        session = ServerSession(self.config or self._early_config)
        self.counters.connections += 1
        if self._open >= self.settings.max_clients:
            full = RefusedError(f"server full: {self.settings.max_clients} connections", m.ErrorCode.SERVER_FULL,
                                close_code=1013)  # 1013: try again later
            await self._reject(ws, session, full, peer, None)
            return
        self._open += 1
        try:
            await self._handle(ws, session, peer)
        finally:
            self._open -= 1
            self._watchers.pop(ws, None)

    async def _handle(self, ws: ServerConnection, session: ServerSession, peer: str) -> None:
        sock = ws.transport.get_extra_info("socket")
        if sock is not None and self.settings.send_buffer:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, self.settings.send_buffer)
        try:
            event = await self._next_handshake_event(ws, session)
            await self._watch(ws, session)  # the token passed: Status from now on while the server starts
            if isinstance(event, SceneRequested):
                if not await self._until(self._scene_known, ws, session, peer, "the scene"):
                    return
                await self._send_scene(ws, session, event)
                event = await self._next_handshake_event(ws, session)
                if isinstance(event, ByeReceived):
                    log.info("connection from %s took the scene and left", peer)
                    return
            assert isinstance(event, HelloAccepted)
            if not await self._until(self._scene_known, ws, session, peer, "the scene"):
                return
            if not await self._until(self._grid_ready, ws, session, peer, "a grid"):
                return
            watch = self._watchers.get(ws)
            if watch is not None:  # the phase it is served in (COARSE, READY) before its Welcome
                await watch.flush(ws, self.status())
            if session.config.scene_hash != self.config.scene_hash:  # the scene was replaced meanwhile
                log.info("connection from %s: the scene was replaced during its handshake, closing (close code %d)",
                         peer, GRID_REPLACED_CLOSE)
                await ws.close(GRID_REPLACED_CLOSE, GRID_REPLACED_REASON)
                return
        except ProtocolError as exc:
            await self._reject(ws, session, exc, peer, None)
            return
        except asyncio.TimeoutError:
            err = ProtocolError(f"no Hello within {self.settings.hello_timeout:g} s")
            await self._reject(ws, session, err, peer, None, code=m.ErrorCode.TIMEOUT)
            return
        except ConnectionClosed as exc:
            if not self._too_big(exc, f"connection from {peer}"):
                log.info("connection from %s closed before Hello", peer)
            return
        client = Client(peer, len(self.grid.buckets), len(self.grid.cells),
                        stream_codec=event.codec == Codec.ZSTD_STREAM, takes_parts=session.takes_parts())
        self._connections.add(ws)
        try:
            await self._serve_client(ws, session, client, event.codec)
        except ConnectionClosed:  # gone before or while the Welcome was sent
            log.info("client %d from %s left during the handshake", client.id, peer)
        finally:
            self._connections.discard(ws)
            self.registry.remove(client)
            if client.camera is not None:
                self._cameras_changed()

    async def _next_handshake_event(self, ws, session: ServerSession):
        return session.receive(_binary(await asyncio.wait_for(ws.recv(), self.settings.hello_timeout)))

    # ---------------------------------------------------------------- a starting server's Status
    def status(self) -> m.Status:
        """What the server is doing now: the phase from what it serves, progress and text from the start-up."""
        fraction, text = self.progress() if self.progress is not None else (0.0, "")
        fraction = min(max(float(fraction), 0.0), 1.0) if np.isfinite(fraction) else 0.0
        if self.grid is not None and self._final:
            return m.Status(m.StatusPhase.READY, 1.0, "full grid served")
        phase = (m.StatusPhase.LOADING if self.config is None else m.StatusPhase.BAKING if self.grid is None
                 else m.StatusPhase.COARSE)
        return m.Status(phase, fraction, text)

    async def _watch(self, ws, session: ServerSession) -> None:
        """Status messages for this connection while the full grid is not served: the first one now."""
        if not (self.grid is not None and self._final):
            self._watchers[ws] = watch = _Watch(session)
            await watch.flush(ws, self.status())

    async def _status_loop(self) -> None:
        """Every 1/STATUS_HZ s: the current Status to each watching connection it differs for (a connection
        whose last Status is still being written is skipped until that is out). Once READY is out to a
        connection, it is not watched any more."""
        while True:
            now = self.status()
            for ws, watch in list(self._watchers.items()):
                watch.offer(ws, now)
                if watch.done():
                    self._watchers.pop(ws, None)
            await asyncio.sleep(1.0 / STATUS_HZ)

    async def _until(self, event: asyncio.Event, ws, session: ServerSession, peer: str, what: str) -> bool:
        """Wait for `event` (the scene known, a grid ready) unless the connection closes first (False); a
        session made before the scene was known is rebound to it (RefusedError on a scene mismatch)."""
        if not event.is_set():
            waiting, closed = asyncio.ensure_future(event.wait()), asyncio.ensure_future(ws.wait_closed())
            try:
                await asyncio.wait({waiting, closed}, return_when=asyncio.FIRST_COMPLETED)
            finally:
                waiting.cancel()
                closed.cancel()
            if not event.is_set():
                st = self.status()
                log.info("connection from %s left while waiting for %s (server %s, %.0f%%)", peer, what,
                         st.phase.name.lower(), 100 * st.progress)
                return False
        if session.config.scene_hash is None and self.config is not None:
            session.rebind(self.config)
        return True

    async def _send_scene(self, ws, session: ServerSession, event: SceneRequested) -> None:
        if self.scene_blob is None:
            raise ProtocolError("this server does not send its scene")
        if callable(self.scene_blob):  # made once, on a worker thread; requests meanwhile wait for the same bytes
            self.scene_blob = asyncio.ensure_future(asyncio.to_thread(self.scene_blob))
        if isinstance(self.scene_blob, asyncio.Future):
            self.scene_blob = await asyncio.shield(self.scene_blob)
        for data in session.scene_data(event.request, self.scene_blob):
            await ws.send(data)
            self.counters.bytes_out += len(data)
            self.counters.messages_out += 1

    def _http(self, connection: ServerConnection, request: Request) -> Response | None:
        """Plain GETs get the web page's files (webpage.answer); websocket upgrades go on to _handler."""
        if "websocket" in request.headers.get("Upgrade", "").lower():
            return self._check_origin(request)
        a = webpage.answer(request.path, example=self.settings.web_example)
        if a.status != 200:
            log.info("HTTP %d for %s", a.status, request.path[:200])
        headers = Headers([("Content-Type", a.content_type), ("Content-Length", str(len(a.body))),
                           ("Cache-Control", "no-cache"), ("X-Content-Type-Options", "nosniff")])
        return Response(a.status, a.reason, headers, a.body)

    def _check_origin(self, request: Request) -> Response | None:
        """A browser says which page opens a websocket (Origin): only this server's own page and the
        allowed origins may; any web page could otherwise reach a loopback server. No Origin: not a browser."""
        origin = request.headers.get("Origin")
        if origin is None or origin in self.settings.allow_origins:
            return None
        scheme = "https" if self.settings.tls_cert else "http"
        if origin == f"{scheme}://{request.headers.get('Host', '')}":
            return None
        self.counters.rejected += 1
        log.warning("websocket from origin %s refused (allowed: this server's page%s)", origin[:200],
                    "".join(f", {o}" for o in self.settings.allow_origins))
        body = b"origin not allowed\n"
        headers = Headers([("Content-Type", "text/plain"), ("Content-Length", str(len(body)))])
        return Response(403, "Forbidden", headers, body)

    async def _serve_client(self, ws, session: ServerSession, client: Client, codec: Codec) -> None:
        grid = self.grid
        await ws.send(session.welcome(client.id, self.settings.tick_hz, len(grid.buckets), len(grid.cells),
                                      grid.instances))
        client.sent(b"")
        if self.grid is not grid:  # replaced while the Welcome was on its way: this client goes to the new one
            self._replaced.add(client.id)
            await self._close_replaced(ws, client)
            return
        self.registry.add(client)
        log.info("client %d from %s connected (codec %s)", client.id, client.peer, codec_name(codec))
        reader = asyncio.create_task(self._read(ws, session, client))
        writer = asyncio.create_task(self._write(ws, session, client))
        self._live[client.id] = (client, (reader, writer))
        try:
            done, _ = await asyncio.wait({reader, writer}, return_when=asyncio.FIRST_COMPLETED)
            for task in (reader, writer):
                task.cancel()
            await asyncio.gather(reader, writer, return_exceptions=True)
        finally:
            self._live.pop(client.id, None)
        if client.id in self._replaced:
            await self._close_replaced(ws, client)
            return
        exc = next((t.exception() for t in done if not t.cancelled() and t.exception()), None)
        if isinstance(exc, ProtocolError):
            await self._reject(ws, session, exc, client.peer, client.id)
        elif isinstance(exc, ConnectionClosed) and self._too_big(exc, f"client {client.id} from {client.peer}"):
            pass
        elif isinstance(exc, ConnectionClosed) or exc is None:
            rcvd = exc.rcvd if isinstance(exc, ConnectionClosed) else None
            why = f"close {rcvd.code}" if rcvd else "connection lost" if exc else "said Bye"
            est, link = client.rate.mbit, client.rate.link_mbit
            log.info("client %d from %s left (%s) after %d messages, %.1f kB (it read %.2f Mbit/s at the last "
                     "measure; rate estimate %s; link-limited in %d windows, at %s)", client.id, client.peer, why,
                     client.messages_sent, client.bytes_sent / 1e3, client.acked_mbit,
                     "none" if est is None else f"{est:.2f} Mbit/s", client.rate.limited_windows,
                     "-" if link is None else f"{link:.3f} Mbit/s")
        else:
            raise exc

    async def _close_replaced(self, ws, client: Client) -> None:
        """The grid was replaced: the new phase's Status (READY when the full grid came), then the close."""
        self._replaced.discard(client.id)
        log.info("client %d from %s: grid replaced, closing (close code %d) after %d messages", client.id,
                 client.peer, GRID_REPLACED_CLOSE, client.messages_sent)
        watch = self._watchers.pop(ws, None)
        try:
            if watch is not None:
                await watch.flush(ws, self.status())
            await ws.close(GRID_REPLACED_CLOSE, GRID_REPLACED_REASON)
        except ConnectionClosed:
            pass

    def _too_big(self, exc: ConnectionClosed, who: str) -> bool:
        """websockets itself closes (1009, no Error message) on a frame beyond max_size: log it as ours."""
        if exc.sent is not None and exc.sent.code == 1009:
            self.counters.rejected += 1
            log.warning("%s closed on protocol error: message over %d bytes (close code 1009)", who,
                        4 * self.settings.limits.client_message_bytes)
            return True
        return False

    async def _reject(self, ws, session: ServerSession, exc: ProtocolError, peer: str, client_id,
                      code: m.ErrorCode | None = None) -> None:
        if code is None:
            data, close_code = session.fail(exc)
        else:
            data, close_code = m.encode(m.Error(code, str(exc))), 1008
        self.counters.rejected += 1
        who = f"client {client_id} from {peer}" if client_id else f"connection from {peer}"
        kind = "refused" if isinstance(exc, RefusedError) else "closed on protocol error"
        log.warning("%s %s: %s (close code %d)", who, kind, exc, close_code)
        try:
            await ws.send(data)
            await ws.close(close_code, str(exc)[:120])
        except ConnectionClosed:
            pass

    async def _read(self, ws, session: ServerSession, client: Client) -> None:
        async for data in ws:
            event = session.receive(_binary(data))
            if isinstance(event, CameraReceived):
                client.camera = (event.camera.view, event.camera.projection)
                self.counters.cameras += 1
                self._cameras_changed()  # (cells kept back for it are looked at again at the next tick)
            elif isinstance(event, SceneEditReceived):  # the session let through only allowed, sane edits
                self._edit(event.edit.instance, event.edit.transform)
                log.info("client %d from %s moved instance %d", client.id, client.peer, event.edit.instance)
            elif isinstance(event, ByeReceived):
                return

    def scene_edit(self, instance: int, transform: np.ndarray) -> None:
        """Move `instance` to `transform` (checked as a SceneEdit is) from the next tick on, as a client's
        SceneEdit does; callable from any thread (psao.Server.move)."""
        self._on_loop(self._edit, instance, transform)

    def _edit(self, instance: int, transform: np.ndarray) -> None:
        self.on_scene_edit(instance, transform)
        self.counters.edits += 1
        self.registry.wake_all()

    def _cameras_changed(self) -> None:
        """O(1) per Camera message: the tick hears the merged views once, before its next run."""
        self._cameras_changed_since_tick = True

    def _merge_cameras(self) -> None:
        if self._cameras_changed_since_tick and self.on_cameras is not None:
            self._cameras_changed_since_tick = False
            self.counters.camera_merges += 1
            self.on_cameras([c.camera for c in self.registry if c.camera is not None])

    async def _send(self, ws, client: Client, data: bytes) -> None:
        rate = pace_rate(client.rate, self.settings.fanout)
        if rate is not None:
            await self._pace(client, len(data), rate)
        await ws.send(data)
        client.sent(data)
        self.counters.bytes_out += len(data)
        self.counters.messages_out += 1
        await self._probe(ws, client)

    async def _pace(self, client: Client, nbytes: int, rate: float) -> None:
        """Hold a message until the client's pacing `rate` (bytes/s) lets it go: a token bucket,
        FanoutSettings.pace_burst seconds deep (the bytes sent to it by any time are at most the rate's since
        it connected, plus the burst, plus one message)."""
        now = time.perf_counter()
        start = max(client.paced_until, now - self.settings.fanout.pace_burst)
        if start > now:
            self.counters.paced_seconds += start - now
            client.rate.note_held()
            await asyncio.sleep(start - now)
        client.paced_until = start + nbytes / rate

    def _state_digest(self) -> str:
        """Digest of the state now (grid and transforms); computed once per tick and edit, not per client."""
        key = (self.tick, self.counters.edits)
        if self._digest_of is None or self._digest_of[0] != key:
            g = self.grid
            self._digest_of = (key, state_digest(g.instances, g.buckets, g.cells, self.transforms()))
        return self._digest_of[1]

    def _digest_later(self) -> Callable[[], str]:
        """The state digest now, as a function to call on another thread: the one kept for this state, or
        a hash of a copy of the arrays taken now (the next tick's apply writes the grid in place)."""
        key = (self.tick, self.counters.edits)
        if self._digest_of is not None and self._digest_of[0] == key:
            kept = self._digest_of[1]
            return lambda: kept
        g = self.grid
        arrays = (g.instances.copy(), g.buckets.copy(), g.cells.copy(), np.array(self.transforms(), copy=True))
        return lambda: state_digest(*arrays)

    def _log_digest(self, client: Client, seq: int) -> None:
        """After the message `seq`, which leaves nothing pending, the client's mirror must equal this state."""
        if self._digests:
            self._write_digest(client, seq, self._state_digest())

    def _write_digest(self, client: Client, seq: int, digest: str) -> None:
        self._digests.write(json.dumps({"conn": client.id, "seq": seq, "tick": self.tick, "digest": digest}) + "\n")

    async def _write(self, ws, session: ServerSession, client: Client) -> None:
        grid, limits = self.grid, self.settings.limits
        plan = SnapshotPlan.of(grid, limits, self.settings.snapshot_cells_per_chunk)

        async def chunk(i: int) -> bytes:
            cap = len(grid.cells)
            b, c = plan.bucket_chunks[i], plan.cell_chunks[i]
            client.clear(b, c, cap)
            tids = client.read_transforms(self.transforms())
            delta = read_delta(grid, self.transforms(), tids, b, c)
            if i == len(plan) - 1 and not client.pending_anything():
                self._log_digest(client, seq=len(plan))  # Welcome is message 0, chunk i is message i + 1
            return await asyncio.to_thread(session.snapshot, i, len(plan), delta)

        # The next chunk is read and compressed while this one is on its way (stream order is kept:
        # chunk i+1 is compressed only after chunk i was).
        upcoming = asyncio.create_task(chunk(0))
        try:
            for i in range(len(plan)):
                data = await upcoming
                if i + 1 < len(plan):
                    upcoming = asyncio.create_task(chunk(i + 1))
                await self._until_read(ws, client)
                await self._send(ws, client, data)
        finally:
            upcoming.cancel()
        client.assigned = len(plan) + 1
        client.streaming = True
        while True:
            await self._until_read(ws, client)
            if client.outbox:  # shared Updates, in order, before anything of its own
                item = client.outbox.popleft()
                data = (session.update_of_parts(item.frames) if isinstance(item, Parts) else session.shared(item))
                await self._send(ws, client, data)
                client.updates_sent += 1
                self.counters.updates_out += 1
                continue
            await client.wake.wait()
            client.wake.clear()
            if not (client.shared or client.on_parts or client.outbox or client.in_flight or self.fanout.behind(client)):
                client.busy = True
                try:
                    await self._send_own_update(ws, session, client)
                finally:
                    client.busy = False

    async def _until_read(self, ws, client: Client) -> None:
        """Wait while the client is behind (Fanout.behind): until the answer to a probe shows it has read
        enough. Its changes meanwhile wait in its pending sets (or its outbox)."""
        if not self.fanout.behind(client):
            return
        client.rate.note_held()
        while self.fanout.behind(client):
            if client.probe is None:  # (the last answer came before the messages sent while it was awaited)
                await self._probe(ws, client, now=True)
            client.wake.clear()
            await client.wake.wait()
        client.wake.set()  # what woke it meanwhile (pending changes) is looked at now

    async def _probe(self, ws, client: Client, now: bool = False) -> None:
        """After a message: a ping once probe_every messages wait to be shown read (one ping at a time).
        Its answer comes back behind everything sent before it, so when it does, the client has read those
        messages (Client.messages_read); it wakes the sender, which may be holding back for it."""
        if client.probe is not None or (client.unread() < self.settings.fanout.probe_every and not now):
            return
        mark = client.messages_sent
        client.probe = pong = await ws.ping()
        acked, pinged = client.bytes_sent, time.perf_counter()

        def answered(f: asyncio.Future) -> None:
            client.probe = None
            if f.cancelled() or f.exception() is not None:
                return  # the connection ended
            client.messages_read = max(client.messages_read, mark)
            now = time.perf_counter()
            if now - client.acked_at >= 1.0:  # what its link carried, measured over a second or more
                if client.acked_at:
                    client.acked_mbit = 8 * (acked - client.acked_bytes) / (now - client.acked_at) / 1e6
                client.acked_bytes, client.acked_at = acked, now
            client.rate.answered(now - pinged, acked, now, self.settings.fanout)
            client.wake.set()

        pong.add_done_callback(answered)

    async def _send_own_update(self, ws, session: ServerSession, client: Client) -> None:
        """One Update of this client's own: pending buckets, pending cells in its view, moved transforms."""
        grid, limits = self.grid, self.settings.limits
        transforms = self.transforms()
        tids = client.changed_transforms(transforms)
        budget = self.fanout.cells_budget(client, self.settings.tick_hz)
        b, c, drained = client.take_pending(limits, len(grid.cells), self.fanout.in_view(client, grid, transforms),
                                            self.fanout.distance(client, grid, transforms), budget)
        if not (len(b) or len(c) or len(tids)):
            return
        tids = client.read_transforms(transforms)
        delta = read_delta(grid, transforms, tids, b, c)
        seq = client.next_seq()
        if drained:
            self._log_digest(client, seq)
        if len(b) == limits.max_buckets_per_message or len(c) == min(budget or limits.max_cells_per_message,
                                                                      limits.max_cells_per_message):
            client.wake.set()  # more than one message's worth: go again right away (paced under a cap)
        t_encode = time.perf_counter()
        if len(b) + len(c) <= self.settings.fanout.inline_rows:
            data = session.update(self.tick, self.time, delta)
        else:
            data = await asyncio.to_thread(session.update, self.tick, self.time, delta)
        self.counters.encode_seconds += time.perf_counter() - t_encode
        self.counters.cells_sent += len(c)
        self.counters.buckets_sent += len(b)
        await self._send(ws, client, data)
        if len(c):
            client.bytes_per_cell = (len(data) / len(c) if not client.bytes_per_cell
                                     else 0.8 * client.bytes_per_cell + 0.2 * len(data) / len(c))
        client.updates_sent += 1
        self.counters.updates_out += 1


class _Watch:
    """A connection's Status messages: the last one offered, and the send of it (one at a time)."""

    def __init__(self, session: ServerSession):
        self.session = session
        self.last: tuple | None = None
        self.sending: asyncio.Task | None = None

    @staticmethod
    def key(status: m.Status) -> tuple:
        return status.phase, round(100 * status.progress), status.text  # a change of a per cent counts

    def offer(self, ws, status: m.Status) -> bool:
        """Send `status` unless it is the last one sent or a send is still under way; whether it went."""
        key = self.key(status)
        if key == self.last or (self.sending is not None and not self.sending.done()):
            return False
        self.last = key
        self.sending = asyncio.ensure_future(_send_quietly(ws, self.session.status(status)))
        return True

    def done(self) -> bool:
        """READY went out: nothing more to tell this connection."""
        return (self.last is not None and self.last[0] == m.StatusPhase.READY
                and (self.sending is None or self.sending.done()))

    async def flush(self, ws, status: m.Status) -> None:
        """After the send under way, `status` unless it was the last one sent."""
        if self.sending is not None:
            await self.sending
        if self.key(status) != self.last:
            self.last = self.key(status)
            await ws.send(self.session.status(status))


async def _send_quietly(ws, data: bytes) -> None:
    """A send whose connection may be gone meanwhile (its handler sees that itself)."""
    try:
        await ws.send(data)
    except ConnectionClosed:
        pass


def tls_context(cert: Path, key: Path) -> ssl.SSLContext:
    ctx = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
    try:
        ctx.load_cert_chain(cert, key)
    except (OSError, ssl.SSLError) as exc:
        raise ConfigError(f"cannot use TLS certificate {cert} with key {key}: {getattr(exc, 'strerror', None) or exc}") from None
    return ctx


def _binary(data) -> bytes:
    if isinstance(data, str):
        raise HeaderError("text message: PSAO messages are binary")
    return data
