"""Video AO streaming: the split-rendering competitor that streams pixels instead of points.

Per client, the server rasterises the client's view, ray-traces AO for every covered pixel with Embree
(`spp` cosine-weighted rays within the AO distance, the RTAO reference's rays with a per-frame seed),
optionally accumulates it over frames (history reprojected with depth) and denoises it, and encodes the
AO image as the luma plane of a video (H.264 by default, through PyAV's own FFmpeg) at a target
bitrate. The client decodes the frames and shows the newest one that has arrived: with a latency L the
frame shown at time t was rendered for the pose at t - L, optionally reprojected to the current pose
with the client's depth, as streaming systems do.

    settings = VideoSettings(codec="h264", bitrate_mbit=2.0, fps=60, spp=8)
    with VideoServer(scene, settings) as server:
        ao, cost = server.render(frame)            # a RenderedFrame: G-buffer, transforms, skin time
    stream = encode_stream(ao_frames, settings)    # packets, bytes, encode seconds per frame
    decoded = decode_stream(stream)                # (H, W) float32 AO per frame

Everything here is offline and frame by frame; the costs (rays, trace and encode seconds per frame) are
measured per call and reported per client.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from fractions import Fraction

import numpy as np

from psao.eval.errors import EvalError

# Codec name on the command line -> PyAV encoder. Decoding uses FFmpeg's decoder of the same format.
CODECS = {"h264": "libx264", "hevc": "libx265", "vp9": "libvpx-vp9", "av1": "libsvtav1"}
DECODERS = {"h264": "h264", "hevc": "hevc", "vp9": "vp9", "av1": "libdav1d"}
# Real-time encoder options: no B-frames and no look-ahead, so every frame leaves the encoder at once.
REALTIME_OPTIONS = {"h264": {"preset": "veryfast", "tune": "zerolatency"},
                    "hevc": {"preset": "veryfast", "tune": "zerolatency", "x265-params": "log-level=error"},
                    "vp9": {"deadline": "realtime", "cpu-used": "8", "lag-in-frames": "0"},
                    "av1": {"preset": "10"}}
HISTORY_LIMIT = 0.98  # the largest history weight of the temporal accumulation
GAUSS_TRUNCATE = 4.0  # the denoise kernel reaches this many sigmas


@dataclass
class VideoSettings:
    codec: str = "h264"  # one of CODECS
    bitrate_mbit: float = 2.0  # target bitrate, Mbit/s
    fps: float = 60.0  # frames the server renders and sends per second
    spp: int = 8  # AO rays per pixel per frame
    keyint: int = 60  # frames between key frames
    accumulate: float = 0.0  # weight of the reprojected history in each frame (0 = off, < HISTORY_LIMIT)
    denoise_px: float = 1.0  # sigma in pixels of a depth-aware Gaussian over the traced AO (0 = off)
    seed: int = 0x51DE0  # rays are seeded by pixel index + seed + frame number
    workers: int = 0  # Embree worker processes; 0 = all cores

    def check(self) -> None:
        if self.codec not in CODECS:
            raise EvalError(f"unknown video codec {self.codec!r} (known: {', '.join(CODECS)})")
        if not (math.isfinite(self.bitrate_mbit) and self.bitrate_mbit > 0):
            raise EvalError(f"video bitrate must be > 0 Mbit/s, got {self.bitrate_mbit:g}")
        if not (math.isfinite(self.fps) and 1 <= self.fps <= 240):
            raise EvalError(f"video frame rate must be within 1..240 fps, got {self.fps:g}")
        if self.spp < 1:
            raise EvalError(f"video rays per pixel must be >= 1, got {self.spp}")
        if self.keyint < 1:
            raise EvalError(f"video key frame interval must be >= 1, got {self.keyint}")
        if not (0.0 <= self.accumulate <= HISTORY_LIMIT):
            raise EvalError(f"video accumulation weight must be within 0..{HISTORY_LIMIT}, got {self.accumulate:g}")
        if not (math.isfinite(self.denoise_px) and 0.0 <= self.denoise_px <= 16.0):
            raise EvalError(f"video denoise sigma must be within 0..16 pixels, got {self.denoise_px:g}")


def check_latency(latency_ms: float) -> float:
    if not (math.isfinite(latency_ms) and latency_ms >= 0):
        raise EvalError(f"latency must be >= 0 ms, got {latency_ms:g}")
    return float(latency_ms)


# ---------------------------------------------------------------------------------------------- codec
def _even(n: int) -> int:
    return n + (n & 1)


def ao_to_yuv(ao: np.ndarray) -> np.ndarray:
    """(H, W) AO in [0, 1] -> (3 H' / 2, W') uint8 yuv420p with the AO in luma (H', W' even: edge
    padded) and neutral chroma."""
    y = np.clip(np.rint(np.asarray(ao, np.float32) * 255.0), 0, 255).astype(np.uint8)
    h, w = y.shape
    y = np.pad(y, ((0, _even(h) - h), (0, _even(w) - w)), mode="edge")
    chroma = np.full((y.shape[0] // 2, y.shape[1]), 128, np.uint8)  # U then V, each (H'/2, W'/2), row-packed
    return np.vstack([y, chroma])


@dataclass
class EncodedStream:
    codec: str
    size: tuple[int, int]  # (W, H) of the AO images
    fps: float
    packets: list[list[bytes]]  # per input frame, the packets the encoder returned for it
    encode_seconds: list[float]  # per input frame
    flushed: list[bytes] = field(default_factory=list)  # packets left in the encoder at the end

    @property
    def total_bytes(self) -> int:
        return sum(len(p) for ps in self.packets for p in ps) + sum(len(p) for p in self.flushed)

    @property
    def mbit_s(self) -> float:
        """Bits sent per second of video."""
        return 8e-6 * self.total_bytes * self.fps / max(len(self.packets), 1)


def _encoder(settings: VideoSettings, width: int, height: int):
    import av

    ctx = av.CodecContext.create(CODECS[settings.codec], "w")
    ctx.width, ctx.height = _even(width), _even(height)
    ctx.pix_fmt = "yuv420p"
    rate = Fraction(settings.fps).limit_denominator(1001)
    ctx.framerate = rate
    ctx.time_base = 1 / rate
    bits = int(round(settings.bitrate_mbit * 1e6))
    ctx.bit_rate = bits
    ctx.gop_size = settings.keyint
    # A streaming rate control: the VBV holds one second at the target rate, so no second exceeds it much.
    ctx.options = {**REALTIME_OPTIONS[settings.codec], "maxrate": str(bits), "bufsize": str(bits)}
    ctx.open()
    return ctx


def encode_stream(frames: list[np.ndarray], settings: VideoSettings) -> EncodedStream:
    """Encode (H, W) AO frames in [0, 1] as one stream at the settings' bitrate and frame rate."""
    import av

    settings.check()
    if not frames:
        raise EvalError("no frames to encode")
    h, w = np.asarray(frames[0]).shape
    ctx = _encoder(settings, w, h)
    packets, seconds = [], []
    for i, ao in enumerate(frames):
        if np.asarray(ao).shape != (h, w):
            raise EvalError(f"video frame {i} has shape {np.asarray(ao).shape}, the stream is {(h, w)}")
        t0 = time.perf_counter()
        vf = av.VideoFrame.from_ndarray(ao_to_yuv(ao), format="yuv420p")
        vf.pts = i
        out = [bytes(p) for p in ctx.encode(vf)]
        seconds.append(time.perf_counter() - t0)
        packets.append(out)
    flushed = [bytes(p) for p in ctx.encode(None)]
    return EncodedStream(settings.codec, (w, h), settings.fps, packets, seconds, flushed)


