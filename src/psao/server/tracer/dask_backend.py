"""Dask back-end: the Embree trace spread over the workers of a Dask distributed cluster.

    make_tracer("dask", center, cluster=ClusterSettings("tcp://host:8786"))   workers of a running scheduler
    make_tracer("dask", center, cluster=ClusterSettings("local:4"))           4 worker processes started here

The static scene reaches each worker once, through a worker plugin that the scheduler also hands to
workers joining later: the plugin carries either the scene's spec (the worker loads the scene itself and
checks, by digest, that it built the very triangles the client holds) or the triangles as zstd bytes. The
worker builds its Embree scene once. Tasks carry chunks of point positions, normals and ids; the worker
makes the rays from (seed, point id) with the local Embree back-end's own code (embree.trace_chunk), so
the result does not depend on how the points are split or which worker traced them.

With tiles (ClusterSettings.tiles) no worker holds the scene: each task carries one spatial tile's points
and only the triangles their rays can reach (tiles.py), so a worker's memory follows the tile, not the scene.

A worker that dies mid-trace takes its running tasks with it; the scheduler runs them again on another
worker (a nanny restarts the dead one, and the scheduler hands it the plugin again).
Workers should run one thread each (`dask worker --nthreads 1 --nworkers N`): embreex holds the GIL.
"""
from __future__ import annotations

import asyncio
import hashlib
import logging
import os
import resource
import threading
import numpy as np
import zstandard

from psao.server.errors import TracerError
from psao.server.geometry import scene_world_geometry
from psao.server.settings import LOCAL_PREFIX, ClusterSettings, TraceSettings, local_workers
from psao.server.tracer.base import CpuAccount, Tracer, recentre, recentre_poses
from psao.server.tracer.embree import EmbreeScenes, trace_chunk
from psao.server.tracer.tiles import cut_triangles, make_tiles, triangle_boxes

try:  # deferred: the error surfaces when the back-end is asked for, not on import of the package
    from distributed import Client, LocalCluster, WorkerPlugin, as_completed, get_worker
    from distributed.comm import connect as comm_connect
    _IMPORT_ERROR = None
except ImportError as exc:
    WorkerPlugin = object
    _IMPORT_ERROR = exc

def geometry_digest(vertices: np.ndarray, faces: np.ndarray) -> str:
    h = hashlib.sha256()
    h.update(np.ascontiguousarray(vertices, np.float32).tobytes())
    h.update(np.ascontiguousarray(faces, np.int32).tobytes())
    return h.hexdigest()


def pack_geometry(vertices: np.ndarray, faces: np.ndarray) -> tuple[bytes, int, int]:
    v = np.ascontiguousarray(vertices, np.float32)
    f = np.ascontiguousarray(faces, np.int32)
    return zstandard.ZstdCompressor(level=3).compress(v.tobytes() + f.tobytes()), len(v), len(f)


def unpack_geometry(payload: bytes, n_vertices: int, n_faces: int) -> tuple[np.ndarray, np.ndarray]:
    raw = zstandard.ZstdDecompressor().decompress(payload, max_output_size=12 * (n_vertices + n_faces))
    v = np.frombuffer(raw, np.float32, 3 * n_vertices).reshape(-1, 3)
    f = np.frombuffer(raw, np.int32, 3 * n_faces, offset=12 * n_vertices).reshape(-1, 3)
    return v, f


# ---------------------------------------------------------------- worker side
# One trace at a time per worker process: the Warp ray buffers of embree._chunk_rays are per process
# (and threads would not help: embreex holds the GIL).
_TRACE_LOCK = threading.Lock()


