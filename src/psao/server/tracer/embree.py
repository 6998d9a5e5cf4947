"""Embree back-end (embreex): occlusion queries limited to the AO distance, spread over processes.

Processes rather than threads: embreex lets go of the GIL while Embree traverses, but making the rays and
testing them against the movers' spheres hold it, so at a tick's sizes two threads traced fewer rays a
second than one. Each worker process keeps its own
Embree scenes (the static one built once at start, the deforming one refitted when its version changes,
embree_refit.py) and traces whole chunks of points: directions are generated in the worker, only positions, normals and
ids travel, and only one float per point comes back.
"""
from __future__ import annotations

import multiprocessing as mp
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
import os
import signal
import threading
import time
from contextlib import contextmanager

import numpy as np

from psao.server.errors import TracerError
from psao.server.settings import TraceSettings
from psao.server.arrays import rows
from psao.server.tracer.base import CpuAccount, TracePart, Tracer, recentre, recentre_poses
from psao.server.tracer.directions import cosine_directions, ray_origins, rotation_of
from psao.server.tracer.embree_refit import RefitMesh

try:  # deferred: the error surfaces when the back-end is asked for, not on import of the package
    from embreex import rtcore, rtcore_scene
    from embreex.mesh_construction import TriangleMesh
    _IMPORT_ERROR = None
except ImportError as exc:  # pragma: no cover - embreex is a hard dependency here
    _IMPORT_ERROR = exc


_DEVICE = None  # one Embree device per process: every scene built here shares it


def _device():
    global _DEVICE
    if _DEVICE is None:
        _DEVICE = rtcore.EmbreeDevice()
    return _DEVICE


def _build_scene(vertices: np.ndarray, faces: np.ndarray):
    if len(faces) == 0:
        return None
    scene = rtcore_scene.EmbreeScene(_device())
    TriangleMesh(scene, np.ascontiguousarray(vertices, np.float32), np.ascontiguousarray(faces, np.int32))
    return scene


