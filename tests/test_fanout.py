"""Compress once, send to many, and per-client culling of sends: the service in-process with real clients
over loopback websockets. Every wait is for an event or a count, never for a duration."""
from __future__ import annotations

import asyncio
import json

import numpy as np
import pytest

from psao.protocol.gridformat import poisson_radius
from psao.protocol.updates import state_digest
from psao.client.connection import MirrorClient
from psao.scene.camera import look_at, perspective
from psao.server.grid import Grid
from psao.server.net.service import Service
from psao.server.settings import FanoutSettings, ServeSettings
from psao.server.tick.testhook import RandomEdits
from test_bad_input_server import HASH, make_grid

PATIENCE = 120.0  # seconds before a wait for an event is a failure (a loaded machine is slow, not wrong)


def read_jsonl(path):
    return [json.loads(line) for line in open(path)] if path.exists() else []


async def until(condition, what: str) -> None:
    async def poll():
        while not condition():
            await asyncio.sleep(0.01)
    try:
        await asyncio.wait_for(poll(), PATIENCE)
    except asyncio.TimeoutError:
        raise AssertionError(f"never happened: {what}") from None


async def start(grid, settings: ServeSettings, tick):
    service = Service(grid, HASH, settings, tick=tick)
    stop, ready = asyncio.Event(), asyncio.Event()
    task = asyncio.create_task(service.run(stop, ready=lambda port: ready.set()))
    await ready.wait()
    return service, stop, task, f"ws://127.0.0.1:{service.port}"


def assert_digests_equal(tmp_path, names, at_least):
    server = {(d["conn"], d["seq"]): d["digest"] for d in read_jsonl(tmp_path / "server.jsonl")}
    for name in names:
        mine = read_jsonl(tmp_path / f"{name}.jsonl")
        both = [d for d in mine if (d["conn"], d["seq"]) in server]
        assert len(both) >= at_least, name
        assert all(server[(d["conn"], d["seq"])] == d["digest"] for d in both), name


def test_clients_joining_at_different_times_and_a_slow_reader_share_updates_and_mirror_exactly(tmp_path):
    """Four clients join one after another while ticks edit the grid; then the fourth reads slowly. The
    in-sync ones take shared Updates (one encode for all), the slow one leaves the shared stream and
    catches up on its own; every logged state matches its mirror bit for bit."""

    async def scenario():
        settings = ServeSettings(port=0, tick_hz=60, stats_interval=1e9, digest_log=tmp_path / "server.jsonl",
                                 send_buffer=4096, fanout=FanoutSettings(join_interval=0.0, max_queued=2))
        service, stop, task, url = await start(make_grid(3000), settings, RandomEdits(150))
        runs, clients = [], []
        try:
            for k in range(3):
                c = MirrorClient(url, HASH, digest_log=tmp_path / f"c{k}.jsonl")
                clients.append(c)
                runs.append(asyncio.create_task(c.run(frames=120)))
                await until(lambda: service.fanout.counters.joins >= k + 1, f"client {k} joins the shared stream")
            slow = MirrorClient(url, HASH, digest_log=tmp_path / "slow.jsonl", recv_buffer=4096)
            runs.append(asyncio.create_task(slow.run(frames=400)))
            on_server = lambda: next((c for c in service.registry if c.id == slow.stats.connection_id), None)  # noqa: E731
            await until(lambda: on_server() is not None and on_server().shared, "the fourth client joins")
            slow.read_delay = 0.2  # now it reads slowly: its outbox fills up
            await until(lambda: not on_server().shared, "the slow reader leaves the shared stream")
            slow.read_delay = 0.0  # and catches up on its own stream
            stats = await asyncio.wait_for(asyncio.gather(*runs), PATIENCE)
        finally:
            stop.set()
            await task
        return service, stats

    service, stats = asyncio.run(scenario())
    f = service.fanout.counters
    assert f.leaves_slow >= 1
    assert f.shared_sends > f.shared_updates >= 60  # updates went to several clients from one encode each
    assert all(s.reconnects == 0 for s in stats)
    # how many of a client's states the server logged as well depends on the machine's speed (a client held
    # back by the read window gets fewer, merged Updates): a few per client, every one equal, is the test
    assert_digests_equal(tmp_path, ["c0", "c1", "c2"], at_least=5)
    assert_digests_equal(tmp_path, ["slow"], at_least=1)


