"""Refinement of static points on a Dask cluster or on this machine's bake tracer, beside the server tick.

`psao serve --progressive [--cluster ...]` bakes with a few rays per point and refines to `--rays` while
serving. The tick refines in its own time budget, one slice of each point's target ray set per round; a
`ClusterRefiner` adds the cluster's workers: it takes batches of the static points that hold only the
first grid's estimate (RefineQueue.first_grid; the tick leaves those to it and keeps the points reset by a
change, which it reaches sooner), those in a client's view first, traces each point's whole target ray set (the bake's rays and seed) in one go on the cluster
(DaskTracer.start, so the tick never waits for it) and, when a batch comes back, adds it to the points'
history as all their slices at once (RefineQueue.add): a refined point then holds exactly the AO of a full
local trace, as one the tick refined does. The tick writes the codes into the grid with its own.

    refiner = ClusterRefiner(dask_tracer, RefineSettings())
    tick = ServerTick(bake, settings, close_bake_tracer=False, refiner=refiner)

While a batch is out its points are left out of the tick's own picks (`busy`), so no ray is traced twice.
A point whose neighbourhood changes meanwhile (a mover came near: the tick resets its history) is
`forget`-ed: its batch's answer for it is dropped when it comes back, and it waits again.
Per-tick work (60 Hz) stays local: a Dask task costs milliseconds of scheduling.

Without a cluster, `BackgroundTracer` gives the bake's own (Embree) tracer the same interface: its batches
run one after another on a thread of their own, in the tracer's worker processes, so a scene at rest is
refined at the tracer's full speed rather than within the ticks' budget alone.
"""
from __future__ import annotations

import logging
import time
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from psao.server.errors import TracerError
from psao.server.settings import TraceSettings

log = logging.getLogger("psao.refine")


@dataclass
class RefineSettings:
    batch_points: int = 16384  # points per batch (one task each without tiles)
    batches_per_thread: int = 2  # batches in flight per worker thread of the cluster
    scan: int = 4  # waiting points looked at per point sent (a part of a sweep over the queue)


@dataclass
class _Batch:
    ids: np.ndarray  # point ids
    rays: int  # rays per point in this batch
    seed: int  # of its ray set
    pending: object  # the DaskTracer's PendingTrace


