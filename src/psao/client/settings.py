"""The client's command-line settings and their defaults, in one place: the connection (`psao client`)
and the frames drawn (`psao client --render`, `psao render`). The options of the AO methods themselves
are src/psao/client/render/renderer.py's MethodOptions.

Plain dataclasses that import only the client's errors, so `psao client --help` and the benchmarks read
them for free. A range is checked once, by the dataclass's check(), which the command line calls.
"""
from __future__ import annotations

from dataclasses import dataclass

from psao.client.errors import ConnectError


@dataclass
class ConnectSettings:
    # Codec names in preference order: the first one the server also offers is used.
    codecs: tuple[str, ...] = ("zstd-stream", "zstd", "lz4", "none")
    read_delay: float = 0.0  # seconds paused after every message (0: none; more simulates a slow client)
    reconnect_timeout: float = 10.0  # seconds without a message before the client gives up
    digest_every: int = 1  # with a digest log: after the first Update, a digest every this many Updates

    def check(self) -> None:
        """ConnectError for a setting out of range (digest_every: MirrorClient's own check)."""
        if not self.read_delay >= 0:
            raise ConnectError(f"read delay must be >= 0 seconds, got {self.read_delay}")


@dataclass
class FrameSettings:
    size: str = "640x360"  # pixels, width x height
    ao: str = "psao"  # AO methods drawn, comma-separated (see renderer.parse_ao_modes)
    fps: float = 30.0  # frames per second the streaming client renders at, whatever the server's tick rate
    tick_rate: float = 30.0  # server ticks per second assumed when a frame carries no camera time
    frames: int = 1  # `psao render`: frames spread over the camera path
    out: str = "frames"  # `psao render`: output folder
