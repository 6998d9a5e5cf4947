"""Many connections at once over real loopback sockets: camera handling is linear in clients (the tick hears
the merged cameras at most once per tick), a connection cap refuses the extra ones with SERVER_FULL, and
clients vanishing mid-handshake leave no traceback in the server's log."""
from __future__ import annotations

import asyncio
import logging

from websockets.asyncio.client import connect

from psao.protocol import messages as m
from psao.client.connection import MirrorClient
from psao.server.net.service import Service
from psao.server.settings import ServeSettings
from psao.server.tick.testhook import RandomEdits
from test_bad_input_server import EYE, HASH, hello, make_grid
from serving import HANG_S


class CameraCountingTick(RandomEdits):
    """Random edits, and a record of every set_cameras call (the tick's per-camera-set work)."""

    def __init__(self):
        super().__init__(5, seed=3)
        self.calls: list[int] = []

    def set_cameras(self, cameras) -> None:
        self.calls.append(len(cameras))


async def start(settings: ServeSettings, tick=None):
    service = Service(make_grid(), HASH, settings, tick=tick or RandomEdits(5, seed=1))
    stop, ready = asyncio.Event(), asyncio.Event()
    task = asyncio.create_task(service.run(stop, ready=lambda port: ready.set()))
    await asyncio.wait_for(ready.wait(), HANG_S)
    return service, stop, task, f"ws://127.0.0.1:{service.port}"


def test_cameras_merged_once_per_tick():
    n_clients, n_cameras = 6, 40

    async def main():
        tick = CameraCountingTick()
        service, stop, task, url = await start(ServeSettings(port=0, tick_hz=5, stats_interval=1e9), tick)
        conns = [await connect(url, compression=None, max_size=None) for _ in range(n_clients)]
        try:
            for ws in conns:
                await ws.send(hello())
            for k in range(n_cameras):
                view = EYE.copy()
                view[2, 3] = -1.0 - k
                for ws in conns:
                    await ws.send(m.encode(m.Camera(view, EYE)))
            while service.counters.cameras < n_clients * n_cameras:
                await asyncio.sleep(0.02)
            ticks = service.counters.ticks
            while service.counters.ticks < ticks + 2:  # the tick after the last camera has run
                await asyncio.sleep(0.02)
            return list(tick.calls), service.counters
        finally:
            for ws in conns:
                await ws.close()
            stop.set()
            await task

    calls, counters = asyncio.run(main())
    assert counters.cameras == n_clients * n_cameras
    assert 1 <= len(calls) <= counters.ticks  # never once per Camera message
    assert calls[-1] == n_clients  # the merge holds every client's latest camera


async def refusal(url):
    """Connect and read: the server speaks first (an Error) when it will not serve this connection."""
    async with connect(url, compression=None, max_size=None) as ws:
        data = await asyncio.wait_for(ws.recv(), HANG_S)
        await ws.wait_closed()
        return m.Error.parse(data[12:]), ws.close_code


def test_connections_over_the_cap_are_refused_with_server_full(caplog):
    caplog.set_level(logging.INFO, logger="psao.serve")

    async def main():
        service, stop, task, url = await start(ServeSettings(port=0, tick_hz=30, stats_interval=1e9, max_clients=2))
        clients = [MirrorClient(url, HASH, reconnect=False) for _ in range(2)]
        runs = [asyncio.create_task(c.run()) for c in clients]
        try:
            while min(c.stats.updates for c in clients) < 2:
                await asyncio.sleep(0.05)
            refused = await refusal(url)
            clients[0].stop()
            await runs[0]
            while service.open_connections > 1:
                await asyncio.sleep(0.02)
            third = MirrorClient(url, HASH, reconnect=False)
            stats = await asyncio.wait_for(third.run(frames=2), HANG_S)
            return refused, stats
        finally:
            for c in clients:
                c.stop()
            await asyncio.gather(*runs)
            stop.set()
            await task

    (error, code), stats = asyncio.run(main())
    assert error.code == m.ErrorCode.SERVER_FULL and code == 1013 and "server full" in error.text
    assert stats.updates >= 2  # a place freed is a place taken
    assert any("server full: 2 connections" in r.getMessage() for r in caplog.records)


