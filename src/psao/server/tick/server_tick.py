"""The server tick (DESIGN.md, server tick steps 1-5): animate, select, trace, quantise, threshold.

    tick = ServerTick(bake_result, TickSettings())   # static Embree scene built once, workers started
    grid = tick.grid                                   # the grid it writes (bake.grid)
    tick.set_cameras([(view, proj), ...])              # from the clients' Camera messages
    tick(grid, t)                                      # one tick at scene time t (a psao.server.tick.base.Tick)
    plan = tick.prepare(t); tick.apply(plan)           # the same in two halves: prepare writes no grid
    tick.transforms()                                  # (n, 4, 4) float32, for every Update
    tick.edit(instance, transform)                     # a scene edit: applied by the next prepare

A scene edit places an instance at a transform from then on (SceneAnimator.place); the next tick sees
it as motion, so what it touches is selected and re-traced like any other motion (budgeted: its points'
histories reset and queue). An edited static instance becomes a rigid mover: its triangles leave the
tracer's static scene and its points the static index (a tracer rebuild, once per instance).

Points are identified by their stable point id (bake.scene_point_ids: ids_of[i][k] is the id of point
k of instance i's PointSet, which is how a skinned point finds its triangle). The tick keeps per id: instance, current grid location (slot, index),
local position and normal, world position (static points: computed once), and a stale flag (a point the
selection wanted but no client could see).

Rigid instances never touch their points: the client moves them with the transform. Skinned instances
never touch them either: the grid keeps every skinned point where the bake generated it, in the mesh's
rest (bind) pose, and the client looks a fragment up by its rest-pose position and normal (the G-buffer's
local targets carry the rest pose of the posed fragment: same triangle, same barycentrics). Each tick
re-places the skinned points on the deformed mesh only for tracing (`local_pos` / `local_nrm`: where a
point is now, in instance space), so a skinned tick writes AO into fixed points and the thresholded
changes are all it sends.

Two ways to trace (TickSettings.budget):
    None      every selected point in a view is re-traced with `rays` rays in this very tick, however
              long that takes (the reference the budgeted tick is measured against)
    settings  the time-budgeted tick of psao.server.tick.budget: selected points have their ray history reset
              and wait in a priority queue; each tick traces as many as its time budget allows: a point
              reset since its last trace gets its whole `rays`-ray set at once (the unbudgeted trace; a
              static one with kept static hits as an exact trace, below), a point refining a history
              (a few-ray first grid) one slice (`round_rays` rays) of it, accumulating up to `rays`:
              a point's rounds together are exactly its unbudgeted trace. First, exact_share of
              the budget traces static points near movers whole from the bake's static hits (only the
              rays the static scene lets through, against the movers: the full trace's AO), in the
              same tracer call. A scene at rest converges and then traces nothing; idle budget refines
              points the bake traced with fewer rays than `rays` (progressive start).
"""
from __future__ import annotations

import logging
import threading
import time
from collections import deque
from dataclasses import dataclass, fields

import numpy as np

from psao.protocol import pointword as pw
from psao.protocol.errors import EditError
from psao.server.tick.animate import (Frame, PlacedPoints, SceneAnimator, SkinnedPoints, affine, bounds_of, changed_meshes,
                                 to_world_points)
from psao.server.arrays import rows
from psao.server.bake import BakeResult
from psao.server.geometry import scene_center, scene_point_ids, to_world
from psao.server.tick.budget import DEFAULT_TICK_HZ, RefineQueue, TraceBudget, first_by_key, first_within, measure_tracer
from psao.server.tick.base import Tick
from psao.server.tick.summary import view_wait_counts
from psao.server.errors import ConfigError, TracerError
from psao.server.grid import NO_POINT, Grid
from psao.server.tick.selection import (INSIDE_CHANGE, BlockIndex, MotionInput, NearCache, cameras_planes, in_any_view,
                                   reach_boxes, merge_disjoint, rigid_in_company)
from psao.server.settings import TickSettings, TraceSettings
from psao.server.tracer.static_hits import StaticHits
from psao.server.tracer import make_tracer
from psao.server.tracer.base import TracePart

log = logging.getLogger("psao.tick")
AHEAD_TICKS = 4  # a full look keeps the best of what it saw for the next tick: this many ticks' worth of points


@dataclass
class TickStats:
    tick: int
    t: float  # scene time, seconds
    considered: int  # points the tick owns
    skipped: int  # considered - traced
    traced: int
    changed: int  # AO written (|new - old| > threshold)
    moved: int  # skinned points re-placed on their deformed triangles (traced from there; the grid keeps them at rest)
    cells_dirty: int  # cells marked dirty after the tick (= cells this tick dirtied when the service drains every tick)
    seconds_animate: float
    seconds_select: float
    seconds_trace: float
    seconds_grid: float
    seconds_total: float
    queue: int = 0  # points waiting for a trace (budgeted) or for a view (unbudgeted)
    queue_oldest_ms: float = 0.0  # how long the longest-waiting of them has waited
    budget_ms: float = 0.0  # the trace budget of this tick, with that of a tick before that pooled its trace into
    # this one (0: unbudgeted, or a tick that pooled its trace into the next: BudgetSettings.pool_traces)
    budget_used: float = 0.0  # trace seconds / budget; above 1 when even the smallest batch did not fit
    service_ms: float = 0.0  # what the automatic budget leaves the service a tick besides the stages (the median
    # of what it reported: TraceBudget.observe_service)
    batch: int = 0  # points the rounds' part of the budget allowed this tick (slices, whole ray sets, exact ones)
    exact: int = 0  # static points near movers given their whole ray set from kept static hits first (exact_share; in traced)
    refilled: int = 0  # static points near movers traced whole with their static hits kept again (in traced)
    cpu_prepare: float = 0.0  # CPU seconds the thread that ran prepare (animate, select, trace) spent in it: the
    # wall seconds of those stages less this is time spent waiting (for the GIL, a core, the tracer's worker
    # processes, whose CPU is not counted here)
    # the points this tick re-traced for the first time since their history was reset, in a client's view: how
    # long each waited for it, counted in the bins of summary.VIEW_WAIT_EDGES_MS (budgeted tick; None otherwise)
    view_waits: list | None = None

    def to_dict(self) -> dict:
        return {f.name: getattr(self, f.name) for f in fields(self)}  # (scalars: no deep copy, 4x cheaper than asdict)


