"""FrameRenderer: geometry pass, the AO methods asked for, composite; frames back as numpy arrays.

    with FrameRenderer(scene, size=(640, 360), ao_mode="psao,gtao") as r:   # or "both" = psao,ssao
        r.upload_grid(instances, buckets, cells)          # or update_grid(...) with dirty rows only
        r.set_transforms(transforms)                      # (n_instances, 4, 4), last received
        r.set_skin_time(server_time)                      # skinned meshes posed as the server posed them
        frame = r.render(view, proj)                      # Frame

Matrices are numpy math convention (column vectors, M @ v); proj is an OpenGL clip matrix.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from psao.client.errors import RenderError
from psao.client.render.aogan_pass import AoganPass
from psao.client.render.composite import CompositePass, read_channel
from psao.client.render.context import check_frame_size, create_context, present, release_context
from psao.client.render.gbuffer import GBuffer, GBufferArrays, GeometryPass, LightSettings
from psao.client.render.gpu_grid import GpuGrid
from psao.client.render.gtao_pass import GtaoPass, GtaoSettings
from psao.client.render.mlp_pass import MlpPass, load_mlp_weights
from psao.client.render.nnao_net import load_nnao_weights
from psao.client.render.nnao_pass import NnaoPass
from psao.client.render.psao_pass import PsaoPass, PsaoSettings
from psao.client.render.ssao_pass import SsaoPass, SsaoSettings
from psao.client.render.timing import PassTimer

AO_METHODS = ("psao", "ssao", "gtao", "nnao", "mlp", "aogan")  # every AO method the renderer runs, in drawing order
AO_ALIASES = {"both": ("psao", "ssao")}


def parse_ao_modes(text: str) -> tuple[str, ...]:
    """'psao', 'both' or a comma-separated list of AO_METHODS -> the methods, in AO_METHODS order."""
    names = []
    for part in str(text).split(","):
        part = part.strip().lower()
        if not part:
            continue
        found = AO_ALIASES.get(part, (part,))
        for name in found:
            if name not in AO_METHODS:
                raise RenderError(f"unknown AO method {part!r}: expected one of {', '.join(AO_METHODS + tuple(AO_ALIASES))}")
            names.append(name)
    if not names:
        raise RenderError("no AO method given")
    return tuple(m for m in AO_METHODS if m in names)


@dataclass
class MethodOptions:
    """Settings of the baseline methods beside PSAO."""

    ssao_samples: int = SsaoSettings.samples  # SSAO kernel size
    gtao_preset: str = "quality"  # a key of GTAO_PRESETS
    mlp_weights: str | None = None  # weights file of `psao train mlp` for this scene
    nnao_weights: str | None = None  # weights file of `psao train nnao`; None = the shipped one
    nnao_samples: int = 64  # first-layer cells evaluated per pixel (of 961)
    aogan_weights: str | None = None  # weights file of `psao train aogan`; None = the shipped one

    @classmethod
    def from_args(cls, args) -> "MethodOptions":
        """From parsed `psao render` / `psao client` arguments (absent options keep their defaults)."""
        d = cls()
        return cls(ssao_samples=int(getattr(args, "ssao_samples", d.ssao_samples)),
                   gtao_preset=str(getattr(args, "gtao_preset", d.gtao_preset)),
                   mlp_weights=getattr(args, "mlp_weights", None), nnao_weights=getattr(args, "nnao_weights", None),
                   nnao_samples=int(getattr(args, "nnao_samples", d.nnao_samples)),
                   aogan_weights=getattr(args, "aogan_weights", None))


@dataclass
class Frame:
    composite: dict[str, np.ndarray]  # mode -> (H, W, 3) uint8 sRGB, lit colour x AO
    ao: dict[str, np.ndarray]  # mode -> (H, W) float32 AO in [0, 1], 1 on background
    gbuffer: GBufferArrays | None  # None when render(..., read_gbuffer=False)
    gpu_ms: dict[str, float] = field(default_factory=dict)  # pass -> GPU milliseconds (timer queries)
    psao_weight: np.ndarray | None = None  # (H, W) float32 eq. 4 weight sum; 0 on covered pixels = hole

    @property
    def mask(self) -> np.ndarray | None:
        return None if self.gbuffer is None else self.gbuffer.mask


class FrameRenderer:
    def __init__(
        self,
        scene,
        size=(640, 360),
        ao_mode: str = "psao",
        ssao_samples: int = 16,
        ctx=None,
        window: bool = False,
        light: LightSettings | None = None,
        psao: PsaoSettings | None = None,
        timing: bool = True,
        options: MethodOptions | None = None,
    ):
        self.modes = parse_ao_modes(ao_mode)
        options = options or MethodOptions(ssao_samples=int(ssao_samples))
        self._own_ctx = ctx is None
        self.window = bool(window) and ctx is None
        self.ctx = ctx if ctx is not None else create_context(window=window, size=size)
        self._objects: list = []
        try:
            self.size = check_frame_size(self.ctx, size)
            self.scene = scene
            self.transforms = np.stack([np.asarray(i.transform, dtype=np.float64) for i in scene.instances]) \
                if scene.instances else np.zeros((0, 4, 4))
            self.gbuffer = self._own(GBuffer(self.ctx, self.size))
            self.geometry = self._own(GeometryPass(self.ctx, scene, light))
            self.grid = self._own(GpuGrid(self.ctx))
            self.psao = self.ssao = self.gtao = None
            self.passes = {}  # method -> pass with .output (AO in channel 0)
            if "psao" in self.modes:
                self.psao = self.passes["psao"] = self._own(PsaoPass(self.ctx, self.gbuffer, self.grid, psao))
            if "ssao" in self.modes:
                settings = SsaoSettings(samples=int(options.ssao_samples), radius=float(scene.ao_distance))
                self.ssao = self.passes["ssao"] = self._own(SsaoPass(self.ctx, self.gbuffer, settings))
            if "gtao" in self.modes:
                settings = GtaoSettings.preset(options.gtao_preset, float(scene.ao_distance))
                self.gtao = self.passes["gtao"] = self._own(GtaoPass(self.ctx, self.gbuffer, settings))
            if "nnao" in self.modes:
                arrays = load_nnao_weights(options.nnao_weights)[0]
                self.passes["nnao"] = self._own(NnaoPass(self.ctx, self.gbuffer, arrays, float(scene.ao_distance),
                                                         options.nnao_samples))
            if "mlp" in self.modes:
                self.passes["mlp"] = self._own(MlpPass(self.ctx, self.gbuffer, self._mlp_arrays(options)))
            if "aogan" in self.modes:
                from psao.client.render.aogan_net import load_generator  # PyTorch only when asked for

                model = load_generator(options.aogan_weights)[0]
                self.passes["aogan"] = self._own(AoganPass(self.ctx, self.gbuffer, model, float(scene.ao_distance)))
            self.composites = {m: self._own(CompositePass(self.ctx, self.gbuffer)) for m in self.modes}
            self.timer = PassTimer(self.ctx, enabled=timing)
        except BaseException:
            self.release()
            raise

    def _mlp_arrays(self, options: MethodOptions):
        if not options.mlp_weights:
            raise RenderError("AO method mlp needs a weights file (--mlp-weights FILE, from `psao train mlp`)")
        return load_mlp_weights(options.mlp_weights, self.scene)[0]

    def _own(self, obj):
        self._objects.append(obj)
        return obj

    # -- grid ------------------------------------------------------------------------------------------
    def upload_grid(self, instances: np.ndarray, buckets: np.ndarray, cells: np.ndarray) -> None:
        """Full upload: INSTANCE_DTYPE records, uint32 buckets (n, 8, 2), uint32 cells (capacity, 8)."""
        n = len(np.asarray(instances).reshape(-1))
        if n != len(self.scene.instances):
            raise RenderError(f"grid has {n} instance records, the scene has {len(self.scene.instances)} instances")
        self.grid.upload(instances, buckets, cells)

    def update_grid(self, bucket_idx, bucket_rows, cell_slots, cell_rows, cell_capacity: int | None = None) -> None:
        """Dirty rows only (the mirror's changes since the last call); grows the cell buffer if needed."""
        self.grid.update(bucket_idx, bucket_rows, cell_slots, cell_rows, cell_capacity)

    def set_transforms(self, transforms) -> None:
        """Local-to-world matrices per instance (n, 4, 4): the last ones the server sent."""
        t = np.asarray(transforms, dtype=np.float64)
        if t.shape != (len(self.scene.instances), 4, 4):
            raise RenderError(f"transforms have shape {t.shape}, expected ({len(self.scene.instances)}, 4, 4)")
        if not np.isfinite(t).all():
            raise RenderError("transforms contain NaN or infinity")
        self.transforms = t.copy()

    @property
    def skin_time(self) -> float | None:
        """Seconds at which skinned meshes are drawn now (None: rest pose)."""
        return self.geometry.skin_time

    def set_skin_time(self, t: float | None) -> None:
        """Scene time (seconds) at which skinned meshes are drawn: the server time of the last Update,
        the pose the server traced the AO it sent from (the lookup reads the rest pose of the drawn points
        either way). None = rest pose. No-op without skins."""
        if t is not None and not np.isfinite(t):
            raise RenderError(f"skin time {t} is not a finite number")
        self.geometry.set_skin_time(t)

    # -- frames ------------------------------------------------------------------------------------------
    def render(self, view, proj, read_gbuffer: bool = True) -> Frame:
        view = np.asarray(view, dtype=np.float64)
        proj = np.asarray(proj, dtype=np.float64)
        if view.shape != (4, 4) or proj.shape != (4, 4):
            raise RenderError("view and projection must be 4x4 matrices")
        self.submit(view, proj)
        gpu_ms = {**self.timer.collect(), **self.cpu_ms()}
        ao = {}
        weight = None
        if self.psao is not None:
            ao["psao"] = read_channel(self.psao.output, self.size, 2, 0)
            weight = read_channel(self.psao.output, self.size, 2, 1)
        for mode, p in self.passes.items():
            if mode != "psao":
                ao[mode] = read_channel(p.output, self.size, 1, 0)
        return Frame(
            composite={m: c.read() for m, c in self.composites.items()},
            ao=ao,
            gbuffer=self.gbuffer.read() if read_gbuffer else None,
            gpu_ms=gpu_ms,
            psao_weight=weight,
        )

    def cpu_ms(self) -> dict[str, float]:
        """CPU milliseconds of the passes that run on the CPU (AOGAN), last frame, as "MODE_cpu"."""
        return {f"{m}_cpu": p.cpu_ms for m, p in self.passes.items() if hasattr(p, "cpu_ms")}

    def submit(self, view: np.ndarray, proj: np.ndarray) -> None:
        """Issue every pass of one frame without reading anything back (benchmarks time this)."""
        t = self.timer
        with t.measure("gbuffer"):
            self.geometry.draw(self.gbuffer, view, proj, self.transforms)
        if self.psao is not None:
            with t.measure("psao"):
                self.psao.run()
        if self.ssao is not None:
            with t.measure("ssao"):
                self.ssao.run_occlusion(view, proj)
            with t.measure("ssao_blur"):
                self.ssao.run_blur()
        for mode, p in self.passes.items():
            if mode not in ("psao", "ssao"):
                p.run(view, proj, t)  # times its own stages as MODE and MODE_*
        with t.measure("composite"):
            for mode, comp in self.composites.items():
                comp.run(self.passes[mode].output)
        if self.window:  # show the first mode's composite; the window is a view, frames still come back
            present(self.ctx, next(iter(self.composites.values())).fbo)

    # -- lifetime ------------------------------------------------------------------------------------------
    def release(self) -> None:
        for obj in reversed(self._objects):
            obj.release()
        self._objects = []
        timer = getattr(self, "timer", None)
        if timer is not None:
            timer.release()
        if self._own_ctx and self.ctx is not None:
            release_context(self.ctx)
        self.ctx = None

    def __enter__(self) -> "FrameRenderer":
        return self

    def __exit__(self, *exc) -> None:
        self.release()
