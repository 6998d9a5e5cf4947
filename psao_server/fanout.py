"""Compress once, send to many: a tick's changes as one shared Update, or into each client's pending sets.

Every tick the service hands the grid's dirty buckets and cells here (`plan`). Clients on the shared
stream (protocol.session.SharedStream) whose extended view holds every dirty cell, and who are not
behind, get the tick's changes as one Update encoded once for all of them (`SharePlan.encode` in a
worker thread, then `deliver` puts the same bytes in each one's outbox). Every other client gets the
dirty sets in its pending sets, and its own sender streams what lies in its view on its own zstd stream
(protocol.codecs.OWN_STREAM_ZSTD: small, and a fast level), leaving cells outside its view pending.

A client joins the shared stream when it is in sync (its snapshot done, nothing pending; an Update of
its own that is still being encoded or sent goes out first, as it was read first) at a tick where the shared stream starts a new frame; the stream restarts for
waiting clients at most once per `join_interval` (a restart costs every member one message without
history). A member leaves it when the tick's dirty cells reach outside its view (culling) or when
`max_queued` shared messages wait in its outbox (a slow reader): from then on its own sender takes over,
after the queued messages.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from protocol.session import ServerConfig, SharedStream

from .clients import Client, read_delta
from .sendview import CellPlaces, client_planes
from .settings import FanoutSettings


@dataclass
class FanoutCounters:
    shared_updates: int = 0  # Updates encoded once for the shared stream
    shared_sends: int = 0  # their deliveries (one per member)
    restarts: int = 0  # frames the shared stream started after its first
    joins: int = 0
    leaves_view: int = 0  # members that left because the tick's cells reached outside their view
    leaves_slow: int = 0  # members that left with max_queued messages waiting


@dataclass
class SharePlan:
    """One tick's shared Update: its content (read when planned) and who receives it."""

    stream: SharedStream
    tick: int
    server_time: float
    delta: object  # GridDelta
    members: list[Client]

    def encode(self) -> bytes:
        return self.stream.update(self.tick, self.server_time, self.delta)


class Fanout:
    def __init__(self, config: ServerConfig, settings: FanoutSettings):
        self.settings = settings
        self.stream = SharedStream(config)
        self.sent_transforms: np.ndarray | None = None  # what the shared stream's members were last sent
        self.last_restart = -np.inf
        self.counters = FanoutCounters()
        self._places: CellPlaces | None = None  # every slot's place, kept across ticks
        self._placed_with: np.ndarray | None = None  # the transforms it holds
        self._stale = np.zeros(0, np.int64)  # slots changed since (the ticks' dirty cells)

    def planes(self, client: Client) -> np.ndarray | None:
        """The client's extended frustum, or None when it sees everything (no culling, no usable camera)."""
        if not self.settings.cull:
            return None
        return client.view_planes(lambda camera: client_planes(camera, self.settings.view))

    def places(self, grid, transforms: np.ndarray) -> CellPlaces:
        """Where every cell slot is, for all the clients: worked out in full when the pool changes size,
        else again only for the slots the ticks changed and the cells of instances that moved."""
        t = np.ascontiguousarray(transforms, np.float32)
        if (self._places is None or len(self._places.centres) != len(grid.cells)
                or self._placed_with.shape != t.shape):
            self._places = CellPlaces(grid, np.arange(len(grid.cells)), t)
        else:
            moved = np.flatnonzero(np.any(self._placed_with.reshape(len(t), -1) != t.reshape(len(t), -1), axis=1))
            rows = self._stale
            if len(moved):
                rows = np.union1d(rows, np.flatnonzero(np.isin(grid.cell_instance, moved)))
            if len(rows):
                self._places.refresh(grid, rows, t)
        self._placed_with = t.copy()
        self._stale = np.zeros(0, np.int64)
        return self._places

    def in_view(self, client: Client, grid, transforms: np.ndarray):
        """`slots -> bool` for take_pending, or None when the client sees every cell."""
        planes = self.planes(client)
        if planes is None:
            return None
        return lambda slots: self.places(grid, transforms).in_view(planes, self.settings.view, slots)

    def plan(self, clients: list[Client], grid, bucket_ids: np.ndarray, cell_slots: np.ndarray, transforms: np.ndarray,
             tick: int, server_time: float, now: float) -> SharePlan | None:
        """Decide who gets this tick's changes shared; mark them pending for everyone else. Reads the grid
        (on the loop, before anything else may change it)."""
        capacity = len(grid.cells)
        changed_rows = bool(len(bucket_ids) or len(cell_slots))
        self._stale = np.union1d(self._stale, cell_slots)  # their places may have changed
        members, joiners = [], []
        for c in clients:
            planes = self.planes(c)
            sees_all = True
            if planes is not None and len(cell_slots):
                sees_all = bool(self.places(grid, transforms).in_view(planes, self.settings.view, cell_slots).all())
            if c.shared:
                if sees_all and len(c.outbox) < self.settings.max_queued:
                    members.append(c)
                    continue
                c.shared = False
                self.counters.leaves_view += not sees_all
                self.counters.leaves_slow += sees_all
            elif (sees_all and c.stream_codec and c.streaming and not c.outbox and not c.pending_anything()
                  and (changed_rows or len(c.changed_transforms(transforms)))):  # a scene at rest sends nothing
                joiners.append(c)
                continue
            c.mark(bucket_ids, cell_slots, capacity)
        restart = bool(joiners) and (not members or now - self.last_restart >= self.settings.join_interval)
        if restart:
            self.stream.restart()
            self.last_restart = now
            self.counters.restarts += self.stream.messages > 0
            self.counters.joins += len(joiners)
            members += joiners
        else:
            for c in joiners:
                c.mark(bucket_ids, cell_slots, capacity)
        if not members:
            return None
        now_t = np.ascontiguousarray(transforms, np.float32)
        if restart or self.sent_transforms is None or self.sent_transforms.shape != now_t.shape:
            tids = np.arange(len(now_t), dtype=np.uint32)
        else:
            a = self.sent_transforms.reshape(len(now_t), -1).view(np.uint32)
            tids = np.flatnonzero(np.any(a != now_t.reshape(len(now_t), -1).view(np.uint32), axis=1)).astype(np.uint32)
        if not (restart or len(tids) or len(bucket_ids) or len(cell_slots)):
            return None
        self.sent_transforms = now_t.copy()
        for c in members:
            c.shared = True
            c.sent_transforms = self.sent_transforms
        return SharePlan(self.stream, tick, server_time, read_delta(grid, now_t, tids, bucket_ids, cell_slots), members)

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
