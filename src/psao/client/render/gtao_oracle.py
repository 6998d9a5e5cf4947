"""numpy evaluation of src/psao/client/shaders/gtao.frag.glsl, step for step: the oracle the GTAO shader is tested against.

    raw = gtao_numpy(depth, normal, view, proj, GtaoSettings(...))   # (H, W) before the blur

`depth` (H, W) view depth (0 = background) and `normal` (H, W, 3) world normals are top-down images, as
GBuffer.read() returns them; the shader works in GL's bottom-up texel rows, so they are flipped in and
the result flipped back out.
"""
from __future__ import annotations

import numpy as np

from psao.client.render.gtao_pass import GtaoSettings, gtao_noise, unproject_vector


def _view_position(px, py, depth, size, unproject):
    ndc_x = px / size[0] * 2.0 - 1.0
    ndc_y = py / size[1] * 2.0 - 1.0
    return np.stack([(ndc_x + unproject[2]) * unproject[0] * depth, (ndc_y + unproject[3]) * unproject[1] * depth,
                     -depth], axis=-1)


def gtao_numpy(depth: np.ndarray, normal: np.ndarray, view: np.ndarray, proj: np.ndarray,
               settings: GtaoSettings) -> np.ndarray:
    d_img = np.asarray(depth, np.float64)[::-1]
    n_img = np.asarray(normal, np.float64)[::-1]
    h, w = d_img.shape
    size = (w, h)
    un = unproject_vector(np.asarray(proj, np.float64))
    ys, xs = np.nonzero(d_img > 0)
    out = np.ones((h, w), np.float64)
    if len(xs) == 0:
        return out[::-1].astype(np.float32)
    d = d_img[ys, xs]
    P = _view_position(xs + 0.5, ys + 0.5, d, size, un)
    V = -P / np.linalg.norm(P, axis=1, keepdims=True)
    N = n_img[ys, xs] @ np.asarray(view, np.float64)[:3, :3].T
    N /= np.linalg.norm(N, axis=1, keepdims=True)
    N = np.where(np.sum(N * V, axis=1, keepdims=True) < 0, -N, N)
    noise = gtao_noise()[ys & 3, xs & 3]
    radius = settings.search_radius
    radius_px = radius * 0.5 * h * proj[1, 1] / d
    min_s = 1.0 / np.maximum(radius_px, 1.0)
    falloff_range = max(settings.falloff, 1e-4) * radius
    falloff_mul, falloff_add = -1.0 / falloff_range, radius / falloff_range

    def tap_depth(px, py):
        inside = (px >= 0) & (py >= 0) & (px < w) & (py < h)
        x0, y0 = np.floor(px - 0.5), np.floor(py - 0.5)
        fx, fy = px - 0.5 - x0, py - 0.5 - y0
        lx, hx = np.clip(x0, 0, w - 1).astype(np.int64), np.clip(x0 + 1, 0, w - 1).astype(np.int64)
        ly, hy = np.clip(y0, 0, h - 1).astype(np.int64), np.clip(y0 + 1, 0, h - 1).astype(np.int64)
        a, b, c, e = d_img[ly, lx], d_img[ly, hx], d_img[hy, lx], d_img[hy, hx]
        ok = inside & (np.minimum(np.minimum(a, b), np.minimum(c, e)) > 0)
        with np.errstate(divide="ignore"):
            inv = ((1 / a) * (1 - fx) + (1 / b) * fx) * (1 - fy) + ((1 / c) * (1 - fx) + (1 / e) * fx) * fy
        return np.where(ok, 1.0 / np.where(ok, inv, 1.0), 0.0)

    def tap(horizon, low, px, py):
        dq = tap_depth(px, py)
        delta = _view_position(px, py, dq, size, un) - P
        dist = np.linalg.norm(delta, axis=1)
        ok = (dq > 0) & (dist > 0)
        weight = np.clip(dist * falloff_mul + falloff_add, 0.0, 1.0)
        c = low + (np.sum(delta * V, axis=1) / np.where(dist > 0, dist, 1.0) - low) * weight
        new = np.where(c > horizon, c, np.maximum(low, horizon + (c - horizon) * settings.thickness))
        return np.where(ok, new, horizon)

    def arc(hh, n, cos_n, sin_n):
        return 0.25 * (cos_n + 2.0 * hh * sin_n - np.cos(2.0 * hh - n))

    visible = np.zeros(len(xs))
    open_ = np.zeros(len(xs))
    for i in range(settings.slices):
        phi = (i + noise[:, 0]) * np.pi / settings.slices
        omega = np.stack([np.cos(phi), np.sin(phi)], axis=1)
        dirv = np.concatenate([omega, np.zeros((len(xs), 1))], axis=1)
        ortho = dirv - np.sum(dirv * V, axis=1, keepdims=True) * V
        axis = np.cross(dirv, V)
        axis /= np.linalg.norm(axis, axis=1, keepdims=True)
        pn = N - axis * np.sum(N * axis, axis=1, keepdims=True)
        pn_len = np.linalg.norm(pn, axis=1)
        valid = pn_len >= 1e-6
        cos_n = np.clip(np.sum(pn * V, axis=1) / np.where(valid, pn_len, 1.0), -1.0, 1.0)
        n = np.sign(np.sum(ortho * pn, axis=1)) * np.arccos(cos_n)
        sin_n = np.sin(n)
        low0, low1 = np.cos(n + np.pi / 2), np.cos(n - np.pi / 2)
        hc0, hc1 = low0.copy(), low1.copy()
        search = radius_px >= 1.0
        for j in range(settings.steps):
            s = (j + noise[:, 1]) / settings.steps
            off = ((s * s + min_s) * radius_px)[:, None] * omega
            t0 = np.stack([xs, ys], axis=1) + 0.5 + off
            t1 = np.stack([xs, ys], axis=1) + 0.5 - off
            hc0 = np.where(search, tap(hc0, low0, t0[:, 0], t0[:, 1]), hc0)
            hc1 = np.where(search, tap(hc1, low1, t1[:, 0], t1[:, 1]), hc1)
        h0 = n + np.clip(-np.arccos(np.clip(hc1, -1, 1)) - n, -np.pi / 2, np.pi / 2)
        h1 = n + np.clip(np.arccos(np.clip(hc0, -1, 1)) - n, -np.pi / 2, np.pi / 2)
        visible += np.where(valid, pn_len * (arc(h0, n, cos_n, sin_n) + arc(h1, n, cos_n, sin_n)), 0.0)
        open_ += np.where(valid, pn_len * (cos_n + n * sin_n), 0.0)
    ratio = np.clip(visible / np.where(open_ > 0, open_, 1.0), 0, 1)
    out[ys, xs] = np.where(open_ > 0, ratio ** settings.power, 1.0)
    return out[::-1].astype(np.float32)
