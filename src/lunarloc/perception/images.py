"""Image normalisation before stereo matching and tracking (the detector's stereo and visual
odometry share it)."""

from __future__ import annotations

from enum import Enum

import numpy as np

__all__ = ["ImageNormalization", "normalize_image"]


class ImageNormalization(str, Enum):
    """What the images go through before corners, stereo matching and tracking.

    ``local-contrast``: each pixel becomes its contrast against a Gaussian-weighted local
    mean, ``(I - mean) / (mean + 4)``, so a brightness gradient that moves with the camera
    (the rover's lamp fall-off, its light cone on the ground) is divided out instead of
    pulling the Lucas-Kanade flow toward zero. ``clahe``: OpenCV's contrast-limited
    adaptive histogram equalisation. ``lift``: dark regions are brightened to a target
    level, ``I * max(target / (mean + 4), 1)`` with the same local mean (the gain setting is
    the target grey level), and regions already as bright are left as they are (the
    detector's stereo at night: the unlit far field gets the contrast SGBM's penalties
    are set for, the lamp-lit near field and daylight scenes are unchanged). ``none``: the
    raw images. The sky mask is always taken from the raw image.
    """

    NONE = "none"
    LOCAL_CONTRAST = "local-contrast"
    CLAHE = "clahe"
    LIFT = "lift"


def normalize_image(
    image: np.ndarray,
    method: ImageNormalization,
    sigma_px: float,
    gain: float,
    clahe=None,
    mean_shrink: int = 1,
) -> np.ndarray:
    """A uint8 grayscale image after :class:`ImageNormalization` (same shape).

    ``local-contrast``: ``(I - mean) / (mean + 4) * gain + 128`` with a Gaussian local mean
    of standard deviation `sigma_px`; ``lift``: ``I * max(gain / (mean + 4), 1)``;
    ``clahe``: `clahe` (an OpenCV CLAHE object; one with clip limit 2 and 8x8 tiles when
    None); ``none``: `image` itself. Shared by visual
    odometry and the detector's stereo (:class:`lunarloc.perception.stereo.StereoConfig`).
    mean_shrink > 1: the local mean is blurred on the image reduced that many times and
    interpolated back (a wide Gaussian costs ~10x less; the mean is smooth anyway).
    """
    from lunarloc.core.errors import import_cv2

    cv2 = import_cv2()
    method = ImageNormalization(method)
    if method is ImageNormalization.NONE:
        return image
    if method is ImageNormalization.CLAHE:
        return (clahe or cv2.createCLAHE(clipLimit=2.0, tileGridSize=(8, 8))).apply(image)
    f = image.astype(np.float32)
    k = max(int(mean_shrink), 1)
    if k > 1 and min(f.shape) >= 4 * k:
        small = cv2.resize(f, (f.shape[1] // k, f.shape[0] // k), interpolation=cv2.INTER_AREA)
        mean = cv2.resize(
            cv2.GaussianBlur(small, (0, 0), float(sigma_px) / k),
            (f.shape[1], f.shape[0]),
            interpolation=cv2.INTER_LINEAR,
        )
    else:
        mean = cv2.GaussianBlur(f, (0, 0), float(sigma_px))
    if method is ImageNormalization.LIFT:
        out = f * np.maximum(float(gain) / (mean + 4.0), 1.0)
    else:
        out = (f - mean) / (mean + 4.0) * float(gain) + 128.0
    return np.clip(np.rint(out), 0, 255).astype(np.uint8)


def _aligned(a: np.ndarray, align: int = 64) -> np.ndarray:
    """A C-contiguous copy of the float32 array `a` whose data start on an `align`-byte boundary."""
    n = a.size * 4
    buf = np.empty(n + align, np.uint8)
    k = -buf.ctypes.data % align
    out = buf[k : k + n].view(np.float32).reshape(a.shape)
    out[...] = a
    return out


def gradient_magnitude(cv2, gx: np.ndarray, gy: np.ndarray) -> np.ndarray:
    """cv2.magnitude of the float32 gradients, the same bits in every run. OpenCV's IPP path
    rounds the pixels before the output's first 32-byte boundary otherwise than the rest, and a
    fresh numpy array is 16-byte aligned (32 or not, by chance of the heap): the orientation
    features' last digits moved from run to run. Inputs and output here start on 64-byte
    boundaries, so every pixel takes the same path in every run."""
    return cv2.magnitude(_aligned(gx), _aligned(gy), _aligned(np.zeros_like(gx)))
