"""Fuzz the decoders both ends run on untrusted bytes: `python -m benchmarks.fuzz --inputs N`.

Targets (N inputs spread over them, seeded, reproducible):
  server   ServerSession.receive after a handshake: mutated Hello, Camera, SceneEdit, Bye and random bytes
  client   ClientSession.receive + Mirror.apply: mutated Welcome, Snapshot and Update messages for every
           codec (the zstd stream included: a session per input, fed the valid prefix first)
  exact    unmutated streams: the mirror's digest must equal the source grid's after every message
  scene    the TOML scene reader on mutated scene text

An input may parse or be refused with the end's own error (ProtocolError, MirrorError, SceneError);
anything else is a crash. Verdicts: no crash, every digest exact, and every input run.
"""
from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks.verdicts import Verdicts
from psao.protocol import messages as m
from psao.protocol.codecs import Codec
from psao.protocol.errors import ProtocolError
from psao.protocol.gridformat import EMPTY, FREE_CELL, INSTANCE_DTYPE
from psao.protocol.limits import DEFAULT_LIMITS
from psao.protocol.session import ClientConfig, ClientSession, ServerConfig, ServerSession
from psao.protocol.updates import GridDelta, Layout, state_digest
from psao.client.errors import MirrorError
from psao.client.mirror import Mirror
from psao.scene.errors import SceneError

HASH = bytes(range(32))
SCENE_TOML = """[scene]
name = "fuzz"
ao_distance = 0.5
[[mesh]]
name = "box"
generator = "box"
[[mesh]]
name = "ring"
generator = "torus"
sections = 12
[[instance]]
name = "a"
mesh = "box"
translate = [0, 0.5, 0]
scale = [1, 2, 1]
[[instance]]
name = "b"
mesh = "ring"
rotate = { axis = [0, 1, 0], degrees = 30 }
[[camera_path]]
name = "orbit"
fov_y = 50
[[camera_path.key]]
time = 0
eye = [3, 2, 3]
target = [0, 0.5, 0]
"""


def mutate(rng, data: bytes) -> bytes:
    """1-3 of: a byte changed, the tail cut, a byte inserted, a 4-byte field set to an extreme."""
    p = bytearray(data)
    for _ in range(int(rng.integers(1, 4))):
        op = int(rng.integers(0, 4))
        if op == 0 and p:
            p[int(rng.integers(len(p)))] = int(rng.integers(0, 256))
        elif op == 1 and p:
            del p[int(rng.integers(len(p))):]
        elif op == 2:
            p.insert(int(rng.integers(len(p) + 1)), int(rng.integers(0, 256)))
        elif len(p) >= 4:
            at = int(rng.integers(len(p) - 3))
            p[at:at + 4] = int(rng.choice([0, 1, 0x7FFFFFFF, 0xFFFFFFFF, 1 << 24])).to_bytes(4, "little")
    return bytes(p)


