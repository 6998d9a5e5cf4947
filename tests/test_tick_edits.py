"""Scene edits through the server tick: a real Service with the real ServerTick (Embree) behind it, a
watching MirrorClient and an editing client over loopback websockets. After an edit moves an instance,
the AO around it is re-traced, the watcher's mirror equals the server's grid, and every point's AO is
a full trace of the scene as edited. Nothing waits on speed: the test waits for events and counts."""
from __future__ import annotations

import asyncio
import contextlib

import numpy as np
import pytest
from websockets.asyncio.client import connect

from psao.protocol import messages as m
from psao.protocol import pointword as pw
from psao.protocol.codecs import Codec, codec_mask
from psao.protocol.session import scene_hash_bytes
from psao.client.connection import MirrorClient
from psao.scene import load_scene
from psao.server.bake import bake_scene
from psao.server.tick.budget import BudgetSettings
from psao.server.net.service import Service
from psao.server.settings import BakeSettings, ServeSettings, TickSettings
from psao.server.tick.server_tick import AtRest, ServerTick
from serving import HANG_S

EDIT_TOKEN = "edit-secret"
BOULDER = "boulder3"  # a static instance of the courtyard, on the floor


def served_tick():
    scene = load_scene("builtin:courtyard")
    bake = bake_scene(scene, BakeSettings(density=8, rays=8, workers=1), show_progress=False)
    # min_points above the scene's size: every tick traces everything waiting (no dependence on speed)
    budget = BudgetSettings(budget_ms=1.0, round_rays=4, min_points=10**6)
    tick = ServerTick(bake, TickSettings(rays=8, workers=1, budget=budget))
    return scene, tick, AtRest(tick)  # as `psao serve --allow-edits` runs it: held at t = 0


async def until(condition, what: str, limit_s: float = 120.0):
    """Wait for an event (a generous deadline only against hanging forever)."""
    loop = asyncio.get_running_loop()
    end = loop.time() + limit_s
    while not condition():
        assert loop.time() < end, f"waited {limit_s:g} s for {what}"
        await asyncio.sleep(0.05)


def full_trace_codes(tick, ids):
    frame = tick.last_frame
    pos, nrm = tick.world_points(frame, ids)
    tick.pose_tracer(frame)
    return pw.quantise_ao(tick.tracer.visibility(pos, nrm, ids, tick.trace_settings))


