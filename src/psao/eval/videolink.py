"""The video competitor's frames over a real socket: a client that asks for frames at its frame rate and a
server that answers each request with that frame's encoded packets, so that a link between them
(psao.eval.links) delays the frames and caps their rate as it would a video streamer's.

    with VideoLinkServer(packets, host) as server:      # packets: per frame, its encoded packets (bytes)
        # in the client's namespace, for `frames` requests at `fps`:
        python -m psao.eval.videolink HOST PORT --fps 30 --frames 150 --out LOG.json
    log = read_receive_log(LOG.json)                    # request and arrival wall times, packets received

The client sends request k (a big-endian uint32, the frame index) at its start + k / fps, as a streaming
client sends its pose; the server, on reading request k, sends frame k: a header (uint32 frame index,
uint32 packet count), then per packet a uint32 length and its bytes. The client reads frames on a second
thread and records the wall time (time.time(): the host and the namespace share the clock) at which each
frame's last byte arrived, and every packet it received, so that what is decoded and shown is what
crossed the link. It stops once every frame requested has arrived or DRAIN_S after its last request.
Both ends use TCP with Nagle's algorithm off: the link's delay, loss (retransmissions) and rate cap
(a queue that builds when the stream exceeds it) are TCP's, as for a real streamer over TCP.
"""
from __future__ import annotations

import argparse
import json
import socket
import struct
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path

REQUEST = struct.Struct("!I")  # frame index
FRAME = struct.Struct("!II")  # frame index, packet count
PACKET = struct.Struct("!I")  # packet length, bytes
DRAIN_S = 10.0  # seconds the client waits for frames after its last request
CONNECT_TIMEOUT_S = 30.0  # seconds for the client's connection
ACCEPT_TIMEOUT_S = 60.0  # seconds the server waits for its one client


def frame_message(index: int, packets: list[bytes]) -> bytes:
    """Frame `index`'s message: its header, then each packet with its length."""
    return FRAME.pack(index, len(packets)) + b"".join(PACKET.pack(len(p)) + p for p in packets)


class VideoLinkServer:
    """A TCP listener on `host` (a free port) serving one client: each request k read is answered with
    frame k of `packets` (requests beyond the last frame are ignored). `bytes_sent` counts the messages."""

    def __init__(self, packets: list[list[bytes]], host: str):
        self.messages = [frame_message(k, ps) for k, ps in enumerate(packets)]
        self.sock = socket.create_server((host, 0))
        self.sock.settimeout(ACCEPT_TIMEOUT_S)
        self.port = self.sock.getsockname()[1]
        self.bytes_sent = 0
        self.error: str | None = None
        self._thread = threading.Thread(target=self._serve, daemon=True)
        self._thread.start()

    def _serve(self) -> None:
        try:
            conn, _ = self.sock.accept()
        except OSError as exc:
            self.error = f"no client: {exc}"
            return
        with conn:
            conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            conn.settimeout(None)
            buf = b""
            try:
                while chunk := conn.recv(4096):
                    buf += chunk
                    while len(buf) >= REQUEST.size:
                        (k,), buf = REQUEST.unpack_from(buf), buf[REQUEST.size:]
                        if k < len(self.messages):
                            conn.sendall(self.messages[k])
                            self.bytes_sent += len(self.messages[k])
            except OSError as exc:  # the client closed while a frame was on its way
                self.error = str(exc)

    def close(self) -> None:
        self.sock.close()
        self._thread.join(timeout=5.0)

    def __enter__(self) -> "VideoLinkServer":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


@dataclass
class ReceiveLog:
    """What the client saw: per frame requested, its request's and its arrival's wall time (None: it
    never arrived), and the packets of each frame that arrived."""

    requests: list[float]
    arrivals: list[float | None]
    packets: list[list[bytes]]  # per frame that arrived, in order (frames arrive in order)
    bytes_received: int

    @property
    def arrived(self) -> int:
        return sum(a is not None for a in self.arrivals)


def _read_exact(conn: socket.socket, n: int) -> bytes:
    out = bytearray()
    while len(out) < n:
        chunk = conn.recv(n - len(out))
        if not chunk:
            raise EOFError
        out += chunk
    return bytes(out)


def receive(host: str, port: int, fps: float, frames: int) -> ReceiveLog:
    """Connect, request `frames` frames at `fps`, read them as they come (see the module)."""
    conn = socket.create_connection((host, port), timeout=CONNECT_TIMEOUT_S)
    conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    conn.settimeout(None)
    requests: list[float] = []
    arrivals: list[float | None] = [None] * frames
    packets: list[list[bytes]] = []
    total = [0]
    done = threading.Event()

    def reader() -> None:
        try:
            for _ in range(frames):
                k, n = FRAME.unpack(_read_exact(conn, FRAME.size))
                ps = [_read_exact(conn, PACKET.unpack(_read_exact(conn, PACKET.size))[0]) for _ in range(n)]
                arrivals[k] = time.time()
                packets.append(ps)
                total[0] += FRAME.size + sum(PACKET.size + len(p) for p in ps)
        except (EOFError, OSError):
            pass
        done.set()

    thread = threading.Thread(target=reader, daemon=True)
    thread.start()
    start = time.monotonic()
    for k in range(frames):
        time.sleep(max(0.0, start + k / fps - time.monotonic()))
        requests.append(time.time())
        conn.sendall(REQUEST.pack(k))
    done.wait(DRAIN_S)
    try:
        conn.shutdown(socket.SHUT_RDWR)  # wakes the reader if frames are still missing
    except OSError:
        pass
    thread.join(timeout=5.0)
    conn.close()
    return ReceiveLog(requests, arrivals, list(packets), total[0])


def write_receive_log(log: ReceiveLog, path: Path) -> None:
    """The log as JSON (packets hex-encoded)."""
    path.write_text(json.dumps({"requests": log.requests, "arrivals": log.arrivals, "bytes_received": log.bytes_received,
                                "packets": [[p.hex() for p in ps] for ps in log.packets]}))


def read_receive_log(path: Path) -> ReceiveLog:
    d = json.loads(Path(path).read_text())
    return ReceiveLog(d["requests"], d["arrivals"], [[bytes.fromhex(p) for p in ps] for ps in d["packets"]],
                      d["bytes_received"])


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m psao.eval.videolink", description=__doc__.splitlines()[0])
    p.add_argument("host")
    p.add_argument("port", type=int)
    p.add_argument("--fps", type=float, required=True, help="requests per second")
    p.add_argument("--frames", type=int, required=True, help="frames requested")
    p.add_argument("--out", type=Path, required=True, help="the receive log (JSON)")
    args = p.parse_args(argv)
    if not (args.fps > 0 and args.frames >= 1):
        print("videolink: error: --fps must be > 0 and --frames >= 1", file=sys.stderr)
        return 2
    try:
        log = receive(args.host, args.port, args.fps, args.frames)
    except OSError as exc:
        print(f"videolink: error: {args.host}:{args.port}: {exc}", file=sys.stderr)
        return 1
    write_receive_log(log, args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
