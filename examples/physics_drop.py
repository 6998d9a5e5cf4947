"""Application-driven motion: this script's own loop drops the robot lab's three crates under gravity and
drives the scene's clock, through the Python API (psao.Server), while clients watch.

    .venv/bin/python examples/physics_drop.py [--seconds 6] [--port 8765] [--density 64]

Open the printed page in a browser to watch the crates fall and bounce, with the AO under them following.
A headless psao.Client in this process watches too: at the end its mirror digests are compared with the
server's (exit 1 when any differs or none could be compared).
"""
from __future__ import annotations

import argparse
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

import psao
from psao.eval.digests import compare_digests
from psao.server.settings import BakeSettings, ServeSettings

GRAVITY = 9.81  # m/s^2
RESTITUTION = 0.45  # the share of its speed a crate keeps at a bounce
STEP_HZ = 30.0  # simulation steps per second of scene time (and of wall time: the loop runs in real time)


@dataclass
class Crate:
    name: str
    rest: np.ndarray  # (4, 4) where it lies on what is under it
    drop_at: float  # seconds of scene time when it is let go
    height: float = 2.0  # metres above its rest position it is let go from
    lift: float = 0.0  # metres above rest now
    speed: float = 0.0  # m/s, upwards positive

    def step(self, t: float, dt: float) -> None:
        if t < self.drop_at:
            self.lift = self.height
            return
        self.speed -= GRAVITY * dt
        self.lift += self.speed * dt
        if self.lift <= 0.0:  # a bounce on what it rests on
            self.lift = 0.0
            self.speed = -self.speed * RESTITUTION if abs(self.speed) > 0.3 else 0.0

    def matrix(self) -> np.ndarray:
        m = self.rest.copy()
        m[1, 3] += self.lift
        return m


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seconds", type=float, default=6.0, help="seconds of scene time to simulate")
    ap.add_argument("--port", type=int, default=8765, help="TCP port (0 picks a free one)")
    ap.add_argument("--density", type=float, default=64.0, help="points per square metre of the bake")
    args = ap.parse_args(argv)

    work = Path(tempfile.mkdtemp(prefix="psao-drop-"))
    serve = ServeSettings(port=args.port, tick_hz=30, digest_log=work / "server.jsonl")
    settings = psao.ServerSettings(serve=serve, bake=BakeSettings(density=args.density, rays=64), animate=True,
                                   clock="app")
    with psao.Server("builtin:robots", settings) as server:
        print(f"serving {server.scene.name}: open http://{serve.host}:{server.port}/ to watch", flush=True)
        crates = [Crate(name, server.scene.instances[server.instance(name)].transform.copy(), drop_at)
                  for name, drop_at in (("crate0", 0.5), ("crate1", 1.0), ("crate2", 2.0))]
        with psao.Client(server.url, digest_log=work / "client.jsonl") as client:
            t, dt = 0.0, 1.0 / STEP_HZ
            next_step = time.perf_counter()
            while t < args.seconds:
                for c in crates:
                    c.step(t, dt)
                    server.move(c.name, c.matrix())
                server.set_time(t)  # the robots walk on the same clock
                t += dt
                next_step += dt
                time.sleep(max(0.0, next_step - time.perf_counter()))
            final = {server.instance(c.name): c.matrix().astype(np.float32) for c in crates}
            client.wait_for(lambda: all(np.allclose(client.mirror.transforms[i], m) for i, m in final.items()),
                            60.0, "the crates' final poses")
            print(f"the client received {client.updates} Updates ({client.stats.bytes_received / 1e6:.2f} MB); "
                  f"the server ran {server.ticks} ticks", flush=True)
    compared, differ, _ = compare_digests(work / "server.jsonl", [work / "client.jsonl"])
    print(f"mirror: {compared} states compared with the server's, {differ} differ", flush=True)
    return 0 if compared and not differ else 1


if __name__ == "__main__":
    sys.exit(main())
