"""Quality of PSAO on an animated scene: the server's tick run in this process, frame by frame.

    with AnimatedServer(scene, AnimatedSettings(BakeSettings(density=256, rays=128), tick_rays=32, tick_hz=60)) as server:
        frames = qr.render(server.grid, poses, before_frame=server.frame_state)

For each frame at scene time t the server ticks at t - (k-1)/tick_hz ... t (`ticks_per_frame` ticks,
the last one at the frame's time, the frame's camera as the only client view), then the frame is drawn
from the grid and the instance transforms of that last tick, as a client in lockstep would. The RTAO
reference places the occluders with the same transforms (reference_images uses the frame's transforms).

Skinned meshes are drawn posed at the frame's time (the time of the server's last tick), the deformed
triangles the server traced its points on (its grid keeps them in the rest pose, which the G-buffer's local
targets carry); the reference traces that same pose.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from psao.eval.errors import EvalError
from psao.server.settings import BakeSettings, ServeSettings, TickSettings


@dataclass
class AnimatedSettings:
    bake: BakeSettings = field(default_factory=BakeSettings)  # the server's bake before its first tick
    tick_rays: int = TickSettings.rays  # rays per re-traced point in a tick
    tick_hz: float = ServeSettings.tick_hz  # ticks per second: spacing of the ticks before a frame
    ticks_per_frame: int = 2  # ticks run up to each frame's time (the first one may cover a long jump)


class AnimatedServer:
    def __init__(self, scene, settings: AnimatedSettings, show_progress: bool = False):
        from psao.server.bake import bake_scene
        from psao.server.tick.server_tick import ServerTick

        if settings.ticks_per_frame < 1 or not settings.tick_hz > 0:
            raise EvalError("animated evaluation needs >= 1 tick per frame and a tick rate > 0")
        self.scene = scene
        self.settings = settings
        bake = bake_scene(scene, settings.bake,
                          show_progress=show_progress)
        self.points = int(bake.stats.get("points_kept", 0))
        self.tick = ServerTick(bake, TickSettings(rays=settings.tick_rays))
        self.grid = self.tick.grid
        self.stats: list = []

    def frame_state(self, pose) -> tuple[object, np.ndarray]:
        """Tick up to the pose's time with its camera; the grid and transforms a client would draw."""
        s = self.settings
        self.tick.set_cameras([(pose.view, pose.proj)])
        for k in range(s.ticks_per_frame - 1, -1, -1):
            self.stats.append(self.tick(self.grid, max(0.0, pose.time - k / s.tick_hz)))
        return self.grid, np.asarray(self.tick.transforms(), np.float64)

    def mean_tick_ms(self) -> float:
        """Mean milliseconds of the ticks after each frame's first (those follow 1/tick_hz of motion)."""
        s = self.settings
        steady = [st.seconds_total for i, st in enumerate(self.stats) if i % s.ticks_per_frame != 0]
        return 1e3 * float(np.mean(steady)) if steady else float("nan")

    def close(self) -> None:
        self.tick.close()

    def __enter__(self) -> "AnimatedServer":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def is_animated(scene) -> bool:
    from psao.scene import is_dynamic

    return any(is_dynamic(scene, i) for i in range(len(scene.instances)))
