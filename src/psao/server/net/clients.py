"""Per-connection streaming state: pending dirty sets, the snapshot plan, what each client was sent.

DESIGN.md, server tick step 6: a tick's dirty buckets and cells go to each client either as its share
of an Update encoded once for many (psao.server.net.fanout: the client's `outbox`) or into its pending sets;
a send of its own drains the pending buckets and the pending cells inside the client's extended view (at
most one message's worth) and reads the grid's content at that moment; cells outside the view stay
pending until they enter it. Nothing is dropped and nothing is queued twice: a client that is slow to
read simply has more pending the next time, and receives the latest content of everything it missed.
"""
from __future__ import annotations

import asyncio
import itertools
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from psao.protocol.gridformat import EMPTY, FREE_CELL
from psao.protocol.limits import Limits
from psao.protocol.updates import GridDelta
from psao.server.net.rate import RateEstimate


def _read_only(a: np.ndarray) -> np.ndarray:
    """A view of `a` that cannot be written through."""
    v = a.view()
    v.flags.writeable = False
    return v


def changed_buckets(buckets: np.ndarray) -> np.ndarray:
    """Buckets that differ from an empty one (a fresh mirror starts with all buckets empty)."""
    return np.flatnonzero(np.any(buckets != EMPTY, axis=(1, 2))).astype(np.uint32)


def changed_cells(cells: np.ndarray) -> np.ndarray:
    """Cells that differ from FREE_CELL (a fresh mirror starts with every slot free)."""
    return np.flatnonzero(np.any(cells != FREE_CELL, axis=1)).astype(np.uint32)


def read_delta(grid, transforms: np.ndarray, transform_ids, bucket_ids, cell_slots) -> GridDelta:
    """The grid's current content at these indices (copies)."""
    bucket_ids = np.asarray(bucket_ids, np.uint32)
    cell_slots = np.asarray(cell_slots, np.uint32)
    transform_ids = np.asarray(transform_ids, np.uint32)
    return GridDelta(
        cell_capacity=len(grid.cells),
        transform_ids=transform_ids,
        transforms=transforms[transform_ids],
        bucket_ids=bucket_ids,
        buckets=grid.buckets[bucket_ids],
        cell_slots=cell_slots,
        cells=grid.cells[cell_slots],
    )


def changed_transform_ids(sent: np.ndarray | None, transforms: np.ndarray) -> np.ndarray:
    """Instances whose float32 transform differs bitwise from `sent` (every one where nothing, or another
    number of them, was sent), as uint32 ids."""
    if sent is None or sent.shape != transforms.shape:
        return np.arange(len(transforms), dtype=np.uint32)
    a = sent.reshape(len(transforms), -1).view(np.uint32)
    b = np.ascontiguousarray(transforms, np.float32).reshape(len(transforms), -1).view(np.uint32)
    return np.flatnonzero(np.any(a != b, axis=1)).astype(np.uint32)