def decode_stream(stream: EncodedStream) -> list[np.ndarray]:
    """(H, W) float32 AO per encoded frame, in order (luma / 255)."""
    import av

    ctx = av.CodecContext.create(DECODERS[stream.codec], "r")
    w, h = stream.size
    out = []
    for p in [p for ps in stream.packets for p in ps] + list(stream.flushed) + [None]:
        for frame in ctx.decode(av.Packet(p) if p is not None else None):
            y = frame.to_ndarray(format="yuv420p")[:_even(h)]
            out.append((y[:h, :w].astype(np.float32) / 255.0))
    if len(out) != len(stream.packets):
        raise EvalError(f"the decoder returned {len(out)} frames for {len(stream.packets)} encoded")
    return out


# ------------------------------------------------------------------------------------ image filters
def masked_gaussian(ao: np.ndarray, mask: np.ndarray, depth: np.ndarray, sigma: float) -> np.ndarray:
    """Gaussian of the AO over covered pixels only (normalised convolution). Depth edges are kept: the
    image is cut into layers 5% apart in depth, and a pixel blends only with pixels of its own layer and
    the two next to it.

    Computed as one sum over the kernel's offsets on whole images (a cross-bilateral filter whose range
    weight is 1 for layers at most one apart, else 0), with scipy's Gaussian kernel (radius 4 sigma) and
    its "nearest" edges (edge-padded images): the same values as a masked Gaussian per depth layer, in
    (2 radius + 1)^2 vector operations instead of two image filters per layer."""
    ao = np.asarray(ao, np.float32)
    mask = np.asarray(mask, bool)
    if sigma <= 0 or not mask.any():
        return ao.copy()
    logd = np.log(np.maximum(np.asarray(depth, np.float32), 1e-6))
    radius = int(GAUSS_TRUNCATE * sigma + 0.5)  # scipy.ndimage.gaussian_filter's kernel radius
    x = np.arange(-radius, radius + 1, dtype=np.float64)
    kernel = np.exp(-0.5 * (x / sigma) ** 2)
    kernel = (kernel / kernel.sum()).astype(np.float32)
    h, w = ao.shape
    # Integer layers (int16: half the memory traffic of float32); uncovered pixels get a layer no
    # covered pixel is within one of, so they never blend in.
    layer = np.where(mask, np.clip(np.floor(logd / 0.05), -30000, 30000), -32000).astype(np.int16)
    # Numerator and denominator in one array: [AO on covered pixels, 1], edge-padded like scipy's "nearest".
    both = np.pad(np.stack([np.where(mask, ao, 0.0), np.ones_like(ao)]).astype(np.float32),
                  ((0, 0), (radius, radius), (radius, radius)), mode="edge")
    layer_pad = np.pad(layer, radius, mode="edge")
    acc = np.zeros((2, h, w), np.float32)
    diff = np.empty((h, w), np.int16)
    near = np.empty((h, w), bool)
    term = np.empty((2, h, w), np.float32)
    for dy in range(2 * radius + 1):
        for dx in range(2 * radius + 1):
            np.subtract(layer_pad[dy:dy + h, dx:dx + w], layer, out=diff)
            np.abs(diff, out=diff)
            np.less_equal(diff, 1, out=near)
            np.multiply(both[:, dy:dy + h, dx:dx + w], near, out=term)
            term *= kernel[dy] * kernel[dx]
            acc += term
    num, den = acc
    out = ao.copy()
    ok = mask & (den > 1e-6)
    out[ok] = num[ok] / den[ok]
    return out


