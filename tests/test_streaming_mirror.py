"""End to end, real processes on loopback: `psao serve` with random edits and several `psao client`s.

The server logs the sha256 of its whole state (instances, buckets, cells, transforms) after every
message that left nothing pending for that client; each client logs the digest of its mirror after every
Snapshot and Update. Wherever both exist for the same (connection, message), they must be equal: the
mirror equals the server bit for bit after that message. Clients: one plain, one throttled (tiny socket
buffer, slow reads: the server must fold many ticks into one update), one behind a proxy that cuts its
connection twice, each time after the same number of messages (it must reconnect and resync), and one killed with SIGKILL mid-stream and restarted.
"""
from __future__ import annotations

import asyncio
import json
import signal
import subprocess
import threading
import time
from pathlib import Path
from urllib.parse import urlsplit

import pytest
from serving import HANG_S, server_url
from support.cli import psao_process as psao  # started, not run to completion

ROOT = Path(__file__).resolve().parents[1]
SCENE = "builtin:courtyard"


def wait_for(predicate, timeout: float, what: str):
    end = time.time() + timeout
    while time.time() < end:
        value = predicate()
        if value:
            return value
        time.sleep(0.05)
    raise AssertionError(f"timed out waiting for {what}")


def read_jsonl(path: Path) -> list[dict]:
    if not path.exists():
        return []
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


class FrameCounter:
    """Counts complete websocket messages in a server-to-client byte stream: the HTTP upgrade response,
    then RFC 6455 frames."""

    def __init__(self):
        self.buffer = b""
        self.upgraded = False
        self.messages = 0

    def feed(self, data: bytes) -> None:
        self.buffer += data
        if not self.upgraded:
            end = self.buffer.find(b"\r\n\r\n")
            if end < 0:
                return
            self.buffer, self.upgraded = self.buffer[end + 4:], True
        while len(self.buffer) >= 2:
            b0, b1 = self.buffer[0], self.buffer[1]
            n, head = b1 & 0x7F, 2
            if n == 126:
                if len(self.buffer) < 4:
                    return
                n, head = int.from_bytes(self.buffer[2:4], "big"), 4
            elif n == 127:
                if len(self.buffer) < 10:
                    return
                n, head = int.from_bytes(self.buffer[2:10], "big"), 10
            head += 4 if b1 & 0x80 else 0
            if len(self.buffer) < head + n:
                return
            self.buffer = self.buffer[head + n:]
            if b0 & 0x80 and b0 & 0x0F in (0x0, 0x1, 0x2):  # FIN of a data message
                self.messages += 1


class CuttingProxy:
    """TCP proxy on loopback that aborts its first `cuts` connections once the server has sent `after`
    websocket messages on each: cuts happen at the same point of the stream however fast the machine is."""

    def __init__(self, target_port: int, after: int, cuts: int):
        self.target_port, self.after, self.cuts = target_port, after, cuts
        self.port = None
        self.connections = 0
        self.cut = 0
        self._loop = asyncio.new_event_loop()
        self._ready = threading.Event()
        self._thread = threading.Thread(target=self._main, daemon=True)
        self._thread.start()
        self._ready.wait(5)

    def _main(self):
        asyncio.set_event_loop(self._loop)
        server = self._loop.run_until_complete(asyncio.start_server(self._handle, "127.0.0.1", 0))
        self.port = server.sockets[0].getsockname()[1]
        self._ready.set()
        self._loop.run_forever()
        server.close()

    async def _handle(self, reader, writer):
        self.connections += 1
        counter = FrameCounter() if self.connections <= self.cuts else None
        up_reader, up_writer = await asyncio.open_connection("127.0.0.1", self.target_port)

        async def pipe(src, dst, count: FrameCounter | None):
            try:
                while data := await src.read(65536):
                    if count is not None:
                        count.feed(data)
                        if count.messages >= self.after:
                            self.cut += 1
                            writer.transport.abort()
                            up_writer.transport.abort()
                            return
                    dst.write(data)
                    await dst.drain()
            except (ConnectionError, OSError):
                pass
            finally:
                dst.close()

        await asyncio.gather(pipe(reader, up_writer, None), pipe(up_reader, writer, counter), return_exceptions=True)

    def close(self):
        self._loop.call_soon_threadsafe(self._loop.stop)
        self._thread.join(5)


