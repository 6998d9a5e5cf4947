"""GTAO baseline (src/psao/client/shaders/gtao.frag.glsl, then the bilateral blur of ssao_blur.frag.glsl).

Ground-truth-based AO as Jimenez et al. (2016) describe it and XeGTAO implements it: horizon search in
screen-space slices, the cosine-weighted visibility between the horizons in closed form, a thickness
heuristic, then the depth- and normal-aware 4x4 blur that also denoises SSAO (the 4x4 noise tile spreads
slice rotations and step offsets over the blur footprint). Presets trade slices x steps: "speed" 2x4,
"quality" 4x8 (default), "ultra" 8x12.

The screen-space heuristics take XeGTAO's published defaults (XeGTAO.h, XE_GTAO_DEFAULT_*), which
compensate for what a depth buffer cannot show: the search radius is the scene's AO distance times 1.457,
taps fade over the last 61.5% of it, and the visibility is raised to the power 2.2. A G-buffer normal that
faces away from the camera (a single-sided surface seen from behind) is turned towards it, as XeGTAO's
normals reconstructed from depth always are: the depth buffer only describes the camera's side.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from psao.client.errors import RenderError
from psao.client.render.gbuffer import GBuffer
from psao.client.render.screenpass import GLOwner, ScreenPass

GTAO_PRESETS = {"speed": (2, 4), "quality": (4, 8), "ultra": (8, 12)}  # name -> (slices, steps per side)


@dataclass
class GtaoSettings:
    slices: int = 4  # screen-space slice directions per pixel
    steps: int = 8  # horizon taps per side of a slice
    radius: float = 0.6  # world units; the renderer sets it to the scene's AO distance
    radius_multiplier: float = 1.457  # search radius = radius x this (XeGTAO's default)
    falloff: float = 0.615  # fraction of the search radius over which taps fade out (XeGTAO's default)
    thickness: float = 0.1  # horizon blend back towards lower taps (0 = plain max; thin occluders)
    power: float = 2.2  # visibility is raised to this power (XeGTAO's FinalValuePower default)

    @property
    def search_radius(self) -> float:
        """World units: how far the horizon search reaches (the shader's u_radius)."""
        return self.radius * self.radius_multiplier

    @classmethod
    def preset(cls, name: str, radius: float) -> "GtaoSettings":
        if name not in GTAO_PRESETS:
            raise RenderError(f"GTAO preset {name!r}: expected one of {', '.join(GTAO_PRESETS)}")
        slices, steps = GTAO_PRESETS[name]
        return cls(slices=slices, steps=steps, radius=float(radius))

    def check(self) -> None:
        if not (1 <= self.slices <= 64 and 1 <= self.steps <= 64):
            raise RenderError(f"GTAO slices {self.slices} and steps {self.steps} must be within 1..64")
        if not (self.radius > 0 and 0 < self.radius_multiplier <= 4 and 0 < self.falloff <= 1
                and 0 <= self.thickness <= 1 and 0 < self.power <= 8):
            raise RenderError("GTAO radius must be > 0, radius multiplier within (0, 4], falloff within (0, 1], "
                              "thickness within [0, 1], power within (0, 8]")


def gtao_noise() -> np.ndarray:
    """4x4 RGBA32F tile: x = slice rotation (a 4x4 Bayer order, so a blur footprint sees 16 rotations),
    y = step offset (the R1 sequence in the same order)."""
    bayer = np.array([[0, 8, 2, 10], [12, 4, 14, 6], [3, 11, 1, 9], [15, 7, 13, 5]], dtype=np.float64)
    tile = np.zeros((4, 4, 4), dtype=np.float32)
    tile[..., 0] = (bayer + 0.5) / 16.0
    tile[..., 1] = np.mod(0.5 + bayer * 0.6180339887498949, 1.0)
    return tile


def unproject_vector(proj: np.ndarray) -> tuple[float, float, float, float]:
    """(1/P00, 1/P11, P02, P12): what the screen-space passes need to rebuild view positions from depth."""
    return (1.0 / proj[0, 0], 1.0 / proj[1, 1], proj[0, 2], proj[1, 2])


class BilateralBlur(ScreenPass):
    """The 4x4 depth- and normal-aware blur (ssao_blur.frag.glsl) shared by the screen-space methods."""

    def __init__(self, ctx, size, radius: float):
        super().__init__(ctx, size, "ssao_blur.frag.glsl", samplers=("u_ao", "u_depth", "u_normal"))
        self.set(u_radius=float(radius))

    def run(self, raw, gbuffer: GBuffer) -> None:
        self.draw([raw, gbuffer["depth"], gbuffer["normal"]])


class GtaoPass(GLOwner):
    def __init__(self, ctx, gbuffer: GBuffer, settings: GtaoSettings):
        settings.check()
        self.settings = settings
        self._gbuffer = gbuffer
        self._objects = []
        try:
            defines = {"GTAO_SLICES": int(settings.slices), "GTAO_STEPS": int(settings.steps)}
            self.horizon = self._keep(ScreenPass(ctx, gbuffer.size, "gtao.frag.glsl", defines,
                                                 samplers=("u_depth", "u_normal", "u_noise")))
            self.blur = self._keep(BilateralBlur(ctx, gbuffer.size, settings.radius))
            self._noise = self._keep(ctx.texture((4, 4), 4, gtao_noise().tobytes(), dtype="f4"))
            self._noise.filter = (ctx.NEAREST, ctx.NEAREST)
            self.horizon.set(u_radius=float(settings.search_radius), u_falloff=float(settings.falloff),
                             u_thickness=float(settings.thickness), u_power=float(settings.power))
        except BaseException:
            self.release()
            raise

    @property
    def raw(self):
        return self.horizon.output

    @property
    def output(self):
        return self.blur.output

    def run(self, view: np.ndarray, proj: np.ndarray, timer) -> None:
        gb = self._gbuffer
        self.horizon.program["u_view_rot"].write(np.ascontiguousarray(np.asarray(view, np.float32)[:3, :3].T).tobytes())
        self.horizon.set(u_unproject=unproject_vector(proj), u_pixels_per_unit=float(0.5 * gb.size[1] * proj[1, 1]))
        with timer.measure("gtao"):
            self.horizon.draw([gb["depth"], gb["normal"], self._noise])
        with timer.measure("gtao_blur"):
            self.blur.run(self.raw, gb)