def project(points: np.ndarray, view: np.ndarray, proj: np.ndarray, size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """World points (P, 3) -> (x, y) pixel coordinates (top-down rows, pixel centres at .5) and whether
    each lies in front of the camera."""
    w, h = size
    p = np.c_[np.asarray(points, np.float64), np.ones(len(points))] @ (np.asarray(proj) @ np.asarray(view)).T
    front = p[:, 3] > 1e-9
    wc = np.where(front, p[:, 3], 1.0)
    x = (p[:, 0] / wc * 0.5 + 0.5) * w
    y = (0.5 - p[:, 1] / wc * 0.5) * h
    return x, y, front


def reproject(src_ao: np.ndarray, src_world: np.ndarray, src_mask: np.ndarray, src_view, src_proj,
              dst_world: np.ndarray, dst_mask: np.ndarray, tolerance: float = 0.02) -> tuple[np.ndarray, np.ndarray]:
    """An AO image rendered for (src_view, src_proj) warped to the pixels of another view, with that
    view's own world positions (its depth): each destination pixel projects into the source image and
    takes the source pixel there when that pixel saw the same surface (world positions within
    `tolerance` x the distance to the camera). Returns (AO, valid); where not valid (disoccluded or
    off-screen) the AO is the source's value at the same screen position, as a plain stream shows it."""
    h, w = dst_mask.shape
    out = np.asarray(src_ao, np.float32).copy()
    valid = np.zeros((h, w), bool)
    idx = np.flatnonzero(dst_mask.reshape(-1))
    if not len(idx):
        return out, valid
    pts = np.asarray(dst_world, np.float64).reshape(-1, 3)[idx]
    x, y, front = project(pts, src_view, src_proj, (w, h))
    xi, yi = np.floor(x).astype(np.int64), np.floor(y).astype(np.int64)
    inside = front & (xi >= 0) & (xi < w) & (yi >= 0) & (yi < h)
    xi, yi = np.clip(xi, 0, w - 1), np.clip(yi, 0, h - 1)
    seen = np.asarray(src_world, np.float64)[yi, xi]
    eye = np.linalg.inv(np.asarray(src_view, np.float64))[:3, 3]
    dist = np.linalg.norm(pts - eye, axis=1)
    same = inside & np.asarray(src_mask, bool)[yi, xi] & (np.linalg.norm(seen - pts, axis=1) <= tolerance * dist)
    flat = out.reshape(-1)
    flat[idx[same]] = np.asarray(src_ao, np.float32)[yi[same], xi[same]]
    valid.reshape(-1)[idx[same]] = True
    return out, valid


# ------------------------------------------------------------------------------------------- server
@dataclass
class FrameCost:
    rays: int  # rays traced for the frame
    trace_seconds: float  # wall time of the tracing (every Embree worker)
    filter_seconds: float  # accumulation and denoise


class VideoServer:
    """The server side of one client's video stream: AO traced for the client's G-buffer, frame by
    frame (frames must come in stream order when accumulating)."""

    def __init__(self, scene, settings: VideoSettings):
        from psao.server.geometry import scene_center
        from psao.server.tracer import make_tracer

        settings.check()
        self.scene = scene
        self.settings = settings
        self.tracer = make_tracer("embree", scene_center(scene), workers=settings.workers)
        self._geometry_key = None
        self._history = None  # (ao, world, mask, view, proj) of the previous frame
        self.frame_number = 0

    def reset(self) -> None:
        """Start a new stream: no history to accumulate with."""
        self._history = None

    def _set_geometry(self, transforms, skin_time) -> None:
        from psao.eval.reference import frame_geometry

        key = (np.asarray(transforms, np.float64).tobytes(), skin_time)
        if key != self._geometry_key:
            self.tracer.set_static(*frame_geometry(self.scene, transforms, skin_time))
            self.tracer.warm_up()
            self._geometry_key = key

    def trace(self, frame) -> tuple[np.ndarray, int, float]:
        """(H, W) AO of one RenderedFrame's covered pixels (1 elsewhere), rays and trace seconds."""
        from psao.eval.quality import rest_transforms
        from psao.server.settings import TraceSettings

        transforms = rest_transforms(self.scene) if frame.transforms is None else frame.transforms
        self._set_geometry(transforms, frame.skin_time)
        gb = frame.gbuffer
        mask = np.asarray(gb.mask, bool)
        ao = np.ones(mask.shape, np.float32)
        ids = np.flatnonzero(mask.reshape(-1))
        if not len(ids):
            return ao, 0, 0.0
        world = np.asarray(gb.world, np.float64).reshape(-1, 3)[ids]
        normal = np.asarray(gb.normal, np.float64).reshape(-1, 3)[ids]
        normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-12)
        s = self.settings
        trace = TraceSettings(rays=s.spp, ao_distance=float(self.scene.ao_distance),
                              seed=(s.seed + 7919 * self.frame_number) & 0x7FFFFFFF)
        t0 = time.perf_counter()
        ao.reshape(-1)[ids] = self.tracer.visibility(world, normal.astype(np.float32), ids, trace)
        return ao, len(ids) * s.spp, time.perf_counter() - t0

    def render(self, frame) -> tuple[np.ndarray, FrameCost]:
        """The AO image the server encodes for this frame, and what it cost."""
        ao, rays, trace_s = self.trace(frame)
        t0 = time.perf_counter()
        gb, s = frame.gbuffer, self.settings
        mask = np.asarray(gb.mask, bool)
        if s.accumulate > 0 and self._history is not None:
            h_ao, h_world, h_mask, h_view, h_proj = self._history
            old, valid = reproject(h_ao, h_world, h_mask, h_view, h_proj, gb.world, mask)
            ao = np.where(valid, s.accumulate * old + (1 - s.accumulate) * ao, ao).astype(np.float32)
        if s.accumulate > 0:
            self._history = (ao.copy(), np.asarray(gb.world), mask, frame.pose.view, frame.pose.proj)
        shown = masked_gaussian(ao, mask, gb.depth, s.denoise_px) if s.denoise_px > 0 else ao
        self.frame_number += 1
        return np.where(mask, np.clip(shown, 0, 1), 1.0).astype(np.float32), \
            FrameCost(rays, trace_s, time.perf_counter() - t0)

    def close(self) -> None:
        self.tracer.close()

    def __enter__(self) -> "VideoServer":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
