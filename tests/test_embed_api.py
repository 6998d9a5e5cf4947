"""The Python API: psao.Server moved by the application and psao.Client in the same process, over a real
websocket on loopback, with real Embree; mirrors exact, bad moves refused at the call while serving goes on."""
from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

import psao
from psao.protocol.errors import EditError
from psao.protocol.session import scene_hash_bytes
from psao.server.errors import ConfigError, InstanceError
from psao.server.settings import BakeSettings, ServeSettings

SMALL = BakeSettings(density=24.0, rays=16, workers=1)
SHOTS = Path(__file__).resolve().parents[1] / "out" / "embed_api"


def read_jsonl(path):
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


def served(tmp_path, scene="builtin:cornell", **kw):
    serve = ServeSettings(port=0, tick_hz=30, stats_interval=1e9, digest_log=tmp_path / "server.jsonl")
    return psao.Server(scene, psao.ServerSettings(serve=serve, bake=SMALL, **kw))


def assert_mirror_exact(tmp_path, at_least: int) -> None:
    server = {(d["conn"], d["seq"]): d["digest"] for d in read_jsonl(tmp_path / "server.jsonl")}
    mine = [d for d in read_jsonl(tmp_path / "client.jsonl") if (d["conn"], d["seq"]) in server]
    assert len(mine) >= at_least
    assert all(server[(d["conn"], d["seq"])] == d["digest"] for d in mine)


def lifted(z: float) -> np.ndarray:
    m = np.eye(4)
    m[1, 3] = z
    return m


def test_the_application_moves_an_instance_and_the_client_follows_exactly(tmp_path):
    seen = []
    with served(tmp_path) as server:
        with psao.Client(server.url, digest_log=tmp_path / "client.jsonl",
                         on_update=lambda mirror, transforms, tick: seen.append(tick)) as client:
            block = server.instance("tall_block")
            before = client.mirror.transforms[block].copy()
            target = server.scene.instances[block].transform @ lifted(0.05)
            server.move("tall_block", target)
            client.wait_for(lambda: np.allclose(client.mirror.transforms[block], target.astype(np.float32)), 60.0,
                            "the moved block's transform")
            assert not np.allclose(before, client.mirror.transforms[block])
            assert server.service.counters.edits == 1
    assert seen and seen == sorted(seen)
    assert_mirror_exact(tmp_path, at_least=2)


@pytest.mark.parametrize("instance, matrix, says", [
    ("no_such_thing", np.eye(4), "no instance named 'no_such_thing'"),
    (99, np.eye(4), "no instance 99"),
    ("tall_block", np.full((4, 4), np.nan), "NaN or infinity"),
    ("tall_block", np.diag([1.0, 0.0, 1.0, 1.0]), "axis scales"),
    ("tall_block", np.eye(3), "must be 4x4"),
    ("tall_block", np.ones((4, 4)), "last row must be 0 0 0 1"),
])
def test_a_bad_move_is_one_error_at_the_call_and_the_server_keeps_serving(tmp_path, instance, matrix, says):
    with served(tmp_path) as server:
        with psao.Client(server.url, digest_log=tmp_path / "client.jsonl") as client:
            with pytest.raises(EditError, match=says) as err:
                server.move(instance, matrix)
            assert "\n" not in str(err.value)
            assert server.service.counters.edits == 0
            block = server.instance("tall_block")  # still served: a good move reaches the client
            target = server.scene.instances[block].transform @ lifted(0.05)
            server.move(block, target)
            client.wait_for(lambda: np.allclose(client.mirror.transforms[block], target.astype(np.float32)), 60.0,
                            "the moved block's transform")
    assert_mirror_exact(tmp_path, at_least=1)


