"""Training of the scaled-down AOGAN (PyTorch, CPU) on this project's G-buffers and dense RTAO.

Data: frames of the training scenes (camera path and orbit, as for NNAO) rendered by the client's
renderer at `size`, with the RTAO reference traced at every covered pixel (`spp` rays). Training: random
`patch` x `patch` crops, batch 8; the generator loss is the paper's eq. 1 without the VGG-19 perceptual
term (no pretrained network offline; the paper's ablation B2 is the reference point): lambda1 = 0.001 times
the WGAN adversarial term plus lambda3 = 1 times DSSIM = 0.5 (1 - SSIM). The PatchGAN critic follows WGAN
(eq. 4) with weight clipping and `critic_steps` updates per generator update (the paper: 5), all on the
batch and generator output of that step (one generator pass fewer per critic update on a CPU). Adam.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from psao.client.render.aogan_net import build_critic, build_generator, gbuffer_inputs, require_torch, state_arrays


@dataclass
class AoganDataSettings:
    frames: int = 12  # per scene
    size: tuple[int, int] = (320, 180)
    spp: int = 128
    seed: int = 1


@dataclass
class AoganTrainSettings:
    steps: int = 600  # generator updates
    critic_steps: int = 5  # critic updates per generator update (the paper)
    batch: int = 8  # the paper's batch size
    patch: int = 64  # crop size
    lr: float = 2e-4  # the paper: 1e-4 over 30 epochs; fewer steps here
    lambda_adv: float = 0.001  # lambda1
    lambda_dssim: float = 1.0  # lambda3
    clip: float = 0.01  # WGAN weight clipping of the critic
    seed: int = 1


@dataclass
class AoganTrainResult:
    arrays: dict[str, np.ndarray]
    losses: list[float] = field(default_factory=list)  # generator DSSIM per step
    seconds: float = 0.0


def build_dataset(scenes, settings: AoganDataSettings, progress=None) -> tuple[np.ndarray, np.ndarray]:
    """(inputs (F, 6, H, W), RTAO (F, H, W)) over every scene and frame."""
    from psao.client.render.renderer import FrameRenderer
    from psao.eval.learn.nnao_train import scene_frames
    from psao.eval.quality import rest_transforms
    from psao.eval.reference import ReferenceSettings, reference_ao

    xs, ys = [], []
    for scene in scenes:
        with FrameRenderer(scene, settings.size, "ssao", timing=False) as r:
            for view, proj in scene_frames(scene, settings.frames, settings.size):
                gb = r.render(view, proj).gbuffer
                ao = reference_ao(scene, gb, rest_transforms(scene), ReferenceSettings(spp=settings.spp, cache_dir=None),
                                  show_progress=False)
                xs.append(gbuffer_inputs(gb.depth, gb.normal, view, proj, float(scene.ao_distance)))
                ys.append(ao.astype(np.float32))
                if progress is not None:
                    progress(len(ys))
    return np.stack(xs), np.stack(ys)


def ssim_torch(a, b, window: int = 7):
    """Mean SSIM of (N, 1, H, W) images in [0, 1] with a uniform window (data range 1)."""
    torch = require_torch()
    f = torch.nn.functional
    c1, c2 = 0.01 ** 2, 0.03 ** 2
    mu_a, mu_b = f.avg_pool2d(a, window, 1), f.avg_pool2d(b, window, 1)
    var_a = f.avg_pool2d(a * a, window, 1) - mu_a ** 2
    var_b = f.avg_pool2d(b * b, window, 1) - mu_b ** 2
    cov = f.avg_pool2d(a * b, window, 1) - mu_a * mu_b
    s = ((2 * mu_a * mu_b + c1) * (2 * cov + c2)) / ((mu_a ** 2 + mu_b ** 2 + c1) * (var_a + var_b + c2))
    return s.mean()


def train_aogan(x: np.ndarray, y: np.ndarray, settings: AoganTrainSettings | None = None,
                progress=None) -> AoganTrainResult:
    torch = require_torch()
    settings = settings or AoganTrainSettings()
    t0 = time.perf_counter()
    torch.manual_seed(settings.seed)
    rng = np.random.default_rng(settings.seed)
    gen, critic = build_generator(), build_critic()
    opt_g = torch.optim.Adam(gen.parameters(), lr=settings.lr, betas=(0.5, 0.999))
    opt_d = torch.optim.Adam(critic.parameters(), lr=settings.lr, betas=(0.5, 0.999))
    n, _, h, w = x.shape
    p = min(settings.patch, h, w) // 8 * 8

    def batch():
        f = rng.integers(0, n, settings.batch)
        oy = rng.integers(0, h - p + 1, settings.batch)
        ox = rng.integers(0, w - p + 1, settings.batch)
        xb = np.stack([x[i, :, a:a + p, b:b + p] for i, a, b in zip(f, oy, ox)])
        yb = np.stack([y[i, a:a + p, b:b + p] for i, a, b in zip(f, oy, ox)])[:, None]
        xt = torch.from_numpy(xb)
        return xt, torch.from_numpy(yb), (xt.abs().sum(dim=1, keepdim=True) > 0)

    def generate(xb, fg):
        return torch.where(fg, gen(xb), torch.ones_like(xb[:, :1]))

    losses = []
    for step in range(settings.steps):
        xb, yb, fg = batch()
        with torch.no_grad():  # the critic's updates of this step all see this generator output
            fake = generate(xb, fg)
        for _ in range(settings.critic_steps):  # eq. 4: E[D(G(x))] - E[D(y)]
            loss_d = critic(torch.cat([xb, fake], 1)).mean() - critic(torch.cat([xb, yb], 1)).mean()
            opt_d.zero_grad()
            loss_d.backward()
            opt_d.step()
            with torch.no_grad():
                for q in critic.parameters():
                    q.clamp_(-settings.clip, settings.clip)
        fake = generate(xb, fg)
        dssim = 0.5 * (1.0 - ssim_torch(fake, yb))
        loss_g = settings.lambda_adv * -critic(torch.cat([xb, fake], 1)).mean() + settings.lambda_dssim * dssim
        opt_g.zero_grad()
        loss_g.backward()
        opt_g.step()
        losses.append(float(dssim.detach()))
        if progress is not None:
            progress(step + 1, settings.steps, losses[-1])
    gen.eval()
    return AoganTrainResult(state_arrays(gen), losses, time.perf_counter() - t0)