class TwoSides:
    """Points on the floor at x < -15 and at x > 15; `ticks` ticks rewrite the AO of points on both sides."""

    def __init__(self, ticks: int, seed: int = 0):
        self.ticks = ticks
        self.done = 0
        self.rng = np.random.default_rng(seed)

    @staticmethod
    def grid(n: int = 4000) -> Grid:
        rng = np.random.default_rng(1)
        pos = np.column_stack([rng.uniform(15, 20, n), np.zeros(n), rng.uniform(-2.5, 2.5, n)])
        pos[: n // 2, 0] *= -1
        nrm = np.tile(np.float32([0, 1, 0]), (n, 1))
        return Grid.build([(pos, nrm, poisson_radius(50.0, n), 0)])

    def __call__(self, grid: Grid, t: float) -> None:
        if self.done >= self.ticks:
            return
        self.done += 1
        table = grid.point_table()
        pick = self.rng.choice(len(table), 200, replace=False)
        grid.set_ao(table.slot[pick], table.index[pick], self.rng.integers(0, 256, len(pick)).astype(np.uint32))


def camera_towards(x: float):
    return look_at((0.0, 2.0, 0.0), (x, 0.0, 0.0)), perspective(60.0, 16 / 9, 0.1, 100.0)


def test_cells_outside_a_clients_view_wait_until_it_turns_around(tmp_path):
    """A client looking at -x receives the changes at -x only; what changed at +x stays pending (its
    mirror still holds the old cells there, every other row equals the server's); once it turns around
    it receives them and its mirror equals the server's whole state."""
    hook = TwoSides(ticks=0)

    async def scenario():
        settings = ServeSettings(port=0, tick_hz=60, stats_interval=1e9)
        service, stop, task, url = await start(TwoSides.grid(), settings, hook)
        looking = {"x": -10.0}
        client = MirrorClient(url, HASH, camera=lambda t: camera_towards(looking["x"]))
        run = asyncio.create_task(client.run())
        try:
            await until(lambda: client.stats.snapshot_seconds is not None and len(service.registry) == 1
                        and next(iter(service.registry)).camera is not None, "the snapshot and a camera")
            server_client = next(iter(service.registry))
            hook.ticks = hook.done + 20  # the edits start once the client has the whole state and a view

            def quiet():  # everything in its view sent and received; what is left pending lies outside it
                if not (hook.done >= hook.ticks and not server_client.busy and not server_client.outbox
                        and not server_client.in_flight
                        and client.stats.messages == server_client.messages_sent
                        and not server_client.pending_buckets.any()):
                    return False
                in_view = service.fanout.in_view(server_client, service.grid, service.transforms())
                return not in_view(np.flatnonzero(server_client.pending_cells)).any()

            await until(quiet, "the edits sent")
            await asyncio.sleep(0)
            grid, mirror = service.grid, client.mirror
            pending = np.flatnonzero(server_client.pending_cells)
            kept = np.zeros(len(grid.cells), bool)
            kept[pending] = True
            left = grid.cells[pending]
            before = dict(pending=len(pending),
                          same_elsewhere=mirror.cells[~kept].tobytes() == grid.cells[~kept].tobytes(),
                          buckets=mirror.buckets.tobytes() == grid.buckets.tobytes(),
                          stale_kept=int(np.any(mirror.cells[pending] != left, axis=1).sum()),
                          far_side=bool(len(pending)) and all(_cell_x(grid, s) > 0 for s in pending))
            looking["x"] = 10.0
            await until(lambda: not server_client.pending_anything() and not server_client.busy
                        and not server_client.in_flight and client.stats.messages == server_client.messages_sent, "the turned client drained")
            after = state_digest(grid.instances, grid.buckets, grid.cells, service.transforms())
            mine = state_digest(mirror.instances, mirror.buckets, mirror.cells, mirror.transforms)
        finally:
            run.cancel()  # (stop() takes effect at the next message, and a scene at rest sends none)
            await asyncio.gather(run, return_exceptions=True)
            stop.set()
            await task
        return before, after, mine

    before, after, mine = asyncio.run(scenario())
    assert before["pending"] > 50 and before["far_side"]  # the +x changes waited
    assert before["stale_kept"] > 0  # the mirror really lacks them
    assert before["same_elsewhere"] and before["buckets"]  # everything it was sent is exact
    assert mine == after


def _cell_x(grid: Grid, slot: int) -> float:
    from psao.server.net.sendview import CellPlaces

    return float(CellPlaces(grid, np.array([slot]), np.tile(np.eye(4), (1, 1, 1))).centres[0, 0])


def test_cell_places_kept_across_ticks_equal_places_worked_out_anew():
    """The fan-out keeps every slot's place across ticks, working out again only the slots a tick changed
    and, when they are tested, the cells of instances that moved: that must equal working everything out
    from scratch, for the cells a tick tests and for all of them."""
    from psao.protocol.session import ServerConfig
    from psao.server.net.fanout import Fanout
    from psao.server.tick.selection import camera_planes
    from psao.server.net.sendview import CellPlaces

    grid = TwoSides.grid(2000)
    rng = np.random.default_rng(3)
    settings = FanoutSettings()
    fanout = Fanout(ServerConfig(HASH), settings)
    transforms = np.tile(np.eye(4, dtype=np.float32), (1, 1, 1))
    planes = camera_planes(look_at(np.array([0.0, 1, 0]), np.array([5.0, 1, 0])), perspective(60.0, 1.5, 0.05, 100.0),
                           settings.view.fov_margin)
    fanout.places(grid, transforms)
    for step in range(4):
        pos = np.column_stack([rng.uniform(-20, 20, 50), np.zeros(50), rng.uniform(-2.5, 2.5, 50)])
        grid.insert_points(0, pos, np.tile(np.float32([0, 1, 0]), (50, 1)), np.full(50, 128, np.uint32))
        _, cells = grid.take_dirty()
        transforms = transforms.copy()
        transforms[0] = np.diag(np.float32([-1, 1, -1, 1])) @ transforms[0]  # it turns half round: its sides swap
        transforms[0, :3, 3] += np.float32(step + 1)  # and moves
        fanout.plan([], grid, np.zeros(0, np.uint32), cells, transforms, step, 0.0, 0.0)
        fresh = CellPlaces(grid, np.arange(len(grid.cells)), transforms)
        # a tick's tests: some cells, each under the latest move (the camera sees one side)
        rows = rng.choice(np.flatnonzero(np.isfinite(fresh.centres[:, 0])), 300)
        tested = fanout._places_kept(grid, transforms).in_view(planes, settings.view, rows)
        np.testing.assert_array_equal(tested, fresh.in_view(planes, settings.view, rows))
        assert 0 < tested.sum() < len(rows) or step  # (the camera leaves some out, keeps others)
        kept = fanout.places(grid, transforms)
        np.testing.assert_array_equal(kept.centres, fresh.centres)
        np.testing.assert_array_equal(kept.reach, fresh.reach)
        np.testing.assert_array_equal(kept.xyz, fresh.xyz)
        np.testing.assert_array_equal(kept.slack, fresh.slack)
        np.testing.assert_array_equal(kept.owner, fresh.owner)


def test_dirty_cells_kept_for_the_places_stay_bounded_while_no_place_is_asked_for(monkeypatch):
    """No client tests a place (none connected, or none culls): the ticks' dirty cells the places must
    look at again are merged as they pile up, held in at most twice the slots changed (or MERGE_ROWS)."""
    from psao.protocol.session import ServerConfig
    from psao.server.net import fanout as fanout_module
    from psao.server.net.sendview import CellPlaces

    monkeypatch.setattr(fanout_module, "MERGE_ROWS", 100)
    grid = TwoSides.grid(2000)
    fanout = fanout_module.Fanout(ServerConfig(HASH), FanoutSettings())
    transforms = np.tile(np.eye(4, dtype=np.float32), (1, 1, 1))
    fanout.places(grid, transforms)
    rng = np.random.default_rng(4)
    changed = set()
    for step in range(200):
        pos = np.column_stack([rng.uniform(-20, 20, 10), np.zeros(10), rng.uniform(-2.5, 2.5, 10)])
        grid.insert_points(0, pos, np.tile(np.float32([0, 1, 0]), (10, 1)), np.full(10, 128, np.uint32))
        _, cells = grid.take_dirty()
        cells = np.concatenate([cells, rng.choice(len(grid.cells), 30)]).astype(np.uint32)  # and AO changes
        changed.update(cells.tolist())
        fanout.plan([], grid, np.zeros(0, np.uint32), cells, transforms, step, 0.0, 0.0)
        assert sum(len(a) for a in fanout._changed) <= max(100, 2 * len(changed))
    assert sum(len(a) for a in fanout._changed) < 200 * 30  # (merged: fewer than were noted)
    kept = fanout.places(grid, transforms)  # and the places are those of the grid now
    fresh = CellPlaces(grid, np.arange(len(grid.cells)), transforms)
    np.testing.assert_array_equal(kept.centres, fresh.centres)


def test_in_view_is_the_plane_test_of_every_cell():
    """CellPlaces.in_view against its definition, cell by cell: in when every plane's signed distance of
    the centre is >= -(distance margin + reach); a slot with no place (free) is always in."""
    from psao.server.tick.selection import camera_planes
    from psao.server.net.sendview import CellPlaces
    from psao.server.settings import ViewSettings

    grid = TwoSides.grid(2000)
    rng = np.random.default_rng(5)
    pos = np.column_stack([rng.uniform(-20, 20, 300), np.zeros(300), rng.uniform(-2.5, 2.5, 300)])
    grid.insert_points(0, pos, np.tile(np.float32([0, 1, 0]), (300, 1)), np.full(300, 128, np.uint32))
    places = CellPlaces(grid, np.arange(len(grid.cells)), np.tile(np.eye(4), (1, 1, 1)))
    view = ViewSettings()
    from psao.scene.camera import look_at, perspective

    cameras = [(look_at(np.array(eye, float), np.array(target, float)), perspective(60.0, 1.5, 0.05, 100.0))
               for eye, target in [((0, 1, 0), (5, 1, 0)), ((0, 1, 0), (-5, 1, 0)), ((3, 4, -8), (0, 0, 0))]]
    wants = []
    for view_m, proj in cameras:
        planes = camera_planes(view_m, proj, view.fov_margin)
        want = np.array([not np.isfinite(c).all()
                         or all(float(p[:3] @ c + p[3]) >= -(view.distance_margin + r) for p in planes)
                         for c, r in zip(places.centres, places.reach)])
        rows = np.sort(rng.choice(len(want), len(want) // 2, replace=False))
        assert 0 < want.sum() < len(want)  # the camera leaves some cells out, keeps others
        np.testing.assert_array_equal(places.in_view(planes, view), want)
        np.testing.assert_array_equal(places.in_view(planes, view, rows), want[rows])
        assert places.in_view(None, view, rows).all()
        wants.append(want)
    # many cameras at once: the same answers (planes of several clients worked out together, each cell
    # against every camera, or each cell against its own camera)
    from psao.server.net.sendview import clients_planes

    stacked = clients_planes([None, (np.full((4, 4), np.nan), np.eye(4))] + cameras, view)
    assert stacked[0] is None and stacked[1] is None  # no camera yet; one that makes no frustum
    for (view_m, proj), planes in zip(cameras, stacked[2:]):
        np.testing.assert_array_equal(planes, camera_planes(view_m, proj, view.fov_margin))
    planes = np.stack(stacked[2:])
    rows = rng.choice(len(places.slack), 500)
    np.testing.assert_array_equal(places.in_views(planes, view, rows), np.array(wants)[:, rows])
    own = rng.integers(0, len(cameras), len(rows))
    np.testing.assert_array_equal(places.in_view_each(planes, own, view, rows), np.array(wants)[own, rows])
    # the same answers when the tests run in blocks smaller than the cameras and rows (a crowd of clients)
    from psao.server.net import sendview

    for block in (2, 7):  # 2: fewer cameras a block than there are; 7: rows in blocks, every camera at once
        with pytest.MonkeyPatch.context() as mp:
            mp.setattr(sendview, "BLOCK", block)
            np.testing.assert_array_equal(places.in_views(planes, view, rows), np.array(wants)[:, rows])
            np.testing.assert_array_equal(places.in_views(planes, view), np.array(wants))
            np.testing.assert_array_equal(places.in_view_each(planes, own, view, rows), np.array(wants)[own, rows])


def test_who_sees_every_dirty_cell_is_worked_out_for_all_clients_at_once():
    """The shared stream's view test (whether a client's extended view holds every dirty cell), done for
    many clients in one pass, answers as the plane test of each client alone does."""
    from psao.protocol.session import ServerConfig
    from psao.server.net.clients import Client
    from psao.server.net.fanout import Fanout

    grid = TwoSides.grid(2000)
    rng = np.random.default_rng(9)
    pos = np.column_stack([rng.uniform(-20, 20, 300), np.zeros(300), rng.uniform(-2.5, 2.5, 300)])
    grid.insert_points(0, pos, np.tile(np.float32([0, 1, 0]), (300, 1)), np.full(300, 128, np.uint32))
    settings = ServeSettings()
    fanout = Fanout(ServerConfig(HASH, "", "", settings.codec, settings.layout, settings.zstd, settings.limits),
                    settings.fanout)
    transforms = np.tile(np.eye(4, dtype=np.float32), (len(grid.instances), 1, 1))
    clients = []
    for k in range(12):  # some see one side, some the other, some all; one has no camera yet
        c = Client("test", len(grid.buckets), len(grid.cells))
        if k:
            eye = np.array([rng.uniform(-30, 30), rng.uniform(1, 15), rng.uniform(-30, 30)])
            c.camera = (look_at(eye, np.array([rng.uniform(-20, 20), 0.0, 0.0])), perspective(50.0, 1.5, 0.05, 100.0))
        clients.append(c)
    used = np.flatnonzero(grid.cells[:, -1] != 0xFFFFFFFF)
    for trial in range(20):
        dirty = np.sort(rng.choice(used, int(rng.integers(1, 40)), replace=False)).astype(np.uint32)
        places = fanout.places(grid, transforms)
        want = {c.id: bool(places.in_view(fanout.planes(c), settings.fanout.view, dirty).all()) for c in clients}
        assert fanout._sees_all(clients, grid, transforms, dirty) == want
        assert 0 < sum(want.values()) < len(clients) or trial  # (the first draw has both answers)
    assert fanout._sees_all(clients, grid, transforms, np.zeros(0, np.uint32)) == {c.id: True for c in clients}


def test_clients_with_different_views_share_parts_and_mirror_exactly(tmp_path):
    """Three clients, two looking at -x and one at +x, while ticks change cells on both sides: their
    Updates are made of tiles compressed once (a tile goes to every client whose view holds it), what
    lies outside a client's view waits for it, and after they all turn around every mirror equals the
    server's state; every digest the server logged for them matches the client's."""
    hook = TwoSides(ticks=0)
    sides = [-10.0, -10.0, 10.0]

    async def scenario():
        settings = ServeSettings(port=0, tick_hz=60, stats_interval=1e9, digest_log=tmp_path / "server.jsonl",
                                 fanout=FanoutSettings(parts_from=2))
        service, stop, task, url = await start(TwoSides.grid(), settings, hook)
        looking = list(sides)
        clients = [MirrorClient(url, HASH, camera=lambda t, k=k: camera_towards(looking[k]),
                                digest_log=tmp_path / f"c{k}.jsonl", digest_every=1) for k in range(3)]
        runs = [asyncio.create_task(c.run()) for c in clients]

        def on_server(c):
            return next((s for s in service.registry if s.id == c.stats.connection_id), None)

        def settled(c):
            s = on_server(c)
            return (s is not None and not s.busy and not s.in_flight and not s.outbox and c.stats.messages == s.messages_sent
                    and not s.pending_buckets.any())

        try:
            await until(lambda: all(c.stats.snapshot_seconds is not None and on_server(c) is not None
                                    and on_server(c).camera is not None for c in clients), "snapshots and cameras")
            hook.ticks = hook.done + 30

            def quiet():
                if hook.done < hook.ticks or not all(settled(c) for c in clients):
                    return False
                for c in clients:
                    s = on_server(c)
                    in_view = service.fanout.in_view(s, service.grid, service.transforms())
                    if in_view(np.flatnonzero(s.pending_cells)).any():
                        return False
                return True

            await until(quiet, "the edits sent")
            grid = service.grid
            before = []
            for c in clients:
                pending = np.flatnonzero(on_server(c).pending_cells)
                kept = np.zeros(len(grid.cells), bool)
                kept[pending] = True
                before.append(dict(pending=len(pending), exact_elsewhere=c.mirror.cells[~kept].tobytes()
                                   == grid.cells[~kept].tobytes(), on_parts=on_server(c).on_parts))
            counters = service.fanout.counters
            shared = (counters.parts_encoded, counters.parts_sent, counters.part_updates)
            looking[:] = [-x for x in sides]
            await until(lambda: all(settled(c) and not on_server(c).pending_anything() for c in clients),
                        "the turned clients drained")
            server = state_digest(grid.instances, grid.buckets, grid.cells, service.transforms())
            mirrors = [state_digest(c.mirror.instances, c.mirror.buckets, c.mirror.cells, c.mirror.transforms)
                       for c in clients]
        finally:
            for r in runs:
                r.cancel()
            await asyncio.gather(*runs, return_exceptions=True)
            stop.set()
            await task
        return before, shared, server, mirrors

    before, (encoded, sent, updates), server, mirrors = asyncio.run(scenario())
    assert all(b["on_parts"] and b["exact_elsewhere"] and b["pending"] > 20 for b in before)
    assert updates >= 3 * 30 - 10 and sent > encoded > 0  # the two clients looking the same way shared tiles
    assert mirrors == [server] * 3
    assert_digests_equal(tmp_path, ["c0", "c1", "c2"], at_least=1)


def test_a_client_that_stops_reading_is_sent_nothing_more_then_one_merged_catch_up(tmp_path):
    """A client stops reading while every tick changes the grid. Kernel and library buffers would take
    megabytes of Updates for it; instead the server stops once max_unread messages wait to be shown read
    (a ping sent after them unanswered), at every tick. When the client reads again, it gets the ticks it
    missed merged into a few Updates, and its mirror equals the server bit for bit."""
    from websockets.asyncio.client import connect

    from psao.protocol.codecs import Codec
    from psao.protocol.session import ClientConfig, ClientSession, SnapshotReceived, UpdateReceived
    from psao.client.mirror import Mirror

    fan = FanoutSettings(max_unread=4, probe_every=2)

    async def scenario():
        unread_seen = []  # per tick: the most messages any client had not been shown to have read
        edits = RandomEdits(150)

        def tick(grid, t):
            edits(grid, t)
            unread_seen.append(max((c.unread() for c in service.registry if c.streaming), default=0))

        settings = ServeSettings(port=0, tick_hz=60, stats_interval=1e9, digest_log=tmp_path / "server.jsonl",
                                 fanout=fan)
        service, stop, task, url = await start(make_grid(3000), settings, tick)
        session = ClientSession(ClientConfig(HASH, "", frozenset(Codec)))
        try:
            async with connect(url, compression=None, max_size=None) as ws:
                await ws.send(session.hello())
                mirror, seq, updates = None, 0, 0

                async def read_one():
                    nonlocal mirror, seq, updates
                    event = session.receive(await ws.recv())
                    if mirror is None:
                        mirror = Mirror.from_welcome(event.welcome)
                    elif isinstance(event, SnapshotReceived):
                        mirror.apply(event.snapshot.delta)
                        if event.complete:
                            mirror.complete()
                    elif isinstance(event, UpdateReceived):
                        mirror.apply(event.update.delta)
                        updates += 1
                    seq += 1

                while not (mirror is not None and session.state.name == "STREAMING"):
                    await read_one()
                me = next(c for c in service.registry if c.id == session.welcome.connection_id)
                # now it reads nothing (its websocket library still reads a few messages ahead, and answers
                # the pings among them): the server holds back once it is behind, and then sends no more
                for _ in range(100):
                    await until(lambda: service.fanout.behind(me), "the server sees the client behind")
                    sent, at_tick = me.messages_sent, service.tick
                    await until(lambda: service.tick >= at_tick + 30, "30 more ticks")
                    if me.messages_sent == sent:
                        break
                assert me.messages_sent == sent  # nothing more while nothing is read
                # it reads again: the ticks it missed come merged, and its mirror catches up exactly
                updates_before, tick_before = updates, service.tick
                server = {}
                while True:
                    await read_one()
                    server.update({d["seq"]: d["digest"] for d in read_jsonl(tmp_path / "server.jsonl")
                                   if d["conn"] == me.id})
                    if seq - 1 in server and updates > updates_before:
                        assert mirror.digest() == server[seq - 1]
                        break
                merged_ticks = service.tick - tick_before
        finally:
            stop.set()
            await task
        return unread_seen, updates - updates_before, merged_ticks, service

    unread_seen, updates_after, ticks, service = asyncio.run(scenario())
    assert max(unread_seen) <= fan.max_unread  # never more than that sent and not shown read, at any tick
    assert max(unread_seen) == fan.max_unread  # (and it was reached: the client was held back)
    assert service.counters.ticks > 60
    assert updates_after >= 1


def test_a_crowd_sending_cameras_every_tick_has_its_pending_cells_looked_at_every_few_ticks():
    """Clients on shared parts whose cameras change every tick (as a crowd's do): each one's pending cells
    are tested against its view at most once per catch_up_every ticks, and the cells a client turns
    towards still reach it within that many ticks, with the grid's latest content."""
    from psao.protocol.session import ServerConfig
    from psao.server.net.clients import Client
    from psao.server.net.fanout import Fanout

    grid = TwoSides.grid(2000)
    settings = ServeSettings()
    every = settings.fanout.catch_up_every
    assert every > 1
    fanout = Fanout(ServerConfig(HASH, "", "", settings.codec, settings.layout, settings.zstd, settings.limits),
                    settings.fanout)
    transforms = np.tile(np.eye(4, dtype=np.float32), (len(grid.instances), 1, 1))
    clients = [Client("test", len(grid.buckets), len(grid.cells), streaming=True, takes_parts=True)
               for _ in range(settings.fanout.parts_from)]
    looked_at: dict[int, list[int]] = {c.id: [] for c in clients}
    real_catch_ups, tick = fanout._catch_ups, [0]

    def catch_ups(who, *args, **kwargs):  # the real test, with who was looked at recorded
        for c in who:
            looked_at[c.id].append(tick[0])
        return real_catch_ups(who, *args, **kwargs)

    fanout._catch_ups = catch_ups
    hook, rng = TwoSides(ticks=10 ** 6, seed=3), np.random.default_rng(4)
    plus = np.flatnonzero(np.isfinite(fanout.places(grid, transforms).centres[:, 0])
                          & (fanout.places(grid, transforms).centres[:, 0] > 0))
    sent_plus: dict[int, int] = {}  # client id -> the first tick a +x cell pending for it was sent to it
    for tick[0] in range(1, 41):
        turned = tick[0] > 20  # the last client turns towards +x at tick 21
        for k, c in enumerate(clients):  # a camera a little different every tick
            c.camera = camera_towards((10.0 if turned and k == 0 else -10.0) + 1e-3 * tick[0])
        hook(grid, 0.0)
        b, cells = grid.take_dirty()
        share, parted = fanout.plan(clients, grid, b, cells, transforms, tick[0], 0.0, float(tick[0]))
        assert share is None and len(parted) == len(clients)  # every client keeps +x cells back: all on parts
        plan = fanout.plan_parts(parted, grid, b, cells, transforms, tick[0], 0.0)
        for r in plan.recipes:
            own = r.own_part.cell_slots if r.own_part is not None else np.zeros(0)
            if len(np.intersect1d(own, plus)) and r.client.id not in sent_plus:
                sent_plus[r.client.id] = tick[0]
                np.testing.assert_array_equal(r.own_part.cells, grid.cells[r.own_part.cell_slots])
    for c in clients:
        ticks = looked_at[c.id]
        assert len(ticks) >= 40 // every - 1
        assert min(np.diff(ticks)) >= every, ticks  # never more often than every `every` ticks
    assert sent_plus == {clients[0].id: sent_plus[clients[0].id]} and 21 <= sent_plus[clients[0].id] < 21 + every
