"""Scene delivery: SceneRequest / SceneData bytes, the scene file format, the session flow, a real server
sending its scene to `psao client URL` without --scene, and the HTTP allow-list on the serve port."""
from __future__ import annotations

import asyncio
import urllib.error
import urllib.request
from pathlib import Path

import numpy as np
import pytest
import zstandard

from psao.protocol import messages as m
from psao.protocol.errors import LimitError, PayloadError, RefusedError, UnexpectedMessage
from psao.protocol.limits import Limits
from psao.protocol.scenefile import CameraPathData, InstanceData, MeshData, SceneFile, SkinData, skin_pose
from psao.protocol.session import ClientConfig, ClientSession, SceneReceived, SceneRequested, ServerConfig, ServerSession
from psao.client.connection import MirrorClient, fetch_scene
from psao.scene import load_scene
from psao.server.grid import Grid
from psao.server.net.scene_export import scene_blob, scene_file
from psao.server.net.service import Service
from psao.server.settings import ServeSettings
from psao.server.net.webpage import ASSETS, answer
from serving import HANG_S

HASH = bytes(range(32))
H = bytes.fromhex


def header(mtype: int, length: int) -> bytes:
    return b"PSAO" + H("0100") + bytes([mtype, 0]) + length.to_bytes(4, "little")


def test_scene_request_bytes_both_ways():
    data = m.encode(m.SceneRequest(HASH, "tk"))
    assert data == header(9, 36) + HASH + H("0200") + b"tk"
    back = m.SceneRequest.parse(bytes(32) + H("0000"))
    assert back == m.SceneRequest(m.NO_SCENE, "")
    with pytest.raises(LimitError):
        m.SceneRequest.parse(bytes(32) + H("ffff") + b"x" * 0xFFFF)
    with pytest.raises(PayloadError):
        m.SceneRequest.parse(bytes(31))


def test_scene_data_bytes_both_ways_and_limits():
    data = m.encode(m.SceneData(HASH, 1, 3, 10, b"abc"))
    assert data == header(10, 47) + HASH + H("01000000") + H("03000000") + H("0a000000") + b"abc"
    assert m.SceneData.parse(HASH + H("00000000") * 3) == m.SceneData(HASH, 0, 0, 0, b"")
    small = Limits(scene_bytes=8, scene_chunk_bytes=4)
    with pytest.raises(LimitError):
        m.SceneData.parse(HASH + H("00000000") + H("01000000") + H("09000000"), small)
    with pytest.raises(LimitError):
        m.SceneData.parse(HASH + H("00000000") + H("01000000") + H("05000000") + b"12345", small)
    with pytest.raises(PayloadError):  # chunk index beyond the count
        m.SceneData.parse(HASH + H("02000000") + H("02000000") + H("05000000"))


def tiny_scene_file(skinned=True) -> SceneFile:
    skin = None
    if skinned:
        mats = np.zeros((2, 1, 3, 4), np.float32)
        mats[:, 0, :, :3] = np.eye(3)
        mats[1, 0, 1, 3] = 2.0  # joint 0 moves up by 2 at t = period / 2
        skin = SkinData(np.zeros((3, 4), np.uint8), np.tile([[1, 0, 0, 0]], (3, 1)).astype(np.float32), 1.0, mats)
    mesh = MeshData("tri", np.array([[0, 0, 0], [1, 0, 0], [0, 0, 1]], np.float32), np.array([[0, 2, 1]], np.uint32),
                    True, (0.5, 0.25, 1.0), skin)
    path = CameraPathData("p", 60.0, True, np.array([[0, 1, 2, 3, 0, 0, 0]], np.float32))
    return SceneFile("t", 2.0, [mesh], [InstanceData("i", 0, np.eye(4, dtype=np.float32))], [path])


