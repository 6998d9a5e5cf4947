"""Sparse hash grid of AO points, one virtual grid per mesh instance (paper section 3.2, DESIGN.md).

The arrays `instances`, `buckets` and `cells` are exactly what goes on the wire and into the client's
lookup tables (layout in src/psao/protocol/gridformat.py). Beside them the server keeps, per cell slot and point
index, what the client never needs: the exact local position (tracing from the quantised one could start
rays below the surface), the unquantised normal, a stable point id (it seeds the point's ray directions,
so unchanged geometry gives unchanged AO) and the instance the cell belongs to.

Every edit marks the cells and buckets it touches dirty; `take_dirty()` hands them to the streaming layer.
All edits are vectorised over arrays of points; the per-cell bookkeeping (allocated points first, used
bucket entries first, sorted by key) is restored by `_compact_cells` / `_compact_buckets` on the touched rows only.
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass

import numpy as np

from psao.protocol import gridformat as gf
from psao.protocol import pointword as pw
from psao.server.errors import GridError
from psao.server.settings import GridSettings

NO_POINT = -1


@dataclass
class PointTable:
    """All allocated points, flattened (server side)."""

    slot: np.ndarray  # (P,) uint32
    index: np.ndarray  # (P,) int64, 0..6 within the cell
    instance: np.ndarray  # (P,) int64
    point_id: np.ndarray  # (P,) int64, stable id (seeds ray directions)
    local_pos: np.ndarray  # (P, 3) float64, exact
    local_normal: np.ndarray  # (P, 3) float32, exact
    ao_code: np.ndarray  # (P,) uint32

    def __len__(self) -> int:
        return len(self.slot)


@dataclass
class InsertStats:
    inserted: int = 0
    dropped_cell_full: int = 0  # the key's KEY_CELLS cells are full
    dropped_bucket_full: int = 0
    dropped_outside: int = 0

    @property
    def dropped(self) -> int:
        return self.dropped_cell_full + self.dropped_bucket_full + self.dropped_outside


def instance_record(lo: np.ndarray, hi: np.ndarray, poisson_r: float, n_cells_hint: int, flags: int,
                    settings: GridSettings, margin_cells: int = 1) -> np.ndarray:
    """Grid geometry of one instance from its local point bounds (lo, hi) and Poisson radius.

    The grid is padded by `margin_cells` on every side. If the dimensions would exceed MAX_DIM per axis the cell size grows (and with it the chance of
    cell overflow, reported by the build statistics) rather than failing.
    """
    r = settings.radius_factor * poisson_r
    s = settings.cell_factor * r
    extent = np.maximum(np.asarray(hi, np.float64) - np.asarray(lo, np.float64), 0.0)
    need = float(extent.max()) / (gf.MAX_DIM - 2 * margin_cells - 1)
    if s < need:
        s = need
        r = s / settings.cell_factor
    origin = np.asarray(lo, np.float64) - margin_cells * s
    dims = np.floor(extent / s).astype(np.int64) + 1 + 2 * margin_cells
    rec = np.zeros((), dtype=gf.INSTANCE_DTYPE)
    rec["origin"] = origin.astype(np.float32)
    rec["cell_size"] = np.float32(s)
    rec["dims"] = dims.astype(np.uint32)
    rec["radius"] = np.float32(r)
    rec["flags"] = flags
    rec["bucket_count"] = gf.next_pow2(math.ceil(settings.bucket_factor * max(n_cells_hint, 1) / gf.BUCKET_ENTRIES))
    return rec


class Grid:
    def __init__(self, instances: np.ndarray, capacity: int):
        self.instances = instances
        n_buckets = int(instances["bucket_count"].sum()) if len(instances) else 0
        self.buckets = np.full((n_buckets, gf.BUCKET_ENTRIES, 2), gf.EMPTY, dtype=np.uint32)
        self.cells = np.tile(gf.FREE_CELL, (capacity, 1))
        self.dirty_cells = np.zeros(capacity, dtype=bool)
        self.dirty_buckets = np.zeros(n_buckets, dtype=bool)
        # Server-side companions of `cells`.
        self.point_local = np.zeros((capacity, gf.POINTS_PER_CELL, 3), dtype=np.float64)
        self.point_normal = np.zeros((capacity, gf.POINTS_PER_CELL, 3), dtype=np.float32)
        self.point_id = np.full((capacity, gf.POINTS_PER_CELL), NO_POINT, dtype=np.int64)
        self.cell_instance = np.full(capacity, -1, dtype=np.int64)
        self.free_slots = list(range(capacity - 1, -1, -1))  # stack: pop() gives the lowest slot
        self.stats = InsertStats()

    # ------------------------------------------------------------------ construction
    @classmethod
    def build(cls, instance_points: list[tuple], settings: GridSettings | None = None,
              point_ids: list[np.ndarray] | None = None) -> "Grid":
        """instance_points: per instance (local_pos (P,3), local_normal (P,3), poisson_radius, flags[, back (P,)
        bool: back-side points of a double-sided instance])."""
        settings = settings or GridSettings()
        records = []
        offset = 0
        total_cells = 0
        for pos, _nrm, rp, flags, *rest in instance_points:
            pos = np.asarray(pos, np.float64)
            if len(pos) == 0:
                lo = hi = np.zeros(3)
            else:
                lo, hi = pos.min(axis=0), pos.max(axis=0)
            rec = instance_record(lo, hi, rp, 1, flags, settings)
            cells_hint = _count_cells(pos, rec, rest[0] if rest else None)
            rec = instance_record(lo, hi, rp, cells_hint, flags, settings)
            rec["bucket_offset"] = offset
            offset += int(rec["bucket_count"])
            total_cells += cells_hint
            records.append(rec)
        instances = np.array(records, dtype=gf.INSTANCE_DTYPE) if records else np.zeros(0, gf.INSTANCE_DTYPE)
        capacity = max(64, int(total_cells * (1.0 + settings.pool_headroom)))
        grid = cls(instances, capacity)
        next_id = 0
        for i, (pos, nrm, _rp, _flags, *rest) in enumerate(instance_points):
            ids = point_ids[i] if point_ids is not None else np.arange(next_id, next_id + len(pos))
            next_id += len(pos)
            grid.insert_points(i, pos, nrm, np.full(len(pos), 255, np.uint32), ids, back=rest[0] if rest else None)
        return grid

    @property
    def capacity(self) -> int:
        return len(self.cells)

    # ------------------------------------------------------------------ queries
    def allocated_cells(self) -> np.ndarray:
        return np.flatnonzero(self.cells[:, gf.KEY_WORD] != gf.EMPTY).astype(np.uint32)

    def allocated_buckets(self) -> np.ndarray:
        return np.flatnonzero(self.buckets[:, 0, 0] != gf.EMPTY).astype(np.uint32)

    def n_points(self) -> int:
        return int((self.point_id != NO_POINT).sum())

    def point_table(self) -> PointTable:
        slot, idx = np.nonzero(self.point_id != NO_POINT)
        return PointTable(
            slot=slot.astype(np.uint32),
            index=idx.astype(np.int64),
            instance=self.cell_instance[slot],
            point_id=self.point_id[slot, idx],
            local_pos=self.point_local[slot, idx],
            local_normal=self.point_normal[slot, idx],
            ao_code=self.cells[slot, idx] & np.uint32(0xFF),
        )

    def take_dirty(self) -> tuple[np.ndarray, np.ndarray]:
        b = np.flatnonzero(self.dirty_buckets).astype(np.uint32)
        c = np.flatnonzero(self.dirty_cells).astype(np.uint32)
        self.dirty_buckets[:] = False
        self.dirty_cells[:] = False
        return b, c

    # ------------------------------------------------------------------ edits
    def cell_of(self, inst: int, local_pos: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Integer cell coordinates (P,3) of local positions and whether each is inside the grid."""
        rec = self.instances[inst]
        g = gf.grid_coords(local_pos, rec["origin"], rec["cell_size"])
        c = np.floor(g).astype(np.int64)
        inside = np.all((c >= 0) & (c < rec["dims"].astype(np.int64)), axis=1) & np.all(np.isfinite(g), axis=1)
        return np.where(inside[:, None], c, 0), inside

    def insert_points(self, inst: int, local_pos, normals, ao_code, point_ids=None, back=None) -> np.ndarray:
        """Insert points into instance `inst` (`back`: bool mask of back-side points, which go to the
        BACK_BIT cells). A cell key with more than 7 points gets more cells of the same key in its bucket,
        up to KEY_CELLS. Returns a bool mask of the points kept; points outside the grid, whose bucket has
        no free entry or whose key's cells are all full are dropped and counted in `stats`."""
        local_pos = np.asarray(local_pos, np.float64).reshape(-1, 3)
        normals = np.asarray(normals, np.float32).reshape(-1, 3)
        ao_code = np.broadcast_to(np.asarray(ao_code, np.uint32), (len(local_pos),))
        point_ids = np.arange(len(local_pos), dtype=np.int64) if point_ids is None else np.asarray(point_ids, np.int64)
        kept = np.zeros(len(local_pos), dtype=bool)
        if len(local_pos) == 0:
            return kept
        rec = self.instances[inst]
        cell, inside = self.cell_of(inst, local_pos)
        self.stats.dropped_outside += int((~inside).sum())
        keys = gf.cell_key(cell[:, 0], cell[:, 1], cell[:, 2], rec["dims"])
        if back is not None:
            keys = np.where(np.asarray(back, bool), keys | gf.BACK_BIT, keys).astype(np.uint32)
        order = np.flatnonzero(inside)
        order = order[np.argsort(keys[order], kind="stable")]
        # Rounds: each key fills one cell with room (an existing one or a new entry of the same key in its
        # bucket); what does not fit goes on to the next round. A point is dropped only when its bucket
        # has no free entry left.
        while len(order):
            ukeys, first, counts = np.unique(keys[order], return_index=True, return_counts=True)
            slots, used = self._cells_with_room(inst, ukeys, cell[order[first]])
            cell_of_point = np.repeat(np.arange(len(ukeys)), counts)
            rank = np.arange(len(order)) - first[cell_of_point]
            ok_cell = slots[cell_of_point] >= 0
            self.stats.dropped_bucket_full += int((slots[cell_of_point] == -1).sum())
            self.stats.dropped_cell_full += int((slots[cell_of_point] == -2).sum())
            idx = used[cell_of_point] + rank
            fits = ok_cell & (idx < gf.POINTS_PER_CELL)
            pts, pslot, idx = order[fits], slots[cell_of_point[fits]], idx[fits]
            self._write_points(pslot, idx, rec, cell[pts], local_pos[pts], normals[pts], ao_code[pts], point_ids[pts])
            self.dirty_cells[pslot] = True
            kept[pts] = True
            self.stats.inserted += len(pts)
            order = order[ok_cell & ~fits]
        return kept

    def set_ao(self, slots, idx, ao_code) -> np.ndarray:
        """Set the AO byte of points; marks only cells whose words really change. Returns the changed mask."""
        slots = np.asarray(slots, np.int64)
        idx = np.asarray(idx, np.int64)
        old = self.cells[slots, idx]
        new = pw.with_ao(old, ao_code)
        changed = new != old
        self.cells[slots[changed], idx[changed]] = new[changed]
        self.dirty_cells[slots[changed]] = True
        return changed

    def remove_points(self, slots, idx) -> None:
        slots = np.asarray(slots, np.int64)
        idx = np.asarray(idx, np.int64)
        self.cells[slots, idx] = 0
        self.point_id[slots, idx] = NO_POINT
        touched = np.unique(slots)
        self.dirty_cells[touched] = True
        self._compact_cells(touched)
        empty = touched[self.point_id[touched, 0] == NO_POINT]
        if len(empty):
            self._free_cells(empty)

    def move_points(self, slots, idx, new_local_pos, new_normals) -> np.ndarray:
        """Re-quantise points at new positions/normals, keeping AO and id. Points that stay in their cell
        are rewritten in place; points that leave it are removed and re-inserted. Returns kept mask."""
        slots = np.asarray(slots, np.int64)
        idx = np.asarray(idx, np.int64)
        new_local_pos = np.asarray(new_local_pos, np.float64).reshape(-1, 3)
        new_normals = np.asarray(new_normals, np.float32).reshape(-1, 3)
        kept = np.ones(len(slots), dtype=bool)
        if len(slots) == 0:
            return kept
        ao = self.cells[slots, idx] & np.uint32(0xFF)
        ids = self.point_id[slots, idx].copy()
        insts = self.cell_instance[slots]
        side = self.cells[slots, gf.KEY_WORD] & gf.BACK_BIT
        stay = np.zeros(len(slots), dtype=bool)
        for inst in np.unique(insts).tolist():
            sel = np.flatnonzero(insts == inst)
            rec = self.instances[inst]
            cell, inside = self.cell_of(inst, new_local_pos[sel])
            keys = gf.cell_key(cell[:, 0], cell[:, 1], cell[:, 2], rec["dims"]) | side[sel]
            same = inside & (keys == self.cells[slots[sel], gf.KEY_WORD])
            s_sel = sel[same]
            frac = gf.grid_coords(new_local_pos[s_sel], rec["origin"], rec["cell_size"]) - cell[same]
            words = pw.pack_point(pw.quantise_cell_fraction(frac), pw.oct_encode(new_normals[s_sel]), ao[s_sel])
            changed = words != self.cells[slots[s_sel], idx[s_sel]]
            _scatter(self.cells, slots[s_sel], idx[s_sel], words)
            self.dirty_cells[slots[s_sel][changed]] = True
            _scatter(self.point_local, slots[s_sel], idx[s_sel], new_local_pos[s_sel])
            _scatter(self.point_normal, slots[s_sel], idx[s_sel], new_normals[s_sel])
            stay[s_sel] = True
        leave = np.flatnonzero(~stay)
        if len(leave):
            self.remove_points(slots[leave], idx[leave])
            for inst in np.unique(insts[leave]).tolist():
                sel = leave[insts[leave] == inst]
                kept[sel] = self.insert_points(inst, new_local_pos[sel], new_normals[sel], ao[sel], ids[sel],
                                               back=side[sel] != 0)
        return kept

    # ------------------------------------------------------------------ internals
    def _write_points(self, pslot, idx, rec, cell, local_pos, normals, ao_code, ids) -> None:
        """Pack points (instance-local positions in `cell`, unit normals, AO codes) and store them with their
        ids at (cell slot, entry)."""
        frac = gf.grid_coords(local_pos, rec["origin"], rec["cell_size"]) - cell
        _scatter(self.cells, pslot, idx, pw.pack_point(pw.quantise_cell_fraction(frac), pw.oct_encode(normals), ao_code))
        _scatter(self.point_local, pslot, idx, local_pos)
        _scatter(self.point_normal, pslot, idx, normals)
        _scatter(self.point_id, pslot, idx, ids)

    def _buckets_of(self, inst: int, cell_xyz: np.ndarray) -> np.ndarray:
        rec = self.instances[inst]
        c = np.asarray(cell_xyz).reshape(-1, 3)
        return gf.bucket_index(c[:, 0], c[:, 1], c[:, 2], rec["dims"], int(rec["bucket_offset"]), int(rec["bucket_count"])).astype(np.int64)

    def _cells_with_room(self, inst: int, keys: np.ndarray, cell_xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """For each (unique) key: the slot of its first cell with room and the points it holds, allocating
        a new cell of that key in the bucket where all its cells are full; slot -1 where the bucket is full,
        -2 where the key already owns KEY_CELLS full cells."""
        b = self._buckets_of(inst, cell_xyz)
        entries = self.buckets[b]  # (U, 8, 2) copy
        live = entries[:, :, 0] != gf.EMPTY
        held = np.zeros(entries.shape[:2], np.int64)
        held[live] = (self.point_id[entries[:, :, 1][live].astype(np.int64)] != NO_POINT).sum(axis=1)
        match = (entries[:, :, 0] == keys[:, None]) & (held < gf.POINTS_PER_CELL)
        found = match.any(axis=1)
        e = match.argmax(axis=1)
        rows = np.arange(len(b))
        slots = np.where(found, entries[rows, e, 1].astype(np.int64), -1)
        used = np.where(found, held[rows, e], 0)
        # A key that already owns KEY_CELLS full cells takes no more: its bucket stays readable in one pass.
        owned = (entries[:, :, 0] == keys[:, None]).sum(axis=1)
        capped = ~found & (owned >= gf.KEY_CELLS)
        new = np.flatnonzero(~found & ~capped)
        slots[capped] = -2
        if len(new) == 0:
            return slots, used
        # New cells sharing a bucket take consecutive free entries after the used ones.
        nb = b[new]
        order = np.argsort(nb, kind="stable")
        new, nb = new[order], nb[order]
        ub, ufirst, ucount = np.unique(nb, return_index=True, return_counts=True)
        rank = np.arange(len(new)) - np.repeat(ufirst, ucount)
        entry = (self.buckets[nb, :, 0] != gf.EMPTY).sum(axis=1) + rank
        fits = entry < gf.BUCKET_ENTRIES
        new, nb, entry = new[fits], nb[fits], entry[fits]
        fresh = self._allocate_slots(len(new))
        self.buckets[nb, entry, 0] = keys[new]
        self.buckets[nb, entry, 1] = fresh
        self.cells[fresh] = gf.FREE_CELL
        self.cells[fresh, gf.KEY_WORD] = keys[new]
        self.cell_instance[fresh] = inst
        self.dirty_buckets[nb] = True
        self.dirty_cells[fresh] = True
        self._compact_buckets(np.unique(nb))  # a key's new cell goes next to its others
        slots[new] = fresh
        return slots, used

    def _allocate_slots(self, k: int) -> np.ndarray:
        """k free slots, lowest first. Freed slots are taken before the pool doubles, so the pool stays
        within twice the most cells ever allocated at once (plus the build's headroom). It never shrinks:
        renumbering the slots would resend every cell to every client."""
        while len(self.free_slots) < k:
            self._grow(self.capacity * 2)
        taken = self.free_slots[len(self.free_slots) - k:][::-1]
        del self.free_slots[len(self.free_slots) - k:]
        return np.asarray(taken, dtype=np.int64)

    def _grow(self, capacity: int) -> None:
        old = self.capacity
        for name, fill in (("cells", gf.FREE_CELL), ("point_local", 0), ("point_normal", 0), ("point_id", NO_POINT),
                           ("cell_instance", -1), ("dirty_cells", False)):
            arr = getattr(self, name)
            new = np.empty((capacity,) + arr.shape[1:], arr.dtype)
            new[:old] = arr
            new[old:] = fill
            setattr(self, name, new)
        self.free_slots = list(range(capacity - 1, old - 1, -1)) + self.free_slots

    def _free_cells(self, slots: np.ndarray) -> None:
        """Free empty cells: clear their bucket entries (re-compacting those buckets) and return the slots."""
        for inst in np.unique(self.cell_instance[slots]).tolist():
            sel = slots[self.cell_instance[slots] == inst]
            keys = self.cells[sel, gf.KEY_WORD]
            b = self._buckets_of(inst, gf.key_to_cell(keys, self.instances[inst]["dims"]))
            # a key may own several cells (overflow): clear the entry of this very slot
            hit = (self.buckets[b, :, 0] == keys[:, None]) & (self.buckets[b, :, 1] == sel[:, None].astype(np.uint32))
            rows, cols = np.nonzero(hit)
            self.buckets[b[rows], cols] = gf.EMPTY
            ub = np.unique(b)
            self._compact_buckets(ub)
            self.dirty_buckets[ub] = True
        self.cells[slots] = gf.FREE_CELL
        self.cell_instance[slots] = -1
        self.dirty_cells[slots] = True
        self.free_slots.extend(slots.tolist())

    def _compact_cells(self, slots: np.ndarray) -> None:
        """Allocated points first within each cell (stable), as the paper's compaction does."""
        if len(slots) == 0:
            return
        empty = self.point_id[slots] == NO_POINT
        order = np.argsort(empty, axis=1, kind="stable")
        for name in ("point_local", "point_normal", "point_id"):
            arr = getattr(self, name)
            arr[slots] = np.take_along_axis(arr[slots], order[..., None] if arr.ndim == 3 else order, axis=1)
        pts = self.cells[slots, : gf.POINTS_PER_CELL]
        self.cells[slots, : gf.POINTS_PER_CELL] = np.take_along_axis(pts, order, axis=1)

    def _compact_buckets(self, rows: np.ndarray) -> None:
        """Entries sorted by key (stable), which puts the used ones first (EMPTY is the largest key) and a
        key's cells next to each other, as the lookup reads them."""
        order = np.argsort(self.buckets[rows, :, 0], axis=1, kind="stable")
        self.buckets[rows] = np.take_along_axis(self.buckets[rows], order[..., None], axis=1)

    # ------------------------------------------------------------------ persistence
    def save(self, path, scene_hash: str = "", meta: dict | None = None) -> None:
        """npz with the wire arrays (instances, buckets, cells), the server side and metadata.
        Keys read by the client without importing the server: instances, buckets, cells, scene_hash, meta_json."""
        np.savez_compressed(
            path,
            instances=self.instances, buckets=self.buckets, cells=self.cells,
            point_local=self.point_local, point_normal=self.point_normal, point_id=self.point_id,
            cell_instance=self.cell_instance, scene_hash=np.array(scene_hash),
            meta_json=np.array(json.dumps(meta or {})),
        )

    @classmethod
    def load(cls, path) -> tuple["Grid", str, dict]:
        try:
            with np.load(path, allow_pickle=False) as z:
                grid = cls.__new__(cls)
                grid.instances = z["instances"]
                grid.buckets = z["buckets"]
                grid.cells = z["cells"]
                grid.point_local = z["point_local"]
                grid.point_normal = z["point_normal"]
                grid.point_id = z["point_id"]
                grid.cell_instance = z["cell_instance"]
                scene_hash = str(z["scene_hash"])
                meta = json.loads(str(z["meta_json"]))
        except (OSError, KeyError, ValueError) as exc:
            raise GridError(f"{path}: not a PSAO grid file ({exc})") from None
        if grid.instances.dtype != gf.INSTANCE_DTYPE or grid.cells.ndim != 2 or grid.cells.shape[1] != gf.CELL_WORDS:
            raise GridError(f"{path}: grid arrays have the wrong layout")
        grid.dirty_cells = np.zeros(len(grid.cells), dtype=bool)
        grid.dirty_buckets = np.zeros(len(grid.buckets), dtype=bool)
        grid.free_slots = np.flatnonzero(grid.cells[:, gf.KEY_WORD] == gf.EMPTY)[::-1].tolist()
        grid._compact_buckets(np.arange(len(grid.buckets)))  # files written before buckets were kept sorted
        grid.stats = InsertStats()
        return grid, scene_hash, meta


def _scatter(arr: np.ndarray, slots: np.ndarray, idx: np.ndarray, values: np.ndarray) -> None:
    """arr[slots, idx] = values, through a flat view of the first two axes where arr is C-contiguous (numpy
    scatters rows of one flat index several times faster than pairs of indices)."""
    if arr.flags.c_contiguous:
        arr.reshape((-1,) + arr.shape[2:])[slots * arr.shape[1] + idx] = values
    else:
        arr[slots, idx] = values


def _count_cells(pos: np.ndarray, rec: np.ndarray, back=None) -> int:
    if len(pos) == 0:
        return 0
    c = np.floor(gf.grid_coords(pos, rec["origin"], rec["cell_size"])).astype(np.int64)
    keys = gf.cell_key(c[:, 0], c[:, 1], c[:, 2], rec["dims"]).astype(np.int64)
    if back is not None:
        keys = keys + np.asarray(back, bool) * (1 << 30)
    _, counts = np.unique(keys, return_counts=True)
    return int((-(-counts // gf.POINTS_PER_CELL)).sum())  # a key with more than 7 points takes more cells
