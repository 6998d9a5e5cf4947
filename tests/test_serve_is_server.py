"""`psao serve` is a thin layer over psao.Server: its flags become ServerSettings, and the start it runs
(listen, load, a coarse first grid, the full grid) is psao.Server's, which an application gets too. Real
websockets on loopback, real Embree."""
from __future__ import annotations

import argparse
import threading

import pytest

import psao
from psao.client.errors import ConnectError
from psao.scene.errors import SceneNotFound
from psao.server.cli import serve
from psao.server.embed import bind_listener
from psao.server.errors import ConfigError
from psao.server.settings import BakeSettings, ServeSettings
from test_embed_api import assert_mirror_exact, read_jsonl

SMALL = BakeSettings(density=24.0, rays=16, workers=1)


def parsed(*argv: str) -> argparse.Namespace:
    p = argparse.ArgumentParser()
    serve.add_arguments(p)
    return p.parse_args(list(argv))


def test_the_flags_become_the_servers_settings():
    s = serve.server_settings(parsed("builtin:cornell", "--animate", "--rays", "16", "--tick-rays", "4",
                                     "--tick-hz", "20", "--first-points", "300", "--port", "0"))
    assert (s.animate, s.progressive, s.tick_rays, s.first_points) == (True, True, 4, 300)
    assert (s.serve.tick_hz, s.bake.rays, s.serve.port) == (20.0, 16, 0)
    assert not s.tick_at_rest and s.fast_scene_first  # a grid at rest is served with no tick by the command
    still = serve.server_settings(parsed("builtin:cornell", "--test-edits", "5"))
    assert not still.progressive and still.test_edits == 5  # the test hook turns the progressive start off
    with pytest.raises(ConfigError, match="--animate and --test-edits both edit the grid"):
        serve.server_settings(parsed("builtin:cornell", "--animate", "--test-edits", "5"))
    # the same refusal from the API names its settings
    with pytest.raises(ConfigError, match="animate and test_edits both edit the grid"):
        psao.ServerSettings(animate=True, test_edits=5).check()


def test_an_application_server_starts_progressively_and_the_client_follows_both_grids(tmp_path):
    """progressive=True: the coarse first grid is served as soon as it is baked, the full one replaces it
    (the client reconnects to it); the mirror equals the server's on both."""
    digests = tmp_path / "server.jsonl"
    settings = psao.ServerSettings(serve=ServeSettings(port=0, tick_hz=30, stats_interval=1e9, digest_log=digests),
                                   bake=SMALL, progressive=True, first_points=100, tick_rays=4)
    server = psao.Server("builtin:cornell", settings)
    try:
        server.start(wait=False)
        with psao.Client(server.url, digest_log=tmp_path / "client.jsonl") as client:
            client.wait_for(lambda: client.snapshots >= 2, 300.0, "the full grid's snapshot")
        assert server.service.grids_replaced == 1
        assert server.tick is not None and server.service.grid is server.tick.grid
    finally:
        server.stop()
    assert_mirror_exact(tmp_path, at_least=2)  # both snapshots
    assert len({d["conn"] for d in read_jsonl(digests)}) >= 2  # the coarse grid's connection and the full one's


def test_a_scene_that_does_not_load_fails_start_with_its_error_and_frees_the_port():
    server = psao.Server("builtin:no_such_scene", psao.ServerSettings(bake=SMALL))
    with pytest.raises(SceneNotFound, match="no_such_scene"):
        server.start()
    assert server.service.port is not None
    bind_listener("127.0.0.1", server.service.port).close()  # the port is free again


def test_request_stop_from_another_thread_ends_wait_and_serving():
    server = psao.Server("builtin:cornell", psao.ServerSettings(bake=SMALL)).start()
    client = psao.Client(server.url).start()
    stopper = threading.Thread(target=server.request_stop)  # as psao serve's signal handler does
    stopper.start()
    server.wait()
    stopper.join()
    with pytest.raises(ConnectError, match="connection lost"):  # psao.Client hears the server go
        client.stop()
    server.stop()
    bind_listener("127.0.0.1", server.service.port).close()  # it stopped listening