def test_scene_file_bytes_and_round_trip():
    raw = tiny_scene_file(skinned=False).serialize()
    head = b"PSCN" + H("0100") + H("0000") + np.float64(2.0).tobytes() + H("0100") + b"t" + H("01000000") * 3
    mesh = (H("0300") + b"tri" + bytes([1, 0, 0, 0]) + np.array([0.5, 0.25, 1.0], "<f4").tobytes()
            + H("03000000") + H("01000000"))
    assert raw.startswith(head + mesh)
    back = SceneFile.parse(raw)
    assert back.meshes[0].double_sided and back.meshes[0].color == (0.5, 0.25, 1.0) and back.meshes[0].skin is None
    assert np.array_equal(back.meshes[0].faces, [[0, 2, 1]])
    sk = SceneFile.parse(tiny_scene_file().serialize()).meshes[0].skin
    assert sk.period == 1.0 and sk.matrices.shape == (2, 1, 3, 4)
    assert skin_pose(sk, 0.25)[0, 1, 3] == pytest.approx(1.0) and skin_pose(sk, 1.75)[0, 1, 3] == pytest.approx(1.0)
    assert skin_pose(sk, 0.5)[0, 3, 3] == 1.0


@pytest.mark.parametrize("cut, error", [
    (lambda b: b[:-1], PayloadError),  # truncated
    (lambda b: b"XSCN" + b[4:], PayloadError),  # magic
    (lambda b: b + b"\0", PayloadError),  # trailing bytes
])
def test_bad_scene_files_are_protocol_errors(cut, error):
    with pytest.raises(error):
        SceneFile.parse(cut(tiny_scene_file().serialize()))


def test_scene_file_counts_checked_before_allocation():
    raw = bytearray(tiny_scene_file(skinned=False).serialize())
    at = raw.index(b"tri") + 3 + 4 + 12  # the mesh's vertex count
    raw[at:at + 4] = (1 << 30).to_bytes(4, "little")
    with pytest.raises(LimitError):
        SceneFile.parse(bytes(raw))
    raw[at:at + 4] = (1000).to_bytes(4, "little")  # under the limit, but not in the data
    with pytest.raises(PayloadError):
        SceneFile.parse(bytes(raw))


