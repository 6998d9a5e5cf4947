"""Browser Origin allow-list and TLS (a self-signed certificate made here with openssl), over real sockets."""
from __future__ import annotations

import asyncio
import logging
import shutil
import ssl
import subprocess

import pytest
from websockets.asyncio.client import connect
from websockets.exceptions import InvalidStatus

from psao.client.connection import MirrorClient
from psao.client.errors import ConnectError
from psao.server.errors import ConfigError
from psao.server.settings import ServeSettings
from test_bad_input_server import HASH, hello
from test_service_crowd import start
from serving import HANG_S


async def opens(url, origin=None, **kw) -> bool:
    """Whether the server lets a websocket with this Origin header through its handshake."""
    try:
        async with connect(url, compression=None, max_size=None, origin=origin, **kw) as ws:
            await ws.send(hello())
            await asyncio.wait_for(ws.recv(), HANG_S)  # the Welcome
            return True
    except InvalidStatus as exc:
        assert exc.response.status_code == 403
        return False


def test_origin_allow_list(caplog):
    caplog.set_level(logging.INFO, logger="psao.serve")

    async def main():
        settings = ServeSettings(port=0, tick_hz=30, stats_interval=1e9, allow_origins=("https://viewer.example",))
        service, stop, task, url = await start(settings)
        own = f"http://127.0.0.1:{service.port}"
        try:
            return [await opens(url, o) for o in (None, own, "https://viewer.example", "http://evil.example",
                                                  "null")]
        finally:
            stop.set()
            await task

    assert asyncio.run(main()) == [True, True, True, False, False]
    assert any("origin http://evil.example refused" in r.getMessage() for r in caplog.records)


@pytest.fixture
def self_signed(tmp_path):
    if shutil.which("openssl") is None:
        pytest.skip("no openssl here")
    cert, key = tmp_path / "cert.pem", tmp_path / "key.pem"
    subprocess.run(["openssl", "req", "-x509", "-newkey", "rsa:2048", "-nodes", "-keyout", str(key), "-out", str(cert),
                    "-days", "1", "-subj", "/CN=localhost", "-addext", "subjectAltName=IP:127.0.0.1,DNS:localhost"],
                   check=True, capture_output=True)
    return cert, key


def test_tls_with_a_self_signed_certificate(self_signed):
    cert, key = self_signed

    async def main():
        settings = ServeSettings(port=0, tick_hz=30, stats_interval=1e9, tls_cert=cert, tls_key=key)
        service, stop, task, _ = await start(settings)
        wss = f"wss://127.0.0.1:{service.port}"
        try:
            good = await asyncio.wait_for(MirrorClient(wss, HASH, reconnect=False, tls_ca=cert).run(frames=3), HANG_S)
            with pytest.raises(ConnectError, match="cannot connect"):  # not trusted without the certificate
                await MirrorClient(wss, HASH, reconnect=False).run(frames=1)
            with pytest.raises(ConnectError):  # plain ws:// to a TLS port
                await MirrorClient(f"ws://127.0.0.1:{service.port}", HASH, reconnect=False).run(frames=1)
            own = await opens(wss, f"https://127.0.0.1:{service.port}", ssl=ssl.create_default_context(cafile=str(cert)))
            return good, own
        finally:
            stop.set()
            await task

    stats, own_page = asyncio.run(main())
    assert stats.updates >= 3 and own_page


def test_tls_settings_checked(tmp_path, self_signed):
    cert, _ = self_signed
    with pytest.raises(ConfigError, match="both a certificate and its key"):
        ServeSettings(tls_cert=cert).check()
    from psao.server.net.service import tls_context

    (tmp_path / "junk.pem").write_text("not a key")
    with pytest.raises(ConfigError, match="cannot use TLS certificate"):
        tls_context(cert, tmp_path / "junk.pem")