def test_an_edit_is_retraced_and_the_mirror_equals_the_server():
    """The courtyard's rolling boulders are rigid movers of the tick (posed at t = 0): the edited boulder
    joins them."""
    scene, tick, served = served_tick()
    i = next(k for k, inst in enumerate(scene.instances) if inst.name == BOULDER)
    moved = np.array(scene.instances[i].transform, np.float32)
    moved[0, 3] += 2.0  # two metres along x: off its old place, onto floor it did not shade
    settings = ServeSettings(port=0, tick_hz=20, stats_interval=1e9, allow_edits=True, edit_token=EDIT_TOKEN)
    service = Service(tick.grid, scene_hash_bytes(scene.content_hash()), settings, tick=served,
                      transforms=tick.transforms, on_scene_edit=served.edit)
    scene_hash = scene_hash_bytes(scene.content_hash())

    def settled():
        return tick.stats_history and tick.stats_history[-1].queue == 0

    async def body():
        stop, ready = asyncio.Event(), asyncio.Event()
        server = asyncio.create_task(service.run(stop, ready=lambda port: ready.set()))
        await asyncio.wait_for(ready.wait(), HANG_S)
        url = f"ws://127.0.0.1:{service.port}"
        watcher = MirrorClient(url, scene_hash, reconnect=False)
        task = asyncio.create_task(watcher.run())
        try:
            await until(lambda: watcher.stats.snapshot_seconds is not None and settled(), "the watcher's snapshot")
            before = watcher.mirror.cells.copy()
            async with connect(url, compression=None, max_size=None) as ws:
                await ws.send(m.encode(m.Hello(scene_hash, codec_mask(Codec), EDIT_TOKEN)))
                await ws.send(m.encode(m.SceneEdit(i, moved)))
                await until(lambda: np.array_equal(watcher.mirror.transforms[i], moved), "the edit to reach the watcher")
            await until(settled, "the re-trace of what the edit touched")
            ticks_then = service.tick
            await until(lambda: service.tick >= ticks_then + 3, "a few more ticks")  # their sends drained
            await until(lambda: np.array_equal(watcher.mirror.buckets, tick.grid.buckets) and np.array_equal(
                watcher.mirror.cells[:len(before)], tick.grid.cells[:len(before)]), "the mirror to catch up")
            return before, watcher.mirror.cells.copy(), watcher.mirror.transforms.copy()
        finally:
            watcher.stop()  # it returns after its next message: a scene at rest sends none, so cancel it too
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task
            stop.set()
            await asyncio.wait_for(server, HANG_S)

    try:
        before, after, transforms = asyncio.run(body())
        assert np.array_equal(transforms[i], moved)
        # the service told the tick's budget what it spent on each tick besides the tick's stages
        assert tick.budget.service_observed > 0 and tick.budget.service_s >= 0
        np.testing.assert_array_equal(after, tick.grid.cells[:len(after)])  # the mirror is the server's grid
        # AO changed on the floor around the boulder (its old place lit up, its new place darkened)
        n = min(len(before), len(after))
        ao_before, ao_after = before[:n, :7] & 0xFF, after[:n, :7] & 0xFF
        same_points = (before[:n, :7] >> 8) == (after[:n, :7] >> 8)  # same word apart from AO
        floor = tick.grid.cell_instance[:n] == next(k for k, inst in enumerate(scene.instances) if inst.name == "floor")
        changed = (ao_before != ao_after) & same_points & floor[:, None]
        assert changed.sum() > 20
        assert ((ao_after > ao_before) & changed).any() and ((ao_after < ao_before) & changed).any()
        # and what the server holds is the scene as edited: every point's accumulated AO is its full trace
        ids = np.flatnonzero(tick.present())
        total, unocc = tick.queue._blend(ids)
        np.testing.assert_array_equal(pw.quantise_ao(unocc / total), full_trace_codes(tick, ids))
    finally:
        tick.close()


def test_an_edit_of_an_unknown_instance_is_refused():
    from psao.protocol.errors import EditError

    _, tick, _ = served_tick()
    try:
        with pytest.raises(EditError):
            tick.edit(10**6, np.eye(4))
    finally:
        tick.close()


def test_edits_while_animating_converge_to_a_full_trace_of_the_edited_scene():
    """Edits between animated ticks (a static instance, then a rolling boulder taken off its path): once
    the scene stops and the queue drains, every point's AO is a full trace of the scene as it stands."""
    scene, tick, _ = served_tick()
    names = [inst.name for inst in scene.instances]
    try:
        tick(tick.grid, 0.1)
        placed = np.array(scene.instances[names.index(BOULDER)].transform, np.float64)
        placed[2, 3] -= 1.5
        tick.edit(names.index(BOULDER), placed)
        tick(tick.grid, 0.2)
        rolling = tick.kinds.rigid[0] if tick.kinds.rigid[0] != names.index(BOULDER) else tick.kinds.rigid[1]
        lifted = tick.animator.transforms(0.3)[rolling].copy()
        lifted[1, 3] += 1.0
        tick.edit(rolling, lifted)
        for t in (0.3, 0.6):
            tick(tick.grid, t)
        assert np.allclose(tick.transforms()[names.index(BOULDER)], placed)
        assert np.allclose(tick.transforms()[rolling], lifted)  # the edit holds against its animation
        while tick(tick.grid, 0.6).queue > 0:
            pass
        ids = np.flatnonzero(tick.present())
        total, unocc = tick.queue._blend(ids)
        np.testing.assert_array_equal(pw.quantise_ao(unocc / total), full_trace_codes(tick, ids))
    finally:
        tick.close()