class Grid:
    """A small grid in the wire layout, edited at random."""

    def __init__(self, rng, n_buckets=64, capacity=96):
        self.rng = rng
        self.instances = np.zeros(2, INSTANCE_DTYPE)
        self.instances["bucket_count"] = n_buckets // 2
        self.instances["bucket_offset"] = (0, n_buckets // 2)
        self.buckets = np.full((n_buckets, 8, 2), EMPTY, np.uint32)
        self.cells = np.tile(FREE_CELL, (capacity, 1))
        self.transforms = np.tile(np.eye(4, dtype=np.float32), (2, 1, 1))

    def edit(self, k: int) -> GridDelta:
        r = self.rng
        b = np.unique(r.integers(0, len(self.buckets), k)).astype(np.uint32)
        c = np.unique(r.integers(0, len(self.cells), k)).astype(np.uint32)
        self.buckets[b, :2] = r.integers(0, 1 << 20, (len(b), 2, 2))
        self.cells[c, :3] = 0x80000000 | r.integers(0, 1 << 31, (len(c), 3))
        self.cells[c, 7] = r.integers(0, 1 << 20, len(c))
        self.transforms[int(r.integers(2))] += np.float32(0.5)
        t = np.arange(2, dtype=np.uint32)
        return GridDelta(len(self.cells), t, self.transforms[t], b, self.buckets[b], c, self.cells[c])

    def digest(self) -> str:
        return state_digest(self.instances, self.buckets, self.cells, self.transforms)


def stream(rng, codec: Codec, layout: Layout, n_updates: int):
    """(messages of one connection, digest after each) from a fresh server session."""
    g = Grid(rng)
    server = ServerSession(ServerConfig(HASH, codec=codec, layout=layout))
    client = ClientSession(ClientConfig(HASH, codecs=frozenset({codec})))
    server.receive(client.hello())
    msgs = [server.welcome(1, 60.0, len(g.buckets), len(g.cells), g.instances)]
    digests = [None]
    msgs.append(server.snapshot(0, 1, g.edit(40)))
    digests.append(g.digest())
    for tick in range(n_updates):
        msgs.append(server.update(tick, tick / 60, g.edit(int(rng.integers(1, 20)))))
        digests.append(g.digest())
    return msgs, digests


def feed(msgs, codec: Codec) -> Mirror | None:
    """Run messages through a fresh client session and lazy mirror, the way MirrorClient does."""
    client = ClientSession(ClientConfig(HASH, codecs=frozenset({codec})))
    mirror = None
    for data in msgs:
        event = client.receive(data)
        if hasattr(event, "welcome"):
            mirror = Mirror.from_welcome(event.welcome, DEFAULT_LIMITS)
            continue
        mirror.received(len(data))
        delta = event.snapshot.delta if hasattr(event, "snapshot") else event.update.delta
        mirror.apply(delta)
        if getattr(event, "complete", False):
            mirror.complete()
    return mirror


class Tally:
    def __init__(self):
        self.inputs = self.refused = self.parsed = 0
        self.crashes: list[str] = []

    def run(self, what: str, fn, expected=(ProtocolError, MirrorError)) -> None:
        self.inputs += 1
        try:
            fn()
            self.parsed += 1
        except expected:
            self.refused += 1
        except Exception as exc:  # the finding: an error type the caller does not handle
            self.crashes.append(f"{what}: {type(exc).__name__}: {exc}"[:300])


def fuzz_server(rng, n: int, t: Tally) -> None:
    originals = [m.encode(m.Camera(np.eye(4), np.eye(4))), m.encode(m.SceneEdit(1, np.eye(4))), m.encode(m.Bye())]
    hello = m.encode(m.Hello(HASH, 0xFF, "tok"))
    for i in range(n):
        def one():
            s = ServerSession(ServerConfig(HASH, token="tok", edit_token="edit"))
            if i % 4 == 0:
                s.receive(mutate(rng, hello))
            else:
                s.receive(hello)
                s.receive(mutate(rng, originals[i % 3]) if i % 7 else bytes(rng.integers(0, 256, 40, np.uint8)))
        t.run("server", one)


def fuzz_client(rng, n: int, t: Tally) -> None:
    codecs = [Codec.NONE, Codec.ZSTD, Codec.LZ4, Codec.ZSTD_STREAM]
    streams = {(c, lay): stream(rng, c, lay, 3)[0] for c in codecs for lay in Layout}  # each input mutates one
    for i in range(n):
        codec, layout = codecs[i % 4], list(Layout)[i % 2]
        msgs = streams[codec, layout]
        k = int(rng.integers(len(msgs)))
        bad = msgs[:k] + [mutate(rng, msgs[k])] + msgs[k + 1:]
        t.run(f"client {codec.name}", lambda: feed(bad, codec))


def check_exact(rng, n: int, t: Tally) -> int:
    """Unmutated streams: the mirror equals the source after every message. Returns digests compared."""
    compared = 0
    for i in range(n):
        codec = [Codec.NONE, Codec.ZSTD, Codec.LZ4, Codec.ZSTD_STREAM][i % 4]
        msgs, digests = stream(rng, codec, list(Layout)[i % 2], 4)
        for k in range(2, len(msgs) + 1):
            mirror = feed(msgs[:k], codec)
            compared += 1
            if mirror.digest() != digests[k - 1]:
                t.crashes.append(f"exact {codec.name}: mirror differs after message {k - 1}")
        t.inputs += 1
    return compared


def fuzz_scene(rng, n: int, t: Tally) -> None:
    from psao.scene.tomlscene import load_toml_scene

    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "s.toml"
        for _ in range(n):
            path.write_bytes(mutate(rng, SCENE_TOML.encode()))
            t.run("scene", lambda: load_toml_scene(path), expected=(SceneError,))


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.fuzz", description=__doc__.splitlines()[0])
    p.add_argument("--inputs", type=int, default=20000, help="inputs in all (default 20000)")
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)
    if args.inputs < 10:
        print("benchmarks.fuzz: error: --inputs must be >= 10", file=sys.stderr)
        return 2
    rng = np.random.default_rng(args.seed)
    t = Tally()
    t0 = time.perf_counter()
    n = args.inputs
    fuzz_server(rng, n * 4 // 10, t)
    fuzz_client(rng, n * 4 // 10, t)
    compared = check_exact(rng, max(1, n // 20), t)
    fuzz_scene(rng, n - t.inputs, t)
    seconds = time.perf_counter() - t0
    print(f"fuzz: {t.inputs} inputs in {seconds:.1f} s: {t.parsed} parsed, {t.refused} refused with the end's own "
          f"error, {len(t.crashes)} crashes; {compared} mirror digests compared")
    for line in t.crashes[:20]:
        print(f"  crash: {line}")
    v = Verdicts("fuzz")
    v.check("inputs run", t.inputs, ">=", n)
    v.check("crashes (errors other than the protocol's, the mirror's, the scene's)", len(t.crashes), "<=", 0)
    v.check("mirror digests compared", compared, ">=", 1)
    return v.exit_code()


if __name__ == "__main__":
    sys.exit(main())
