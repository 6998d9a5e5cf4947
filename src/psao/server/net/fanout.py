"""Compress once, send to many: a tick's changes as one shared Update, as Updates made of shared parts,
or into each client's pending sets.

Every tick the service hands the grid's dirty buckets and cells here (`plan`). Clients on the shared
stream (psao.protocol.session.SharedStream) whose extended view holds every dirty cell, and who are not
behind, get the tick's changes as one Update encoded once for all of them (`SharePlan.encode` on the
encode thread, then `deliver` puts the same bytes in each one's outbox).

Clients off the shared stream whose views keep cells back (culling), when there are at least
`parts_from` of them, get Updates made of shared parts (`plan_parts`): the tick's dirty cells are grouped
into world-space tiles, each tile is compressed once as a zstd frame (psao.protocol.session.SharedParts), and
a client's Update is a head frame (tick, moved transforms, dirty buckets: shared by every client in step,
else its own) and the frames of the tiles that hold a cell of its extended view; the other dirty cells
stay pending for it, and pending cells that its moved camera now sees go in a part of its own.

Every other client gets the dirty sets in its pending sets, and its own sender streams what lies in its
view on its own zstd stream (psao.protocol.codecs.OWN_STREAM_ZSTD: small, and a fast level), leaving cells
outside its view pending.

A client joins the shared stream when it is in sync (its snapshot done, nothing pending; an Update of
its own that is still being encoded or sent goes out first, as it was read first) at a tick where the
shared stream starts a new frame; the stream restarts for waiting clients at most once per
`join_interval` (a restart costs every member one message without history). A member leaves it when the
tick's dirty cells reach outside its view (culling) or when `max_queued` shared messages wait for it (a
slow reader): from then on its own sender takes over, after the queued messages.

A client is behind (`behind`) when `max_unread` messages sent to it wait to be shown read (a ping sent
after them not yet answered: the answer queues behind them in every buffer on the way): nothing more is
sent to it, no shared Update or part is queued for it, and its changes wait in its pending sets until its
own sender sends them, merged, once it has read. A slow reader thus gets fewer, larger Updates instead of
falling seconds behind.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from psao.protocol.gridformat import CELL_WORDS
from psao.protocol.session import ServerConfig, SharedParts, SharedStream
from psao.protocol.updates import GridDelta

from psao.server.net.clients import Client, changed_transform_ids, read_delta
from psao.server.net.rate import pace_rate
from psao.server.net.sendview import CellPlaces, client_planes, clients_planes
from psao.server.settings import FanoutSettings


MERGE_ROWS = 1 << 16  # dirty cells noted for the places (Fanout._note_changed) before they are merged
RAW_CELL_BYTES = 4 * CELL_WORDS  # a cell row uncompressed: the bytes per cell assumed before a client's first Update
MIN_BUDGET_CELLS = 16  # an Update under a rate cap carries at least this many cells (it goes later instead)


@dataclass
class FanoutCounters:
    shared_updates: int = 0  # Updates encoded once for the shared stream
    shared_sends: int = 0  # their deliveries (one per member)
    restarts: int = 0  # frames the shared stream started after its first
    joins: int = 0
    leaves_view: int = 0  # members that left because the tick's cells reached outside their view
    leaves_slow: int = 0  # members that left as slow readers (max_queued messages waiting, or behind)
    part_updates: int = 0  # Updates made of shared parts (one per client and tick)
    parts_encoded: int = 0  # tile parts compressed (each once, for every client whose view holds the tile)
    parts_sent: int = 0  # tile parts in those Updates
    catch_ups: int = 0  # Updates of parts that also carried a client's own part (cells come into its view)


@dataclass
class SharePlan:
    """One tick's shared Update: its content (read when planned) and who receives it."""

    stream: SharedStream
    tick: int
    server_time: float
    delta: object  # GridDelta
    members: list[Client]
    restart: bool  # the stream starts a new frame at this Update (clients join)

    def encode(self) -> bytes:
        """The Update's bytes (on the encode thread: every use of the stream's compressor is there, in order)."""
        if self.restart:
            self.stream.restart()
        return self.stream.update(self.tick, self.server_time, self.delta)