def matched(server_log: list[dict], client_log: list[dict]) -> tuple[int, int, set]:
    """(pairs compared, pairs different, connection ids compared)."""
    ours = {(d["conn"], d["seq"]): d["digest"] for d in server_log}
    compared = differ = 0
    conns = set()
    for d in client_log:
        key = (d["conn"], d["seq"])
        if key in ours:
            compared += 1
            differ += ours[key] != d["digest"]
            conns.add(d["conn"])
    return compared, differ, conns


@pytest.mark.slow
def test_mirrors_equal_server_bit_for_bit(tmp_path):
    server_log = tmp_path / "server.jsonl"
    server = psao("serve", SCENE, "--density", "6", "--rays", "4", "--port", "0", "--tick-hz", "30",
                  "--test-edits", "300", "--send-buffer", "8192", "--no-cull", "--no-adapt-rate", "--digest-log", str(server_log),
                  stdout=subprocess.DEVNULL,
                  stderr=open(tmp_path / "server.err", "w"))
    procs = [server]
    proxy = None
    try:
        err = tmp_path / "server.err"
        url = server_url(server, err, 120)
        port = urlsplit(url).port
        proxy = CuttingProxy(port, after=40, cuts=2)
        common = ["--json", "--reconnect-timeout", "20"]
        logs = {k: tmp_path / f"{k}.jsonl" for k in ("plain", "slow", "cut", "killed")}
        plain = psao("client", url, SCENE, "--frames", "300", "--digest-log", str(logs["plain"]), *common)
        slow = psao("client", url, SCENE, "--frames", "40", "--read-delay", "0.25", "--recv-buffer", "4096",
                    "--digest-log", str(logs["slow"]), *common)
        cut = psao("client", f"ws://127.0.0.1:{proxy.port}", SCENE, "--frames", "150", "--digest-log", str(logs["cut"]),
                   *common)
        killed = psao("client", url, SCENE, "--digest-log", str(logs["killed"]), *common)
        procs += [plain, slow, cut, killed]
        wait_for(lambda: len(read_jsonl(logs["killed"])) >= 30, HANG_S, "the doomed client to get going")
        killed.send_signal(signal.SIGKILL)
        killed.wait(10)
        restarted = psao("client", url, SCENE, "--frames", "40", "--digest-log", str(logs["killed"]), *common)
        procs.append(restarted)

        reports = {}
        for name, p in (("plain", plain), ("slow", slow), ("cut", cut), ("restarted", restarted)):
            out, _ = p.communicate(timeout=HANG_S)
            assert p.returncode == 0, f"client {name} failed"
            reports[name] = json.loads(out.strip().splitlines()[-1])
        server.send_signal(signal.SIGTERM)
        server.wait(20)
        assert server.returncode == 0
        server_text = err.read_text()
        assert "stopped on SIGTERM" in server_text
    finally:
        if proxy:
            proxy.close()
        for p in procs:
            if p.poll() is None:
                p.kill()
                p.wait()

    slog = read_jsonl(server_log)
    results = {name: matched(slog, read_jsonl(path)) for name, path in logs.items()}
    for name, (compared, differ, _) in results.items():
        assert differ == 0, f"{name}: {differ} of {compared} mirror states differ from the server"
    assert results["plain"][0] >= 250  # snapshot + almost every one of 300 updates compared
    assert results["slow"][0] >= 30
    assert results["cut"][0] >= 100 and len(results["cut"][2]) >= 3  # resynced on 2 new connections
    assert results["killed"][0] >= 50 and len(results["killed"][2]) == 2
    assert reports["cut"]["reconnects"] >= 2 and proxy.cut == 2
    assert reports["plain"]["updates"] == 300 and reports["plain"]["mirror_cells"] > 1000
    # The slow reader was sent fewer, bigger updates: each folds the ticks it could not take.
    ticks = [d["tick"] for d in read_jsonl(logs["slow"]) if d["tick"] >= 0]
    assert max(b - a for a, b in zip(ticks, ticks[1:])) >= 2
    assert "left (" in server_text  # disconnections logged, the killed one included
