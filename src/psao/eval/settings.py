"""The evaluation commands' settings and their defaults, in one place: `psao bench` (and its video
comparison) and `psao demo`. Frame sizes and AO method options are the client's (src/psao/client/settings.py,
MethodOptions); bake and tick settings the server's (src/psao/server/settings.py).
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from psao.client.settings import FrameSettings


@dataclass
class BenchSettings:
    densities: tuple[float, ...] = (128, 256, 512, 1024)  # PSAO densities N, points per world unit^2
    tick_hz: tuple[float, ...] = (5, 15, 30, 60)  # server tick rates of the stream, Hz
    frames: int = 4  # frames along the camera path scored per scene
    size: str = FrameSettings.size  # pixels, width x height
    methods: tuple[str, ...] = ("ssao", "gtao", "psao")  # AO methods scored against RTAO
    mlp_steps: int = 1500  # Adam steps of MLP baking, per scene
    stream_seconds: float = 3.0  # seconds a client runs after its snapshot, per density and tick rate
    out: Path = Path("out") / "bench"  # tables, charts and images
    cache: Path = Path("out") / ".cache"  # grids and RTAO references
    image_scale: float = 1.0  # scale of the side-by-side PNGs


@dataclass
class VideoSweepSettings:
    bitrates: tuple[float, ...] = (0.25, 0.5, 1, 2, 4, 8)  # Mbit/s targets of the sweep
    latencies_ms: tuple[float, ...] = (0, 50, 100)  # milliseconds from pose to display
    clients: tuple[int, ...] = (1, 10, 100)  # client counts of the server-cost table


@dataclass(frozen=True)
class DemoSettings:
    scene: str = "builtin:courtyard"
    density: float = 96.0  # points per unit^2: a fraction of the bench's densities, so the demo stays short
    rays: int = 32  # AO rays per point in the demo bake (and per re-traced point)
    frames: int = 24  # frames rendered along the camera path
    scored: int = 3  # of which scored against RTAO
    client_scored: int = 2  # frames of the streaming client's own scored against RTAO
    spp: int = 64  # RTAO rays per pixel for the demo's reference (the bench's is ReferenceSettings.spp)
    size: str = FrameSettings.size  # pixels, width x height
    stream_seconds: float = 4.0  # seconds the streaming client runs after its snapshot
    tick_hz: float = 30.0  # the served stream's tick rate
    out: Path = Path("out") / "demo"
