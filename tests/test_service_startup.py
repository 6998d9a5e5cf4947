"""A service that listens before it has a scene and a grid (`psao serve` loads and bakes behind it), in-process
over real loopback sockets: connections are answered at once, told the phase in Status messages while they
wait, checked (token at once, scene hash once it is known) and served the coarse grid, then the full one."""
from __future__ import annotations

import asyncio
import json
import threading

import pytest
from websockets.asyncio.client import connect
from websockets.exceptions import ConnectionClosed

from psao.protocol import messages as m
from psao.protocol.session import (GRID_REPLACED_CLOSE, ClientConfig, ClientSession, RemoteError, SceneReceived,
                                   SnapshotReceived, StatusReceived, Welcomed)
from psao.client.connection import MirrorClient
from psao.client.errors import ConnectError
from psao.server.net.service import Service
from psao.server.settings import ServeSettings
from psao.server.tick.progressive import StartupProgress
from psao.server.tick.testhook import RandomEdits
from psao.protocol.scenefile import SceneFile
from serving import HANG_S
from test_bad_input_server import HASH, make_grid

OTHER = bytes(32)
P = m.StatusPhase


def scene_blob() -> bytes:
    """A real (empty) scene blob: one zstd frame of a scene file."""
    import zstandard

    return zstandard.ZstdCompressor().compress(SceneFile("empty", 1.0).serialize())


async def starting_service(**more):
    progress = StartupProgress("loading test scene")
    settings = ServeSettings(port=0, tick_hz=30, stats_interval=1e9, **more)
    service = Service(None, None, settings, progress=progress)
    stop, ready = asyncio.Event(), asyncio.Event()
    task = asyncio.create_task(service.run(stop, ready=lambda port: ready.set()))
    await ready.wait()
    return service, progress, stop, task


def from_thread(fn, *args, **kw):
    """fn(*args) on a thread of its own, as the start-up thread calls the service."""
    t = threading.Thread(target=fn, args=args, kwargs=kw)
    t.start()
    t.join()


class Raw:
    """One websocket connection with a ClientSession: every event kept in order."""

    def __init__(self, ws, session: ClientSession):
        self.ws, self.session, self.events = ws, session, []

    async def until(self, done) -> list:
        """Read events until done(event) is true for one; returns the events read."""
        got = []
        while True:
            event = self.session.receive(await asyncio.wait_for(self.ws.recv(), HANG_S))
            got.append(event)
            self.events.append(event)
            if done(event):
                return got


def is_status(phase, progress=None):
    return lambda e: (isinstance(e, StatusReceived) and e.status.phase == phase
                      and (progress is None or abs(e.status.progress - progress) < 1e-6))


