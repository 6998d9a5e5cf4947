"""AOGAN (Ren et al., "AOGAN: generative adversarial ambient occlusion"), scaled down to run and train on a
CPU: the attention U-Net generator from G-buffer normals and positions to AO, and the PatchGAN critic
used in training. Needs PyTorch (the optional 'learned' extra); inference runs in the client process on
the G-buffer read back, so its time is CPU milliseconds.

Input channels (view space, positions divided by the AO distance r so one network serves any scene
scale): normal xyz, position xyz / r; background pixels are zero and come out as AO 1.
Generator: AOGAN_LEVELS down blocks (conv 3x3, batch norm, LeakyReLU 0.2, 2x2 max pool), a bottleneck,
and as many up blocks (transposed conv, the attention gate of eq. 7 on the skip connection with weights
1, 0.5, 0.25, ..., conv 3x3, batch norm, LeakyReLU), then a 1x1 conv and a sigmoid.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from psao.client.errors import RenderError

AOGAN_CHANNELS = (12, 24, 48)  # per level (the paper's are wider; this trains on two CPU cores)
AOGAN_INPUTS = 6
AOGAN_THREADS = 1  # PyTorch CPU threads: OpenMP workers that spin on a shared, busy machine cost 10-50x
DEFAULT_AOGAN_WEIGHTS = Path(__file__).resolve().parent / "aogan_weights.npz"


def require_torch():
    try:
        import torch
    except ImportError:
        raise RenderError("AOGAN needs PyTorch: pip install 'psao[learned]' (torch==2.13.0, CPU)") from None
    if torch.get_num_threads() != AOGAN_THREADS:
        torch.set_num_threads(AOGAN_THREADS)
    return torch


def build_generator(channels=AOGAN_CHANNELS):
    torch = require_torch()
    nn = torch.nn

    def conv_block(c_in, c_out):
        return nn.Sequential(nn.Conv2d(c_in, c_out, 3, padding=1), nn.BatchNorm2d(c_out), nn.LeakyReLU(0.2))

    class AttentionGate(nn.Module):
        """Eq. 7: x' = w_l * sigmoid(W_c * relu(W_x * x + W_g * g)) * x."""

        def __init__(self, c, weight):
            super().__init__()
            self.wx = nn.Conv2d(c, c, 1)
            self.wg = nn.Conv2d(c, c, 1)
            self.wc = nn.Conv2d(c, 1, 1)
            self.weight = weight

        def forward(self, x, g):
            alpha = torch.sigmoid(self.wc(torch.relu(self.wx(x) + self.wg(g))))
            return self.weight * alpha * x

    class Generator(nn.Module):
        def __init__(self):
            super().__init__()
            c = list(channels)
            self.down = nn.ModuleList()
            prev = AOGAN_INPUTS
            for ch in c:
                self.down.append(conv_block(prev, ch))
                prev = ch
            self.pool = nn.MaxPool2d(2)
            self.bottom = conv_block(c[-1], 2 * c[-1])
            self.ups, self.gates, self.convs = nn.ModuleList(), nn.ModuleList(), nn.ModuleList()
            prev = 2 * c[-1]
            for level, ch in reversed(list(enumerate(c))):
                self.ups.append(nn.ConvTranspose2d(prev, ch, 2, stride=2))
                self.gates.append(AttentionGate(ch, 0.5 ** level))
                self.convs.append(conv_block(2 * ch, ch))
                prev = ch
            self.out = nn.Conv2d(prev, 1, 1)

        def forward(self, x):
            skips = []
            for block in self.down:
                x = block(x)
                skips.append(x)
                x = self.pool(x)
            x = self.bottom(x)
            for up, gate, conv, skip in zip(self.ups, self.gates, self.convs, reversed(skips)):
                g = up(x)
                x = conv(torch.cat([gate(skip, g), g], dim=1))
            return torch.sigmoid(self.out(x))

    return Generator()


def build_critic():
    """PatchGAN critic on (G-buffer inputs, AO): a map of patch scores, no sigmoid (WGAN)."""
    nn = require_torch().nn
    return nn.Sequential(
        nn.Conv2d(AOGAN_INPUTS + 1, 16, 4, stride=2, padding=1), nn.LeakyReLU(0.2),
        nn.Conv2d(16, 32, 4, stride=2, padding=1), nn.LeakyReLU(0.2),
        nn.Conv2d(32, 1, 4, stride=1, padding=1))


def gbuffer_inputs(depth: np.ndarray, normal: np.ndarray, view: np.ndarray, proj: np.ndarray, radius: float) -> np.ndarray:
    """(6, H, W) float32 network input from top-down depth (0 = background) and world normals."""
    h, w = depth.shape
    proj = np.asarray(proj, np.float64)
    fg = depth > 0
    n = np.asarray(normal, np.float64) @ np.asarray(view, np.float64)[:3, :3].T
    n /= np.maximum(np.linalg.norm(n, axis=2, keepdims=True), 1e-30)
    px = (np.arange(w) + 0.5) / w * 2.0 - 1.0
    py = 1.0 - (np.arange(h) + 0.5) / h * 2.0  # top-down rows
    x = (px[None, :] + proj[0, 2]) / proj[0, 0] * depth
    y = (py[:, None] + proj[1, 2]) / proj[1, 1] * depth
    pos = np.stack([x, y, -depth], axis=2) / radius
    out = np.concatenate([n, pos], axis=2) * fg[..., None]
    return np.ascontiguousarray(out.transpose(2, 0, 1), dtype=np.float32)


def state_arrays(model) -> dict[str, np.ndarray]:
    """The model's parameters and batch-norm statistics as float32 arrays (what the weights file holds)."""
    return {k: v.detach().cpu().numpy().astype(np.float32) for k, v in model.state_dict().items()
            if v.dtype.is_floating_point}


def load_generator(path=None):
    """The generator in eval mode with the weights of `path` (default: the shipped file), shapes checked."""
    from psao.client.render.weights import load_weights

    torch = require_torch()
    model = build_generator()
    expected = {k: tuple(v.shape) for k, v in state_arrays(model).items()}
    arrays, header = load_weights(path or DEFAULT_AOGAN_WEIGHTS, "aogan", expected)
    state = model.state_dict()
    for k, v in arrays.items():
        if k in state:
            state[k] = torch.from_numpy(v)
    model.load_state_dict(state)
    model.eval()
    return model, arrays, header


def infer(model, inputs: np.ndarray) -> np.ndarray:
    """(6, H, W) -> (H, W) AO; the frame is padded to a multiple of 2^levels (edge replicate) and cropped."""
    torch = require_torch()
    _, h, w = inputs.shape
    m = 1 << len(AOGAN_CHANNELS)
    ph, pw = (-h) % m, (-w) % m
    x = np.pad(inputs, ((0, 0), (0, ph), (0, pw)), mode="edge")
    with torch.inference_mode():
        y = model(torch.from_numpy(x)[None])[0, 0].numpy()
    ao = y[:h, :w].astype(np.float32)
    ao[~np.any(inputs != 0, axis=0)] = 1.0
    return ao