class _Rigid:
    """A rigidly moving mesh traced in its own local frame: built once; each tick only its pose changes,
    and rays are taken into the local frame instead (an affine map keeps the ray parameter t, so the
    occlusion distance needs no rescaling)."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray):
        self.scene = _build_scene(vertices, faces)
        v = np.asarray(vertices, np.float64)
        self.centre = (v.min(axis=0) + v.max(axis=0)) / 2 if len(v) else np.zeros(3)  # a bounding sphere, local frame
        self.radius = float(np.sqrt(((v - self.centre) ** 2).sum(axis=1).max())) if len(v) else 0.0
        self._pose_key: bytes | None = None  # the pose _placed last worked out, and its answer
        self._pose_placed = None

    def _placed(self, pose: np.ndarray):
        """(world sphere centre, radius, inverse pose) at `pose`: the chunks of one call share a pose, so it
        is worked out once per pose (a 3x3 singular value decomposition and an inverse cost more than a
        small chunk's sphere test)."""
        key = pose.tobytes()
        if key != self._pose_key:
            scale = float(np.linalg.norm(pose[:3, :3], 2))  # the largest stretch, shear included
            self._pose_placed = (pose[:3, :3] @ self.centre + pose[:3, 3], self.radius * scale, np.linalg.inv(pose))
            self._pose_key = key
        return self._pose_placed

    def placed_sphere(self, pose: np.ndarray) -> tuple[np.ndarray, float]:
        """The world bounding sphere (centre, radius) at `pose`."""
        centre, radius, _ = self._placed(pose)
        return centre, radius

    def occlude(self, pose: np.ndarray, origins, dirs, tmax, hit: np.ndarray, rays: np.ndarray,
                retest: bool = False) -> None:
        """Mark in `hit` which of the rays `rays` (indices of world, re-centred rays whose segments reach this
        mesh's bounding sphere at `pose`: mover_rays; with `retest`, that may reach it) this mesh at `pose`
        (4x4 local -> world) occludes: they are taken into the local frame and traced."""
        if self.scene is None or len(rays) == 0:
            return
        centre, radius, inv = self._placed(pose)
        if retest:
            rays = rays[segments_reach_sphere(rows(origins, rays), rows(dirs, rays), tmax, centre, radius)]
        if len(rays):
            o = (rows(origins, rays) @ inv[:3, :3].T + inv[:3, 3]).astype(np.float32)
            d = (rows(dirs, rays) @ inv[:3, :3].T).astype(np.float32)
            hit[rays] = self.scene.run(o, d, dists=np.full(len(rays), tmax, np.float32), query="OCCLUDED") != -1


def segments_reach_sphere(origins, dirs, tmax: float, centre, radius: float) -> np.ndarray:
    """Bool per ray: whether the segment origin + t dir, t in [0, tmax], comes within `radius` of
    `centre` (dirs need not be unit: t is the ray parameter). Conservative by a relative 1e-4 of the radius."""
    # per coordinate (einsum over (N, 3) float32 costs several times more)
    c = [np.float32(centre[k]) - origins[:, k] for k in range(3)]
    d = [dirs[:, k] for k in range(3)]
    dd = d[0] * d[0] + d[1] * d[1] + d[2] * d[2]
    t = np.clip((d[0] * c[0] + d[1] * c[1] + d[2] * c[2]) / np.maximum(dd, np.float32(1e-30)), 0.0, tmax)
    gap = [c[k] - t * d[k] for k in range(3)]
    r = np.float32(grown(radius))
    return gap[0] * gap[0] + gap[1] * gap[1] + gap[2] * gap[2] <= r * r


def grown(radius):
    """A bounding sphere's radius with the slack that keeps the float32 segment tests conservative."""
    return radius * (1 + 1e-4) + 1e-6


PIECE_SLABS = 4  # bounding spheres per deforming piece (PieceSlabs): tighter spheres, fewer rays traced


class PieceSlabs:
    """The deforming triangles cut into runs, each bounded by a sphere per pose. Per piece (`parts`:
    consecutive vertex counts, a triangle belonging to the piece of its first vertex; None: one piece), its
    triangles are cut into `slabs` runs along the piece's longest axis by their centroids in the first pose,
    so a limb far from the body gets a sphere of its own and fewer rays reach a sphere. The runs are chosen
    once per mesh; each pose only gathers every run's vertices and reduces them (min, max, farthest corner),
    so a skinned mesh's spheres cost a few vectorised passes a tick. Every triangle lies within the sphere
    of its run in every pose, whatever the pose the runs were chosen in."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, parts, slabs: int = PIECE_SLABS):
        v = np.asarray(vertices, np.float64)
        f = np.asarray(faces, np.int64)
        self.faces = np.array(faces, copy=True)
        self.parts = None if parts is None else tuple(int(n) for n in parts)
        if parts is None or sum(int(n) for n in parts) != len(v):
            parts = [len(v)]  # (pieces that do not cover every vertex: one piece)
        piece = np.searchsorted(np.cumsum([int(n) for n in parts]), f[:, 0], side="right")
        runs = []
        for k in np.unique(piece):
            mine = np.flatnonzero(piece == k)
            corners = v[f[mine]]  # (T, 3, 3)
            lo, hi = corners.min(axis=(0, 1)), corners.max(axis=(0, 1))
            along = corners.mean(axis=1)[:, int(np.argmax(hi - lo))]
            for run in np.array_split(mine[np.argsort(along, kind="stable")], min(slabs, len(mine))):
                runs.append(np.unique(f[run]))  # the run's corners, each vertex once
        self.index = np.concatenate(runs) if runs else np.zeros(0, np.int64)
        sizes = np.array([len(r) for r in runs], np.int64)
        self.starts = np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(np.int64)
        self.sizes = sizes

    def same_mesh(self, faces: np.ndarray, parts) -> bool:
        """Whether `faces` and `parts` are the ones the runs were chosen for."""
        same_parts = (parts is None and self.parts is None
                      or parts is not None and self.parts is not None and tuple(int(n) for n in parts) == self.parts)
        return same_parts and faces.shape == self.faces.shape and np.array_equal(faces, self.faces)

    def spheres(self, vertices: np.ndarray) -> list[tuple[np.ndarray, float]]:
        """(centre, radius) per run in the pose `vertices`."""
        if len(self.sizes) == 0:
            return []
        p = np.asarray(vertices, np.float64)[self.index]
        centre = (np.minimum.reduceat(p, self.starts, axis=0) + np.maximum.reduceat(p, self.starts, axis=0)) / 2
        gap = p - np.repeat(centre, self.sizes, axis=0)
        radius = np.sqrt(np.maximum.reduceat(np.einsum("pi,pi->p", gap, gap), self.starts))
        return [(c, float(r)) for c, r in zip(centre, radius)]


def sphere_bits(count: int) -> np.ndarray:
    """(count,) uint32: the bit of sphere s in mover_rays' answer (s % 32: beyond 32 spheres, bits are shared
    and a ray's bit only says that it may reach one of the spheres that share it)."""
    return (np.uint32(1) << (np.arange(count) % 32).astype(np.uint32)).astype(np.uint32)


def mover_rays(origins, dirs, tmax, hit, rays_per_point: int, spheres: list[tuple[np.ndarray, float]]) -> np.ndarray:
    """(R,) uint32 per ray: sphere_bits of the spheres (centre, radius) its segment reaches, for rays not
    `hit` yet (0 for the others). Rays come in runs of `rays_per_point` sharing an origin. Only these rays
    can be occluded by a mover inside one of the spheres: the rest (most rays, even near a mover) are never
    traced against the movers. Compiled (kernels.RayBuffers.reached) where Warp is present."""
    centres = np.array([c for c, _ in spheres], np.float64).reshape(-1, 3)
    radii = np.array([r for _, r in spheres], np.float64)
    buffers = _ray_buffers()
    if buffers is not False:
        return buffers.reached(origins, dirs, hit, rays_per_point, tmax, centres, grown(radii))
    out = np.zeros(len(origins), np.uint32)
    points = origins[::rays_per_point]
    for c, r, bit in zip(centres, radii, sphere_bits(len(radii))):
        gap = points - c.astype(np.float32)
        near = np.flatnonzero(np.einsum("pi,pi->p", gap, gap) <= (tmax + grown(r)) ** 2)
        rays = (near[:, None] * rays_per_point + np.arange(rays_per_point)).ravel()
        rays = rays[~hit[rays]]
        out[rays[segments_reach_sphere(origins[rays], dirs[rays], tmax, c, r)]] |= bit
    return out


class EmbreeScenes:
    """The Embree scenes of one process: static (built once), rigid movers (built once, posed per call)
    and the deforming rest (per version: refitted while its triangles stay the same, else rebuilt)."""

    def __init__(self, static_vertices, static_faces, rigid=()):
        self.static = _build_scene(static_vertices, static_faces)
        self.rigid = [_Rigid(v, f) for v, f in rigid]
        self.rigid_poses = None
        self.dynamic = None
        self.dynamic_spheres: list[tuple[np.ndarray, float]] = []  # bounding spheres of its pieces' runs
        self._slabs: PieceSlabs | None = None  # the runs of the deforming mesh, kept while it only moves
        self.dynamic_version = -1
        self._refit: RefitMesh | None = None

    def update_dynamic(self, version, vertices, faces, rigid_poses=None, parts=None):
        """The deforming triangles of `version` (vertices None: none; `parts`: vertex counts of its
        separately moving pieces, see RefitMesh) and the rigid movers' poses."""
        if version != self.dynamic_version:
            self.dynamic = self._deforming(vertices, faces, parts) if vertices is not None else None
            self.dynamic_spheres = self._spheres(vertices, faces, parts) if self.dynamic is not None else []
            self.dynamic_version = version
        self.rigid_poses = rigid_poses

    def _spheres(self, vertices, faces, parts):
        if len(faces) == 0:
            return []
        if self._slabs is None or not self._slabs.same_mesh(faces, parts):
            self._slabs = PieceSlabs(vertices, faces, parts)
        return self._slabs.spheres(vertices)

    def _deforming(self, vertices, faces, parts):
        if self._refit is not None and self._refit.same_mesh(vertices, faces, parts):
            self._refit.move(vertices)
            return self._refit.scene
        self._refit = RefitMesh.build(vertices, faces, _device(), parts)
        return self._refit.scene if self._refit is not None else _build_scene(vertices, faces)

    def occluded(self, origins, dirs, tmax, rays_per_point: int = 1, static_hit: np.ndarray | None = None,
                 static_out: np.ndarray | None = None, static_known: np.ndarray | None = None) -> np.ndarray:
        """A ray is occluded if any scene hits within tmax; each further scene only sees the rays the
        ones before let through. Rays come in runs of `rays_per_point` that share an origin (a point's).
        `static_hit`: per ray, whether the static scene occludes it, known already (static_occluded): the
        static scene is not traced for those rays (all of them, or where `static_known` is True; it traces
        the others), the moving parts see only the other rays. `static_out`: filled with the static
        scene's own answer per ray (what the static scene decides before the movers are asked)."""
        if len(origins) % rays_per_point:
            raise TracerError(f"{len(origins)} rays are not runs of {rays_per_point}")
        dists = np.full(len(origins), tmax, np.float32)
        hit = self._static_answers(origins, dirs, dists, static_hit, static_known)
        if static_out is not None:
            static_out[:] = hit
        self._movers_occlude(origins, dirs, tmax, dists, rays_per_point, hit)
        return hit

    def _static_answers(self, origins, dirs, dists, static_hit, static_known) -> np.ndarray:
        """Per ray, whether the static scene occludes it: `static_hit` where known (all rays without
        `static_known`), traced (one query for the rest) elsewhere."""
        if static_hit is not None and static_known is None:
            return np.array(static_hit, dtype=bool)
        hit = np.zeros(len(origins), dtype=bool) if static_hit is None else np.array(static_hit, dtype=bool)
        todo = None if static_known is None else np.flatnonzero(~np.asarray(static_known, bool))
        if static_known is not None:
            hit[todo] = False
        if self.static is None or (todo is not None and len(todo) == 0):
            return hit
        if todo is None:
            return self.static.run(origins, dirs, dists=dists, query="OCCLUDED") != -1
        hit[todo] = self.static.run(rows(origins, todo), rows(dirs, todo), dists=dists[todo], query="OCCLUDED") != -1
        return hit

    def _movers_occlude(self, origins, dirs, tmax, dists, rays_per_point: int, hit: np.ndarray) -> None:
        """Mark in `hit` the rays not hit yet that a mover occludes (only those reaching its spheres)."""
        rigid = ([(mesh, pose) for mesh, pose in zip(self.rigid, self.rigid_poses) if mesh.scene is not None]
                 if self.rigid_poses is not None else [])
        spheres = self.dynamic_spheres + [mesh.placed_sphere(pose) for mesh, pose in rigid]
        if not spheres:
            return
        bits = sphere_bits(len(spheres))
        reach = mover_rays(origins, dirs, tmax, hit, rays_per_point, spheres)
        todo = np.flatnonzero(reach)
        if self.dynamic is not None:
            mine = todo[(reach[todo] & np.bitwise_or.reduce(bits[:len(self.dynamic_spheres)])) != 0]
            if len(mine):
                hit[mine] = self.dynamic.run(rows(origins, mine), rows(dirs, mine), dists=dists[mine],
                                             query="OCCLUDED") != -1
        shared = len(spheres) > len(np.unique(bits))  # a bit then stands for several spheres: test each again
        for (mesh, pose), bit in zip(rigid, bits[len(self.dynamic_spheres):]):
            mine = todo[(reach[todo] & bit) != 0]
            mesh.occlude(pose, origins, dirs, tmax, hit, mine[~hit[mine]], retest=shared)


# Per thread (so per process too): Warp ray buffers, or False when Warp is unavailable. Two tracers of one
# process may trace at once on different threads (the server tick's, and its refiner's on a thread of its
# own), and one set of buffers would hand each the other's rays.
_RAYS = threading.local()


@contextmanager
def numpy_rays():
    """Within it, this thread makes its rays with numpy instead of the Warp kernel: no Warp import (half a
    second) for a small in-process trace at start-up; the directions agree within 2e-5 (tests/test_tracer.py)."""
    before = getattr(_RAYS, "buffers", None)
    _RAYS.buffers = False
    try:
        yield
    finally:
        _RAYS.buffers = before


def _ray_buffers():
    """This thread's kernels.RayBuffers (made at its first use), or False: numpy instead (no Warp here, or
    within numpy_rays)."""
    rays = getattr(_RAYS, "buffers", None)
    if rays is None:
        try:
            from psao.server.tracer.kernels import RayBuffers  # (Warp: imported at the first trace that makes rays)
            rays = RayBuffers()
        except ImportError:
            rays = False
        _RAYS.buffers = rays
    return rays


def _chunk_rays(pos, nrm, ids, s: TraceSettings, first):
    """Origins and directions of directions.py, (P * K', 3) each, for the slice of each point's ray set
    that starts at `first` (one int or one per point); through the compiled Warp kernel when Warp is
    present (numpy temporaries cost about as much as Embree's traversal), else numpy."""
    rays = _ray_buffers()
    if rays is False:
        dirs = cosine_directions(ids, nrm, s.rays, s.seed, first, s.slices).reshape(-1, 3)
        return np.repeat(ray_origins(pos, nrm, s.ao_distance), len(dirs) // max(len(pos), 1), axis=0), dirs
    return rays.rays(pos, nrm, *rotation_of(ids, s.seed), s.rays, s.ao_distance, first, s.slices)


def trace_chunk(scenes: EmbreeScenes, pos, nrm, ids, s: TraceSettings, first=None, static_bits=None,
                 keep_static: bool = False):
    """Visibility of a chunk of points, with the seconds the Embree query and the whole chunk took in this
    worker (perf_counter: a CPU-time clock is a system call, which on a loaded machine can cost more
    than a small chunk's tracing) and the static scene's answers, bit-packed per point (P, ceil(K / 8)),
    when `keep_static` (else None). `static_bits`: those answers known already (whole ray sets only):
    the static scene is not traced. The tracer's throughput against bare Embree is measured as a run of
    its own (benchmarks/bench_realtime.py), not from these."""
    return _trace_chunks(scenes, [(pos, nrm, ids, s, first, static_bits, keep_static)])[0]


def _trace_chunks(scenes: EmbreeScenes, chunks: list[tuple]) -> list[tuple]:
    """trace_chunk of each chunk (pos, nrm, ids, settings, first, static_bits, keep_static), the chunks of
    one AO distance traced together: each chunk's rays are made as its own, then the static scene is
    queried once for every ray whose answer is not given and the movers once for all of them, so a call of
    several small parts (a tick's) pays each query's fixed cost once. A ray's answer does not depend on the
    rays traced beside it: the answers are each chunk's own. The seconds are shared out by rays."""
    if not chunks:
        return []
    if len({c[3].ao_distance for c in chunks}) > 1:
        return [r for c in chunks for r in _trace_chunks(scenes, [c])]
    t0 = time.perf_counter()
    made = []
    for pos, nrm, ids, s, first, _, _ in chunks:
        org, dirs = _chunk_rays(pos, nrm, ids, s, s.slice if first is None else first)
        made.append((org, dirs) if len(chunks) == 1 else (org.copy(), dirs.copy()))  # (buffers: reused per call)
    counts = [len(org) for org, _ in made]
    per_point = [max(n // max(len(c[0]), 1), 1) for n, c in zip(counts, chunks)]
    org = made[0][0] if len(made) == 1 else np.concatenate([o for o, _ in made])
    dirs = made[0][1] if len(made) == 1 else np.concatenate([d for _, d in made])
    t1 = time.perf_counter()
    given = [None if c[5] is None else np.unpackbits(c[5], axis=1, count=k).ravel().astype(bool)
             for c, k in zip(chunks, per_point)]
    static_hit = static_known = None
    if any(g is not None for g in given):
        static_hit = np.concatenate([np.zeros(n, bool) if g is None else g for g, n in zip(given, counts)])
        if any(g is None for g in given):
            static_known = np.concatenate([np.full(n, g is not None) for g, n in zip(given, counts)])
    keep = any(c[6] for c in chunks)
    static = np.empty(len(org), bool) if keep else None
    run = int(np.gcd.reduce(per_point))  # every chunk's rays are runs of this many that share an origin
    hit = scenes.occluded(org, dirs, chunks[0][3].ao_distance, run, static_hit, static, static_known)
    t2 = time.perf_counter()
    out, at, total = [], 0, max(len(org), 1)
    for c, n in zip(chunks, counts):
        p = len(c[0])
        vis = 1.0 - hit[at:at + n].reshape(p, -1).mean(axis=1, dtype=np.float32)
        bits = np.packbits(static[at:at + n].reshape(p, -1), axis=1) if c[6] else None
        out.append((vis, (t2 - t1) * n / total, (time.perf_counter() - t0) * n / total, bits))
        at += n
    return out


# ---- worker-process side
_WORKER: EmbreeScenes | None = None


def worker_context():
    """The multiprocessing context of every worker pool that uses Embree: forkserver. Embree runs on TBB,
    whose worker threads and locks do not survive a fork: a process forked while the parent's TBB threads
    were busy (an in-process trace or scene build a moment before) waits forever on a lock held by a thread
    it does not have. Workers forked from the fork server, which never touches Embree, start clean; the
    server preloads this module and the Warp ray kernels (tracer/forkserver_preload.py), so a worker starts
    with them loaded."""
    ctx = mp.get_context("forkserver")
    ctx.set_forkserver_preload(["psao.server.tracer.forkserver_preload"])
    return ctx


def load_ray_kernels() -> None:
    """Load this thread's ray maker now (the Warp kernels, compiled on first use), not in the first trace."""
    _chunk_rays(np.zeros((1, 3), np.float32), np.array([[0, 0, 1]], np.float32), np.zeros(1, np.int64),
                TraceSettings(rays=1), 0)


def _alive(pid: int) -> bool:
    """Whether process `pid` runs (a zombie does not)."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] not in ("Z", "X")
    except FileNotFoundError:
        return False
    except OSError:  # no /proc here: ask the kernel
        try:
            os.kill(pid, 0)
            return True
        except ProcessLookupError:
            return False


def die_with(parent: int) -> None:
    """End this worker when `parent` (the process that made the pool, not the fork server that forked us)
    dies, even by kill -9: nothing else would, the pool's own shutdown never runs. A daemon thread watches."""

    def watch():
        while _alive(parent):
            time.sleep(0.25)
        os._exit(1)

    threading.Thread(target=watch, name="parent-watch", daemon=True).start()


def _worker_init(parent, static_vertices, static_faces, rigid):
    global _WORKER
    die_with(parent)
    # Ctrl-C reaches the whole process group: the parent shuts the pool down, workers must not die first.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    _WORKER = EmbreeScenes(static_vertices, static_faces, rigid)


def _worker_trace(job):
    version, dyn_v, dyn_f, parts, poses, pos, nrm, ids, s, first, static_bits, keep_static = job
    _WORKER.update_dynamic(version, dyn_v, dyn_f, poses, parts)
    return trace_chunk(_WORKER, pos, nrm, ids, s, first, static_bits, keep_static)


def _worker_ping(_):
    return _WORKER is not None


class EmbreeTracer(Tracer):
    name = "embree"
    supports_static_hits = True

    def __init__(self, center=(0.0, 0.0, 0.0), workers: int = 0):
        if _IMPORT_ERROR is not None:
            raise TracerError(f"the embree back-end needs embreex: {_IMPORT_ERROR}")
        self.center = np.asarray(center, np.float64)
        self.workers = workers or os.cpu_count() or 1
        self._static = (np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int32))
        self._dynamic = (None, None, None)  # deforming vertices, faces, parts
        self._dynamic_version = 0
        self._rigid: list = []
        self._poses = None
        self._local: EmbreeScenes | None = None
        self._pool = None
        self.account = CpuAccount()

    # geometry -------------------------------------------------------------
    def _recentre(self, vertices) -> np.ndarray:
        return recentre(vertices, self.center)

    def set_static(self, vertices, faces) -> None:
        self.close()
        self._static = (self._recentre(vertices), np.asarray(faces, np.int32))
        self._local = EmbreeScenes(*self._static, self._rigid)

    def set_rigid(self, meshes) -> None:
        self.close()
        self._rigid = [(np.asarray(v, np.float32), np.asarray(f, np.int32)) for v, f in meshes]
        self._local = EmbreeScenes(*self._static, self._rigid)

    def set_dynamic(self, vertices, faces, rigid_transforms=None, parts=None) -> None:
        self._poses = recentre_poses(rigid_transforms, self.center)
        # The deforming part is refitted (in every process that traces it) only when it is given anew.
        if vertices is None or len(faces) == 0:
            if self._dynamic[0] is None:
                return
            self._dynamic = (None, None, None)
        else:
            self._dynamic = (self._recentre(vertices), np.asarray(faces, np.int32), parts)
        self._dynamic_version += 1
        # The in-process scenes catch up lazily, when a small call traces here rather than in the workers.

    # tracing --------------------------------------------------------------
    def _jobs(self, positions, normals, point_ids, s: TraceSettings, slice_of=None, static_bits=None,
              keep_static: bool = False, spread: bool = True):
        pos = self._recentre(positions)
        nrm = np.asarray(normals, np.float32)
        ids = np.asarray(point_ids, np.int64)
        # With `spread` (for the workers) at least one chunk per worker, so small point sets are spread over
        # every worker too; traced here, as few chunks as chunk_points allows (each has fixed costs).
        step = max(1, min(s.chunk_points, -(-len(pos) // (self.workers if spread else 1))))
        for i in range(0, len(pos), step):
            yield (self._dynamic_version, *self._dynamic, self._poses, pos[i:i + step], nrm[i:i + step],
                   ids[i:i + step], s, None if slice_of is None else slice_of[i:i + step],
                   None if static_bits is None else static_bits[i:i + step], keep_static)

    def _ensure_pool(self):
        if self._pool is None and self.workers > 1:
            load_ray_kernels()  # compiled here on first use, once, before the fork server loads them too
            # ProcessPoolExecutor rather than Pool: a dead worker raises BrokenProcessPool instead of hanging.
            self._pool = ProcessPoolExecutor(self.workers, mp_context=worker_context(),
                                             initializer=_worker_init,
                                             initargs=(os.getpid(), *self._static, self._rigid))
        return self._pool

    def warm_up(self) -> None:
        """Start the worker processes and build their scenes now, so start-up is not counted as tracing."""
        pool = self._ensure_pool()
        if pool is not None:
            list(pool.map(_worker_ping, range(self.workers)))

    def visibility(self, positions, normals, point_ids, settings: TraceSettings, progress=None,
                   slice_of=None) -> np.ndarray:
        return self._trace_parts([TracePart(positions, normals, point_ids, settings, slice_of)], progress)[0][0]

    def visibility_and_static_hits(self, positions, normals, point_ids, settings: TraceSettings,
                                   progress=None) -> tuple[np.ndarray, np.ndarray]:
        """visibility() of each point's whole ray set, and which of those rays the static scene alone
        occludes, bit-packed (P, ceil(rays / 8)) uint8 (np.packbits order): the static scene answers first
        in every trace, so keeping its answers costs no extra ray."""
        return self._trace_parts([TracePart(positions, normals, point_ids, settings, keep_static=True)], progress)[0]

    def visibility_parts(self, parts: list[TracePart]) -> list[tuple[np.ndarray, np.ndarray | None]]:
        """visibility() of several batches (each its own settings, slices, static hits) in one hand-over to
        the workers: a tick that traces several kinds of batch pays the pool's per-call cost once. Per part:
        (visibility, the static scene's packed answers where the part keeps them (keep_static), else None)."""
        return self._trace_parts(parts)

    def _trace_parts(self, parts: list[TracePart], progress=None) -> list[tuple[np.ndarray, np.ndarray | None]]:
        """Per part: (visibility, the static scene's packed answers when it keeps them, else None)."""
        if self._local is None:
            raise TracerError("set_static() must be called before tracing")
        for part in parts:
            if (part.static_hit is not None or part.keep_static) and part.settings.slices != 1:
                raise TracerError("static hits are kept for whole ray sets only")
        points = sum(len(p.positions) for p in parts)
        rays = sum(len(p.positions) * p.settings.rays_traced for p in parts)
        big = points >= 2 * self.workers and rays >= min(p.settings.local_rays for p in parts) if parts else False
        pool = self._ensure_pool() if big else None
        jobs, owner = [], []
        for k, part in enumerate(parts):
            hit = None if part.static_hit is None else np.asarray(part.static_hit)
            if hit is not None and hit.dtype != np.uint8:  # (P, rays) bool: packed as the workers take it
                hit = np.packbits(hit.reshape(len(part.positions), -1).astype(bool), axis=1)
            for job in self._jobs(part.positions, part.normals, part.point_ids, part.settings,
                                  None if part.slice_of is None else np.asarray(part.slice_of, np.int64), hit,
                                  part.keep_static, spread=pool is not None):
                jobs.append(job)
                owner.append(k)
        if pool is None:
            dyn_v, dyn_f, dyn_parts = self._dynamic
            self._local.update_dynamic(self._dynamic_version, dyn_v, dyn_f, self._poses, dyn_parts)
        out = [([], []) for _ in parts]
        try:
            results = pool.map(_worker_trace, jobs) if pool else self._trace_here(jobs)
            for k, (vis, cpu_query, cpu_total, kept) in zip(owner, results):
                out[k][0].append(vis)
                out[k][1].append(kept)
                self.account.add(len(vis) * parts[k].settings.rays_traced, cpu_query, cpu_total,
                                 self.workers if pool is not None else 1)
                if progress is not None:
                    progress(len(vis))
        except BrokenProcessPool as exc:
            self._pool.shutdown(wait=False, cancel_futures=True)
            self._pool = None
            raise TracerError(f"an Embree worker process died: {exc}") from None
        answers = []
        for part, (vis, kept) in zip(parts, out):
            v = np.concatenate(vis).astype(np.float32) if vis else np.zeros(0, np.float32)
            b = None
            if part.keep_static:
                b = np.concatenate(kept) if kept else np.zeros((0, (part.settings.rays + 7) // 8), np.uint8)
            answers.append((v, b))
        return answers

    def _trace_here(self, jobs: list[tuple]):
        """_trace_chunks of `jobs` in this process, as it goes: consecutive jobs together up to chunk_points
        points a query, so a tick's few small parts pay each query's fixed cost once while a large call (a
        bake on one process) keeps its rays within chunk_points points and reports progress chunk by chunk."""
        group, points = [], 0
        for job in jobs:
            chunk = job[5:]  # (pos, nrm, ids, settings, first, static_bits, keep_static)
            if group and points + len(chunk[0]) > chunk[3].chunk_points:
                yield from _trace_chunks(self._local, group)
                group, points = [], 0
            group.append(chunk)
            points += len(chunk[0])
        yield from _trace_chunks(self._local, group)

    def _local_rays(self, positions, normals, point_ids, settings: TraceSettings):
        """Origins and directions of each point's whole `settings.rays`-ray set, in this process."""
        if self._local is None:
            raise TracerError("set_static() must be called before tracing")
        whole = TraceSettings(rays=settings.rays, ao_distance=settings.ao_distance, seed=settings.seed)
        return _chunk_rays(self._recentre(positions), np.asarray(normals, np.float32),
                           np.asarray(point_ids, np.int64), whole, 0)

    def static_occluded(self, positions, normals, point_ids, settings: TraceSettings) -> np.ndarray:
        """(P, rays) bool: which rays of each point's whole ray set the static scene alone occludes (traced
        in this process, ray by ray against the static scene alone). The server never calls it: it is the
        reference the tests compare the kept answers (visibility_and_static_hits) with."""
        org, dirs = self._local_rays(positions, normals, point_ids, settings)
        if self._local.static is None or len(org) == 0:
            return np.zeros((len(positions), settings.rays), bool)
        dists = np.full(len(org), settings.ao_distance, np.float32)
        return (self._local.static.run(org, dirs, dists=dists, query="OCCLUDED") != -1).reshape(len(positions), -1)

    def visibility_given_static(self, positions, normals, point_ids, settings: TraceSettings,
                                static_hit: np.ndarray) -> np.ndarray:
        """visibility() of each point's whole ray set, given `static_hit` (which of those rays the static
        scene occludes: (P, rays) bool as static_occluded gives, or bit-packed (P, ceil(rays / 8)) uint8 as
        visibility_and_static_hits keeps): only the rays the static scene lets through are traced, against
        the moving parts alone (in the workers, as visibility), so the static scene costs nothing; the
        answer is the full trace's. The tick traces such parts through visibility_parts with its other
        batches; this one-part call is what the tests compare with the full trace."""
        return self.visibility_parts([TracePart(positions, normals, point_ids, settings, static_hit=static_hit)])[0][0]

    def throughput(self) -> dict:
        return self.account.rates(self.workers if self._pool is not None else 1)

    @property
    def worker_pids(self) -> tuple[int, ...]:
        """The process ids of the worker pool's processes; () while no call has needed the pool."""
        return tuple(self._pool._processes) if self._pool is not None else ()

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None