def test_connections_are_answered_checked_and_served_as_the_server_starts():
    async def main():
        service, progress, stop, task = await starting_service(token="tk")
        url = f"ws://127.0.0.1:{service.port}"
        try:
            async with connect(url, compression=None, max_size=None) as a_ws, \
                    connect(url, compression=None, max_size=None) as c_ws, \
                    connect(url, compression=None, max_size=None) as d_ws:
                a = Raw(a_ws, ClientSession(ClientConfig(HASH, token="tk")))
                await a_ws.send(a.session.hello())
                first = await a.until(lambda e: True)
                assert is_status(P.LOADING, 0.0)(first[0]) and first[0].status.text == "loading test scene"
                # a wrong token is refused at once, while the scene is still loading
                async with connect(url, compression=None, max_size=None) as b_ws:
                    b = Raw(b_ws, ClientSession(ClientConfig(HASH, token="guess")))
                    await b_ws.send(b.session.hello())
                    with pytest.raises(RemoteError, match="wrong token") as refused:
                        await b.until(lambda e: True)
                    assert refused.value.code == m.ErrorCode.UNAUTHORIZED
                c = Raw(c_ws, ClientSession(ClientConfig(None, token="tk")))
                await c_ws.send(c.session.scene_request())
                await c.until(is_status(P.LOADING))
                d = Raw(d_ws, ClientSession(ClientConfig(OTHER, token="tk")))
                await d_ws.send(d.session.hello())
                await d.until(is_status(P.LOADING))
                progress.set(0.5, "loading test scene")
                await a.until(is_status(P.LOADING, 0.5))  # progress goes out as it changes

                from_thread(service.set_scene, HASH, scene_blob)
                await a.until(is_status(P.BAKING))
                got = await c.until(lambda e: isinstance(e, SceneReceived))
                assert got[-1].scene_hash == HASH
                await c_ws.send(c.session.bye())
                with pytest.raises(RemoteError, match="scene hash mismatch"):  # checked once the scene is known
                    await d.until(lambda e: False)

                progress.set(0.0, "baking the full grid")
                coarse, full = make_grid(400, seed=1), make_grid(3000, seed=2)
                from_thread(service.replace_grid, coarse, None, None, final=False)
                got = await a.until(lambda e: isinstance(e, SnapshotReceived) and e.complete)
                assert any(isinstance(e, Welcomed) for e in got)
                assert any(is_status(P.COARSE)(e) for e in got)
                assert got[[isinstance(e, Welcomed) for e in got].index(True)].welcome.cell_capacity == len(coarse.cells)
                progress.set(0.6, "baking the full grid")
                await a.until(is_status(P.COARSE, 0.6))  # clients on the coarse grid hear the full bake's progress

                from_thread(service.replace_grid, full, None, None, final=True)
                await a.until(is_status(P.READY, 1.0))  # before the close that sends it to the full grid
                with pytest.raises(ConnectionClosed) as closed:
                    await a.until(lambda e: False)
                assert closed.value.rcvd.code == GRID_REPLACED_CLOSE
                # after READY a new connection gets no Status: Welcome first
                async with connect(url, compression=None, max_size=None) as e_ws:
                    e = Raw(e_ws, ClientSession(ClientConfig(HASH, token="tk")))
                    await e_ws.send(e.session.hello())
                    got = await e.until(lambda ev: True)
                    assert isinstance(got[0], Welcomed) and got[0].welcome.cell_capacity == len(full.cells)
        finally:
            stop.set()
            await task
        return service

    service = asyncio.run(main())
    assert service.grids_replaced == 1 and service.status().phase == P.READY


def test_mirror_client_waits_through_the_start_and_stays_exact_on_both_grids(tmp_path):
    """A MirrorClient connected before the scene is known: its log shows the phases, it gets the coarse grid
    (ticked from its first tick), reconnects to the full grid by itself, and after every message that left
    nothing pending its mirror equals the server's state, on both grids."""
    slog, clog = tmp_path / "server.jsonl", tmp_path / "client.jsonl"
    lines: list[str] = []
    statuses: list[m.Status] = []
    sizes: list[int] = []

    async def main():
        service, progress, stop, task = await starting_service(digest_log=slog)
        url = f"ws://127.0.0.1:{service.port}"
        coarse_updates = asyncio.Event()
        loop = asyncio.get_running_loop()

        def on_update(mirror, transforms, tick):
            if len(sizes) == 1 and client.stats.updates >= 3:
                loop.call_soon(coarse_updates.set)
            if len(sizes) == 2 and client.stats.updates >= 8:
                client.stop()

        client = MirrorClient(url, HASH, digest_log=clog, reconnect=False, log=lines.append,
                              on_status=statuses.append, on_snapshot=lambda mirror: sizes.append(len(mirror.cells)),
                              on_update=on_update)
        run = asyncio.create_task(client.run())
        try:
            while not client.stats.status_messages:
                await asyncio.sleep(0.01)
            progress.set(0.1, "baking a coarse grid")
            from_thread(service.set_scene, HASH, None)
            from_thread(service.replace_grid, make_grid(500, seed=3), RandomEdits(10, seed=4), None, final=False)
            await asyncio.wait_for(coarse_updates.wait(), HANG_S)
            from_thread(service.replace_grid, make_grid(2500, seed=5), RandomEdits(10, seed=6), None, final=True)
            stats = await asyncio.wait_for(run, HANG_S)
        finally:
            stop.set()
            await task
        return stats

    stats = asyncio.run(main())
    phases = [s.phase for s in statuses]
    assert phases[0] == P.LOADING and P.COARSE in phases and phases[-1] == P.READY
    assert phases == sorted(phases)  # never back
    assert any("server loading" in ln for ln in lines) and any("server ready 100%" in ln for ln in lines)
    assert stats.grid_replacements == 1 and stats.reconnects == 0 and len(sizes) == 2 and sizes[0] < sizes[1]
    server = {(d["conn"], d["seq"]): d["digest"] for d in map(json.loads, slog.read_text().splitlines())}
    mine = [json.loads(line) for line in clog.read_text().splitlines()]
    pairs = [(server[(d["conn"], d["seq"])], d["digest"]) for d in mine if (d["conn"], d["seq"]) in server]
    assert pairs and all(a == b for a, b in pairs)
    assert len({d["conn"] for d in mine if (d["conn"], d["seq"]) in server}) == 2  # compared on both grids


