"""The server tick (DESIGN.md, server tick steps 1-5): animate, select, trace, quantise, threshold.

    tick = ServerTick(bake_result, TickSettings())   # static Embree scene built once, workers started
    grid = tick.grid                                   # serve this grid (fit_grid may have replaced bake.grid)
    tick.set_cameras([(view, proj), ...])              # from the clients' Camera messages
    tick(grid, t)                                      # one tick at scene time t (the service's TickFn)
    plan = tick.prepare(t); tick.apply(plan)           # the same in two halves: prepare writes no grid
    tick.transforms()                                  # (n, 4, 4) float32, for every Update

Points are identified by their stable point id (Grid.build numbers them instance by instance in
PointSet order, so id - first id of the instance is the point's index in its PointSet: that is how a
skinned point finds its triangle). The tick keeps per id: instance, current grid location (slot, index),
local position and normal, world position (static points: computed once), and a stale flag (a point the
selection wanted but no client could see).

Rigid instances never touch their points: the client moves them with the transform. Skinned instances
re-place every point on the deformed mesh; points that leave their cell are moved by the grid, and
points the grid could not keep (full cell or bucket) are kept aside ("parked") and re-inserted, with
freshly traced AO, as soon as they fit again. Grid.build sizes an instance's box from its rest pose, so
ServerTick first grows the boxes of skinned instances to their whole animation (TickSettings.fit_grid):
that replaces bake.grid, and the service must be given tick.grid.
"""
from __future__ import annotations

import logging
import time
from collections import deque
from dataclasses import asdict, dataclass, field

import numpy as np

from protocol import pointword as pw
from psao_server.animate import (Frame, SceneAnimator, SkinnedPoints, grid_for_animation, skinned_point_bounds,
                                 to_world_points)
from psao_server.bake import BakeResult, back_side_mask, scene_center, to_world
from psao_server.errors import ConfigError
from psao_server.grid import NO_POINT, Grid
from psao_server.selection import (BlockIndex, MotionInput, ViewSettings, camera_planes, in_any_view, reach_boxes,
                                   rigid_in_company, static_points_near)
from psao_server.tracer import TraceSettings, make_tracer

log = logging.getLogger("psao.tick")


@dataclass
class TickSettings:
    threshold: int = 2  # AO codes (of 255): a traced point is written only when |new - stored| > threshold
    rays: int = 32  # rays per traced point
    seed: int = 0  # ray seed; equal to the bake's so a synced bake needs no re-trace
    selection: bool = True  # False: re-trace every visible point every tick (the baseline)
    view: ViewSettings = field(default_factory=ViewSettings)
    tracer: str = "embree"
    workers: int = 0  # tracer processes, 0 = all cores
    block: float = 0.0  # world units of the static-point block index; 0 = the AO distance
    fit_grid: bool = True  # grow skinned instances' grid boxes to cover their whole animation (replaces the grid)
    history: int = 3600  # TickStats kept in stats_history (a minute at 60 Hz); older ones are dropped

    def check(self) -> None:
        if not 0 <= self.threshold <= 255:
            raise ConfigError(f"tick threshold must be within 0..255 AO codes, got {self.threshold}")
        if self.rays < 1:
            raise ConfigError(f"tick rays must be >= 1, got {self.rays}")
        if not (0 <= self.view.fov_margin < 180 and self.view.distance_margin >= 0):
            raise ConfigError(f"view margins out of range: {self.view}")


@dataclass
class TickStats:
    tick: int
    t: float  # scene time, seconds
    considered: int  # points the tick owns
    skipped: int  # considered - traced
    traced: int
    changed: int  # AO written (|new - old| > threshold) or re-inserted
    moved: int  # skinned points given new local positions
    parked: int  # skinned points the grid cannot hold at the moment
    cells_dirty: int  # cells marked dirty after the tick (= cells this tick dirtied when the service drains every tick)
    seconds_animate: float
    seconds_select: float
    seconds_trace: float
    seconds_grid: float
    seconds_total: float

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass
class TickPlan:
    """A prepared tick: what apply() writes."""
    frame: Frame
    moved: np.ndarray  # ids of held skinned points with a new local position or normal
    ids: np.ndarray  # ids traced
    codes: np.ndarray  # their new AO codes
    seconds: tuple[float, float, float]  # animate, select, trace