def test_session_scene_flow_chunks_cache_and_token():
    blob = zstandard.ZstdCompressor().compress(tiny_scene_file().serialize())
    server = ServerSession(ServerConfig(HASH, token="s", limits=Limits(scene_chunk_bytes=16)))
    client = ClientSession(ClientConfig(None, token="s"))
    event = server.receive(client.scene_request())
    assert isinstance(event, SceneRequested)
    msgs = server.scene_data(event.request, blob)
    assert len(msgs) == -(-len(blob) // 16) > 1
    got = [client.receive(d) for d in msgs]
    assert got[:-1] == [None] * (len(msgs) - 1) and isinstance(got[-1], SceneReceived)
    assert got[-1].scene.meshes[0].name == "tri" and client.scene_hash == HASH
    assert server.receive(client.hello()).codec is not None
    # A client holding the scene gets one empty SceneData.
    c2, s2 = ClientSession(ClientConfig(None, token="s")), ServerSession(ServerConfig(HASH, token="s"))
    (only,) = s2.scene_data(s2.receive(c2.scene_request(HASH)).request, blob)
    assert c2.receive(only) == SceneReceived(HASH, None, 0)
    # Wrong token: refused before any scene byte; a second request: unexpected.
    with pytest.raises(RefusedError):
        ServerSession(ServerConfig(HASH, token="s")).receive(ClientSession(ClientConfig(None, token="x")).scene_request())
    with pytest.raises(UnexpectedMessage):
        s3 = ServerSession(ServerConfig(HASH))
        c3 = ClientSession(ClientConfig(None))
        s3.receive(c3.scene_request())
        s3.receive(m.encode(m.SceneRequest()))


def test_client_with_a_scene_refuses_another_servers_scene():
    client = ClientSession(ClientConfig(bytes(32)))
    client.scene_request()
    with pytest.raises(RefusedError):
        client.receive(m.encode(m.SceneData(HASH, 0, 1, 3, b"abc")))


def test_exported_builtin_scene_poses_like_the_original():
    scene = load_scene("builtin:robots")
    f = SceneFile.parse(scene_file(scene).serialize())
    for mesh, got in zip(scene.meshes, f.meshes):
        assert np.allclose(mesh.vertices, got.vertices, atol=1e-5)
        if mesh.skin is not None:
            # Sampled at 120 Hz: within 5 mm of the animator (the error is largest at the kink of the walk
            # cycle's knee angle, max(0, -cos)), against an AO distance of 1 m.
            for t in np.linspace(0.0, 4.0, 41):
                assert np.abs(mesh.skin.skinning_matrices(t) - skin_pose(got.skin, t)).max() < 5e-3


def test_http_allow_list_serves_only_page_files():
    assert answer("/psao_constants.js").status == 200
    for path in ("/../pyproject.toml", "/%2e%2e/pyproject.toml", "/vendor%2Ffzstd.js", "//etc/passwd", "/etc/passwd",
                 "/shaders/../../pyproject.toml", "/node_modules/fzstd/package.json", "/web/index.html", ""):
        assert answer(path).status == 404, path
    for name, _ in ASSETS.values():  # fixed files of the page (or the shared lookup), never built from a request
        assert ".." not in str(name) and (isinstance(name, Path) or not name.startswith("/"))




async def _serve_scene(scene, fn, made: list | None = None, blob: bytes | None = None):
    """Serve a small grid with `scene` to send, `fn(port, service)` the while: its blob `blob`, or made on
    the first request (each making appended to `made`)."""
    from test_streaming_service import make_grid  # a small real grid

    from psao.protocol.session import scene_hash_bytes
    h = scene_hash_bytes(scene.content_hash())
    made = [] if made is None else made
    service = Service(make_grid(200), h, ServeSettings(port=0, tick_hz=30, stats_interval=1e9),
                      scene_blob=blob if blob is not None else lambda: made.append(1) or scene_blob(scene))
    stop, ready = asyncio.Event(), asyncio.Event()
    task = asyncio.create_task(service.run(stop, ready=lambda port: ready.set()))
    await ready.wait()
    try:
        return h, await fn(service.port, service)
    finally:
        stop.set()
        await task


def test_client_without_a_scene_takes_the_servers():
    scene = load_scene("builtin:cornell")

    async def use(port, _service):
        url = f"ws://127.0.0.1:{port}"
        (got, h, nbytes), again = await asyncio.gather(fetch_scene(url), fetch_scene(url))
        assert again[1:] == (h, nbytes)
        stats = await asyncio.wait_for(MirrorClient(url, h).run(frames=0), HANG_S)

        def get(path):
            try:
                with urllib.request.urlopen(f"http://127.0.0.1:{port}{path}") as r:
                    return r.status, r.read()
            except urllib.error.HTTPError as exc:
                return exc.code, exc.read()
        http = await asyncio.to_thread(lambda: [get(p) for p in ("/psao_constants.js", "/../pyproject.toml",
                                                                 "/%2e%2e/Makefile", "/vendor%2Ffzstd.js")])
        return got, h, nbytes, stats, http

    made = []
    h, (got, sent_hash, nbytes, stats, http) = asyncio.run(_serve_scene(scene, use, made))
    assert made == [1]  # made once, for both requests
    assert sent_hash == h and nbytes == len(scene_blob(scene)) and stats.messages >= 2
    assert [m.name for m in got.meshes] == [m.name for m in scene.meshes]
    assert np.allclose(got.meshes[0].vertices, scene.meshes[0].vertices, atol=1e-6)
    assert got.ao_distance == scene.ao_distance and list(got.camera_paths) == list(scene.camera_paths)
    assert http[0][0] == 200 and b"PROTOCOL_VERSION" in http[0][1]
    assert [s for s, _ in http[1:]] == [404, 404, 404]


def test_a_stronger_blob_replaces_the_fast_one_and_holds_the_same_scene():
    """psao serve answers SceneRequests at once with a fast zstd level, then with the strongest level once
    that is compressed (Service.set_scene_blob): both decompress to the same scene file."""
    from psao.server.net.scene_export import SceneExportSettings

    scene = load_scene("builtin:courtyard")
    fast = scene_blob(scene, level=SceneExportSettings.first_zstd_level)
    strong = scene_blob(scene)
    assert len(strong) < len(fast)  # the strongest level is worth its time
    dctx = zstandard.ZstdDecompressor()
    assert dctx.decompress(fast) == dctx.decompress(strong) == scene_file(scene).serialize()

    async def use(port, service):
        url = f"ws://127.0.0.1:{port}"
        first = await fetch_scene(url)
        service.set_scene_blob(strong)
        second = await fetch_scene(url)
        return first, second

    (got1, h1, n1), (got2, h2, n2) = asyncio.run(_serve_scene(scene, use, blob=fast))[1]
    assert (n1, n2) == (len(fast), len(strong)) and h1 == h2
    assert [m.name for m in got1.meshes] == [m.name for m in got2.meshes] == [m.name for m in scene.meshes]
