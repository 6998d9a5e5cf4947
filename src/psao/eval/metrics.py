"""Image metrics on AO images: PSNR, SSIM (scikit-image, data_range=1) and FLIP (flip-evaluator).

Every method and the reference are composited the same way before comparison (`composite_ao`): AO as
visibility in [0, 1] on covered pixels, 1 on background pixels. FLIP sees the AO as an LDR display image
(grey, three equal channels, values as sRGB pixel values: what the AO PNGs show).

flip-evaluator's native code ends the whole process on arguments it does not like, so `flip` checks
shapes, dtypes and ranges first and raises EvalError instead.

LPIPS is not computed: its network weights are not available offline here (LPIPS_NOTE says so in output).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from psao.eval.errors import EvalError

PSNR_CAP = 100.0  # dB reported for identical images (PSNR is infinite there)
LPIPS_NOTE = "LPIPS not computed: its network weights are not available offline on this machine"


@dataclass
class Scores:
    psnr: float  # dB, capped at PSNR_CAP
    ssim: float
    flip: float  # mean FLIP error in [0, 1]
    bias: float = 0.0  # mean of test - reference over the image (> 0: brighter, i.e. too little occlusion)

    def as_dict(self) -> dict:
        return {"psnr": self.psnr, "ssim": self.ssim, "flip": self.flip, "bias": self.bias}


def composite_ao(ao: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """(H, W) float32 AO clipped to [0, 1] on covered pixels, 1 on background."""
    ao = np.asarray(ao, np.float32)
    mask = np.asarray(mask, bool)
    if ao.ndim != 2 or ao.shape != mask.shape:
        raise EvalError(f"AO image {ao.shape} and coverage mask {mask.shape} must be equal 2D shapes")
    if not np.isfinite(ao[mask]).all():
        raise EvalError("AO image has NaN or infinite values on covered pixels")
    return np.where(mask, np.clip(ao, 0.0, 1.0), np.float32(1.0)).astype(np.float32)


def check_pair(reference: np.ndarray, test: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Both (H, W) finite float images in [0, 1] of the same shape, at least 8x8 (SSIM's window)."""
    out = []
    for name, img in (("reference", reference), ("test", test)):
        arr = np.asarray(img)
        if arr.dtype.kind not in "fiu":
            raise EvalError(f"{name} image has dtype {arr.dtype}, expected numbers")
        arr = arr.astype(np.float32)
        if arr.ndim != 2:
            raise EvalError(f"{name} image has shape {arr.shape}, expected (H, W)")
        if min(arr.shape) < 8:
            raise EvalError(f"{name} image {arr.shape} is smaller than 8x8")
        if not np.isfinite(arr).all():
            raise EvalError(f"{name} image has NaN or infinite values")
        if arr.min() < 0.0 or arr.max() > 1.0:
            raise EvalError(f"{name} image has values outside [0, 1] ({arr.min():.3g}..{arr.max():.3g})")
        out.append(arr)
    if out[0].shape != out[1].shape:
        raise EvalError(f"images differ in shape: reference {out[0].shape}, test {out[1].shape}")
    return out[0], out[1]


def psnr(reference: np.ndarray, test: np.ndarray) -> float:
    from skimage.metrics import peak_signal_noise_ratio

    ref, img = check_pair(reference, test)
    if np.array_equal(ref, img):
        return PSNR_CAP
    return float(min(PSNR_CAP, peak_signal_noise_ratio(ref, img, data_range=1.0)))


def ssim(reference: np.ndarray, test: np.ndarray) -> float:
    from skimage.metrics import structural_similarity

    ref, img = check_pair(reference, test)
    return float(structural_similarity(ref, img, data_range=1.0))


def flip(reference: np.ndarray, test: np.ndarray) -> tuple[float, np.ndarray]:
    """(mean FLIP error, (H, W) float32 error map in [0, 1])."""
    import flip_evaluator

    ref, img = check_pair(reference, test)
    rgb = [np.ascontiguousarray(np.repeat(a[..., None], 3, axis=2), dtype=np.float32) for a in (ref, img)]
    error_map, mean, _params = flip_evaluator.evaluate(rgb[0], rgb[1], "LDR", inputsRGB=True, applyMagma=False,
                                                       computeMeanError=True)
    return float(mean), np.asarray(error_map, np.float32).reshape(ref.shape)


def score(reference: np.ndarray, test: np.ndarray) -> tuple[Scores, np.ndarray]:
    """All metrics of one composited AO image against the composited reference, and the FLIP map."""
    mean_flip, error_map = flip(reference, test)
    bias = float(np.mean(np.asarray(test, np.float64) - np.asarray(reference, np.float64)))
    return Scores(psnr=psnr(reference, test), ssim=ssim(reference, test), flip=mean_flip, bias=bias), error_map


def magma(error_map: np.ndarray) -> np.ndarray:
    """FLIP error map -> (H, W, 3) uint8 with matplotlib's magma, as FLIP's own tool shows it."""
    from matplotlib import colormaps

    rgba = colormaps["magma"](np.clip(np.asarray(error_map, np.float32), 0.0, 1.0))
    return (rgba[..., :3] * 255.0 + 0.5).astype(np.uint8)