@dataclass
class PartsRecipe:
    """One client's Update of this tick: the shared head or its own, the tiles it gets, its own part."""

    client: Client
    own_head: GridDelta | None  # None: the shared head
    tiles: list[int]  # keys of PartsPlan.tiles
    own_part: GridDelta | None  # cells that came into its view since they changed
    drained: bool  # nothing left pending afterwards: its mirror then equals the server

    def cells(self, plan: "PartsPlan") -> int:
        """Cell rows its Update carries."""
        own = len(self.own_part.cell_slots) if self.own_part is not None else 0
        return own + sum(b - a for a, b in (plan.tiles[t] for t in self.tiles))


@dataclass
class PartsPlan:
    """One tick's Updates of shared parts: the content (read when planned) and who gets which parts."""

    parts: SharedParts
    tick: int
    server_time: float
    head: GridDelta
    cell_slots: np.ndarray  # the tick's dirty cells, tile by tile (ascending in each tile)
    cells: np.ndarray  # their rows, read when planned
    tiles: dict[int, tuple[int, int]]  # the tiles some client gets, by tile index: their runs of those rows
    recipes: list[PartsRecipe]

    def encode(self) -> list[list[bytes]]:
        """Every recipe's frames: the shared head and tiles are compressed once, own pieces per client."""
        runs = self.parts.cell_runs(self.head.cell_capacity, self.cell_slots, self.cells, list(self.tiles.values()))
        tiles = dict(zip(self.tiles, runs))
        shared_head = None
        out = []
        for r in self.recipes:
            if r.own_head is None:
                shared_head = shared_head or self.parts.head(self.tick, self.server_time, self.head)
                frames = [shared_head]
            else:
                frames = [self.parts.head(self.tick, self.server_time, r.own_head)]
            frames += [tiles[t] for t in r.tiles]
            if r.own_part is not None:
                frames.append(self.parts.part(r.own_part))
            out.append(frames)
        return out


@dataclass
class Parts:
    """An Update of parts waiting in a client's outbox: its frames (ServerSession.update_of_parts)."""

    frames: list[bytes]