@dataclass
class TickPlan:
    """A prepared tick: what apply() writes."""
    frame: Frame
    moved: int  # skinned points re-placed on their deformed triangles
    ids: np.ndarray  # ids traced
    codes: np.ndarray  # their new AO codes
    seconds: tuple[float, float, float]  # animate, select, trace
    batch: int = 0  # points the rounds' part of the budget allowed (budgeted tick)
    budget_s: float = 0.0
    exact: int = 0  # static points near movers the whole traces' share (exact_share) traced from kept static hits
    refilled: int = 0  # static points traced whole with their static hits kept again
    cpu_s: float = 0.0  # CPU seconds of the preparing thread (TickStats.cpu_prepare)
    view_waits: list | None = None  # TickStats.view_waits


class ServerTick(Tick):
    threaded = places_instances = applies_edits = True

    def __init__(self, bake: BakeResult, settings: TickSettings | None = None, baked_time: float | None = 0.0,
                 close_bake_tracer: bool = True, trust_bake: bool = False, refiner=None,
                 tick_hz: float = DEFAULT_TICK_HZ):
        """`baked_time`: the scene time at which the bake traced the grid (its AO then counts as the first
        sync when the bake used the same rays and seed, or always with `trust_bake`: e.g. a 128-ray bake
        kept for the static parts while ticks trace fewer rays; a point re-traced later then jumps to the
        tick's estimate once), or None to re-trace everything visible on the first tick. The bake's
        tracer saw the moving instances as static: it is closed unless told not to. `refiner` (budgeted tick
        only): traces waiting static points elsewhere as well, e.g. psao.server.tick.refine.ClusterRefiner.
        `tick_hz`: the rate it is ticked at until its service tells it its own (set_tick_rate)."""
        self.settings = settings or TickSettings()
        self.settings.check()
        if self.settings.budget is not None:  # (before the tracer starts: its TraceBudget checks it again)
            self.settings.budget.check_rate(tick_hz)
        self.tick_hz = tick_hz
        self._closed = False
        self.scene = bake.scene
        self.grid = bake.grid
        self.animator = SceneAnimator(self.scene)
        self.kinds = self.animator.kinds
        self.trace_settings = TraceSettings(rays=self.settings.rays, ao_distance=self.scene.ao_distance,
                                            seed=self.settings.seed, **self._local_rays())
        if close_bake_tracer and bake.tracer is not None:
            bake.tracer.close()
        self._init_points(bake)
        self._init_tracer()
        self.static_boxes = self.animator.static_bounds()
        self.cameras: list[np.ndarray] = []
        self.core_cameras: list[np.ndarray] = []  # the same views without margins (fov margin 0)
        self._planes_held: dict[int, tuple] = {}  # id(camera) -> (camera, its planes, without margins), from the last set_cameras
        self._edits: dict[int, np.ndarray] = {}  # instance -> transform, from the event loop, until the next prepare
        self._edits_lock = threading.Lock()
        self.stats_history: deque[TickStats] = deque(maxlen=max(1, self.settings.history))
        self.tick_count = 0
        # the bake's AO is this tick's first sync only if it traced the same rays (count and seed)
        same_rays = (bake.stats.get("rays") == self.settings.rays
                     and bake.stats.get("seed", self.settings.seed) == self.settings.seed)
        # (the budgeted tick always takes it, as so many rays of each point's history)
        if baked_time is not None and (same_rays or trust_bake or self.settings.budget is not None):
            # what the bake traced: the movers placed at baked_time, skinned meshes in their bind pose (the
            # first tick then re-traces what posing them changed)
            self.last_frame: Frame | None = self.animator.frame(baked_time, bind_pose=True)
            self._bake_frame = self.last_frame
        else:
            if baked_time is not None:
                log.info("bake traced %s rays (seed %s), the tick %d (seed %d): the first tick re-traces every "
                         "visible point", bake.stats.get("rays"), bake.stats.get("seed", "?"), self.settings.rays,
                         self.settings.seed)
            self.last_frame = self._bake_frame = None
            self.stale[self.present()] = True
        self.budget: TraceBudget | None = None
        self._static_hits: StaticHits | None = self._take_static_hits(bake.static_hits)
        self._posed: Frame | None = None  # the frame the tick's tracer holds the moving part of
        self._priority = None  # select_kernels.PriorityKey, made at the first pick
        self._swept_empty = 0  # waiting-list entries looked at since the tick last found a point of its own
        # the budgeted tick's motion test (BudgetSettings.motion_hz): the frame it last compared with, and
        # the ids it reset then, and the tick that made it
        self._tested_frame: Frame | None = None
        self._tested_ids = np.zeros(0, np.int64)
        self._tested_tick = -1
        self._ahead: np.ndarray | None = None  # the best waiting ids of the last full look (sorted), for the next tick
        if self.settings.budget is not None:
            self._init_budget(bake)
        self.refiner = refiner
        if refiner is not None:
            if self.budget is None:
                raise ConfigError("a refiner needs the budgeted tick (TickSettings.budget)")
            refiner.attach(self)
        self._transforms = (self.last_frame.transforms if self.last_frame else self.animator.transforms(0.0)).astype(np.float32)

    # ------------------------------------------------------------------ set-up
    def _take_static_hits(self, hits: StaticHits | None) -> StaticHits | None:
        """The static scene's answers the whole traces of static points near movers come from (only a tracer
        whose visibility_parts takes them answers from them): the bake's, for ray sets like the tick's. A bake
        that kept them for other ray sets (the progressive start's few-ray bake) gives none known: the tick
        keeps them as it traces static points near movers whole (refill_points a tick, _whole_static), so
        after the first moves around a place its points are re-traced at exact_cost. None where the bake kept
        none (keep_static_hits off, no movers)."""
        if hits is None or not self.tracer.supports_static_hits:
            return None
        if hits.fits(self.settings.rays, self.settings.seed):
            return hits
        return StaticHits(len(hits.known), self.settings.rays, self.settings.seed, self.static_ids)

    @property
    def static_hits(self) -> StaticHits | None:
        """The static hits this tick answers whole traces from (_take_static_hits: the bake's, or its own
        where the bake's are for other ray sets), or None where it traces them (the bake kept none, or the
        tracer cannot take them)."""
        return self._static_hits

    def _init_points(self, bake: BakeResult) -> None:
        self.ids_of = scene_point_ids(bake.pointsets)  # per instance: the id of each point of its PointSet
        # (consecutive per instance: the tick takes an instance's rows as a slice)
        assert all(np.array_equal(ids, np.arange(ids[0], ids[0] + len(ids))) for ids in self.ids_of if len(ids))
        n = sum(len(ps) for ps in bake.pointsets)
        self.inst_of = np.zeros(n, np.int64)
        self.local_pos = np.zeros((n, 3))
        self.local_nrm = np.zeros((n, 3), np.float32)
        for i, (ps, ids) in enumerate(zip(bake.pointsets, self.ids_of)):
            self.inst_of[ids] = i
            self.local_pos[ids], self.local_nrm[ids] = ps.positions, ps.normals
        self.slot = np.full(n, -1, np.int64)
        self.index = np.full(n, -1, np.int64)
        self._relocate_all()
        if self.grid.n_points() != int((self.slot >= 0).sum()):
            raise ConfigError("the grid's point ids do not match the bake's point sets (not built by Grid.build?)")
        self.tracked = self.slot >= 0  # points the grid held after the bake; dropped ones stay dropped
        self.n_tracked = int(self.tracked.sum())
        self.stale = np.zeros(n, dtype=bool)
        self.skinned = {i: SkinnedPoints.from_pointset(self.scene.meshes[self.scene.instances[i].mesh], bake.pointsets[i])
                        for i in self.kinds.skinned}
        self._placed: PlacedPoints | None = None  # all skinned points together, made at the first _deform
        self._placed_on: Frame | None = None  # the frame whose skinned meshes the skinned points were placed on
        # static points: world positions and normals once, and a block index for box queries
        self.world_pos = np.zeros((n, 3))
        self.world_nrm = np.zeros((n, 3), np.float32)
        for i in self.kinds.static:
            ids = np.flatnonzero((self.inst_of == i) & self.tracked)
            self.world_pos[ids], self.world_nrm[ids] = to_world(self.scene.instances[i].transform, self.local_pos[ids],
                                                                self.local_nrm[ids])
        self._index_static()

    def _index_static(self) -> None:
        """The static points' ids, their block index for box queries and their normals."""
        self.static_ids = np.flatnonzero(np.isin(self.inst_of, self.kinds.static) & self.tracked)
        self.moving_point = np.isin(self.inst_of, self.kinds.moving)  # points whose world place follows a frame
        block = self.settings.block or 0.25 * self.scene.ao_distance
        self.block_index = BlockIndex(self.world_pos[self.static_ids], block)
        self.static_normals = self.world_nrm[self.static_ids].astype(np.float64)
        self._static_box = None  # the static points' world box (_points_box), worked out at the first pick
        self.near_cache = NearCache(self.block_index, self.static_normals, self.scene.ao_distance,
                                    self.settings.near_margin * self.scene.ao_distance)

    def _init_tracer(self) -> None:
        s = self.settings
        kwargs = {"workers": s.workers} if s.tracer == "embree" else {}
        self.tracer = make_tracer(s.tracer, scene_center(self.scene), **kwargs)
        self._load_tracer()
        self.tracer.warm_up()  # starts the workers now: their start-up is not counted in a tick

    def _load_tracer(self) -> None:
        """The tracer's static scene and its rigid movers (built once and posed per tick; only deforming
        meshes are rebuilt)."""
        self._posed = None
        self.tracer.set_static(*self.animator.static_geometry())
        self.tracer.set_rigid([(self.scene.meshes[self.scene.instances[i].mesh].vertices,
                                self.scene.meshes[self.scene.instances[i].mesh].faces) for i in self.kinds.rigid])

    def _init_budget(self, bake: BakeResult) -> None:
        """The refinement queue, with the bake's AO as each point's first rays of history when the bake
        belongs to a known time, and the tracer's speed measured once on a few points."""
        self.queue = RefineQueue(len(self.tracked), self.settings.rays, self.settings.budget.keep_rays,
                                 self._round_settings().slices)
        self.queue.exclude(np.flatnonzero(~self.tracked))
        ids = np.flatnonzero(self.present())
        if self.last_frame is not None:
            codes = self.grid.cells[self.slot[ids], self.index[ids]] & np.uint32(0xFF)
            self.queue.seed_from_codes(ids, codes, int(bake.stats.get("rays", self.settings.rays)))
        sample = self.static_ids[:4096] if len(self.static_ids) else ids[:4096]
        frame = self.animator.frame(0.0)
        pos, nrm = self.world_points(frame, sample)
        self.pose_tracer(frame)
        rate = measure_tracer(self.tracer, pos, nrm, sample, self._round_settings())
        self.budget = TraceBudget(self.settings.budget, rate, tick_hz=self.tick_hz)  # (its fixed cost: learnt from the ticks)
        self._queue_now = (self.queue.count, 0.0)  # queue length, oldest wait (ms) as the last trace found them
        log.info("tick budget: tracer measured at %.2f Mrays/s (a call of %d points); %s", rate / 1e6, len(sample),
                 f"{self.settings.budget.budget_ms:g} ms per tick" if self.settings.budget.budget_ms else
                 f"automatic budget ({self.settings.budget.headroom:.0%} of 1/{self.tick_hz:g} s less the other stages)")
        self._pose_bake()
        self._warm_up_select()

    def _pose_bake(self) -> None:
        """The bake traced skinned meshes in their bind pose, which no tick shows: the points that posing
        them at the bake's time changes are traced whole here, before the first tick (start-up, as the bake
        is: not budgeted), and the ticks start from that posed frame. Else the first ticks would spend
        their budgets on that one-off change, showing bind-pose AO meanwhile."""
        if self.last_frame is None or not self.kinds.skinned:
            return
        posed = self.animator.frame(self.last_frame.t)
        self._deform(posed)
        changed, _ = self._motion_candidates(posed, with_change=False)
        changed = changed[self.present()[changed]]
        if len(changed):
            pos, nrm = self.world_points(posed, changed)
            self.pose_tracer(posed)
            vis = self._trace(pos, nrm, changed, self.trace_settings)
            now = time.perf_counter()
            self.queue.reset(changed, now)
            self._store(changed, self.queue.add(changed, vis, self.settings.rays, now, slices=self.queue.slices))
        self.last_frame = posed

    def _warm_up_select(self) -> None:
        """The select stage's one-time costs (its compiled kernels' first loads, each mover's nearby static
        points gathered: about 0.2 s on the courtyard) paid here, not by the first moving tick, in which the
        scene would jump as far: a motion test one tick past the bake's frame and the priority key of a few
        points, which leave the ticks' answers as they are."""
        if self.last_frame is None or not self.kinds.moving:
            return
        frame = self.animator.frame(self.last_frame.t + 1.0 / self.tick_hz)
        self._motion_candidates(frame)
        self.priority(frame, np.flatnonzero(self.tracked)[:16])

    def _round_settings(self) -> TraceSettings:
        """One accumulation round: the target ray set (the bake's rays and seed) dealt into slices of
        `round_rays` rays; each point traces its next slice (RefineQueue.next_slice)."""
        slices = self.settings.rays // min(self.settings.budget.round_rays, self.settings.rays)
        return TraceSettings(rays=self.settings.rays, ao_distance=self.scene.ao_distance, seed=self.settings.seed,
                             slices=slices, **self._local_rays())

    def _local_rays(self) -> dict:
        """The budgeted tick's TraceSettings.local_rays (BudgetSettings.local_rays), as keyword arguments;
        none for the unbudgeted tick (the tracer's default)."""
        return {} if self.settings.budget is None else {"local_rays": self.settings.budget.local_rays}

    def pose_tracer(self, frame: Frame, tracer=None) -> None:
        """The moving part at `frame` (the skinned meshes' triangles, the rigid ones' transforms) into the
        tick's tracer (once per frame: each new pose refits the deforming part in every worker), or into
        `tracer` (the refiner's)."""
        if tracer is None and self._posed is frame:
            return
        (self.tracer if tracer is None else tracer).set_dynamic(
            frame.skinned_vertices, frame.skinned_faces, frame.transforms[self.kinds.rigid], frame.skinned_parts)
        if tracer is None:
            self._posed = frame

    def _retrying(self, call):
        """call(); a worker process that died is logged and the call made once more (the Embree back-end
        starts a fresh pool), so one lost worker does not stop the server."""
        try:
            return call()
        except TracerError as exc:
            log.warning("tracer failed (%s): restarting its workers and tracing this batch again", exc)
            return call()

    def _ray_seconds(self) -> float | None:
        """The wall seconds the tracer's calls have spent making and tracing rays so far (CpuAccount.wall:
        a pooled call's worker seconds over its workers), or None where it does not tell (the budget then
        counts a whole call as its rays')."""
        account = self.tracer.account
        return None if account is None else account.wall

    def _trace(self, pos, nrm, ids, settings: TraceSettings, slice_of=None) -> np.ndarray:
        """The tracer's visibility (with `slice_of`, the given slice of each point's ray set), retrying."""
        extra = {} if slice_of is None else {"slice_of": slice_of}
        return self._retrying(lambda: self.tracer.visibility(pos, nrm, ids, settings, **extra))

    def _trace_parts(self, parts) -> list[tuple[np.ndarray, np.ndarray | None]]:
        """The tracer's visibility_parts, per part (visibility, static hits kept or None), retrying (a
        tracer without static hits of its own, Tracer.supports_static_hits, traces part by part and refuses
        a part that carries them or asks to keep them)."""
        return self._retrying(lambda: self.tracer.visibility_parts(parts))

    def close(self) -> None:
        """Close the tracer and the refiner; once (a second call does nothing)."""
        if self._closed:
            return
        self._closed = True
        self.tracer.close()
        if self.refiner is not None:
            self.refiner.close()

    # ------------------------------------------------------------------ point locations
    def present(self) -> np.ndarray:
        return self.slot >= 0

    def _relocate_cells(self, cells: np.ndarray) -> None:
        ids = self.grid.point_id[cells]
        s, k = np.nonzero(ids != NO_POINT)
        pid = ids[s, k]
        inside = pid < len(self.slot)
        self.slot[pid[inside]] = cells[s[inside]]
        self.index[pid[inside]] = k[inside]

    def _relocate_all(self) -> None:
        self.slot[:] = -1
        self.index[:] = -1
        self._relocate_cells(np.flatnonzero(self.grid.cell_instance >= 0))

    def _check_locations(self, ids: np.ndarray) -> None:
        """Someone else (an edit outside the tick) may have moved points: find them again (ids: points
        believed present; afterwards present() tells where they really are)."""
        ok = self.grid.point_id[self.slot[ids], self.index[ids]] == ids
        if not ok.all():
            log.info("grid edited outside the tick: re-locating every point")
            self._relocate_all()

    # ------------------------------------------------------------------ public API
    def set_cameras(self, cameras) -> None:
        """Cameras as (view 4x4, projection 4x4) pairs (OpenGL conventions); [] means: every point visible,
        and so does a camera whose matrices make no frustum (NaN, singular)."""
        held, self._planes_held = self._planes_held, {}
        new = []
        for c in cameras:  # a camera given again (the same object: its client sent no new one) keeps its planes
            kept = held.get(id(c))
            if kept is not None and kept[0] is c:
                self._planes_held[id(c)] = kept
            else:
                new.append(c)
        # the new ones in one pass; each camera's view without margins too (the budgeted tick's priority)
        for c, planes, core in zip(new, cameras_planes(new, self.settings.view.fov_margin), cameras_planes(new, 0.0)):
            self._planes_held[id(c)] = (c, planes, core)
        self.cameras = [self._planes_held[id(c)][1] for c in cameras]
        self.core_cameras = [self._planes_held[id(c)][2] for c in cameras]

    def edit(self, instance: int, transform: np.ndarray) -> None:
        """A scene edit (already authorised and range-checked by the session): instance `instance` is at
        `transform` from the next tick on. Safe to call while a prepare runs in another thread."""
        if not 0 <= instance < len(self.scene.instances):
            raise EditError(f"SceneEdit: no instance {instance} (the scene has {len(self.scene.instances)})")
        with self._edits_lock:
            self._edits[int(instance)] = np.asarray(transform, np.float64).reshape(4, 4)

    def _take_edits(self) -> bool:
        """Apply the scene edits received since the last tick (at the start of prepare: the tick's own
        thread); whether there were any. Edited static instances become rigid movers: the tracer and the
        static index lose them."""
        with self._edits_lock:
            edits, self._edits = self._edits, {}
        became_rigid = [i for i, m in edits.items() if self.animator.place(i, m)]
        if not became_rigid:
            return bool(edits)
        log.info("scene edit: instance(s) %s now move; tracer rebuilt without them in its static scene", became_rigid)
        for i in became_rigid:
            self.static_boxes.pop(i, None)
            for before in {id(f): f for f in (self.last_frame, self._tested_frame) if f is not None}.values():
                # where it was: the first motion resets what it leaves too
                mesh = self.scene.meshes[self.scene.instances[i].mesh]
                before.bounds[i], before.spheres[i] = bounds_of(affine(mesh.vertices, before.transforms[i]))
        self._index_static()
        self._load_tracer()
        if self._static_hits is not None:
            self._static_hits.forget(self.static_ids)  # the static scene lost the edited instances
        self.tracer.warm_up()
        return True

    def transforms(self) -> np.ndarray:
        """(n_instances, 4, 4) float32 transforms of the last tick."""
        return self._transforms

    def stats_json(self) -> list[dict]:
        return [s.to_dict() for s in self.stats_history]

    def __call__(self, grid: Grid, t: float) -> TickStats:
        """One tick at scene time t: prepare (no grid writes) then apply."""
        if grid is not self.grid:
            raise ConfigError("ServerTick was built for another grid (tick.grid)")
        return self.apply(self.prepare(t))

    def prepare(self, t: float) -> "TickPlan":
        """Animate, select and trace at scene time t without writing the grid: it may run in a worker
        thread while the event loop reads the grid for sending. `apply` must follow before the next one."""
        cpu_start = time.thread_time()
        plan = self._prepare(t)
        plan.cpu_s = time.thread_time() - cpu_start
        return plan

    def _prepare(self, t: float) -> "TickPlan":
        t_start = time.perf_counter()
        edited = self._take_edits()
        last = self.last_frame
        # the same time and no edit (a scene held at rest): the same frame, not worked out again
        frame = (last if last is not None and last.t == t and not edited and last is not self._bake_frame
                 else self.animator.frame(t))
        moved = self._deform(frame)
        t_anim = time.perf_counter()
        if self.budget is not None:
            return self._prepare_budgeted(frame, moved, t_start, t_anim, edited)
        ids, pos, nrm = self._select(frame)
        t_sel = time.perf_counter()
        vis = np.zeros(0, np.float32)
        if len(ids):  # the moving scene is only (re)built when something is traced
            self.pose_tracer(frame)
            vis = self._trace(pos, nrm, ids, self.trace_settings)
        t_trace = time.perf_counter()
        return TickPlan(frame, moved, ids, pw.quantise_ao(vis), (t_anim - t_start, t_sel - t_anim, t_trace - t_sel))

    def _refine(self, changed: np.ndarray, frame: Frame) -> tuple[np.ndarray, np.ndarray]:
        """The refiner's part of a tick: forget the points whose history was just reset, take back the
        batches that are done (ids, AO codes), send new ones (before the tick picks its own: no point twice)."""
        if self.refiner is None:
            return np.zeros(0, np.int64), np.zeros(0, np.uint32)
        self.refiner.forget(changed)
        return self.refiner.step(self, frame)

    def _prepare_budgeted(self, frame: Frame, moved: int, t_start: float, t_anim: float,
                          edited: bool = False) -> "TickPlan":
        """Reset the history of the points the motion may have changed (when a motion test is due), pick as
        many waiting points as the budget allows (priority order of RefineQueue.pick), trace one round of
        rays for them."""
        now = t_anim
        changed = self._motion_reset(frame, now, edited)
        round_settings = self._round_settings()
        refined = self._refine(changed, frame)
        if self._pools_trace(round_settings):
            return self._pooled_plan(frame, moved, refined, t_start, t_anim)
        # A tick that tested motion, or follows one that chose from the best of a full look, looks at the
        # points the last test reset and the queue's sweep; the tick between two motion tests chooses from
        # the best of that look still waiting (their keys change little in a tick: no reset in between).
        light = self._tested_frame is not frame and self._ahead is not None
        scan = max(16 * self.budget.points(round_settings.rays_traced), self.settings.budget.scan_points)
        looked = self._looked_at(changed if len(changed) else self._tested_ids, scan,
                                 among=self._ahead if light else None)
        self._ahead = None
        s = self.trace_settings
        key, _, core = self.priority(frame, looked)  # one pass: the whole traces and the rounds choose by it
        looked_all, in_view = looked, core.copy()  # in a client's view itself (no margins): for view_waits
        most_exact = self.budget.exact_points(s.rays)
        exact, refill = self._whole_static(looked, core, most_exact, s.rays)
        spent = len(exact) * self.budget.exact_rays(s.rays) + len(refill) * s.rays
        k = self.budget.points(round_settings.rays_traced, spent)  # the rounds get what is left
        if not light:  # several ticks' worth of the best, for the next tick if it tests no motion
            self._ahead = np.sort(first_by_key(looked, key, AHEAD_TICKS * (k + most_exact)))
        whole = np.concatenate([refill, exact])
        if len(whole):  # (both sorted, whole within looked)
            rest = np.ones(len(looked), bool)
            rest[np.searchsorted(looked, whole)] = False
            looked, key = looked[rest], key[rest]
        chosen, fresh, cheap = self._rounds(looked, key, k * round_settings.rays_traced)
        batch, n_exact = len(chosen) + len(fresh) + len(cheap), len(exact)
        exact = np.sort(np.concatenate([exact, cheap]))
        whole = np.concatenate([fresh, refill, exact])
        spent = len(exact) * self.budget.exact_rays(s.rays) + (len(refill) + len(fresh)) * s.rays
        t_sel = time.perf_counter()
        codes, whole_codes, ray_s, view_waits = np.zeros(0, np.uint32), np.zeros(0, np.uint32), None, view_wait_counts([])
        if len(chosen) or len(whole):  # one call: the workers' hand-over is paid once
            pos, nrm = self.world_points(frame, chosen)
            fresh_pos, fresh_nrm = self.world_points(frame, fresh)
            parts = [TracePart(pos, nrm, chosen, round_settings, self.queue.next_slice[chosen]),
                     TracePart(fresh_pos, fresh_nrm, fresh, s),
                     TracePart(rows(self.world_pos, refill), rows(self.world_nrm, refill), refill, s, keep_static=True),
                     TracePart(rows(self.world_pos, exact), rows(self.world_nrm, exact), exact, s,
                               static_hit=self._static_hits.packed(exact) if len(exact) else None)]
            self.pose_tracer(frame)
            live = [k for k, p in enumerate(parts) if k == 0 or len(p.point_ids)]  # (empty parts: not sent)
            ray_s = self._ray_seconds()
            vis = dict(zip(live, self._trace_parts([parts[k] for k in live])))
            ray_s = self._ray_seconds() - ray_s if ray_s is not None else None
            vis = [vis.get(k, (np.zeros(0, np.float32), None)) for k in range(len(parts))]
            now = time.perf_counter()
            view_waits = self._view_waits(np.concatenate([chosen, whole]), looked_all, in_view, now)
            codes = self.queue.add(chosen, vis[0][0], round_settings.rays_traced, now)
            if len(whole):  # the full trace's AO: the point's whole ray set at once
                if len(refill):
                    self._static_hits.keep(refill, vis[2][1])
                whole_codes = self.queue.add(whole, np.concatenate([vis[1][0], vis[2][0], vis[3][0]]), s.rays, now,
                                             slices=self.queue.slices)
        t_trace = time.perf_counter()
        budget_s = self.budget.trace_budget_s()  # (before observe_trace: its own and any pooled ticks')
        self.budget.observe_trace(len(chosen) * round_settings.rays_traced + spent, t_trace - t_sel, ray_s)
        # the queue after this round (points out on the refiner wait too); the oldest wait among the points
        # looked at (all of them unless the queue is longer than a sweep's part)
        still = looked[self.queue.done[looked] < self.queue.slices]
        self._queue_now = (self.queue.count, 1e3 * (t_trace - self.queue.waiting_since[still].min()) if len(still) else 0.0)
        # stored with this tick's own: the refiner's, and (last) the static points traced whole
        chosen, codes = np.concatenate([chosen, refined[0], whole]), np.concatenate([codes, refined[1], whole_codes])
        return TickPlan(frame, moved, chosen, codes, (t_anim - t_start, t_sel - t_anim, t_trace - t_sel),
                        batch=batch, budget_s=budget_s, exact=n_exact, refilled=len(refill), view_waits=view_waits)

    def _view_waits(self, traced: np.ndarray, looked: np.ndarray, in_view: np.ndarray, now: float) -> list[int]:
        """view_wait_counts of the waits of the `traced` points (within the sorted `looked`, `in_view` of
        each) that no slice of their ray set holds since their reset (their first re-trace is this one)."""
        if not len(traced):
            return view_wait_counts([])
        first = self.queue.done[traced] == 0
        seen = in_view[np.searchsorted(looked, traced)]
        waited = traced[first & seen]
        return view_wait_counts(1e3 * (now - self.queue.waiting_since[waited]))

    def _pools_trace(self, round_settings: TraceSettings) -> bool:
        """Whether this tick leaves its trace to the next (BudgetSettings.pool_traces): it tested motion,
        the tick before it traced (a trace every other tick at least) and was not the first, and its
        budget allows more than the minimum batch of `round_settings` rounds (below it, every tick traces
        its min_points)."""
        b = self.settings.budget
        return (b.pool_traces and self._tested_tick == self.tick_count and self.budget.pooled == 0
                and self.last_frame is not None and self.last_frame is not self._bake_frame
                and self.budget.points(round_settings.rays_traced) > b.min_points)

    def _pooled_plan(self, frame: Frame, moved: int, refined: tuple, t_start: float, t_anim: float) -> "TickPlan":
        """A tick that traces nothing of its own (the refiner's batches are still stored): its budget goes
        to the next tick, which looks at the points this one's motion test reset (no choice made ahead)."""
        self.budget.pool()
        self._ahead = None
        # the queue's length now; its oldest wait as the last trace call found it
        self._queue_now = (self.queue.count, self._queue_now[1])
        t_sel = time.perf_counter()
        return TickPlan(frame, moved, refined[0], refined[1], (t_anim - t_start, t_sel - t_anim, 0.0),
                        view_waits=view_wait_counts([]))

    def _motion_reset(self, frame: Frame, now: float, edited: bool) -> np.ndarray:
        """Reset the queue's history of the points the motion since the last motion test may have changed,
        when one is due (BudgetSettings.motion_hz, or a scene edit): their ids (sorted), else none. The test
        compares `frame` with the frame of the last test, so motion in between is never missed: it is
        tested over the ticks since at once."""
        before = self._tested_frame if self._tested_frame is not None else self.last_frame
        if before is not None and self.settings.selection and not edited and not self._motion_due(frame):
            return np.zeros(0, np.int64)
        if before is None or not self.settings.selection:
            changed, change = np.flatnonzero(self.tracked), None
        else:
            changed, change = self._motion_candidates(frame, before=before)
        self.queue.reset(changed, now, change)
        self._tested_frame, self._tested_ids, self._tested_tick = frame, changed, self.tick_count
        return changed

    def _motion_due(self, frame: Frame) -> bool:
        """Whether this tick tests motion: at most motion_hz times a second of scene time (the service's
        scene time is its wall time), give or take a quarter of a tick's step (ticks at twice that rate
        test every other one, whatever their jitter), and not twice in a row while ticks come at more than
        half that rate (a tick slowed by its test does not make the next one test too: the ticks between
        tests are the cheap ones); at once when the scene stops with motion since the last test untested.
        Scene time, not the clock: the same scene times make the same tests."""
        hz = self.settings.budget.motion_hz
        step = abs(frame.t - self.last_frame.t) if self.last_frame is not None else 0.0
        since = frame.t - self._tested_frame.t if self._tested_frame is not None else np.inf
        if hz <= 0 or not 0 <= since or (step == 0 and since > 0):
            return True
        just_tested = self._tested_frame is self.last_frame
        return since >= (2.0 if just_tested else 1.0) / hz - 0.25 * step

    def _whole_static(self, waiting: np.ndarray, seen: np.ndarray, most: int, rays: int) -> tuple[np.ndarray, np.ndarray]:
        """The static points among `waiting` (sorted) that get their whole ray set at once this tick: those
        of static instances in some client's view without its margins (`seen`, per waiting point: the
        margins' points wait for the rounds) with an estimated AO change since their last
        trace of at least exact_min_change, the `most` changed most, as (exact, refill), each sorted.
        `exact`: those whose static hits are kept: only the rays the static scene lets through are traced,
        against the moving parts (TracePart.static_hit). `refill`: those whose hits an edit voided, at most
        refill_points of them and what is left of the `most` exact traces' rays, each a full trace of
        `rays` rays that keeps its static hits again (TracePart.keep_static). Both give the full trace's
        AO, which ends their wait."""
        hits = self._static_hits
        if most <= 0 or hits is None:
            return waiting[:0], waiting[:0]
        ids = waiting[seen & hits.static[waiting] & (self.queue.change[waiting] >= self.settings.budget.exact_min_change)]
        top = first_by_key(ids, -self.queue.change[ids].astype(np.float64), most)
        known = hits.known[top]
        exact = top[known]
        left = (most - len(exact)) * self.budget.exact_rays(rays) / max(rays, 1)
        refill = top[~known][:min(self.settings.budget.refill_points, int(left))]
        return np.sort(exact), np.sort(refill)

    def _rounds(self, looked: np.ndarray, key: np.ndarray, rays: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The rounds' points: those of `looked` first in key order whose traces cost at most `rays` rays of
        the measured rate (at least min_points), as (rounds, fresh, cheap). A point refining a history gets
        one slice (`rounds`: round_rays rays); a point with nothing since its last reset gets its whole ray
        set at once (`fresh`: a few-ray slice blended with a history from before the change lags behind
        it), or, a static point with kept static hits, an exact whole trace (`cheap`: the same answer for
        exact_rays of them, BudgetSettings.exact_cost)."""
        per_round = self._round_settings().rays_traced
        rays_all = self.settings.rays
        hits = self._static_hits
        reset = self.queue.unstarted(looked)
        exactable = reset & (hits.static[looked] & hits.known[looked] if hits is not None else False)
        cost = np.where(exactable, self.budget.exact_rays(rays_all), np.where(reset, float(rays_all), float(per_round)))
        at = np.searchsorted(looked, first_within(looked, key, cost, rays, self.settings.budget.min_points))
        ids = looked[at]
        fresh, cheap = reset[at] & ~exactable[at], exactable[at]
        return ids[~fresh & ~cheap], np.sort(ids[fresh]), np.sort(ids[cheap])

    def _looked_at(self, changed: np.ndarray, scan: int, among: np.ndarray | None = None) -> np.ndarray:
        """The waiting points this tick chooses from (sorted): those just reset (`changed`) and all the
        others, or the next `scan` of a sweep over a long queue, not those the refiner has (out now, or the first grid's static points: it traces
        them faster). Once a whole sweep found none, only a reset can make more: until then the queue is
        not looked at (a first grid being refined costs the ticks nothing). `among` (sorted ids): those of
        them still waiting instead (no sweep)."""
        if among is not None:
            looked = among
        else:
            n_list = self.queue.listed
            if len(changed) == 0 and self._swept_empty >= n_list:
                return changed
            looked = self.queue.looked_at(scan, changed)
        looked = looked[self.tracked[looked] & (self.queue.done[looked] < self.queue.slices)]
        if self.refiner is not None:
            looked = looked[~self.refiner.busy[looked] & ~(self.refiner.static[looked] & self.queue.first_grid(looked))]
        if among is None:
            self._swept_empty = 0 if len(looked) or len(changed) else self._swept_empty + min(scan, n_list)
        return looked

    def pick(self, frame: Frame, waiting: np.ndarray, k: int) -> np.ndarray:
        """RefineQueue.pick of `k` of `waiting` with their visibility in the clients' extended views and in
        those views' cores at `frame` (priority)."""
        if len(waiting) == 0:
            return waiting
        return first_by_key(waiting, self.priority(frame, waiting)[0], k)

    def priority(self, frame: Frame, waiting: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(RefineQueue.key of `waiting`, bool in_any_view of each, bool in a view without its margins) with
        their visibility in the clients' extended views and in those views' cores at `frame`, in one compiled
        pass over them (select_kernels.priority_kernel)."""
        if len(waiting) == 0:
            return np.zeros(0), np.zeros(0, bool), np.zeros(0, bool)
        from psao.server.tick.select_kernels import PriorityKey  # (Warp: imported at the first pick)
        if self._priority is None:
            self._priority = PriorityKey()
        key = self._priority(waiting, self.world_pos, self.local_pos, self.inst_of, self.moving_point, frame.transforms,
                             self._view_planes(), self.settings.view.distance_margin, self.queue.rays,
                             self.queue.waiting_since, self.queue.change,
                             float(self.queue.waiting_since[waiting].min()), self._points_box(frame),
                             self._view_planes(self.core_cameras))
        return key, self._priority.visible, self._priority.core

    def _view_planes(self, cameras: list | None = None) -> np.ndarray | None:
        """The clients' extended views (or `cameras`' planes) as (C, 5, 4) planes, or None: every point
        counts as visible (no camera, or one that makes no frustum)."""
        cameras = self.cameras if cameras is None else cameras
        return None if not cameras or any(c is None for c in cameras) else np.stack(cameras)

    def _points_box(self, frame: Frame) -> tuple[np.ndarray, np.ndarray]:
        """A world box around the points (the static ones' and the movers' bounds at `frame`): where the
        pick's union of views is cut into blocks."""
        if self._static_box is None:
            p = self.world_pos[self.static_ids]
            self._static_box = (p.min(axis=0), p.max(axis=0)) if len(p) else (np.full(3, np.inf), np.full(3, -np.inf))
        boxes = [self._static_box] + [frame.bounds[i] for i in self.kinds.moving if i in frame.bounds]
        return np.min([b[0] for b in boxes], axis=0), np.max([b[1] for b in boxes], axis=0)

    def apply(self, plan: "TickPlan") -> TickStats:
        """Write a prepared tick into the grid (thresholded AO): a few milliseconds, on
        the thread that owns the grid. Marks the cells and buckets it changes dirty."""
        g0 = time.perf_counter()
        changed = self._store(plan.ids, plan.codes)
        seconds_grid = self.stats_grid_s = time.perf_counter() - g0
        self.last_frame = plan.frame
        self._transforms = plan.frame.transforms.astype(np.float32)
        n = self.n_tracked
        animate, select, trace = plan.seconds
        stats = TickStats(
            tick=self.tick_count, t=plan.frame.t, considered=n, skipped=n - len(plan.ids), traced=int(len(plan.ids)),
            changed=changed, moved=plan.moved,
            cells_dirty=int(np.count_nonzero(self.grid.dirty_cells)),
            seconds_animate=animate, seconds_select=select, seconds_trace=trace, seconds_grid=seconds_grid,
            seconds_total=animate + select + trace + seconds_grid, cpu_prepare=plan.cpu_s,
            **self._queue_stats(plan, trace))
        self.tick_count += 1
        self.stats_history.append(stats)
        return stats

    def set_tick_rate(self, tick_hz: float) -> None:
        """The service ticks this at `tick_hz` (ConfigError if the trace budget does not fit its period)."""
        if self.budget is not None:
            self.budget.set_tick_hz(tick_hz)
        self.tick_hz = tick_hz

    def observe_service(self, seconds: float) -> None:
        """What the service spent on the last tick besides prepare and apply (its fan-out, the clients'
        messages, waking the next tick): the automatic trace budget leaves it room (TraceBudget.observe_service)."""
        if self.budget is not None:
            self.budget.observe_service(seconds)

    def _queue_stats(self, plan: "TickPlan", trace_s: float) -> dict:
        if self.budget is None:
            return {"queue": int(np.count_nonzero(self.stale))}
        animate, select, _ = plan.seconds
        self.budget.observe_other(animate + select + self.stats_grid_s)
        return {"queue": self._queue_now[0], "queue_oldest_ms": self._queue_now[1],
                "budget_ms": 1e3 * plan.budget_s, "budget_used": trace_s / max(plan.budget_s, 1e-9),
                "service_ms": 1e3 * self.budget.service_s,
                "batch": plan.batch, "exact": plan.exact, "refilled": plan.refilled, "view_waits": plan.view_waits}

    # ------------------------------------------------------------------ steps
    def _deform(self, frame: Frame) -> int:
        """Skinned points to where they are at `frame` on their deformed triangles (the tick's local_pos /
        local_nrm, which it traces from; the grid keeps their rest pose), all together (one PlacedPoints pass) when a
        skinned mesh changed since they were last placed; returns how many points the changed meshes hold."""
        changed = changed_meshes(frame, self._placed_on) if self.skinned else set()
        if not changed:
            return 0
        if self._placed is None:
            self._placed = PlacedPoints(self.scene, self.skinned, self.ids_of, frame.layout)
        self._placed.place(frame.posed, self.local_pos, self.local_nrm)
        self._placed_on = frame
        return sum(len(self.ids_of[i]) for i in self.skinned if self.scene.instances[i].mesh in changed)

    def _select(self, frame: Frame) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Point ids to trace this tick (sorted) with their world positions and normals; updates the
        stale flags."""
        candidates = self.tracked.copy()
        if self.settings.selection and self.last_frame is not None:
            candidates[:] = False
            candidates[self._motion_candidates(frame, with_change=False)[0]] = True
        candidates |= self.stale
        ids = np.flatnonzero(candidates & self.tracked)
        pos, nrm = self.world_points(frame, ids)
        visible = in_any_view(pos, self.cameras, self.settings.view.distance_margin)
        if self.settings.selection:
            self.stale[ids] = ~visible
        return ids[visible], pos[visible], nrm[visible]

    def _moved_since(self, frame: Frame, last: Frame) -> list[int]:
        """Moving instances whose transform or (skinned) mesh differs between the two frames."""
        turned = (frame.transforms != last.transforms).any(axis=(1, 2))
        changed = changed_meshes(frame, last)
        return [i for i in self.kinds.moving if turned[i] or self.scene.instances[i].mesh in changed]

    def _motion_candidates(self, frame: Frame, with_change: bool = True,
                           before: Frame | None = None) -> tuple[np.ndarray, np.ndarray | None]:
        """Ids (sorted, tracked) of the points whose AO the motion since `before` (default: the last tick's
        frame) may have changed, and per id an estimate of how much (static points:
        selection.occlusion_change of the movers' spheres; a mover's own points: _mover_change), or None
        without `with_change` (the unbudgeted tick re-traces them all, in no order). Movers that stood still
        since then count as static boxes for the company test and select nothing themselves. Costs in
        proportion to the points near movers (NearCache), not to the scene."""
        before = self.last_frame if before is None else before
        moved = self._moved_since(frame, before)
        if not moved:
            return np.zeros(0, np.int64), np.zeros(0, np.float32) if with_change else None
        pick = lambda d: {i: d[i] for i in moved if i in d}  # noqa: E731
        motion = MotionInput(pick(frame.bounds), pick(before.bounds),
                             [i for i in self.kinds.rigid if i in moved], [i for i in self.kinds.skinned if i in moved],
                             pick(frame.spheres), pick(before.spheres))
        reach = reach_boxes(motion, self.scene.ao_distance)
        near, change = self.near_cache.near(reach, motion, with_change)
        runs, changes = [], []  # each mover's own points: consecutive ids, none of them static
        standing = {i: frame.bounds[i] for i in self.kinds.moving if i not in moved}
        for i in motion.skinned + rigid_in_company(motion, reach, {**self.static_boxes, **standing}):
            ids = self.ids_of[i]
            ids = ids[self.tracked[ids]]
            if len(ids):
                runs.append(ids)
                if with_change:
                    changes.append(np.full(len(ids), self._mover_change(i, frame, before), np.float32))
        # static ids are tracked
        return merge_disjoint(self.static_ids[near], change, runs, changes if with_change else None)

    def _mover_change(self, i: int, frame: Frame, before: Frame) -> float:
        """How much the AO of a moving instance's own points may have changed since `before`, on the
        scale of selection.occlusion_change: INSIDE_CHANGE once it has moved by its bounding radius or turned
        a radian; a deforming mesh counts as that much. The same constant as the floor of a static point
        inside a mover's sphere, on purpose: both say "the mover's surface moves around this point", so the
        two kinds rank alike."""
        if i in self.kinds.skinned:
            return INSIDE_CHANGE
        a, b = frame.transforms[i], before.transforms[i]
        (c, r), (c0, _) = frame.spheres[i], before.spheres[i]
        with np.errstate(all="ignore"):
            turn = np.linalg.solve(b[:3, :3].T, a[:3, :3].T).T  # a b^-1: the rotation between the frames
            angle = float(np.arccos(np.clip((np.trace(turn) - 1) / 2, -1.0, 1.0)))
        step = float(np.linalg.norm(np.asarray(c) - np.asarray(c0))) / max(float(r), 1e-9)
        return INSIDE_CHANGE * min(1.0, step + (angle if np.isfinite(angle) else 1.0))

    def world_points(self, frame: Frame, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """World positions (P, 3) float64 and normals (P, 3) float32 of points `ids` in `frame`: the moving
        instances' points all in one to_world_points pass, not one per instance (a tick's call holds a few
        points of many movers)."""
        pos, nrm = rows(self.world_pos, ids), rows(self.world_nrm, ids)  # (copies)
        at = np.flatnonzero(self.moving_point[ids])
        if len(at):
            mine = ids[at]
            pos[at], nrm[at] = to_world_points(frame.transforms, self.inst_of[mine], rows(self.local_pos, mine),
                                               rows(self.local_nrm, mine))
        return pos, nrm

    def _store(self, ids: np.ndarray, codes: np.ndarray) -> int:
        """Threshold and write traced AO. Returns the points written."""
        if len(ids) == 0:
            return 0
        self._check_locations(ids[self.slot[ids] >= 0])
        here = self.slot[ids] >= 0  # (a point an edit outside the tick removed stays out)
        ids, codes = ids[here], codes[here]
        old = (self.grid.cells[self.slot[ids], self.index[ids]] & np.uint32(0xFF)).astype(np.int64)
        write = np.abs(codes.astype(np.int64) - old) > self.settings.threshold
        self.grid.set_ao(self.slot[ids][write], self.index[ids][write], codes[write])
        return int(write.sum())


class AtRest(Tick):
    """The server tick with the scene held at t = 0 (no animation plays): refinement, and re-tracing what
    scene edits move."""
    threaded = places_instances = applies_edits = True

    def __init__(self, tick: ServerTick):
        self.tick = tick
        self.grid = tick.grid
        self.set_cameras, self.transforms, self.apply, self.close = tick.set_cameras, tick.transforms, tick.apply, tick.close
        self.edit, self.observe_service, self.set_tick_rate = tick.edit, tick.observe_service, tick.set_tick_rate

    def prepare(self, t: float):
        return self.tick.prepare(0.0)