def test_the_application_clock_poses_the_animation(tmp_path):
    with served(tmp_path, "builtin:robots", animate=True, clock="app") as server:
        movers = [i for i, inst in enumerate(server.scene.instances) if inst.animation is not None]
        assert movers
        with psao.Client(server.url, digest_log=tmp_path / "client.jsonl") as client:
            posed = {}
            for t in (0.5, 1.25):
                server.set_time(t)
                # the movers where the scene's animations put them at time t, and t as the Updates' server time
                want = np.array([server.scene.instances[i].animation.matrix(t) for i in movers], dtype=np.float32)
                client.wait_for(lambda: client.mirror.server_time == pytest.approx(t)
                                and np.allclose(client.mirror.transforms[movers], want, atol=1e-5), 60.0,
                                f"the movers posed at {t}")
                posed[t] = client.mirror.transforms[movers].copy()
            assert not np.allclose(posed[0.5], posed[1.25])
            assert server.ticks > 0
    assert_mirror_exact(tmp_path, at_least=2)


def test_settings_that_cannot_run_are_refused_before_baking():
    with pytest.raises(ConfigError, match="needs animate=True"):
        psao.ServerSettings(clock="app").check()
    with pytest.raises(ConfigError, match="clock must be one of"):
        psao.ServerSettings(clock="sundial").check()
    server = psao.Server("builtin:cornell", psao.ServerSettings(bake=SMALL))
    with pytest.raises(ConfigError, match="set_time needs"):
        server.set_time(1.0)
    with pytest.raises(ConfigError, match="not started"):
        server.move(0, np.eye(4))