class SceneOnWorkers(WorkerPlugin):
    """Worker plugin: the static Embree scene, built once per worker from a spec or from bytes."""

    def __init__(self, digest: str, center, spec: str | None = None, packed: tuple[bytes, int, int] | None = None,
                 rigid=()):
        self.digest = digest
        self.center = np.asarray(center, np.float64)
        self.spec = spec
        self.packed = packed
        self.rigid = list(rigid)  # rigidly moving meshes, (local vertices, faces), posed per task
        self.scenes: EmbreeScenes | None = None
        self.error: str | None = None

    async def setup(self, worker) -> None:
        # Off the worker's event loop: loading and building a large scene takes seconds.
        await asyncio.to_thread(self._build)

    def _build(self) -> None:
        try:
            if self.spec is not None:
                from psao.scene import load_scene  # (deferred: a worker loads a scene file only in this mode)
                v, f = scene_world_geometry(load_scene(self.spec))
                v, f = recentre(v, self.center), np.asarray(f, np.int32)
            else:
                v, f = unpack_geometry(*self.packed)
            if geometry_digest(v, f) != self.digest:
                self.error = (f"scene {self.spec!r} built different triangles here than on the client "
                              f"(another file or numeric library?): use the bytes scene source")
                return
            self.scenes = EmbreeScenes(v, f, self.rigid)
        except Exception as exc:  # reported to the client by _plugin_error and by every task
            self.error = f"cannot load the scene: {type(exc).__name__}: {exc}"
        finally:
            self.packed = None  # the scheduler keeps the plugin's bytes for later workers; this copy is done

    def teardown(self, worker) -> None:
        self.scenes = None

    def ready(self) -> EmbreeScenes:
        if self.scenes is None:
            raise RuntimeError(self.error or "the scene is not built on this worker")
        return self.scenes


def _plugin_error(name: str, dask_worker=None) -> str | None:
    plugin = dask_worker.plugins.get(name)
    return "the scene plugin is missing" if plugin is None else plugin.error


def worker_peak_rss() -> int:
    """Peak resident bytes of this process so far: VmHWM, the high-water mark of its own address space.
    Not ru_maxrss where VmHWM exists: Linux carries ru_maxrss across fork and exec, so a worker spawned by a
    big process would report its parent's size."""
    try:
        with open("/proc/self/status", encoding="ascii") as f:
            for line in f:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) * 1024  # kB
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024  # KiB on Linux


def _trace_points(scenes: EmbreeScenes, pos, nrm, ids, s: TraceSettings) -> dict:
    """Trace a task's points in chunks of s.chunk_points (bounds the ray buffers)."""
    vis = np.empty(len(pos), np.float32)
    cpu_query = cpu_total = 0.0
    for i in range(0, len(pos), s.chunk_points):
        v, q, t, _ = trace_chunk(scenes, pos[i:i + s.chunk_points], nrm[i:i + s.chunk_points], ids[i:i + s.chunk_points], s)
        vis[i:i + len(v)] = v
        cpu_query += q
        cpu_total += t
    return {"vis": vis, "cpu_query": cpu_query, "cpu_total": cpu_total, "pid": os.getpid(), "peak_rss": worker_peak_rss()}


def trace_scene_task(plugin_name: str, dynamic, poses, pos, nrm, ids, s: TraceSettings) -> dict:
    """A chunk of points against the worker's plugin scene, the deforming triangles `dynamic` (version,
    vertices, faces) and the rigid meshes at `poses`."""
    plugin = get_worker().plugins.get(plugin_name)
    if plugin is None:
        raise RuntimeError(f"this worker has no scene plugin {plugin_name}")
    scenes = plugin.ready()
    with _TRACE_LOCK:
        scenes.update_dynamic(*dynamic, poses)
        return _trace_points(scenes, pos, nrm, ids, s)


def trace_tile_task(static, rigid, dynamic, poses, pos, nrm, ids, s: TraceSettings) -> dict:
    """A tile's points against the tile's own triangles (and the rigid meshes at `poses`); the scenes are
    dropped when the task ends."""
    with _TRACE_LOCK:
        scenes = EmbreeScenes(*static, rigid)
        scenes.update_dynamic(*dynamic, poses)
        return _trace_points(scenes, pos, nrm, ids, s)


# ---------------------------------------------------------------- client side
def connect(settings: ClusterSettings):
    """(client, local cluster or None). An unreachable scheduler fails within settings.timeout."""
    address = settings.address
    # distributed logs every failed connection attempt: the one line that matters is the TracerError
    logging.getLogger("distributed").setLevel(logging.ERROR)
    if address.startswith(LOCAL_PREFIX):
        cluster = LocalCluster(n_workers=local_workers(address), threads_per_worker=1, processes=True,
                               dashboard_address=":0", silence_logs=logging.ERROR)
        return Client(cluster, set_as_default=False), cluster
    probe_scheduler(address, settings.timeout)
    return Client(address, timeout=settings.timeout, set_as_default=False), None