@dataclass
class SnapshotPlan:
    """The full-state chunks for a new client: what was allocated when it joined, in sorted chunks.
    Each chunk reads the latest content when it is sent; changes made meanwhile are also pending."""

    bucket_chunks: list[np.ndarray]
    cell_chunks: list[np.ndarray]

    @classmethod
    def of(cls, grid, limits: Limits, cells_per_chunk: int) -> "SnapshotPlan":
        b, c = changed_buckets(grid.buckets), changed_cells(grid.cells)
        per_cells = max(1, min(cells_per_chunk, limits.max_cells_per_message))
        per_buckets = max(1, min(cells_per_chunk, limits.max_buckets_per_message))
        n = max(1, -(-len(c) // per_cells), -(-len(b) // per_buckets))
        return cls(np.array_split(b, n), np.array_split(c, n))

    def __len__(self) -> int:
        return len(self.cell_chunks)


class PendingSet:
    """Indices (cell slots or buckets) pending for one client: a mask to look them up, their count, and
    the indices set since they were last listed, so that testing, counting and listing cost in proportion
    to what is pending rather than to the grid's capacity. Indices given to set/unset are unique."""

    def __init__(self, size: int):
        self.mask = np.zeros(size, dtype=bool)
        self.count = 0
        self._added: list[np.ndarray] | None = []  # holds every set index (and some unset since); None: lost track
        self._added_rows = 0

    def __len__(self) -> int:
        return self.count

    def grow(self, size: int) -> None:
        """Follow the grid's capacity, which only grows: the new indices are not pending."""
        if size > len(self.mask):
            self.mask = np.concatenate([self.mask, np.zeros(size - len(self.mask), dtype=bool)])

    def set(self, idx: np.ndarray) -> None:
        idx = np.asarray(idx, np.int64)
        if not len(idx):
            return
        new = idx[~self.mask[idx]]
        self.mask[new] = True
        self.count += len(new)
        if self._added is not None:
            self._added.append(new)
            self._added_rows += len(new)
            if self._added_rows > len(self.mask) // 8:  # listing by a scan of the mask is as cheap by now
                self._added = None

    def unset(self, idx: np.ndarray) -> None:
        idx = np.asarray(idx, np.int64)
        if not (len(idx) and self.count):
            return
        was = int(np.count_nonzero(self.mask[idx]))
        if was:
            self.mask[idx] = False
            self.count -= was

    def indices(self) -> np.ndarray:
        """The pending indices, ascending."""
        if not self.count:
            out = np.zeros(0, np.int64)
        elif self._added is None:
            out = np.flatnonzero(self.mask)
        else:
            rows = self._added[0] if len(self._added) == 1 else np.concatenate(self._added)
            out = np.sort(rows[self.mask[rows]])
            if len(self._added) > 1:  # an index unset and set again is listed twice
                out = out[np.concatenate(([True], out[1:] != out[:-1]))]
        self._added, self._added_rows = [out], len(out)
        return out


_ids = itertools.count(1)


@dataclass
class Client:
    """One connection's streaming state (the session object holds its protocol state)."""

    peer: str
    n_buckets: int
    capacity: int
    id: int = field(default_factory=lambda: next(_ids))
    buckets_pending: PendingSet = None
    cells_pending: PendingSet = None
    sent_transforms: np.ndarray | None = None  # last transforms sent; None before the first message
    camera: tuple[np.ndarray, np.ndarray] | None = None  # (view, projection) last received
    wake: asyncio.Event = field(default_factory=asyncio.Event)
    stream_codec: bool = True  # the connection's codec is zstd-stream: it may take a shared stream
    streaming: bool = False  # the snapshot has been sent: Updates may follow
    shared: bool = False  # on the shared stream: its Updates come through `outbox` only
    busy: bool = False  # its sender is building or sending an Update of its own
    takes_parts: bool = False  # its client decodes Updates made of shared parts (ZSTD)
    on_parts: bool = False  # its Updates come as shared parts (fanout.plan_parts), through `outbox` only
    caught_up_with: object = None  # the view planes its pending cells were last looked at for (plan_parts)
    caught_up_at: int = -(1 << 62)  # the tick they were last looked at (plan_parts)
    outbox: deque = field(default_factory=deque)  # shared Update bytes waiting to be sent, in order
    in_flight: int = 0  # shared Updates planned for it and still being encoded (they reach `outbox` in order)
    assigned: int = 0  # messages made for this connection so far (Welcome is message 0)
    messages_sent: int = 0
    # messages its client has been shown to have read: its websocket answered a ping sent after them (the
    # answer comes back behind everything sent before the ping, in whatever buffers that waits)
    messages_read: int = 0
    probe: object = None  # the ping whose answer is awaited (service.Service._probe), None when none is
    updates_sent: int = 0
    bytes_sent: int = 0
    paced_until: float = 0.0  # time.perf_counter() when what was sent has drained at its rate cap
    bytes_per_cell: float = 0.0  # bytes its own Updates took per cell (running mean; 0 before the first)
    acked_bytes: int = 0  # bytes sent before the last answered ping: its client has read them
    acked_at: float = 0.0  # time.perf_counter() of that answer
    acked_mbit: float = 0.0  # Mbit/s its client was shown to read, between answers at least a second apart
    rate: RateEstimate = field(default_factory=RateEstimate)  # its throughput as estimated (psao.server.net.rate)
    _planes_of: tuple | None = None  # the camera the cached planes belong to
    _planes: np.ndarray | None = None

    def __post_init__(self):
        self.buckets_pending = PendingSet(self.n_buckets)
        self.cells_pending = PendingSet(self.capacity)

    @property
    def pending_buckets(self) -> np.ndarray:
        """Bool per bucket: pending (read only; changes go through buckets_pending)."""
        return _read_only(self.buckets_pending.mask)

    @property
    def pending_cells(self) -> np.ndarray:
        """Bool per cell slot: pending (read only; changes go through cells_pending)."""
        return _read_only(self.cells_pending.mask)

    def _fit(self, capacity: int) -> None:
        """Follow the grid's capacity, which only grows: the new slots have nothing pending."""
        self.cells_pending.grow(capacity)

    def mark(self, bucket_ids: np.ndarray, cell_slots: np.ndarray, capacity: int) -> None:
        """Pending for its own sender, which takes over from shared parts."""
        self._fit(capacity)
        self.on_parts = False
        self.caught_up_with = None
        self.buckets_pending.set(bucket_ids)
        self.cells_pending.set(cell_slots)
        self.wake.set()

    def clear(self, bucket_ids: np.ndarray, cell_slots: np.ndarray, capacity: int) -> None:
        """What is about to be sent (read now, so the latest content) is no longer pending."""
        self._fit(capacity)
        self.buckets_pending.unset(bucket_ids)
        self.cells_pending.unset(cell_slots)

    def take_pending(self, limits: Limits, capacity: int,
                     in_view: Callable[[np.ndarray], np.ndarray] | None = None,
                     distance: Callable[[np.ndarray], np.ndarray] | None = None,
                     max_cells: int | None = None) -> tuple[np.ndarray, np.ndarray, bool]:
        """Drain at most one message's worth: (bucket ids, cell slots in ascending order, everything
        drained). `in_view` (cell slots -> bool per slot) keeps the cells outside the client's view pending;
        of more cells than a message takes (`max_cells`, at most the limits'), the ones of least `distance`
        (cell slots -> a number per slot) go first."""
        self._fit(capacity)
        b = self.buckets_pending.indices()
        c = self.cells_pending.indices()
        if in_view is not None and len(c):
            c = c[in_view(c)]
        most = limits.max_cells_per_message if max_cells is None else max(1, min(max_cells, limits.max_cells_per_message))
        if distance is not None and len(c) > most:
            c = np.sort(c[np.argpartition(distance(c), most - 1)[:most]])
        b, c = b[: limits.max_buckets_per_message], c[:most]
        self.buckets_pending.unset(b)
        self.cells_pending.unset(c)
        return b.astype(np.uint32), c.astype(np.uint32), not self.pending_anything()

    def changed_transforms(self, transforms: np.ndarray) -> np.ndarray:
        """Instances whose transform differs (bitwise) from what this client was last sent."""
        return changed_transform_ids(self.sent_transforms, transforms)

    def read_transforms(self, transforms: np.ndarray) -> np.ndarray:
        """Ids of the transforms to put in the message being built; from now on they count as sent."""
        ids = self.changed_transforms(transforms)
        self.sent_transforms = np.array(transforms, dtype=np.float32, copy=True)
        return ids

    def pending_anything(self) -> bool:
        return bool(self.buckets_pending.count or self.cells_pending.count)

    def planes_stale(self) -> bool:
        """Whether its camera changed since view_planes last worked out its frustum."""
        return self._planes_of is not self.camera

    def view_planes(self, make: Callable[[tuple], np.ndarray | None]) -> np.ndarray | None:
        """The extended frustum of the last camera (`make(camera)`), kept until the camera changes."""
        if self._planes_of is not self.camera:
            self.keep_planes(make(self.camera))
        return self._planes

    def keep_planes(self, planes: np.ndarray | None) -> None:
        """Keep `planes` as the extended frustum of its current camera (worked out for many clients at once)."""
        self._planes_of, self._planes = self.camera, planes

    def unread(self) -> int:
        """Messages sent that its client has not yet been shown to have read."""
        return self.messages_sent - self.messages_read

    def next_seq(self) -> int:
        """The index of the message being made for this connection."""
        self.assigned += 1
        return self.assigned - 1

    def sent(self, data: bytes) -> None:
        self.messages_sent += 1
        self.bytes_sent += len(data)


class Registry:
    """All connected clients that have passed the handshake."""

    def __init__(self):
        self.clients: dict[int, Client] = {}

    def add(self, client: Client) -> None:
        self.clients[client.id] = client

    def remove(self, client: Client) -> None:
        self.clients.pop(client.id, None)

    def wake_all(self) -> None:
        for c in self.clients.values():
            c.wake.set()

    def __len__(self) -> int:
        return len(self.clients)

    def __iter__(self):
        return iter(list(self.clients.values()))
