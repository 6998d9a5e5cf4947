"""The Python API: psao.Server moved by the application and psao.Client in the same process, over a real
websocket on loopback, with real Embree; mirrors exact, bad moves refused at the call while serving goes on."""
from __future__ import annotations

import json

import numpy as np
import pytest

import psao
from psao.protocol.errors import EditError
from psao.server.errors import ConfigError
from psao.server.settings import BakeSettings, ServeSettings

SMALL = BakeSettings(density=24.0, rays=16, workers=1)


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
    from pathlib import Path

    example = Path(__file__).resolve().parents[1] / "examples" / "physics_drop.py"
    run = subprocess.run([sys.executable, str(example), "--seconds", "2", "--port", "0", "--density", "24"],
                         capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stdout + run.stderr
    assert " 0 differ" in run.stdout and "Traceback" not in run.stderr