class Fanout:
    def __init__(self, config: ServerConfig, settings: FanoutSettings):
        self.settings = settings
        self.config_limits = config.limits
        self.stream = SharedStream(config)
        self.shared_messages = 0  # Updates planned for the shared stream
        self.sent_transforms: np.ndarray | None = None  # what the shared stream's members were last sent
        self.last_restart = -np.inf
        self.counters = FanoutCounters()
        self.parts = SharedParts(config)
        self.head_transforms: np.ndarray | None = None  # what the last shared head brought its clients to
        self._tile_size: float | None = None  # world units of a tile's side
        self._places: CellPlaces | None = None  # every slot's place, kept across ticks
        self._placed_with: np.ndarray | None = None  # the transforms it holds
        self._changed: list[np.ndarray] = []  # the ticks' dirty cells since the places were last brought up to date
        self._changed_rows = 0  # how many (with repeats) those arrays hold
        self._merge_at = MERGE_ROWS  # when they are merged into one (repeats dropped)

    def planes(self, client: Client) -> np.ndarray | None:
        """The client's extended frustum, or None when it sees everything (no culling, no usable camera)."""
        if not self.settings.cull:
            return None
        return client.view_planes(lambda camera: client_planes(camera, self.settings.view))

    def refresh_planes(self, clients: list[Client]) -> None:
        """Work out the extended frustum of every client whose camera changed since its planes were, in one
        pass: a client sends cameras faster than ticks come, so each tick finds most of them changed."""
        if not self.settings.cull:
            return
        moved = [c for c in clients if c.planes_stale()]
        for c, planes in zip(moved, clients_planes([c.camera for c in moved], self.settings.view)):
            c.keep_planes(planes)

    def places(self, grid, transforms: np.ndarray) -> CellPlaces:
        """Where every cell slot is, for all the clients (every place worked out: `_places_kept`, settled)."""
        places = self._places_kept(grid, transforms)
        places.settle()
        return places

    def _places_kept(self, grid, transforms: np.ndarray) -> CellPlaces:
        """The places kept across ticks: worked out in full when the pool changes size, else again only
        for the slots the ticks changed; the cells of instances whose transform changed (bitwise) move
        with them when they are next tested (CellPlaces.defer: a tick tests a few, most stay put)."""
        t = np.ascontiguousarray(transforms, np.float32)
        if (self._places is None or len(self._places.centres) != len(grid.cells)
                or self._placed_with.shape != t.shape):
            self._places = CellPlaces(grid, np.arange(len(grid.cells)), t)
        else:
            moved = changed_transform_ids(self._placed_with, t)
            if len(moved):  # their cells keep their places in the instance's space
                self._places.defer(moved, t)
            if self._changed:
                self._places.refresh(grid, self._changed_slots(), t)
        self._placed_with = t.copy()
        self._changed, self._changed_rows, self._merge_at = [], 0, MERGE_ROWS
        return self._places

    def _note_changed(self, cell_slots: np.ndarray) -> None:
        """The tick's dirty cells: their places may have changed (looked at again by _places_kept). Kept as
        the ticks' arrays (no pass over every slot each tick), merged when they grow (bounded however long
        no place is asked for: by twice the slots changed, or MERGE_ROWS)."""
        if not len(cell_slots):
            return
        self._changed.append(np.asarray(cell_slots, np.int64))
        self._changed_rows += len(cell_slots)
        if self._changed_rows > self._merge_at:
            merged = self._changed_slots()
            self._changed, self._changed_rows = [merged], len(merged)
            self._merge_at = max(MERGE_ROWS, 2 * len(merged))

    def _changed_slots(self) -> np.ndarray:
        return np.unique(np.concatenate(self._changed))

    def tile_size(self, places: CellPlaces) -> float:
        """A tile's side: the extent of the placed cells over settings.tiles_per_axis (fixed once known)."""
        if self._tile_size is None:
            places.settle()
            known = np.isfinite(places.centres).all(axis=1)
            if not known.any():
                return 1.0
            c = places.centres[known]
            self._tile_size = max(float((c.max(axis=0) - c.min(axis=0)).max()) / self.settings.tiles_per_axis, 1e-6)
        return self._tile_size

    def behind(self, c: Client) -> bool:
        """Whether max_unread messages sent to the client wait to be shown read (Client.unread): nothing
        more is sent to it until it has read them, and its changes wait in its pending sets meanwhile."""
        return c.unread() >= self.settings.max_unread

    def takes_parts(self, c: Client) -> bool:
        """A client whose Updates may be made of shared parts now: streaming, its client decodes zstd, off
        the shared stream, not sending an Update of its own, and not behind (a short outbox, its messages
        read)."""
        return (c.takes_parts and c.streaming and not c.shared and not c.busy
                and len(c.outbox) + c.in_flight < self.settings.max_queued and not self.behind(c))

    def plan_parts(self, clients: list[Client], grid, bucket_ids: np.ndarray, cell_slots: np.ndarray,
                   transforms: np.ndarray, tick: int, server_time: float) -> PartsPlan | None:
        """This tick's changes for `clients` (each takes_parts) as Updates of shared parts: the dirty cells
        grouped by world-space tile, each tile compressed once for every client whose extended view holds
        any of its cells; the dirty cells outside a client's view stay pending for it, and pending cells
        that came into its view (its camera moved) go in a part of its own. Reads the grid (on the loop)."""
        limits = self.config_limits
        capacity = len(grid.cells)
        if (len(bucket_ids) > limits.max_buckets_per_message or len(cell_slots) > limits.max_cells_per_message // 2):
            for c in clients:  # a tick this big goes out through the clients' own senders, in several messages
                c.mark(bucket_ids, cell_slots, capacity)
            return None
        now_t = np.ascontiguousarray(transforms, np.float32)
        places = self._places_kept(grid, now_t) if self.settings.cull else None
        slots = np.sort(np.asarray(cell_slots, np.int64))
        # tiles: dirty cells sorted by tile, `starts` where each tile's run begins
        if places is not None and len(slots):
            size = self.tile_size(places)
            places.settle(slots)
            centre = places.centres[slots]
            known = np.isfinite(centre).all(axis=1)
            cell = np.where(known[:, None], np.floor(np.nan_to_num(centre) / size), 0).astype(np.int64)
            key = ((cell[:, 0] & 0x1FFFFF) << 42) | ((cell[:, 1] & 0x1FFFFF) << 21) | (cell[:, 2] & 0x1FFFFF)
            key = np.where(known, key, -1)
            order = np.argsort(key, kind="stable")
            _, starts = np.unique(key[order], return_index=True)
        else:
            order = np.arange(len(slots))
            starts = np.zeros(1 if len(slots) else 0, np.int64)
        sorted_slots = slots[order]
        counts = np.diff(np.append(starts, len(slots)))
        ends = starts + counts
        tids = changed_transform_ids(self.head_transforms, now_t)
        head = read_delta(grid, now_t, tids, bucket_ids, [])
        head_transforms = now_t.copy()
        planes = [self.planes(c) for c in clients]
        visible = self._tiles_in_views(planes, places, slots, order, starts)  # (clients, tiles)
        hidden_rows = np.repeat(~visible, counts, axis=1)  # (clients, dirty cells in tile order)
        catch = []  # clients whose pending cells are looked at again (their camera moved)
        for c, pl in zip(clients, planes):
            c._fit(capacity)
            c.on_parts = True
            c.cells_pending.unset(slots)  # what is sent now carries the latest content; the rest is marked again
            if c.cells_pending.count and (c.caught_up_with is None or (
                    pl is not c.caught_up_with and tick - c.caught_up_at >= self.settings.catch_up_every)):
                c.caught_up_at = tick
                catch.append(c)
        own_parts = self._catch_ups(catch, grid, now_t, places, planes=[self.planes(c) for c in catch])
        recipes, rows_of = [], []  # (rows_of: each recipe's client's row of `visible`)
        seen_by, seen = visible.nonzero()  # every client's tiles in one pass (row-major: by client, ascending)
        seen_at = np.searchsorted(seen_by, np.arange(len(clients) + 1)).tolist()
        seen = seen.tolist()
        for k, c in enumerate(clients):
            tiles = seen[seen_at[k]:seen_at[k + 1]]
            c.cells_pending.set(sorted_slots[hidden_rows[k]])
            own_part = own_parts.get(c.id)
            if c.sent_transforms is self.head_transforms and self.head_transforms is not None \
                    and not c.buckets_pending.count:
                own_head = None
            else:
                c.buckets_pending.set(bucket_ids)
                b = c.buckets_pending.indices()[: limits.max_buckets_per_message]
                c.buckets_pending.unset(b)
                own_head = read_delta(grid, now_t, c.changed_transforms(now_t), b, [])
            c.sent_transforms = head_transforms
            if own_head is None and not (len(tids) or len(bucket_ids) or len(tiles) or own_part is not None):
                continue  # nothing for it this tick
            recipes.append(PartsRecipe(c, own_head, tiles, own_part, not c.pending_anything()))
            rows_of.append(k)
        self.head_transforms = head_transforms
        if not recipes:
            return None
        used = np.flatnonzero(visible[rows_of].any(axis=0))  # the tiles some recipe takes
        rows = grid.cells[sorted_slots]  # one gather; a tile's cells are a run of it (slots ascending in each)
        first, end = starts.tolist(), ends.tolist()
        tiles = {t: (first[t], end[t]) for t in used.tolist()}
        return PartsPlan(self.parts, tick, server_time, head, sorted_slots, rows, tiles, recipes)

    def _tiles_in_views(self, planes: list, places, slots: np.ndarray, order: np.ndarray,
                        starts: np.ndarray) -> np.ndarray:
        """Bool (clients, tiles): whether a client's extended view holds any of a tile's dirty cells (the
        tiles are runs of slots[order] from `starts`); every client's in one pass."""
        visible = np.ones((len(planes), len(starts)), bool)
        culled = [k for k, p in enumerate(planes) if p is not None]
        if places is None or not (culled and len(slots)):
            return visible
        inside = places.in_views(np.stack([planes[k] for k in culled]), self.settings.view, slots)
        visible[culled] = np.logical_or.reduceat(inside[:, order], starts, axis=1)
        return visible

    def _catch_ups(self, clients: list[Client], grid, transforms: np.ndarray, places,
                   planes: list) -> dict[int, GridDelta]:
        """Per client id: its pending cells now in its view (none of this tick's: they go in tiles), as its
        own part, where there are any; every client's cells tested in one pass. Looked at again when its
        camera moved (at most every settings.catch_up_every ticks), or at once when a message could not
        hold them."""
        cands = [c.cells_pending.indices() for c in clients]  # (this tick's cells were taken off them)
        culled = [k for k, p in enumerate(planes) if p is not None and len(cands[k])]
        if places is not None and culled:
            rows = np.concatenate([cands[k] for k in culled])
            lens = [len(cands[k]) for k in culled]
            camera = np.repeat(np.arange(len(culled)), lens)  # each row's client among the culled
            inside = places.in_view_each(np.stack([planes[k] for k in culled]), camera, self.settings.view, rows)
            at = 0  # (slices, not np.split: its per-piece Python costs more than the test at a few dozen clients)
            for k, n in zip(culled, lens):
                cands[k] = cands[k][inside[at:at + n]]
                at += n
        room = self.config_limits.max_cells_per_message // 2
        out = {}
        for c, pl, cand in zip(clients, planes, cands):
            c.caught_up_with = pl if len(cand) <= room else None
            cand = cand[:room]
            if not len(cand):
                continue
            c.cells_pending.unset(cand)
            self.counters.catch_ups += 1
            out[c.id] = read_delta(grid, transforms, [], [], cand)
        return out

    def deliver_parts(self, plan: PartsPlan, frames: list[list[bytes]]) -> list[tuple[PartsRecipe, int]]:
        """Put each client's Update of parts in its outbox; returns (recipe, message index) per client."""
        out = []
        for r, f in zip(plan.recipes, frames):
            r.client.outbox.append(Parts(f))
            r.client.wake.set()
            self.counters.part_updates += 1
            self.counters.parts_sent += len(r.tiles)
            out.append((r, r.client.next_seq()))
        self.counters.parts_encoded += len(plan.tiles)
        return out

    def in_view(self, client: Client, grid, transforms: np.ndarray):
        """`slots -> bool` for take_pending, or None when the client sees every cell."""
        planes = self.planes(client)
        if planes is None:
            return None
        return lambda slots: self._places_kept(grid, transforms).in_view(planes, self.settings.view, slots)

    def distance(self, client: Client, grid, transforms: np.ndarray):
        """`slots -> squared distance of their cells' centres from the client's camera` for take_pending
        (nearest first), or None before its first camera."""
        if client.camera is None:
            return None
        view = np.asarray(client.camera[0], np.float64).reshape(4, 4)  # world -> view, row-major
        eye = -view[:3, :3].T @ view[:3, 3]

        def squared(slots: np.ndarray) -> np.ndarray:
            places = self._places_kept(grid, transforms)
            places.settle(slots)
            d = places.xyz[:, slots] - eye[:, None]  # (a slot whose place is unknown sits at the origin)
            return np.einsum("ij,ij->j", d, d)

        return squared

    def cells_budget(self, client: Client, tick_hz: float) -> int | None:
        """Cells one Update of the client's own may carry at its pacing rate (rate.pace_rate: the estimate
        of its throughput, an explicit cap): a tick's share of the rate over the bytes its Updates took per
        cell (None when it is not paced)."""
        rate = pace_rate(client.rate, self.settings)
        if rate is None:
            return None
        per_tick = rate / tick_hz
        per_cell = client.bytes_per_cell or RAW_CELL_BYTES
        return max(MIN_BUDGET_CELLS, int(per_tick / per_cell))

    def plan(self, clients: list[Client], grid, bucket_ids: np.ndarray, cell_slots: np.ndarray, transforms: np.ndarray,
             tick: int, server_time: float, now: float) -> tuple[SharePlan | None, list[Client]]:
        """Decide who gets this tick's changes on the shared stream, and who in Updates of shared parts
        (returned, for plan_parts: when at least settings.parts_from clients may take them); mark them
        pending for everyone else. Reads the grid (on the loop, before anything else may change it)."""
        others: list[Client] = []
        self.refresh_planes(clients)
        share = self._plan_stream(clients, grid, bucket_ids, cell_slots, transforms, tick, server_time, now, others)
        parted = [c for c in others if self.takes_parts(c)]
        if len(parted) < self.settings.parts_from:
            parted = []
        for c in others:
            if not (parted and self.takes_parts(c)):
                c.mark(bucket_ids, cell_slots, len(grid.cells))
        return share, parted

    def _plan_stream(self, clients: list[Client], grid, bucket_ids: np.ndarray, cell_slots: np.ndarray,
                     transforms: np.ndarray, tick: int, server_time: float, now: float,
                     others: list[Client]) -> SharePlan | None:
        """The shared stream's members this tick (the rest are put in `others`)."""
        changed_rows = bool(len(bucket_ids) or len(cell_slots))
        self._note_changed(cell_slots)
        members, joiners = [], []
        flags = [(c, not c.shared and c.stream_codec and c.streaming and not c.outbox and not c.in_flight
                  and not self.behind(c) and not c.pending_anything()) for c in clients]
        # (the view test is the costly part: only where it decides, every such client's in one pass)
        sees = self._sees_all([c for c, may_join in flags if c.shared or may_join], grid, transforms, cell_slots)
        for c, may_join in flags:
            if not (c.shared or may_join):
                others.append(c)
                continue
            sees_all = sees[c.id]
            if c.shared:
                # (Updates still being encoded for it are the server's lag, not the client's: not counted)
                if sees_all and len(c.outbox) < self.settings.max_queued and not self.behind(c):
                    members.append(c)
                    continue
                c.shared = False
                self.counters.leaves_view += not sees_all
                self.counters.leaves_slow += sees_all
            elif (sees_all and (changed_rows or len(c.changed_transforms(transforms)))):  # a scene at rest sends nothing
                joiners.append(c)
                continue
            others.append(c)
        restart = bool(joiners) and (not members or now - self.last_restart >= self.settings.join_interval)
        if restart:
            self.last_restart = now
            self.counters.restarts += self.shared_messages > 0
            self.counters.joins += len(joiners)
            members += joiners
        else:
            others.extend(joiners)
        if not members:
            return None
        now_t = np.ascontiguousarray(transforms, np.float32)
        tids = changed_transform_ids(None if restart else self.sent_transforms, now_t)
        if not (restart or len(tids) or len(bucket_ids) or len(cell_slots)):
            return None
        self.sent_transforms = now_t.copy()
        for c in members:
            c.shared = True
            c.sent_transforms = self.sent_transforms
        self.shared_messages += 1
        return SharePlan(self.stream, tick, server_time, read_delta(grid, now_t, tids, bucket_ids, cell_slots), members,
                         restart)

    def _sees_all(self, clients: list[Client], grid, transforms: np.ndarray, cell_slots: np.ndarray) -> dict[int, bool]:
        """Per client id: whether its extended view holds every one of these cells (a client without planes
        sees all); the plane tests of all the clients in one pass."""
        out = {c.id: True for c in clients}
        if not len(cell_slots):
            return out
        culled = [(c, p) for c in clients if (p := self.planes(c)) is not None]
        if culled:
            inside = self._places_kept(grid, transforms).in_views(np.stack([p for _, p in culled]), self.settings.view,
                                                           np.asarray(cell_slots, np.int64))
            for (c, _), every in zip(culled, inside.all(axis=1)):
                out[c.id] = bool(every)
        return out

    def deliver(self, plan: SharePlan, data: bytes) -> list[tuple[Client, int]]:
        """Put the encoded Update in every member's outbox; returns (client, message index) per member.
        (Its sender hands it to the connection's session, ServerSession.shared, when it sends it: after
        any Update of its own that was read before this one.)"""
        self.counters.shared_updates += 1
        out = []
        for c in plan.members:
            c.outbox.append(data)
            c.wake.set()
            self.counters.shared_sends += 1
            out.append((c, c.next_seq()))
        return out