def test_clients_leaving_during_the_handshake_leave_no_traceback(caplog):
    caplog.set_level(logging.INFO)

    async def main():
        service, stop, task, url = await start(ServeSettings(port=0, tick_hz=30, stats_interval=1e9))
        try:
            for _ in range(8):
                ws = await connect(url, compression=None, max_size=None)
                await ws.send(hello())
                ws.transport.abort()  # gone before the Welcome can be sent
            while service.open_connections:
                await asyncio.sleep(0.02)
            good = MirrorClient(url, HASH, reconnect=False)
            return await asyncio.wait_for(good.run(frames=2), HANG_S)
        finally:
            stop.set()
            await task

    stats = asyncio.run(main())
    assert stats.updates >= 2
    errors = [r for r in caplog.records if r.levelno >= logging.ERROR or r.exc_info]
    assert not errors, [r.getMessage() for r in errors]


class PreparedEdits(RandomEdits):
    """Random edits as a prepare/apply tick (prepare off the loop, as the server tick runs)."""
    threaded = True

    def prepare(self, t: float):
        return t

    def apply(self, t: float) -> None:
        self(self.grid, t)


def test_ticks_go_on_while_every_default_worker_is_busy():
    """The clients' own encodes run on the loop's default executor; with all of its workers busy (many
    clients encoding) the tick's prepare and the shared encode still run: they have a thread of their own."""
    import threading
    from concurrent.futures import ThreadPoolExecutor

    async def main():
        loop = asyncio.get_running_loop()
        pool = ThreadPoolExecutor(2)
        loop.set_default_executor(pool)
        release = threading.Event()
        tick = PreparedEdits(5, seed=2)
        service, stop, task, url = await start(ServeSettings(port=0, tick_hz=50, stats_interval=1e9), tick)
        tick.grid = service.grid
        blockers = [loop.run_in_executor(None, release.wait) for _ in range(2)]
        try:
            async with connect(url, compression=None, max_size=None) as ws:
                await ws.send(hello())
                ticks = service.counters.ticks
                while service.counters.ticks < ticks + 5:
                    await asyncio.sleep(0.01)
                return service.counters.ticks - ticks
        finally:
            release.set()
            await asyncio.gather(*blockers)
            stop.set()
            await task

    assert asyncio.run(asyncio.wait_for(main(), HANG_S)) >= 5


def test_small_own_updates_do_not_wait_for_a_worker_thread():
    """A client off the shared stream (per-message zstd never shares) gets small Updates of its own encoded
    on the loop: with every default worker busy it still receives them, and its mirror stays exact."""
    import threading
    from concurrent.futures import ThreadPoolExecutor

    from psao.protocol.codecs import Codec
    from psao.protocol.updates import state_digest

    async def main():
        loop = asyncio.get_running_loop()
        loop.set_default_executor(ThreadPoolExecutor(2))
        release = threading.Event()
        service, stop, task, url = await start(ServeSettings(port=0, tick_hz=50, stats_interval=1e9))
        client = MirrorClient(url, HASH, codecs={Codec.ZSTD})
        run = asyncio.create_task(client.run())
        blockers = []
        try:
            while client.stats.snapshot_seconds is None:
                await asyncio.sleep(0.01)
            blockers = [loop.run_in_executor(None, release.wait) for _ in range(2)]
            updates = client.stats.updates
            while client.stats.updates < updates + 5:
                await asyncio.sleep(0.01)
            stop_edits = service.tick_fn
            service.tick_fn = None  # hold still, then compare the whole state
            held = service.tick
            while service.tick < held + 2 or any(c.pending_anything() or c.busy for c in service.registry):
                await asyncio.sleep(0.01)
            while client.stats.messages < next(iter(service.registry)).messages_sent:
                await asyncio.sleep(0.01)
            g, mirror = service.grid, client.mirror
            same = (state_digest(g.instances, g.buckets, g.cells, service.transforms())
                    == state_digest(mirror.instances, mirror.buckets, mirror.cells, mirror.transforms))
            service.tick_fn = stop_edits
            return client.stats.updates - updates, same
        finally:
            release.set()
            await asyncio.gather(*blockers)
            client.stop()
            run.cancel()
            await asyncio.gather(run, return_exceptions=True)
            stop.set()
            await task

    updates, same = asyncio.run(asyncio.wait_for(main(), HANG_S))
    assert updates >= 5 and same
