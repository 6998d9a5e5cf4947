"""The dask tracer back-end on a real LocalCluster: bit-identical to the local Embree tracer however the points
are split (chunks, tiles, spec or bytes scene), a worker killed mid-trace, workers joining later, the CLI."""
from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import trimesh

distributed = pytest.importorskip("distributed")

from psao.protocol.updates import state_digest  # noqa: E402
from serving import HANG_S, server_url, wait_for_log  # noqa: E402
from tracing import full_trace  # noqa: E402
from psao.scene import load_scene  # noqa: E402
from psao.server.bake import bake_scene, sample_probes  # noqa: E402
from psao.server.geometry import scene_center, scene_world_geometry  # noqa: E402
from psao.server.settings import BakeSettings, ClusterSettings, TraceSettings  # noqa: E402
from psao.server.errors import TracerError  # noqa: E402
from psao.server.tracer import make_tracer  # noqa: E402
from psao.server.tracer.dask_backend import _plugin_error  # noqa: E402
from psao.cli import main  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
RAYS = 32
SEED = 9


@pytest.fixture(scope="module")
def cluster():
    lc = distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0")
    yield lc
    lc.close()


@pytest.fixture(scope="module")
def courtyard():
    """Courtyard geometry, 3000 surface probes and their visibility from the local Embree tracer."""
    scene = load_scene("builtin:courtyard")
    v, f = scene_world_geometry(scene)
    probes = sample_probes(scene, 3000, seed=4)
    s = TraceSettings(rays=RAYS, ao_distance=scene.ao_distance, seed=SEED)
    ids = np.arange(len(probes.world_pos)) + 1000
    with make_tracer("embree", scene_center(scene), workers=1) as local:
        local.set_static(v, f)
        ref = local.visibility(probes.world_pos, probes.world_normal, ids, s)
    return scene, (v, f), probes, ids, s, ref


def dask_tracer(scene, address, **kw):
    return make_tracer("dask", scene_center(scene), cluster=ClusterSettings(address, **kw), scene_spec=scene.source)


@pytest.mark.parametrize("kw", [
    dict(chunk_points=397),  # many small tasks, scene loaded from its spec on the workers
    dict(chunk_points=1000, scene_source="bytes"),  # the triangles shipped through the scheduler
    dict(tiles=True, tile_points=300),  # no scene on the workers: each task carries its tile's triangles
])
def test_bit_identical_to_local_tracer(cluster, courtyard, kw):
    scene, geometry, probes, ids, s, ref = courtyard
    done = []
    with dask_tracer(scene, cluster.scheduler_address, **kw) as tracer:
        tracer.set_static(*geometry)
        vis = tracer.visibility(probes.world_pos, probes.world_normal, ids, s, progress=done.append)
        stats = tracer.throughput()
    np.testing.assert_array_equal(vis, ref)
    assert sum(done) == len(ids) and len(done) == stats["cluster_tasks"] >= 3
    assert stats["rays_per_second"] > 0 and stats["cluster_peak_rss_bytes"] > 0


@pytest.mark.parametrize("tiles", [False, True])
def test_moving_geometry_occludes_and_is_replaced(cluster, tiles):
    """A deforming lid and a rigid one (its own mesh, posed per call) cover the floor points, as locally."""
    floor = trimesh.creation.box(extents=(20, 20, 1.0))
    floor.apply_translation((0, 0, -0.5))
    lid = trimesh.creation.box(extents=(10, 10, 0.1))
    lid.apply_translation((0, 0, 0.5))
    pose = np.eye(4)
    pose[:3, 3] = (4.0, 0.0, 0.4)  # the rigid lid covers the points at x > -1
    pos = np.column_stack([np.linspace(-3, 3, 40), np.zeros(40), np.zeros(40)])
    nrm = np.tile([0, 0, 1.0], (40, 1))
    s = TraceSettings(rays=64, ao_distance=2.0)
    out = {}
    for name in ("embree", "dask"):
        kw = {"workers": 1} if name == "embree" else {
            "cluster": ClusterSettings(cluster.scheduler_address, scene_source="bytes", chunk_points=7, tiles=tiles,
                                       tile_points=9)}
        with make_tracer(name, **kw) as tracer:
            tracer.set_static(floor.vertices, floor.faces)
            tracer.set_rigid([(lid.vertices - (0, 0, 0.5), lid.faces)])
            tracer.set_dynamic(lid.vertices, lid.faces)
            deformed = tracer.visibility(pos, nrm, np.arange(40), s)
            tracer.set_dynamic(None, np.zeros((0, 3), int), [pose])
            rigid = tracer.visibility(pos, nrm, np.arange(40), s)
            tracer.set_dynamic(None, np.zeros((0, 3), int))
            out[name] = (deformed, rigid, tracer.visibility(pos, nrm, np.arange(40), s))
    deformed, rigid, bare = out["dask"]
    assert deformed.max() < 0.3 and (bare == 1.0).all()
    assert rigid[pos[:, 0] > 0].max() < 0.3 and rigid[pos[:, 0] < -2].min() > 0.9  # the lid spans x > -1
    for a, b in zip(out["dask"], out["embree"]):
        np.testing.assert_array_equal(a, b)