def probe_scheduler(address: str, timeout: float) -> None:
    """Open and close one connection to the scheduler, so an unreachable one is a TracerError before any
    Client exists (a Client that failed to start complains again when it is collected at exit)."""
    async def probe():
        comm = await comm_connect(address, timeout=timeout)
        await comm.close()

    try:
        asyncio.run(probe())
    except (OSError, TimeoutError) as exc:
        if "Timed out" in str(exc) or isinstance(exc, TimeoutError):
            raise TracerError(f"cannot reach the dask scheduler at {address} within {timeout:g} s") from None
        raise TracerError(f"cannot reach the dask scheduler at {address}: {_first_line(exc)}") from None
    except (ValueError, TypeError) as exc:  # a malformed address
        raise TracerError(f"bad dask scheduler address {address!r}: {_first_line(exc)}") from None


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip()
    return text.splitlines()[0] if text else type(exc).__name__


class DaskTracer(Tracer):
    name = "dask"

    def __init__(self, center=(0.0, 0.0, 0.0), cluster: ClusterSettings | None = None, scene_spec: str | None = None):
        """`scene_spec`: what load_scene() takes to rebuild, on a worker, the geometry set_static() will get
        (the whole scene); used when cluster.scene_source is spec (or auto and the spec is a builtin:)."""
        if cluster is None:
            raise TracerError("the dask back-end needs a cluster: --cluster tcp://HOST:PORT or --cluster local:N")
        cluster.check()
        if _IMPORT_ERROR is not None:
            raise TracerError(f"the dask back-end needs dask[distributed] (pip install 'psao[dask]'): {_IMPORT_ERROR}")
        self.settings = cluster
        self.center = np.asarray(center, np.float64)
        self.scene_spec = self._spec_to_ship(cluster.scene_source, scene_spec)
        self.client, self.local_cluster = connect(cluster)
        self.account = CpuAccount()
        self.tasks_done = 0
        self.tasks_total = 0
        self.workers_lost: set[str] = set()
        self.peak_rss: dict[int, int] = {}  # worker pid -> peak resident bytes seen in its results
        self.plugin_name: str | None = None
        self.threads = 1  # worker threads in the cluster at the last trace
        self._static: tuple[np.ndarray, np.ndarray] | None = None
        self._spec_digest: str | None = None  # the triangles the workers built from scene_spec
        self._boxes = None
        self._rigid: list = []  # (local float32 vertices, int32 faces) of the rigidly moving meshes
        self._poses = None  # their 4x4 poses in the re-centred frame, or None: left out
        self._dynamic = (0, None, None)  # (version, vertices, faces) as the workers' EmbreeScenes take it
        self._dynamic_boxes = None
        self._dynamic_future = None

    @staticmethod
    def _spec_to_ship(source: str, spec: str | None) -> str | None:
        if source == "bytes":
            return None
        if source == "spec" and not spec:
            raise TracerError("the spec scene source needs the scene's spec; use the bytes scene source")
        if source == "auto" and not (spec or "").startswith("builtin:"):
            return None  # files may not exist on the workers' machines
        return spec

    # geometry -------------------------------------------------------------
    def set_static(self, vertices, faces) -> None:
        self.set_geometry(vertices, faces, self._rigid)

    def set_rigid(self, meshes) -> None:
        if self._static is None:
            self._rigid = [(np.asarray(v, np.float32), np.asarray(f, np.int32)) for v, f in meshes]
        else:
            self.set_geometry(None, None, meshes)

    def set_geometry(self, vertices, faces, rigid) -> None:
        """The static triangles (None: keep them) and the rigid meshes at once: one hand-over to the workers."""
        if vertices is not None:
            self._static = (recentre(vertices, self.center), np.asarray(faces, np.int32))
            self._boxes = None
        self._rigid = [(np.asarray(v, np.float32), np.asarray(f, np.int32)) for v, f in rigid]
        self._register()

    def _register(self) -> None:
        """Hand the static scene (and the rigid meshes) to every worker, now and joining later."""
        self._drop_plugin()
        if self.settings.tiles:
            return  # tasks carry their tile's triangles
        v, f = self._static
        digest = geometry_digest(v, f)
        # The spec builds one geometry (the whole scene): other triangles set later (the static part of an
        # animated scene, for refinement) are shipped as bytes.
        by_spec = self.scene_spec is not None and self._spec_digest in (None, digest)
        source = {"spec": self.scene_spec} if by_spec else {"packed": pack_geometry(v, f)}
        plugin = SceneOnWorkers(digest, self.center, rigid=self._rigid, **source)
        self.plugin_name = f"psao-scene-{digest[:16]}-{len(self._rigid)}"
        self.client.register_plugin(plugin, name=self.plugin_name)
        errors = {w: e for w, e in self.client.run(_plugin_error, self.plugin_name).items() if e}
        if errors:
            worker, error = next(iter(errors.items()))
            raise TracerError(f"dask worker {worker}: {error}")
        if by_spec:
            self._spec_digest = digest

    def set_dynamic(self, vertices, faces, rigid_transforms=None, parts=None) -> None:
        self._poses = recentre_poses(rigid_transforms, self.center)
        if (vertices is None or len(faces) == 0) and self._dynamic[1] is None:
            return  # nothing deforms, as before: the workers keep what they built
        version = self._dynamic[0] + 1
        if vertices is None or len(faces) == 0:
            self._dynamic = (version, None, None)
        else:
            self._dynamic = (version, recentre(vertices, self.center), np.asarray(faces, np.int32))
        self._dynamic_boxes = None
        self._dynamic_future = None  # scattered on the next trace that needs it

    def _drop_plugin(self) -> None:
        if self.plugin_name is not None:
            try:
                self.client.unregister_worker_plugin(self.plugin_name)
            except Exception:  # a scheduler that is gone has no plugin left to drop
                pass
            self.plugin_name = None

    # tracing --------------------------------------------------------------
    def warm_up(self) -> None:
        """Wait for the workers (all of a local cluster, at least one of a remote one)."""
        want = local_workers(self.settings.address) if self.local_cluster is not None else 1
        try:
            self.client.wait_for_workers(want, timeout=self.settings.timeout)
        except (TimeoutError, OSError):
            raise TracerError(f"the dask scheduler at {self.settings.address} has no workers after "
                              f"{self.settings.timeout:g} s") from None

    def _workers(self) -> dict[str, int]:
        return self.client.nthreads()

    def _dynamic_arg(self):
        if self._dynamic[1] is None:
            return self._dynamic
        if self._dynamic_future is None:
            self._dynamic_future = self.client.scatter(self._dynamic, broadcast=True, hash=False)
        return self._dynamic_future

    def _scene_jobs(self, pos, nrm, ids, s: TraceSettings, threads: int):
        dynamic = self._dynamic_arg()
        # At least one task per worker thread, so small point sets are spread over every worker too.
        step = max(1, min(self.settings.chunk_points, -(-len(pos) // max(1, threads))))
        for i in range(0, len(pos), step):
            sl = slice(i, i + step)
            yield sl, trace_scene_task, (self.plugin_name, dynamic, self._poses, pos[sl], nrm[sl], ids[sl], s)

    def _tile_jobs(self, tiles, pos, nrm, ids, s: TraceSettings):
        if self._boxes is None:
            self._boxes = triangle_boxes(*self._static)
        version, dv, df = self._dynamic
        if dv is not None and self._dynamic_boxes is None:
            self._dynamic_boxes = triangle_boxes(dv, df)
        for tile in tiles:
            static = cut_triangles(*self._static, self._boxes, tile.lo, tile.hi)
            dynamic = (version, *cut_triangles(dv, df, self._dynamic_boxes, tile.lo, tile.hi)) if dv is not None else (version, None, None)
            idx = tile.points
            yield idx, trace_tile_task, (static, self._rigid, dynamic, self._poses, pos[idx], nrm[idx], ids[idx], s)

    def _jobs(self, positions, normals, point_ids, settings: TraceSettings):
        """(jobs, count, workers now): the tasks of one trace, as (index into the points, function, args)."""
        if self._static is None:
            raise TracerError("set_static() must be called before tracing")
        pos = recentre(positions, self.center)
        nrm = np.asarray(normals, np.float32)
        ids = np.asarray(point_ids, np.int64)
        workers = self._workers()
        threads = self.threads = max(1, sum(workers.values()))
        if self.settings.tiles:
            tiles = make_tiles(pos, settings.ao_distance, self.settings.tile_points)
            jobs, count = self._tile_jobs(tiles, pos, nrm, ids, settings), len(tiles)
        else:
            jobs = list(self._scene_jobs(pos, nrm, ids, settings, threads))
            count = len(jobs)
        self.tasks_total += count
        return jobs, workers

    def visibility(self, positions, normals, point_ids, settings: TraceSettings, progress=None) -> np.ndarray:
        if len(positions) == 0:
            return np.zeros(0, np.float32)
        jobs, workers = self._jobs(positions, normals, point_ids, settings)
        out = np.empty(len(positions), np.float32)
        self._run(jobs, out, settings.rays_traced, window=max(8, 4 * self.threads), progress=progress)
        self.workers_lost |= set(workers) - set(self._workers())
        return out

    def start(self, positions, normals, point_ids, settings: TraceSettings) -> "PendingTrace":
        """Submit a trace and return at once; PendingTrace.done() tells when its visibility is ready.
        Every task is submitted now: meant for batches of a few tasks (refinement), not a whole bake."""
        jobs, _ = self._jobs(positions, normals, point_ids, settings)
        parts = [(index, self.client.submit(fn, *args, pure=False)) for index, fn, args in jobs]
        return PendingTrace(self, len(positions), settings.rays_traced, parts)

    def _account(self, r: dict, rays: int) -> None:
        self.tasks_done += 1
        self.account.add(len(r["vis"]) * rays, r["cpu_query"], r["cpu_total"], self.threads)
        self.peak_rss[r["pid"]] = max(self.peak_rss.get(r["pid"], 0), r["peak_rss"])

    def _run(self, jobs, out: np.ndarray, rays: int, window: int, progress) -> None:
        """Keep `window` tasks in flight (bounded client and scheduler memory on huge bakes), fill `out`."""
        jobs = iter(jobs)
        pending: dict = {}
        done = as_completed(loop=self.client.loop)

        def submit() -> None:
            job = next(jobs, None)
            if job is not None:
                index, fn, args = job
                future = self.client.submit(fn, *args, pure=False)
                pending[future.key] = index
                done.add(future)

        for _ in range(window):
            submit()
        try:
            for future in done:
                r = future.result()
                out[pending.pop(future.key)] = r["vis"]
                future.release()
                self._account(r, rays)
                if progress is not None:
                    progress(len(r["vis"]))
                submit()
        except Exception as exc:
            for future in list(done.futures):
                future.cancel()
            raise TracerError(f"the dask trace failed: {type(exc).__name__}: {_first_line(exc)}") from None

    def progress_note(self) -> str:
        return f"tasks {self.tasks_done}/{self.tasks_total}"

    def throughput(self) -> dict:
        out = self.account.rates(self.threads)
        out.update(cluster=self.settings.address, cluster_threads=self.threads, cluster_tasks=self.tasks_done,
                   cluster_workers_lost=len(self.workers_lost),
                   cluster_peak_rss_bytes=max(self.peak_rss.values(), default=0))
        return out

    def close(self) -> None:
        if self.client is None:
            return
        self._drop_plugin()
        try:
            self.client.close()
        finally:
            if self.local_cluster is not None:
                self.local_cluster.close()
            self.client = None


class PendingTrace:
    """A trace submitted by DaskTracer.start: poll done(), then take result()."""

    def __init__(self, tracer: DaskTracer, n: int, rays: int, parts: list):
        self.tracer, self.n, self.rays, self.parts = tracer, n, rays, parts

    def done(self) -> bool:
        return all(future.done() for _, future in self.parts)

    def result(self) -> np.ndarray:
        """The visibility of every point (waits for what is not done yet)."""
        out = np.empty(self.n, np.float32)
        try:
            for index, future in self.parts:
                r = future.result()
                out[index] = r["vis"]
                self.tracer._account(r, self.rays)
        except Exception as exc:
            self.cancel()
            raise TracerError(f"the dask trace failed: {type(exc).__name__}: {_first_line(exc)}") from None
        finally:
            for _, future in self.parts:
                future.release()
        return out

    def cancel(self) -> None:
        for _, future in self.parts:
            future.cancel()