def test_a_server_stopping_during_its_start_leaves_a_clear_error():
    """The server stops while the client waits for a grid: Bye, and one line naming the state it was in."""
    lines: list[str] = []

    async def main():
        service, progress, stop, task = await starting_service()
        from_thread(service.set_scene, HASH, None)
        progress.set(0.4, "baking a coarse grid")
        client = MirrorClient(f"ws://127.0.0.1:{service.port}", HASH, reconnect=False, log=lines.append)
        run = asyncio.create_task(client.run())
        while not client.stats.status_messages:
            await asyncio.sleep(0.01)
        stop.set()
        await task
        try:
            await asyncio.wait_for(run, HANG_S)
        except ConnectError as exc:
            return str(exc)

    text = asyncio.run(main())
    assert "connection lost (server said Bye) while the server was baking 40%: baking a coarse grid" in text, text
    assert lines == [f"{text.split(': connection lost')[0]}: server baking 40%: baking a coarse grid"]


def test_a_client_waits_for_a_server_that_does_not_listen_yet():
    """Connection refused at first: the client says so once and tries again until the server is up."""
    import socket

    lines: list[str] = []
    with socket.socket() as s:  # a free port, closed again: refused until the service listens on it
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]

    async def main():
        client = MirrorClient(f"ws://127.0.0.1:{port}", HASH, reconnect=False, log=lines.append, start_wait=HANG_S)
        run = asyncio.create_task(client.run(frames=2))
        while not lines:
            await asyncio.sleep(0.01)
        settings = ServeSettings(port=port, tick_hz=30, stats_interval=1e9)
        service = Service(make_grid(300), HASH, settings, tick=RandomEdits(5, seed=1))
        stop = asyncio.Event()
        task = asyncio.create_task(service.run(stop))
        try:
            return await asyncio.wait_for(run, HANG_S)
        finally:
            stop.set()
            await task

    stats = asyncio.run(main())
    assert stats.updates >= 2 and stats.status_messages == 0
    assert len(lines) == 1 and "no server accepts connections yet (connection refused)" in lines[0]


def test_a_refused_start_wait_ends_in_cannot_connect():
    lines: list[str] = []
    client = MirrorClient("ws://127.0.0.1:9", HASH, reconnect=False, start_wait=0.3, log=lines.append)
    try:
        asyncio.run(client.run(frames=1))
    except ConnectError as exc:
        assert "cannot connect (connection refused; tried for" in str(exc)
    else:
        raise AssertionError("connected to port 9")
    assert len(lines) == 1 and client.stats.messages == 0