def test_worker_killed_mid_trace_and_workers_joining_later(cluster, courtyard):
    """SIGKILL a worker that is running a task once two tasks are done: the scheduler re-runs its tasks and
    the result is unchanged. The nanny restarts the worker, and a worker started later by hand (`dask
    worker ADDRESS`, as on another machine) joins: the scheduler hands both the scene plugin."""
    scene, geometry, probes, ids, s, ref = courtyard
    with dask_tracer(scene, cluster.scheduler_address, chunk_points=150) as tracer:
        tracer.set_static(*geometry)
        client = tracer.client
        pids = client.run(os.getpid)
        # started now, so its start-up overlaps the trace below; it joins after the scene plugin was registered
        extra = subprocess.Popen([sys.executable, "-m", "distributed.cli.dask_worker", cluster.scheduler_address,
                                  "--nthreads", "1", "--no-nanny", "--no-dashboard"], cwd=ROOT,
                                 stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        killed = {}

        def kill_a_busy_worker(_points):
            if killed or tracer.tasks_done < 2:
                return
            busy = [w for w, keys in client.processing().items() if keys and w in pids]
            if busy:
                os.kill(pids[busy[0]], signal.SIGKILL)
                killed[busy[0]] = pids[busy[0]]

        try:
            vis = tracer.visibility(probes.world_pos, probes.world_normal, ids, s, progress=kill_a_busy_worker)
            assert killed, "no worker was busy when tasks completed"
            np.testing.assert_array_equal(vis, ref)
            assert set(killed) <= tracer.workers_lost and tracer.throughput()["cluster_workers_lost"] >= 1

            client.wait_for_workers(len(pids) + 1, timeout=HANG_S)  # the nanny's restart and the one started by hand
            workers = client.nthreads()
            assert set(workers).isdisjoint(killed)
            assert set(client.run(_plugin_error, tracer.plugin_name).values()) == {None}
            assert len(set(workers) - set(pids)) == 2  # the restarted worker and the one started by hand
            # every worker, the joined ones too, traces with the scene it was handed
            again = tracer.visibility(probes.world_pos, probes.world_normal, ids, s)
            np.testing.assert_array_equal(again, ref)
        finally:
            extra.terminate()
            extra.wait(60)


def test_spec_that_loads_other_triangles_is_refused(cluster, courtyard):
    scene, geometry, *_ = courtyard
    tracer = make_tracer("dask", scene_center(scene), cluster=ClusterSettings(cluster.scheduler_address),
                         scene_spec="builtin:cornell")
    with pytest.raises(TracerError, match="built different triangles"):
        tracer.set_static(*geometry)
    tracer.close()


def test_bake_on_the_cluster_gives_the_same_grid(cluster):
    scene = load_scene("builtin:cornell")
    grids = {}
    for name, extra in (("local", {}), ("dask", {"cluster": ClusterSettings(cluster.scheduler_address, chunk_points=64)}),
                        ("tiles", {"cluster": ClusterSettings(cluster.scheduler_address, tiles=True, tile_points=100)})):
        result = bake_scene(scene, BakeSettings(density=64, rays=RAYS, seed=SEED, workers=1, **extra), show_progress=False)
        result.tracer.close()
        grids[name] = b"".join(a.tobytes() for a in (result.grid.instances, result.grid.buckets, result.grid.cells))
    assert grids["dask"] == grids["local"] and grids["tiles"] == grids["local"]


# ---------------------------------------------------------------- command line
def grid_arrays(path) -> bytes:
    with np.load(path) as z:
        return b"".join(z[k].tobytes() for k in ("instances", "buckets", "cells"))


def test_cli_bake_local_cluster_and_remote_scheduler(cluster, tmp_path, capsys):
    """--cluster local:N starts (and stops) its own workers; --cluster ADDRESS uses a running scheduler. The
    commands run in this process (psao.cli.main): a second Python start-up would cost more than the bakes."""
    local = bake_scene(load_scene("builtin:cornell"), BakeSettings(density=32, rays=RAYS, workers=1), show_progress=False)
    local.tracer.close()
    want = b"".join(a.tobytes() for a in (local.grid.instances, local.grid.buckets, local.grid.cells))
    common = ["bake", "builtin:cornell", "--density", "32", "--rays", str(RAYS), "--probes", "0", "--json"]
    stats = {}
    for name, extra in (("started", ["--cluster", "local:1", "--tiles", "--tile-points", "60"]),
                        ("remote", ["--cluster", cluster.scheduler_address])):
        capsys.readouterr()
        assert main([*common, "--out", str(tmp_path / f"{name}.npz"), *extra]) == 0, capsys.readouterr().err
        stats[name] = json.loads(capsys.readouterr().out.splitlines()[-1])
        assert grid_arrays(tmp_path / f"{name}.npz") == want
    assert stats["started"]["tracer"] == "dask" and stats["started"]["cluster"] == "local:1"
    assert stats["started"]["cluster_tasks"] >= 2
    assert stats["remote"]["cluster"] == cluster.scheduler_address


def test_cli_serve_progressive_refines_on_the_cluster(cluster, tmp_path, capsys):
    """psao serve --progressive --cluster: the few-ray bake and the refinement of its static points run on the
    cluster; once every point has its rays the client mirrors exactly the server's grid."""
    err, digests = tmp_path / "serve.err", tmp_path / "digests.jsonl"
    proc = subprocess.Popen([sys.executable, "-m", "psao", "serve", "builtin:cornell", "--density", "32", "--rays",
                             str(RAYS), "--tick-rays", "8", "--progressive", "--tick-hz", "20", "--workers", "1",
                             "--no-cull", "--port", "0", "--cluster", cluster.scheduler_address,
                             "--digest-log", str(digests)], cwd=ROOT,
                            stdout=subprocess.DEVNULL, stderr=open(err, "w"), text=True)
    try:
        url = server_url(proc, err)
        wait_for_log(proc, err, re.compile(r"\| queue 0 "))  # every point refined to --rays
        capsys.readouterr()
        assert main(["client", url, "builtin:cornell", "--frames", "0", "--json"]) == 0  # the client in this process
        client = json.loads(capsys.readouterr().out.splitlines()[-1])
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(60) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    refined = re.search(r"refinement beside the ticks: (\d+) batches sent, (\d+) points refined", err.read_text())
    assert refined and int(refined.group(2)) > 0, err.read_text()
    server = [json.loads(line)["digest"] for line in digests.read_text().splitlines()]
    assert client["mirror_digest"] == server[-1]


# ---------------------------------------------------------------- refinement beside the tick
def test_cluster_refines_static_points_as_a_local_trace_would(cluster):
    """psao serve --progressive --cluster: waiting static points go to the cluster in batches while the ticks
    run; a point a batch refined holds exactly the AO of a full local trace of its target ray set, the points a
    batch has out are left out of the tick's picks, and an answer for a point whose neighbourhood changed
    meanwhile is dropped."""
    from psao.server.tick.budget import BudgetSettings
    from psao.server.tick.refine import ClusterRefiner, RefineSettings
    from psao.server.settings import TickSettings
    from psao.server.tick.server_tick import ServerTick
    from psao.protocol import pointword as pw

    scene = load_scene("builtin:courtyard")  # static walls and floor, rigid movers (posed at t = 0 here)
    bake = bake_scene(scene, BakeSettings(density=8, rays=8, seed=SEED, cluster=ClusterSettings(cluster.scheduler_address)),
                      show_progress=False)
    refiner = ClusterRefiner(bake.tracer, RefineSettings(batch_points=1500, batches_per_thread=2))
    settings = TickSettings(rays=32, seed=SEED, budget=BudgetSettings(round_rays=8, budget_ms=0.1), selection=True,
                            workers=1)
    tick = ServerTick(bake, settings, close_bake_tracer=False, refiner=refiner)
    try:
        frame = tick.animator.frame(0.0)
        plan = tick.prepare(0.0)  # the first batches go out, then the tick's own round
        tick.apply(plan)
        out = list(refiner.batches)
        assert len(out) >= 2 and all(refiner.busy[b.ids].all() for b in out)
        assert not np.isin(plan.ids, np.concatenate([b.ids for b in out])).any()
        done_before = tick.queue.done.copy()
        forgotten = out[1].ids[:50]
        refiner.forget(forgotten)
        assert refiner.wait(300)
        plan = tick.prepare(0.0)  # takes them back (and sends the next)
        tick.apply(plan)
        merged = np.concatenate([out[0].ids, out[1].ids[50:], *[b.ids for b in out[2:]]])
        # plan.ids: the tick's own round first, then the refined points it took back; a forgotten point
        # waits again, so the tick's own round may pick it, but no refined answer may bring it back
        own, from_cluster = plan.ids[:len(plan.ids) - len(merged)], plan.ids[len(plan.ids) - len(merged):]
        assert set(from_cluster.tolist()) == set(merged.tolist()) and not np.isin(forgotten, from_cluster).any()
        untouched = forgotten[~np.isin(forgotten, own)]
        assert (tick.queue.done[untouched] == done_before[untouched]).all()
        assert refiner.points_done == len(merged) and refiner.points_dropped == 50

        # the same rays traced here: static scene, rigid movers at the frame's pose, the target ray set
        vis = full_trace(tick, frame, merged, 32, SEED)
        got = tick.grid.cells[tick.slot[merged], tick.index[merged]] & np.uint32(0xFF)
        np.testing.assert_array_equal(got, pw.quantise_ao(vis))
        assert (tick.queue.done[merged] == tick.queue.slices).all()

        # ticks and batches together refine every static point to the target
        static = refiner.static
        for _ in range(10_000):
            if not len(tick.queue.waiting(static)):
                break
            assert refiner.wait(300)
            tick.apply(tick.prepare(0.0))
        assert not len(tick.queue.waiting(static)) and refiner.points_done > 6 * 1500
    finally:
        tick.close()