def test_the_physics_example_runs_and_its_mirror_is_exact():
    import subprocess
    import sys

    example = Path(__file__).resolve().parents[1] / "examples" / "physics_drop.py"
    run = subprocess.run([sys.executable, str(example), "--seconds", "2", "--port", "0", "--density", "24"],
                         capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stdout + run.stderr
    assert " 0 differ" in run.stdout and "Traceback" not in run.stderr


# The added block's footprint on the Cornell floor: x 0.10..0.40, z -0.45..-0.15 (clear of the other blocks);
# floor probes beside it, within a few cm of its faces.
ADDED_AT = np.array([[1.0, 0, 0, 0.25], [0, 1.0, 0, 0.3], [0, 0, 1.0, -0.3], [0, 0, 0, 1.0]])
BESIDE = np.array([[0.06, 0.0, -0.3], [0.44, 0.0, -0.3], [0.25, 0.0, -0.11], [0.08, 0.0, -0.12], [0.42, 0.0, -0.12]])


def floor_ao(client) -> np.ndarray:
    """The AO the client's lookup (the numpy oracle) gives at the floor probes beside the added block."""
    from psao.protocol.reconstruct import reconstruct_ao

    floor = [inst.name for inst in client.scene.instances].index("floor")
    mirror = client.mirror
    ao, weight = reconstruct_ao(mirror.instances, mirror.buckets, mirror.cells, np.full(len(BESIDE), floor), BESIDE,
                                np.tile([0.0, 1.0, 0.0], (len(BESIDE), 1)))
    assert (weight > 0).all()
    return ao


def test_the_application_adds_and_removes_an_instance_and_the_client_follows_exactly(tmp_path):
    scenes = []
    with served(tmp_path) as server:
        with psao.Client(server.url, digest_log=tmp_path / "client.jsonl",
                         on_scene=lambda scene, h: scenes.append(len(scene.instances))) as client:
            first_hash, n = client.scene_hash, len(server.scene.instances)
            open_ao, open_digest = floor_ao(client), client.digest()
            index = server.add_instance("tall_block", ADDED_AT, name="second_block")
            assert index == n and server.instance("second_block") == n
            client.wait_for(lambda: client.snapshots >= 2, 60.0, "the new scene's snapshot")
            assert scenes == [n + 1] and client.scene.instances[n].name == "second_block"
            assert client.scene_hash == scene_hash_bytes(server.scene.content_hash()) != first_hash
            assert len(client.mirror.instances) == n + 1
            assert client.digest() == server_digest(server)
            shaded = floor_ao(client)
            assert (shaded < open_ao - 0.05).all(), (open_ao, shaded)  # the block occludes the floor beside it

            server.move("second_block", ADDED_AT @ lifted(0.1))  # the new instance moves as the others do
            client.wait_for(lambda: np.allclose(client.mirror.transforms[n], (ADDED_AT @ lifted(0.1)).astype(np.float32)),
                            60.0, "the added block's move")

            server.remove_instance("second_block")
            client.wait_for(lambda: client.snapshots >= 3, 60.0, "the snapshot without the block")
            assert scenes == [n + 1, n] and "second_block" not in [i.name for i in client.scene.instances]
            assert len(client.mirror.instances) == n
            # the scene is the first one again: the same hash, the same bake, the same mirror
            assert client.scene_hash == first_hash
            assert client.digest() == server_digest(server) == open_digest
            np.testing.assert_array_equal(floor_ao(client), open_ao)
            assert client.stats.grid_replacements == 2
    assert_mirror_exact(tmp_path, at_least=3)


def server_digest(server) -> str:
    from psao.protocol.updates import state_digest

    grid = server.service.grid
    return state_digest(grid.instances, grid.buckets, grid.cells, server.service.transforms())


@pytest.mark.parametrize("call, says", [
    (lambda s: s.add_instance("no_such_mesh", np.eye(4), name="x"), "no mesh is named 'no_such_mesh'"),
    (lambda s: s.add_instance(42, np.eye(4), name="x"), "no mesh 42"),
    (lambda s: s.add_instance("tall_block", np.eye(4), name="short_block"), "already has an instance named 'short_block'"),
    (lambda s: s.add_instance("tall_block", np.eye(4), name=""), "non-empty string"),
    (lambda s: s.add_instance("tall_block", np.full((4, 4), np.inf), name="x"), "NaN or infinity"),
    (lambda s: s.add_instance("tall_block", np.diag([1.0, 1.0, 0.0, 1.0]), name="x"), "axis scales"),
    (lambda s: s.remove_instance("no_such_thing"), "no instance named 'no_such_thing'"),
    (lambda s: s.remove_instance(99), "no instance 99"),
])
def test_a_bad_add_or_remove_is_one_error_at_the_call_and_the_server_keeps_serving(tmp_path, call, says):
    with served(tmp_path) as server:
        with psao.Client(server.url, digest_log=tmp_path / "client.jsonl") as client:
            first = client.scene_hash
            with pytest.raises(InstanceError, match=says) as err:
                call(server)
            assert "\n" not in str(err.value)
            block = server.instance("tall_block")  # still served, the same scene: a good move reaches the client
            target = server.scene.instances[block].transform @ lifted(0.05)
            server.move(block, target)
            client.wait_for(lambda: np.allclose(client.mirror.transforms[block], target.astype(np.float32)), 60.0,
                            "the moved block's transform")
            assert client.scene_hash == first and client.snapshots == 1
    assert_mirror_exact(tmp_path, at_least=1)


def test_the_web_page_follows_an_added_and_removed_instance_exactly(tmp_path):
    """A real Chromium on the page psao.Server serves: it takes the new scene on each change (its
    SceneRequest names the scene it holds), draws the added block, and its mirror digests equal the
    server's on all three grids."""
    from browser import launched, missing_browser, wait_page

    if missing_browser() is not None:
        pytest.skip(str(missing_browser()))
    serve = ServeSettings(port=0, tick_hz=10, stats_interval=1e9, digest_log=tmp_path / "server.jsonl",
                          fanout=dataclasses.replace(ServeSettings().fanout, cull=False))
    shots = []
    with launched() as browser, psao.Server("builtin:cornell", psao.ServerSettings(serve=serve, bake=SMALL)) as server:
        page = browser.new_page(viewport={"width": 240, "height": 190})
        errors: list[str] = []
        page.on("pageerror", lambda e: errors.append(str(e)))
        page.goto(f"http://127.0.0.1:{server.port}/?width=200&height=150&digests=1", wait_until="commit")
        try:
            counts = []
            for step, change in enumerate((None, lambda: server.add_instance("tall_block", ADDED_AT, name="second_block"),
                                           lambda: server.remove_instance("second_block"))):
                if change is not None:
                    change()
                wait_page(page, f"window.psao && window.psao.connection === {step + 1} && "
                                "window.psao.state === 'streaming' && window.psao.frames >= 1", timeout=120)
                counts.append(page.evaluate("window.psao.scene.instances.length"))
                shots.append(page.evaluate("document.getElementById('view').toDataURL('image/png')"))
            assert page.evaluate("window.psao.reconnects") == 0 and page.evaluate("window.psao.scenes") == 3
            log = page.evaluate("window.psao.digestLog")
        finally:
            page.close()
    assert not errors
    n = len(server.scene.instances)
    assert counts == [n, n + 1, n]
    ref = {(d["conn"], d["seq"]): d["digest"] for d in read_jsonl(tmp_path / "server.jsonl")}
    both = [d for d in log if (d["conn"], d["seq"]) in ref]
    assert len({d["conn"] for d in both}) == 3  # compared on every grid
    assert all(ref[(d["conn"], d["seq"])] == d["digest"] for d in both)
    import base64

    SHOTS.mkdir(parents=True, exist_ok=True)
    for name, url in zip(("before", "added", "removed"), shots):  # for a person to look at
        (SHOTS / f"cornell_{name}.png").write_bytes(base64.b64decode(url.split(",", 1)[1]))
    assert shots[0] != shots[1]  # the added block is drawn


def test_the_server_tick_of_the_api_and_of_psao_serve_takes_the_bakes_settings():
    from psao.server.settings import TickSettings
    from psao.server.tick.budget import BudgetSettings

    budget = BudgetSettings(round_rays=8)
    tick = TickSettings.serving(BakeSettings(rays=16, seed=7, tracer="dask", workers=2), budget)
    assert (tick.rays, tick.seed, tick.workers, tick.budget, tick.selection) == (16, 7, 2, budget, True)
    assert tick.tracer == "embree"  # a Dask bake's tick traces here
    assert TickSettings.serving(BakeSettings(tracer="warp"), budget).tracer == "warp"


def test_a_handshake_under_way_when_the_scene_changes_is_sent_to_the_new_one(tmp_path):
    """A connection that took the scene before an instance was added and says Hello after is closed with
    GRID_REPLACED_CLOSE (not welcomed to a grid of another scene); a new connection naming the old scene is
    refused with SCENE_MISMATCH; one that asks for the scene again gets the new one."""
    from websockets.exceptions import ConnectionClosed
    from websockets.sync.client import connect

    from psao.protocol.errors import ErrorCode
    from psao.protocol.session import GRID_REPLACED_CLOSE, ClientConfig, ClientSession, RemoteError, SceneReceived

    def receive_scene(ws, session) -> SceneReceived:
        while not isinstance(event := session.receive(ws.recv(timeout=60)), SceneReceived):
            pass
        return event

    with served(tmp_path) as server:
        old = scene_hash_bytes(server.scene.content_hash())
        with connect(server.url, max_size=None) as ws:
            session = ClientSession(ClientConfig(None))
            ws.send(session.scene_request())
            assert receive_scene(ws, session).scene_hash == old
            server.add_instance("tall_block", ADDED_AT, name="second_block")
            ws.send(session.hello())
            with pytest.raises(ConnectionClosed) as closed:
                while True:
                    session.receive(ws.recv(timeout=60))
            assert closed.value.rcvd.code == GRID_REPLACED_CLOSE
        with connect(server.url, max_size=None) as ws:
            session = ClientSession(ClientConfig(old))
            ws.send(session.hello())
            with pytest.raises(RemoteError) as refused:
                session.receive(ws.recv(timeout=60))
            assert refused.value.code == ErrorCode.SCENE_MISMATCH
        with connect(server.url, max_size=None) as ws:
            session = ClientSession(ClientConfig(None))
            ws.send(session.scene_request(old))
            new = receive_scene(ws, session)
            assert new.scene is not None and new.scene_hash == scene_hash_bytes(server.scene.content_hash()) != old
            assert len(new.scene.instances) == len(server.scene.instances)
