"""A tiny fully-convolutional rock segmenter for the small-rock stage (issue 29).

The network maps the left image at half resolution to a per-pixel rock probability. It was
trained here on the simulator's labelled (semantic) images by ``benchmarks/train_rock_net.py``
(the data recipe is in its docstring; docs/perception-status.md, "The rock network") and is
shipped as plain arrays (``rock_net.npz`` beside this module; no pickle, never downloaded).
Inference is numpy and OpenCV only: each 3x3 convolution is one matrix product per kernel tap
over the zero-padded image (channels first), its intermediate arrays kept per thread.

Input channels (:func:`net_inputs`, the same function the trainer uses): the image's local
contrast (difference of Gaussians over its local RMS, as the small-rock stage's candidate
search measures it) and its brightness relative to a wider local mean (a lit face, a shadow).

Architecture (read from the file, so a retrained model may change widths): a list of layers,
each a 3x3 (or 1x1) convolution with ReLU except the last; a layer may be preceded by a 2x2
max-pool (``pool``), may be dilated (``dilation``) and may run at a stride (``stride``; the
packaged network's first layer at 2, no pool). The output (logits at the last layer's
resolution) are resized bilinearly to the input's size and passed through a sigmoid. Files
written before strides existed read with stride 1.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np

from lunarloc.core.errors import InputError

NET_PATH = Path(__file__).with_name("rock_net.npz")
#: Preprocessing (fixed; the model was trained with these)
DOG_SIGMA_PX = 2.0
CONTRAST_SIGMA_PX = 8.0
WIDE_SIGMA_PX = 12.0
N_INPUTS = 2
#: the width of the images the network was trained on (the LAC's 1280-pixel images at half
#: resolution); the stage brings other images to it
NET_WIDTH_PX = 640
_FORMAT = 1
#: the products' runs of output pixels (columns): long enough for the BLAS's fast kernels,
#: short enough that it keeps to one thread (a wide, thin product split over threads costs
#: several times its single-thread CPU on a loaded machine)
_COLUMNS = 4096
#: per thread, the layers' intermediate arrays (see _work)
_WORK = threading.local()
#: layers of at most this many input x output channels run as OpenCV correlations
_FILTER2D_MAX_PAIRS = 16


def local_contrast(
    small: np.ndarray,
    dog_sigma_px: float = DOG_SIGMA_PX,
    contrast_sigma_px: float = CONTRAST_SIGMA_PX,
) -> np.ndarray:
    """The local contrast of a half-resolution grey image ((h, w) float32): its difference of
    Gaussians (`dog_sigma_px`) over the local RMS of that difference (`contrast_sigma_px`), what
    the small-rock stage's candidate search measures (the network was trained with the default
    sigmas, 2 and 8 pixels)."""
    import cv2

    s = np.asarray(small, np.float32)
    h, w = s.shape
    dv = s - cv2.GaussianBlur(s, (0, 0), dog_sigma_px)
    e = max(int(contrast_sigma_px // 2), 1)
    var = cv2.resize(dv * dv, (max(w // e, 1), max(h // e, 1)), interpolation=cv2.INTER_AREA)
    var = cv2.resize(cv2.GaussianBlur(var, (0, 0), 2.0), (w, h), interpolation=cv2.INTER_LINEAR)
    return dv / (np.sqrt(var) + 2.0)


def net_inputs(small: np.ndarray, contrast: np.ndarray | None = None) -> np.ndarray:
    """(N_INPUTS, h, w) float32 input channels of a half-resolution grey image `small` ((h, w),
    any real dtype, 0-255): the local contrast (:func:`local_contrast`, or `contrast` when the
    caller has it) clipped to +-8, and the brightness relative to a wide local mean (a Gaussian
    of WIDE_SIGMA_PX taken at a quarter of the image's resolution) clipped to +-4."""
    import cv2

    s = np.asarray(small, np.float32)
    if s.ndim != 2 or s.shape[0] < 4 or s.shape[1] < 4:
        raise InputError(f"rock net input must be an (h, w) image of at least 4x4, got {s.shape}")
    h, w = s.shape
    z = local_contrast(s) if contrast is None else np.asarray(contrast, np.float32)
    if z.shape != s.shape:
        raise InputError(f"rock net: contrast {z.shape} is not the image's {s.shape}")
    q = cv2.resize(s, (max(w // 4, 1), max(h // 4, 1)), interpolation=cv2.INTER_AREA)
    m = cv2.resize(
        cv2.GaussianBlur(q, (0, 0), WIDE_SIGMA_PX / 4), (w, h), interpolation=cv2.INTER_LINEAR
    )
    out = np.empty((N_INPUTS, h, w), np.float32)
    np.clip(z, -8.0, 8.0, out=out[0])
    np.clip((s - m) / (m + 8.0) * 4.0, -4.0, 4.0, out=out[1])
    return out


@dataclass(frozen=True)
class _Layer:
    W: np.ndarray  # (out, in, k, k) float32
    b: np.ndarray  # (out,) float32
    dilation: int
    pool: bool  # a 2x2 max-pool before the convolution
    stride: int = 1  # the convolution at every stride-th pixel of every stride-th row


def _work(key, shape) -> np.ndarray:
    """A float32 array of `shape` for the intermediate result `key`, kept by this thread for the
    next image (its memory reused: the fresh pages of new arrays cost as much as a layer's
    products on the real pairs); grown when an image needs more."""
    bufs = getattr(_WORK, "bufs", None)
    if bufs is None:
        bufs = _WORK.bufs = {}
    size = int(np.prod(shape))
    buf = bufs.get(key)
    if buf is None or buf.size < size:
        buf = bufs[key] = np.empty(size + size // 4, np.float32)
    return buf[:size].reshape(shape)


def _padded(x: np.ndarray, p: int, extra: int, key) -> np.ndarray:
    """x ((c, h, w)) zero padded by p each side and `extra` more rows below, in a work array."""
    c, h, w = x.shape
    xp = _work(key, (c, h + 2 * p + extra, w + 2 * p))
    xp[:, :p] = 0.0
    xp[:, p + h :] = 0.0
    xp[:, p : p + h, :p] = 0.0
    xp[:, p : p + h, p + w :] = 0.0
    xp[:, p : p + h, p : p + w] = x
    return xp


def _matmul(A: np.ndarray, B: np.ndarray, out: np.ndarray, key) -> None:
    """out += A @ B (A (m, k), B (k, n), out (m, n), float32) in runs of _COLUMNS columns
    (one work array for a run's product)."""
    n = B.shape[1]
    tmp = _work(key, (A.shape[0], min(_COLUMNS, n)))
    for a in range(0, n, _COLUMNS):
        b = min(a + _COLUMNS, n)
        t = tmp[:, : b - a]
        np.matmul(A, B[:, a:b], out=t)
        out[:, a:b] += t


def _conv(x: np.ndarray, layer: _Layer, i_layer: int = 0) -> np.ndarray:
    """One 'same' convolution of x ((in, h, w) float32, channels first; may be a view) with
    zero padding, as torch's Conv2d computes it (a cross-correlation). Stride 1: per kernel tap
    one matrix product over the zero-padded image flattened row by row, where a tap's shift is
    a contiguous run of each channel's flattened plane (no copy per tap); the outputs on the
    padded columns are dropped. Stride s: the taps' strided samples gathered once (s x s times
    fewer outputs) and one product. A 1x1 layer: its sums of channels. Returns (out, h', w'),
    h' = ceil(h / s), a view of this thread's work arrays (overwritten by the next image)."""
    cout, cin, k, _ = layer.W.shape
    _, h, w = x.shape
    s = layer.stride
    key = ("y", i_layer)
    if k == 1 and s == 1:
        y = _work(key, (cout, h, w))
        for o in range(cout):
            y[o] = layer.b[o]
            for c in range(cin):
                y[o] += layer.W[o, c, 0, 0] * x[c]
        return y
    d = layer.dilation
    p = d * (k // 2)
    if s > 1:
        ho, wo = (h - 1) // s + 1, (w - 1) // s + 1
        xp = _padded(x, p, 0, ("xp", i_layer))
        cols = _work(("cols", i_layer), (cin, k, k, ho, wo))
        for i in range(k):
            for j in range(k):
                cols[:, i, j] = xp[
                    :, i * d : i * d + s * (ho - 1) + 1 : s, j * d : j * d + s * (wo - 1) + 1 : s
                ]
        y = _work(key, (cout, ho * wo))
        y[:] = layer.b[:, None]
        W = layer.W.reshape(cout, cin * k * k)
        _matmul(W, cols.reshape(cin * k * k, ho * wo), y, ("tmp", i_layer))
        return y.reshape(cout, ho, wo)
    # padding above and below, plus one more row below so that every tap's run fits
    xp = _padded(x, p, 1, ("xp", i_layer))
    wp = w + 2 * p
    flat = xp.reshape(cin, -1)
    n = h * wp  # outputs on the padded width; the columns >= w are dropped
    taps = np.ascontiguousarray(layer.W.transpose(2, 3, 0, 1))  # (k, k, out, in)
    y = _work(key, (cout, n))
    y[:] = layer.b[:, None]
    tmp = _work(("tmp", i_layer), (cout, min(_COLUMNS, n)))  # each tap's product
    for a in range(0, n, _COLUMNS):
        b = min(a + _COLUMNS, n)
        ya, t = y[:, a:b], tmp[:, : b - a]
        for i in range(k):
            for j in range(k):
                off = i * d * wp + j * d
                np.matmul(taps[i, j], flat[:, off + a : off + b], out=t)
                ya += t
    return y.reshape(cout, h, wp)[:, :, :w]


def _conv_planes(x: np.ndarray, layer: _Layer) -> np.ndarray:
    """_conv of x ((in, h, w)) at stride 1 by one OpenCV correlation per input
    and output channel (cheaper for a layer of few channels, the first one: its inputs are
    wide images of 2 channels); returns (out, h, w)."""
    import cv2

    cout, cin = layer.W.shape[:2]
    _, h, w = x.shape
    y = np.empty((cout, h, w), np.float32)
    for o in range(cout):
        y[o] = layer.b[o]
        for c in range(cin):
            y[o] += cv2.filter2D(x[c], -1, layer.W[o, c], borderType=cv2.BORDER_CONSTANT)
    return y


def _pool(x: np.ndarray) -> np.ndarray:
    """2x2 max-pool of (c, h, w) planes (an odd last row or column dropped)."""
    h2, w2 = x.shape[1] // 2, x.shape[2] // 2
    r0, r1 = slice(0, 2 * h2, 2), slice(1, 2 * h2, 2)
    a = np.maximum(x[:, r0, 0 : 2 * w2 : 2], x[:, r1, 0 : 2 * w2 : 2])
    b = np.maximum(x[:, r0, 1 : 2 * w2 : 2], x[:, r1, 1 : 2 * w2 : 2])
    return np.maximum(a, b, out=a)


class RockNet:
    """The network's layers (see the module's docstring); :meth:`probability` runs it."""

    def __init__(self, layers: list[_Layer]) -> None:
        if not layers:
            raise InputError("rock net: no layers")
        cin = N_INPUTS
        for i, L in enumerate(layers):
            if L.W.ndim != 4 or L.W.shape[1] != cin or L.W.shape[2] != L.W.shape[3]:
                raise InputError(
                    f"rock net layer {i}: weights {L.W.shape} do not take {cin} inputs"
                )
            if (
                L.W.shape[2] % 2 == 0
                or L.b.shape != (L.W.shape[0],)
                or L.dilation < 1
                or L.stride < 1
            ):
                raise InputError(f"rock net layer {i}: bad kernel, bias, dilation or stride")
            if not (np.isfinite(L.W).all() and np.isfinite(L.b).all()):
                raise InputError(f"rock net layer {i}: non-finite weights")
            cin = L.W.shape[0]
        if cin != 1:
            raise InputError(f"rock net: the last layer has {cin} outputs, need 1")
        self.layers = layers

    @property
    def n_params(self) -> int:
        return int(sum(L.W.size + L.b.size for L in self.layers))

    def logits(self, x: np.ndarray) -> np.ndarray:
        """The last layer's output ((h', w') float32) for input channels x ((N_INPUTS, h, w))."""
        x = np.asarray(x, np.float32)  # (c, h, w) planes throughout
        n = len(self.layers)
        for i, L in enumerate(self.layers):
            if L.pool:
                x = _pool(x)
            cout, cin = L.W.shape[:2]
            if (
                L.stride == 1
                and L.dilation == 1
                and L.W.shape[2] > 1
                and cin * cout <= _FILTER2D_MAX_PAIRS
            ):
                x = _conv_planes(np.ascontiguousarray(x), L)
            else:
                x = _conv(x, L, i)
            if i < n - 1:
                np.maximum(x, 0.0, out=x)
        return np.array(x[0], np.float32)  # a copy (x may be a work array)

    def probability(self, small: np.ndarray, contrast: np.ndarray | None = None) -> np.ndarray:
        """Rock probability ((h, w) float32, 0-1) of each pixel of a half-resolution grey image
        (`contrast`: its :func:`local_contrast` if the caller has it)."""
        import cv2

        h, w = np.asarray(small).shape[:2]
        z = self.logits(net_inputs(small, contrast))
        if z.shape != (h, w):  # the logits resized, as in training
            z = cv2.resize(z, (w, h), interpolation=cv2.INTER_LINEAR)
        np.clip(z, -30.0, 30.0, out=z)
        np.negative(z, out=z)  # the sigmoid in place: 1 / (1 + exp(-z))
        np.exp(z, out=z)
        z += 1.0
        return np.reciprocal(z, out=z)

    def save(self, path: Path) -> None:
        """Write the layers as plain arrays (read back by :func:`load_rock_net`)."""
        arr: dict[str, np.ndarray] = {
            "format": np.array(_FORMAT),
            "n_layers": np.array(len(self.layers)),
        }
        for i, L in enumerate(self.layers):
            arr[f"W{i}"] = L.W.astype(np.float32)
            arr[f"b{i}"] = L.b.astype(np.float32)
            arr[f"dilation{i}"] = np.array(int(L.dilation))
            arr[f"pool{i}"] = np.array(bool(L.pool))
            arr[f"stride{i}"] = np.array(int(L.stride))
        np.savez_compressed(Path(path), **arr)


def make_layer(W, b, dilation: int = 1, pool: bool = False, stride: int = 1) -> _Layer:
    """A layer from arrays (float32 copies)."""
    return _Layer(
        np.array(W, np.float32),
        np.array(b, np.float32).reshape(-1),
        int(dilation),
        bool(pool),
        int(stride),
    )


def load_rock_net(path: Path) -> RockNet:
    """Read a network written by :meth:`RockNet.save` (``benchmarks/train_rock_net.py fit``);
    a missing, unreadable or malformed file raises InputError."""
    try:
        with np.load(Path(path), allow_pickle=False) as z:
            if int(z["format"]) != _FORMAT:
                raise ValueError(f"format {int(z['format'])}, this version reads {_FORMAT}")
            n = int(z["n_layers"])
            layers = [
                make_layer(
                    z[f"W{i}"],
                    z[f"b{i}"],
                    int(z[f"dilation{i}"]),
                    bool(z[f"pool{i}"]),
                    int(z[f"stride{i}"]) if f"stride{i}" in z.files else 1,  # (older files)
                )
                for i in range(n)
            ]
    except (OSError, KeyError, ValueError, TypeError) as e:
        raise InputError(
            f"rock net {path}: {e} (write one with benchmarks/train_rock_net.py fit)"
        ) from e
    return RockNet(layers)


@lru_cache(maxsize=4)
def rock_net_at(path: str | None) -> RockNet:
    """The network at `path` (None: the packaged rock_net.npz), read once."""
    return load_rock_net(NET_PATH if path is None else Path(path))