class ServerTick:
    def __init__(self, bake: BakeResult, settings: TickSettings | None = None, baked_time: float | None = 0.0,
                 close_bake_tracer: bool = True, trust_bake: bool = False):
        """`baked_time`: the scene time at which the bake traced the grid (its AO then counts as the first
        sync when the bake used the same rays and seed, or always with `trust_bake`: e.g. a 128-ray bake
        kept for the static parts while ticks trace fewer rays; a point re-traced later then jumps to the
        tick's estimate once), or None to re-trace everything visible on the first tick. The bake's
        tracer saw the moving instances as static: it is closed unless told not to."""
        self.settings = settings or TickSettings()
        self.settings.check()
        self.scene = bake.scene
        self.grid = bake.grid
        self.animator = SceneAnimator(self.scene)
        self.kinds = self.animator.kinds
        self.trace_settings = TraceSettings(rays=self.settings.rays, ao_distance=self.scene.ao_distance,
                                            seed=self.settings.seed)
        if close_bake_tracer and bake.tracer is not None:
            bake.tracer.close()
        self._init_points(bake)
        self._init_tracer()
        self.static_boxes = self.animator.static_bounds()
        self.cameras: list[np.ndarray] = []
        self.stats_history: deque[TickStats] = deque(maxlen=max(1, self.settings.history))
        self.tick_count = 0
        # the bake's AO is this tick's first sync only if it traced the same rays (count and seed)
        same_rays = (bake.stats.get("rays") == self.settings.rays
                     and bake.stats.get("seed", self.settings.seed) == self.settings.seed)
        if baked_time is not None and (same_rays or trust_bake):
            self.last_frame: Frame | None = self.animator.frame(baked_time)
        else:
            if baked_time is not None:
                log.info("bake traced %s rays (seed %s), the tick %d (seed %d): the first tick re-traces every "
                         "visible point", bake.stats.get("rays"), bake.stats.get("seed", "?"), self.settings.rays,
                         self.settings.seed)
            self.last_frame = None
            self.stale[self.present()] = True
        self._transforms = (self.last_frame.transforms if self.last_frame else self.animator.transforms(0.0)).astype(np.float32)

    # ------------------------------------------------------------------ set-up
    def _init_points(self, bake: BakeResult) -> None:
        sizes = [len(ps) for ps in bake.pointsets]
        self.first_id = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
        n = int(self.first_id[-1])
        self.inst_of = np.repeat(np.arange(len(sizes)), sizes)
        self.local_pos = np.concatenate([ps.positions for ps in bake.pointsets]).astype(np.float64) if n else np.zeros((0, 3))
        self.local_nrm = np.concatenate([ps.normals for ps in bake.pointsets]).astype(np.float32) if n else np.zeros((0, 3), np.float32)
        self.back = np.concatenate([np.zeros(len(ps), bool) if (b := back_side_mask(ps, self.scene.meshes[inst.mesh].double_sided)) is None
                                    else b for ps, inst in zip(bake.pointsets, self.scene.instances)]) if n else np.zeros(0, bool)
        self.slot = np.full(n, -1, np.int64)
        self.index = np.full(n, -1, np.int64)
        self._relocate_all()
        if self.grid.n_points() != int((self.slot >= 0).sum()):
            raise ConfigError("the grid's point ids do not match the bake's point sets (not built by Grid.build?)")
        self.tracked = self.slot >= 0  # points the grid held after the bake; dropped ones stay dropped
        if self.kinds.skinned and self.settings.fit_grid:
            bounds = skinned_point_bounds(self.scene, bake.pointsets, self.kinds.skinned, self.animator.skinner)
            grown = grid_for_animation(self.grid, bounds)
            if grown is not None:
                log.info("grid boxes of skinned instances grown to cover their animation: the grid is replaced")
                self.grid = bake.grid = grown
                self._relocate_all()
        self.stale = np.zeros(n, dtype=bool)
        self.skinned = {i: SkinnedPoints.from_pointset(self.scene.meshes[self.scene.instances[i].mesh], bake.pointsets[i])
                        for i in self.kinds.skinned}
        # static points: world positions and normals once, and a block index for box queries
        static = np.isin(self.inst_of, self.kinds.static) & self.tracked
        self.static_ids = np.flatnonzero(static)
        self.world_pos = np.zeros((n, 3))
        self.world_nrm = np.zeros((n, 3), np.float32)
        for i in self.kinds.static:
            ids = self.static_ids[self.inst_of[self.static_ids] == i]
            self.world_pos[ids], self.world_nrm[ids] = to_world(self.scene.instances[i].transform, self.local_pos[ids],
                                                                self.local_nrm[ids])
        block = self.settings.block or self.scene.ao_distance
        self.block_index = BlockIndex(self.world_pos[self.static_ids], block)
        self.static_normals = self.world_nrm[self.static_ids].astype(np.float64)

    def _init_tracer(self) -> None:
        s = self.settings
        kwargs = {"workers": s.workers} if s.tracer == "embree" else {}
        self.tracer = make_tracer(s.tracer, scene_center(self.scene), **kwargs)
        self.tracer.set_static(*self.animator.static_geometry())
        if hasattr(self.tracer, "warm_up"):
            self.tracer.warm_up()  # forks the workers: before any thread or event loop starts

    def close(self) -> None:
        self.tracer.close()

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

    def _relocate_instances(self, instances: list[int]) -> None:
        if not instances:
            return
        mine = np.isin(self.inst_of, instances)
        self.slot[mine] = -1
        self.index[mine] = -1
        self._relocate_cells(np.flatnonzero(np.isin(self.grid.cell_instance, instances)))

    def _check_locations(self, ids: np.ndarray) -> None:
        """Someone else (a compaction, a scene edit) may have moved points: find them again (ids: points
        believed present; afterwards present() tells where they really are)."""
        ok = self.grid.point_id[self.slot[ids], self.index[ids]] == ids
        if not ok.all():
            log.info("grid edited outside the tick: re-locating every point")
            self._relocate_all()

    # ------------------------------------------------------------------ public API
    def set_cameras(self, cameras) -> None:
        """Cameras as (view 4x4, projection 4x4) pairs (OpenGL conventions); [] means: every point visible,
        and so does a camera whose matrices make no frustum (NaN, singular)."""
        self.cameras = [camera_planes(v, p, self.settings.view.fov_margin) for v, p in cameras]

    def transforms(self) -> np.ndarray:
        """(n_instances, 4, 4) float32 transforms of the last tick."""
        return self._transforms

    def stats_json(self) -> list[dict]:
        return [s.to_dict() for s in self.stats_history]

    def __call__(self, grid: Grid, t: float) -> TickStats:
        """One tick at scene time t: prepare (no grid writes) then apply."""
        if grid is not self.grid:
            raise ConfigError("ServerTick was built for another grid (after fit_grid, use tick.grid)")
        return self.apply(self.prepare(t))

    def prepare(self, t: float) -> "TickPlan":
        """Animate, select and trace at scene time t without writing the grid: it may run in a worker
        thread while the event loop reads the grid for sending. `apply` must follow before the next one."""
        t_start = time.perf_counter()
        frame = self.animator.frame(t)
        moved = self._deform(frame)
        t_anim = time.perf_counter()
        ids, pos, nrm = self._select(frame)
        t_sel = time.perf_counter()
        vis = np.zeros(0, np.float32)
        if len(ids):  # the moving scene is only (re)built when something is traced
            self.tracer.set_dynamic(frame.dynamic_vertices, frame.dynamic_faces)
            vis = self.tracer.visibility(pos, nrm, ids, self.trace_settings)
        t_trace = time.perf_counter()
        return TickPlan(frame, moved, ids, pw.quantise_ao(vis), (t_anim - t_start, t_sel - t_anim, t_trace - t_sel))

    def apply(self, plan: "TickPlan") -> TickStats:
        """Write a prepared tick into the grid (moves, thresholded AO, re-inserts): a few milliseconds, on
        the thread that owns the grid. Marks the cells and buckets it changes dirty."""
        g0 = time.perf_counter()
        if len(plan.moved):
            self._check_locations(plan.moved)
            go = plan.moved[self.present()[plan.moved]]
            self.grid.move_points(self.slot[go], self.index[go], self.local_pos[go], self.local_nrm[go])
            self._relocate_instances(self.kinds.skinned)
        changed = self._store(plan.ids, plan.codes)
        seconds_grid = time.perf_counter() - g0
        self.last_frame = plan.frame
        self._transforms = plan.frame.transforms.astype(np.float32)
        n = int(self.tracked.sum())
        animate, select, trace = plan.seconds
        stats = TickStats(
            tick=self.tick_count, t=plan.frame.t, considered=n, skipped=n - len(plan.ids), traced=int(len(plan.ids)),
            changed=changed, moved=int(len(plan.moved)), parked=int((self.tracked & ~self.present()).sum()),
            cells_dirty=int(np.count_nonzero(self.grid.dirty_cells)),
            seconds_animate=animate, seconds_select=select, seconds_trace=trace, seconds_grid=seconds_grid,
            seconds_total=animate + select + trace + seconds_grid)
        self.tick_count += 1
        self.stats_history.append(stats)
        return stats

    # ------------------------------------------------------------------ steps
    def _deform(self, frame: Frame) -> np.ndarray:
        """Skinned points to their new local positions (the tick's arrays only); returns the ids of the
        points the grid holds whose position or normal changed (apply moves them)."""
        moved = []
        for i, sp in self.skinned.items():
            mesh = self.scene.meshes[self.scene.instances[i].mesh]
            pos, nrm = sp.follow(mesh.faces, frame.mesh_vertices[self.scene.instances[i].mesh])
            ids = np.arange(self.first_id[i], self.first_id[i + 1])
            change = np.any(pos != self.local_pos[ids], axis=1) | np.any(nrm != self.local_nrm[ids], axis=1)
            self.local_pos[ids], self.local_nrm[ids] = pos, nrm
            moved.append(ids[change & self.present()[ids]])
        return np.concatenate(moved) if moved else np.zeros(0, np.int64)

    def _select(self, frame: Frame) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Point ids to trace this tick (sorted) with their world positions and normals; updates the
        stale flags."""
        candidates = self.tracked.copy() if not self.settings.selection or self.last_frame is None else self._motion_candidates(frame)
        candidates |= self.stale
        ids = np.flatnonzero(candidates & self.tracked)
        pos, nrm = self.world_points(frame, ids)
        visible = in_any_view(pos, self.cameras, self.settings.view.distance_margin)
        if self.settings.selection:
            self.stale[ids] = ~visible
        return ids[visible], pos[visible], nrm[visible]

    def _motion_candidates(self, frame: Frame) -> np.ndarray:
        motion = MotionInput(frame.bounds, self.last_frame.bounds, self.kinds.rigid, self.kinds.skinned,
                             frame.spheres, self.last_frame.spheres)
        reach = reach_boxes(motion, self.scene.ao_distance)
        out = np.zeros(len(self.tracked), dtype=bool)
        near = static_points_near(self.block_index, reach, motion, self.static_normals, self.scene.ao_distance)
        out[self.static_ids[near]] = True
        for i in self.kinds.skinned + rigid_in_company(motion, reach, self.static_boxes):
            out[self.first_id[i]:self.first_id[i + 1]] = True
        return out

    def world_points(self, frame: Frame, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """World positions (P, 3) float64 and normals (P, 3) float32 of points `ids` in `frame`."""
        pos = self.world_pos[ids].copy()
        nrm = self.world_nrm[ids].copy()
        inst = self.inst_of[ids]
        for i in self.kinds.moving:
            sel = np.flatnonzero(inst == i)
            if len(sel):
                pos[sel], nrm[sel] = to_world_points(frame.transforms[i], self.local_pos[ids[sel]], self.local_nrm[ids[sel]])
        return pos, nrm

    def _store(self, ids: np.ndarray, codes: np.ndarray) -> int:
        """Threshold and write traced AO; re-insert parked skinned points. Returns the points written."""
        if len(ids):
            self._check_locations(ids[self.present()[ids]])
        here = self.present()[ids]
        have, new = ids[here], codes[here]
        changed = 0
        if len(have):
            old = (self.grid.cells[self.slot[have], self.index[have]] & np.uint32(0xFF)).astype(np.int64)
            write = np.abs(new.astype(np.int64) - old) > self.settings.threshold
            self.grid.set_ao(self.slot[have][write], self.index[have][write], new[write])
            changed += int(write.sum())
        parked = ids[~here]
        if len(parked):
            insts = self.inst_of[parked]
            for i in np.unique(insts).tolist():
                sel = parked[insts == i]
                kept = self.grid.insert_points(i, self.local_pos[sel], self.local_nrm[sel], codes[~here][insts == i], sel,
                                               back=self.back[sel])
                changed += int(kept.sum())
            self._relocate_instances(np.unique(insts).tolist())
        return changed
