"""Malformed and unwelcome input to a live server over real loopback sockets, from a raw websocket client.

Each bad connection must get an Error message and a close code, alone; a well-behaved client connected
all along keeps receiving updates, and the server logs one line naming the reason.
"""
from __future__ import annotations

import asyncio
import logging
import struct

import numpy as np
import pytest
import zstandard
from websockets.asyncio.client import connect
from websockets.exceptions import ConnectionClosed

from psao.protocol import messages as m
from psao.protocol.codecs import Codec, codec_mask
from psao.protocol.gridformat import poisson_radius
from psao.client.connection import MirrorClient
from psao.server.grid import Grid
from psao.server.net.service import Service
from psao.server.settings import ServeSettings
from psao.server.tick.testhook import RandomEdits
from serving import HANG_S

HASH = bytes(range(32))
ALL = codec_mask(Codec)
EYE = np.eye(4, dtype=np.float32)


def make_grid(n=3000, seed=0) -> Grid:
    """A real grid: points on two faces of a unit box."""
    rng = np.random.default_rng(seed)
    pos = rng.random((n, 3))
    pos[: n // 2, 2] = 0.0
    pos[n // 2 :, 1] = 0.0
    nrm = np.zeros((n, 3), np.float32)
    nrm[: n // 2, 2] = 1.0
    nrm[n // 2 :, 1] = 1.0
    return Grid.build([(pos, nrm, poisson_radius(2.0, n), 0)])


def hello(token="", scene_hash=HASH) -> bytes:
    return m.encode(m.Hello(scene_hash, ALL, token))


def with_header(mtype: int, payload: bytes, codec: int = 0, version: int = 1, length: int | None = None) -> bytes:
    n = len(payload) if length is None else length
    return b"PSAO" + struct.pack("<HBBI", version, mtype, codec, n) + payload


async def raw_exchange(url: str, messages: list, read_all=True) -> tuple[m.Error | None, int | None]:
    """Send messages; read until the server closes. Returns (Error message received, close code)."""
    error = None
    async with connect(url, compression=None, max_size=None) as ws:
        for msg in messages:
            await ws.send(msg)
        try:
            while True:
                data = await asyncio.wait_for(ws.recv(), HANG_S)
                hdr = m.Header.parse(data, 1 << 30)
                if hdr.type == m.MessageType.ERROR:
                    error = m.Error.parse(data[12:])
        except ConnectionClosed:
            pass
        await ws.wait_closed()
        return error, ws.close_code


async def updates_beyond(client, task, count):
    """Returns once `client` has more than `count` updates, or its task ended (a count, not a time)."""
    while client.stats.updates <= count and not task.done():
        await asyncio.sleep(0.05)


async def with_server(body, token="", hello_timeout=HANG_S, **more):
    """Run a server with random edits and one good client; `body(url)` runs meanwhile. The Hello timeout
    is long unless a test asks for one: a loaded machine may take seconds to carry a large first message."""
    grid = make_grid()
    settings = ServeSettings(port=0, tick_hz=30, token=token, stats_interval=1e9, hello_timeout=hello_timeout, **more)
    service = Service(grid, HASH, settings, tick=RandomEdits(20, seed=1))
    stop, ready = asyncio.Event(), asyncio.Event()
    server = asyncio.create_task(service.run(stop, ready=lambda port: ready.set()))
    await asyncio.wait_for(ready.wait(), HANG_S)
    url = f"ws://127.0.0.1:{service.port}"
    good = MirrorClient(url, HASH, token=token, reconnect=False)
    good_task = asyncio.create_task(good.run())
    while good.stats.updates < 5:
        await asyncio.sleep(0.05)
    try:
        before = good.stats.updates
        result = await body(url)
        await asyncio.wait_for(updates_beyond(good, good_task, before + 3), HANG_S)
        assert good.stats.updates > before + 3, "the good client stopped being served"
        assert not good_task.done() and good.stats.reconnects == 0
    finally:
        good.stop()
        await asyncio.wait_for(good_task, HANG_S)
        stop.set()
        await asyncio.wait_for(server, HANG_S)
    return result


def run_case(caplog, messages, token="", after_welcome=False, hello_token=None, **more):
    caplog.clear()
    caplog.set_level(logging.INFO, logger="psao.serve")

    async def body(url):
        msgs = ([hello(token if hello_token is None else hello_token)] if after_welcome else []) + messages
        return await raw_exchange(url, msgs)

    error, code = asyncio.run(with_server(body, token=token, **more))
    warnings = [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING]
    assert len(warnings) == 1, warnings
    return error, code, warnings[0]


VALID_HELLO = hello()


@pytest.mark.parametrize(
    "name, messages, err_code, close_code, reason",
    [
        ("wrong magic", [b"XXXX" + VALID_HELLO[4:]], m.ErrorCode.BAD_HEADER, 1002, "bad magic"),
        ("wrong version", [with_header(1, VALID_HELLO[12:], version=7)], m.ErrorCode.BAD_HEADER, 1002,
         "unsupported protocol version 7"),
        ("truncated header", [VALID_HELLO[:7]], m.ErrorCode.BAD_HEADER, 1002, "truncated header"),
        ("length over the limit", [with_header(1, VALID_HELLO[12:], length=1 << 30)], m.ErrorCode.TOO_LARGE, 1009,
         "over the limit"),
        ("garbage after a valid header", [VALID_HELLO + b"garbage"], m.ErrorCode.BAD_HEADER, 1002, "carries"),
        ("garbage payload", [with_header(1, b"\x01\x00garbage")], m.ErrorCode.BAD_PAYLOAD, 1002, "truncated"),
        ("unknown type", [with_header(77, b"")], m.ErrorCode.BAD_HEADER, 1002, "unknown message type 77"),
        ("text message", ["hello"], m.ErrorCode.BAD_HEADER, 1002, "text message"),
        ("scene mismatch", [hello(scene_hash=bytes(32))], m.ErrorCode.SCENE_MISMATCH, 1008, "scene hash mismatch"),
        ("camera first", [m.encode(m.Camera(EYE, EYE))], m.ErrorCode.UNEXPECTED_MESSAGE, 1002, "expected Hello"),
    ],
)
def test_bad_first_message(caplog, name, messages, err_code, close_code, reason):
    error, code, line = run_case(caplog, messages)
    assert error is not None and error.code == err_code and reason in error.text
    assert code == close_code
    assert reason in line and "127.0.0.1" in line


def test_zstd_bomb_declaring_huge_size(caplog):
    bomb = zstandard.ZstdCompressor(level=3).compress(bytes(512 << 20))
    assert len(bomb) < 64 << 10  # small on the wire, 512 MiB declared
    error, code, line = run_case(caplog, [with_header(1, bomb, codec=Codec.ZSTD)])
    assert error.code == m.ErrorCode.TOO_LARGE and code == 1009
    assert "declares 536870912 bytes" in line


def test_zstd_bomb_without_declared_size(caplog):
    bomb = zstandard.ZstdCompressor(level=3, write_content_size=False).compress(bytes(64 << 20))
    error, code, line = run_case(caplog, [with_header(1, bomb, codec=Codec.ZSTD)])
    assert error.code == m.ErrorCode.TOO_LARGE and code == 1009
    assert "exceeds the limit" in line


def test_camera_with_nan_after_handshake(caplog):
    bad = EYE.copy()
    bad[1, 2] = np.nan
    camera = with_header(m.MessageType.CAMERA, bad.tobytes() + EYE.tobytes())
    error, code, line = run_case(caplog, [camera], after_welcome=True)
    assert error.code == m.ErrorCode.BAD_PAYLOAD and code == 1002
    assert "NaN" in line and "client" in line


EDITS = {"allow_edits": True, "edit_token": "edit-secret"}


def test_scene_edits_refused_by_default(caplog):
    error, code, line = run_case(caplog, [m.encode(m.SceneEdit(0, EYE))], after_welcome=True)
    assert error.code == m.ErrorCode.EDITS_NOT_ALLOWED and code == 1008 and "does not accept scene edits" in line


@pytest.mark.parametrize("token, hello_token", [("", ""), ("view", "view")])
def test_scene_edits_need_the_edit_token(caplog, token, hello_token):
    error, code, line = run_case(caplog, [m.encode(m.SceneEdit(0, EYE))], token=token, after_welcome=True,
                                 hello_token=hello_token, **EDITS)
    assert error.code == m.ErrorCode.EDITS_NOT_ALLOWED and code == 1008 and "need the edit token" in line


def _matrix(scale=1.0, move=0.0, last=(0, 0, 0, 1)):
    t = np.diag(np.float32([scale, scale, scale, 1.0]))
    t[0, 3] = move
    t[3] = last
    return t


@pytest.mark.parametrize("instance, transform, text", [
    (5, EYE, "no instance 5"),
    (0, _matrix(scale=3e38), "axis scales"),
    (0, _matrix(scale=1e-9), "axis scales"),
    (0, _matrix(move=1e9), "translation"),
    (0, _matrix(last=(0, 0, 1, 1)), "last row"),
])
def test_bad_scene_edit(caplog, instance, transform, text):
    error, code, line = run_case(caplog, [m.encode(m.SceneEdit(instance, transform))], after_welcome=True,
                                 hello_token="edit-secret", **EDITS)
    assert error.code == m.ErrorCode.BAD_EDIT and code == 1008 and text in line, line


def test_scene_edit_with_the_edit_token_reaches_other_clients():
    moved = _matrix(scale=2.0, move=0.25)

    async def body(url):
        watcher = MirrorClient(url, HASH, reconnect=False)
        task = asyncio.create_task(watcher.run())
        while watcher.stats.updates < 2:
            await asyncio.sleep(0.05)
        async with connect(url, compression=None, max_size=None) as ws:
            await ws.send(hello("edit-secret"))
            await ws.send(m.encode(m.SceneEdit(0, moved)))
            while not np.array_equal(watcher.mirror.transforms[0], moved):
                await asyncio.sleep(0.05)
        watcher.stop()
        await task
        return True

    assert asyncio.run(with_server(body, **EDITS))


@pytest.mark.parametrize("token, reason", [("", "missing token"), ("guess", "wrong token")])
def test_token_refused(caplog, token, reason):
    error, code, line = run_case(caplog, [hello(token)], token="secret")
    assert error.code == m.ErrorCode.UNAUTHORIZED and code == 1008
    assert reason in line


def test_message_beyond_the_socket_limit(caplog):
    # Past 4x the client limit websockets refuses the frame itself (close 1009, no Error message).
    error, code, line = run_case(caplog, [with_header(1, bytes(300 * 1024))])
    assert error is None and code == 1009 and "message over" in line
    # Between the protocol limit and that, the server still answers with an Error message.
    error, code, line = run_case(caplog, [with_header(1, bytes(100 * 1024))])
    assert error.code == m.ErrorCode.TOO_LARGE and code == 1009 and "over the limit" in line


def test_silent_connection_times_out(caplog):
    error, code, line = run_case(caplog, [], hello_timeout=2.0)
    assert error.code == m.ErrorCode.TIMEOUT and code == 1008 and "no Hello" in line


def test_client_digest_every_counts_updates_and_is_checked():
    from psao.client.errors import ClientError
    with pytest.raises(ClientError, match="digest every"):
        MirrorClient("ws://127.0.0.1:1", b"\0" * 32, digest_every=0)
    client = MirrorClient("ws://127.0.0.1:1", b"\0" * 32, digest_every=3)
    logged = []
    for updates in range(8):  # 0: the Snapshot's chunks; then after the first Update, every third
        client.stats.updates = updates
        logged.append(client.digest_if(1, updates + 5))
    assert logged == [True, True, False, True, False, False, True, False]