class ClusterRefiner:
    """Waiting static points traced on a cluster while the ticks go on."""

    def __init__(self, tracer, settings: RefineSettings | None = None):
        self.tracer = tracer
        self.settings = settings or RefineSettings()
        self.batches: list[_Batch] = []
        self.busy: np.ndarray | None = None  # per point id: out on the cluster now
        self.stale: np.ndarray | None = None  # per point id: out, and its neighbourhood changed since
        self.posed_at: float | None = None  # scene time the cluster's moving geometry was last posed at
        self.submitted = 0  # batches
        self.points_done = 0  # points whose rays were merged
        self.points_dropped = 0  # answers dropped: the neighbourhood changed while they were out

    def attach(self, tick) -> None:
        """Give the cluster the tick's geometry: static triangles, rigid movers (posed per batch)."""
        n = len(tick.tracked)
        self.busy = np.zeros(n, bool)
        self.stale = np.zeros(n, bool)
        scene = tick.scene
        rigid = [(scene.meshes[scene.instances[i].mesh].vertices, scene.meshes[scene.instances[i].mesh].faces)
                 for i in tick.kinds.rigid]
        self.tracer.set_geometry(*tick.animator.static_geometry(), rigid)
        self.static = np.isin(tick.inst_of, tick.kinds.static) & tick.tracked

    def forget(self, ids: np.ndarray) -> None:
        """The history of `ids` was reset: drop the answers for those now out."""
        self.stale[ids[self.busy[ids]]] = True

    def step(self, tick, frame) -> tuple[np.ndarray, np.ndarray]:
        """Merge the batches that came back (ids, AO codes to store), then send new ones up to the limit."""
        ids, codes = self._collect(tick)
        self._submit(tick, frame)
        return ids, codes

    def wait(self, timeout: float) -> bool:
        """Block until every batch out now is back (or `timeout` seconds pass); True if they are."""
        end = time.monotonic() + timeout
        while not all(b.pending.done() for b in self.batches):
            if time.monotonic() > end:
                return False
            time.sleep(0.01)
        return True

    def _collect(self, tick) -> tuple[np.ndarray, np.ndarray]:
        out_ids, out_codes = [], []
        still = []
        for b in self.batches:
            if not b.pending.done():
                still.append(b)
                continue
            self.busy[b.ids] = False
            try:
                vis = b.pending.result()
            except TracerError as exc:  # the points wait again: the tick or a later batch traces them
                log.warning("refinement batch failed (%s): its %d points wait again", exc, len(b.ids))
                self.stale[b.ids] = False
                continue
            keep = ~self.stale[b.ids]
            self.stale[b.ids] = False
            self.points_dropped += int((~keep).sum())
            if keep.any():
                ids = b.ids[keep]
                out_ids.append(ids)
                out_codes.append(tick.queue.add(ids, vis[keep], b.rays, time.perf_counter(), slices=tick.queue.slices))
                self.points_done += len(ids)
        self.batches = still
        if not out_ids:
            return np.zeros(0, np.int64), np.zeros(0, np.uint32)
        return np.concatenate(out_ids), np.concatenate(out_codes)

    def _submit(self, tick, frame) -> None:
        room = self.settings.batches_per_thread * max(1, self.tracer.threads) - len(self.batches)
        if room <= 0:
            return
        queue = tick.queue
        k = room * self.settings.batch_points
        # a part of the queue (a bounded cost on the tick's thread; every waiting point comes up once a sweep):
        # the first grid's static points (the tick has the others: partly refined, or reset by a change)
        waiting = queue.candidates(self.settings.scan * k, sweep=1)
        waiting = waiting[self.static[waiting] & ~self.busy[waiting] & queue.first_grid(waiting)]
        if len(waiting) == 0:
            return
        chosen = tick.pick(frame, waiting, min(len(waiting), k))  # those in a client's view first
        if self.posed_at != frame.t:  # the movers where the tick sees them now
            tick.pose_tracer(frame, self.tracer)
            self.posed_at = frame.t
        pos, nrm = tick.world_points(frame, chosen)
        # the whole target ray set of each point: the bake's rays and seed, as the tick's slices add up to
        s = TraceSettings(rays=queue.target, ao_distance=tick.scene.ao_distance, seed=tick.settings.seed)
        for i in range(0, len(chosen), self.settings.batch_points):
            part = slice(i, i + self.settings.batch_points)
            ids = chosen[part]
            self.batches.append(_Batch(ids, s.rays, s.seed, self.tracer.start(pos[part], nrm[part], ids, s)))
            self.busy[ids] = True
            self.submitted += 1

    def close(self) -> None:
        log.info("refinement beside the ticks: %d batches sent, %d points refined, %d answers dropped (moved meanwhile)",
                 self.submitted, self.points_done, self.points_dropped)
        for b in self.batches:
            b.pending.cancel()
        self.batches = []
        self.tracer.close()


class BackgroundTracer:
    """A local tracer (e.g. the bake's Embree tracer) behind the part of DaskTracer's interface that
    ClusterRefiner uses: set_geometry, set_dynamic, start (-> done, result, cancel), threads, close. Every
    call runs in order on one thread of its own, so a pose set between batches applies to the next one."""

    threads = 1  # one batch traces at a time (in the tracer's worker processes)

    def __init__(self, tracer):
        self.tracer = tracer
        self._thread = ThreadPoolExecutor(1, thread_name_prefix="refine")

    def set_geometry(self, static_vertices, static_faces, rigid) -> None:
        def geometry():
            self.tracer.set_static(static_vertices, static_faces)
            self.tracer.set_rigid(rigid)
        self._thread.submit(geometry).result()

    def set_dynamic(self, vertices, faces, rigid_transforms=None, parts=None) -> None:
        self._thread.submit(self.tracer.set_dynamic, vertices, faces, rigid_transforms, parts)

    def start(self, positions, normals, point_ids, settings: TraceSettings) -> "LocalPending":
        return LocalPending(self._thread.submit(self.tracer.visibility, positions, normals, point_ids, settings))

    def close(self) -> None:
        self._thread.shutdown(wait=True, cancel_futures=True)
        self.tracer.close()


class LocalPending:
    """A batch submitted by BackgroundTracer.start: poll done(), then take result()."""

    def __init__(self, future: Future):
        self.future = future

    def done(self) -> bool:
        return self.future.done()

    def result(self) -> np.ndarray:
        try:
            return self.future.result()
        except TracerError:
            raise
        except Exception as exc:  # noqa: BLE001 - a failed batch is reported like a cluster's
            raise TracerError(f"the refinement trace failed: {type(exc).__name__}: {exc}") from None

    def cancel(self) -> None:
        self.future.cancel()
