"""FastSAM backend (ultralytics), run fully offline on a user-given checkpoint.

FastSAM (Zhao et al. 2023) is a YOLOv8-seg network trained on SA-1B; LunarLoc
prompts it with a uniform 32x32 point grid and keeps every mask that contains a
grid point (ultralytics' point prompt with all-positive labels does exactly that).

Offline rules enforced here, before ultralytics is imported:

* ``YOLO_OFFLINE=1`` (no connectivity checks, no telemetry), ``YOLO_AUTOINSTALL=False``
  (no pip installs at run time), ``YOLO_VERBOSE=False`` unless the caller set them.
* The weights path must exist; otherwise :class:`~lunarloc.core.errors.InputError` is
  raised, so ultralytics never gets a chance to fetch a file by that name.
* No plotting is done (plotting is what downloads fonts).

ONNX
----
:func:`export_onnx` writes a dynamic-shape ONNX file next to a local checkpoint once;
``FastSamSegmenter`` takes it as weights (ultralytics runs it on onnxruntime; extra
``fastsam-onnx``). Speeds of both paths: ``benchmarks/fastsam_speed.py``, which times
networks built by :func:`build_untrained_checkpoint` (FastSAM's architecture, random
weights), and docs/perception.md.

torchvision on CPU-only torch
-----------------------------
ultralytics reads torchvision's *version* at import and imports torchvision before
NMS. The only torchvision wheels on the package index are CUDA builds whose compiled
ops cannot load against the CPU build of torch (``torch==2.13.0+cpu``), which makes
``import torchvision`` raise ``RuntimeError: operator torchvision::nms does not exist``.
The documented route is to install ``torchvision==0.28.0 --no-deps`` (its metadata
satisfies ultralytics) and let :func:`ensure_torchvision` replace the unusable module
with a minimal in-process stand-in whose ``ops.nms`` is ultralytics' own pure-torch
NMS (``ultralytics.utils.nms.TorchNMS.nms``, which matches torchvision's result). A
working torchvision is used as is.
"""

from __future__ import annotations

import logging
import os
import sys
import types
from pathlib import Path

import numpy as np

from lunarloc.core.errors import DependencyError, InputError, import_cv2, require
from lunarloc.perception.masks import InstanceMask, InstanceMasks

__all__ = [
    "FastSamSegmenter",
    "point_grid",
    "ensure_torchvision",
    "configure_offline",
    "build_untrained_checkpoint",
    "export_onnx",
    "import_ultralytics",
    "FASTSAM_SCALES",
]

logger = logging.getLogger(__name__)
logger.addHandler(logging.NullHandler())

_HINT = (
    "install torch==2.13.0 first (CPU build), then torchvision==0.28.0 --no-deps and the extra; "
    "see docs/perception.md"
)


def configure_offline() -> None:
    """Set the environment so that ultralytics never reaches the network or installs."""
    os.environ.setdefault("YOLO_OFFLINE", "1")
    os.environ.setdefault("YOLO_AUTOINSTALL", "False")
    os.environ.setdefault("YOLO_VERBOSE", "False")


def import_ultralytics():
    """Import ultralytics (or raise DependencyError with the install hint) and undo its
    global patch of ``PIL.Image.open``.

    On import ultralytics replaces ``PIL.Image.open`` process-wide with a wrapper that,
    on an unidentified image, tries to install and import ``pi_heif``; lunarloc's own
    image reading would then turn a corrupt PNG in an archive into an internal error
    (``ModuleNotFoundError``) instead of a clear one. lunarloc passes arrays to
    ultralytics and needs no HEIF, so the original ``open`` is put back.
    """
    from PIL import Image

    original = Image.open
    mod = require("ultralytics", "fastsam", _HINT)
    patches = sys.modules.get("ultralytics.utils.patches")
    if getattr(Image.open, "__module__", "") == "ultralytics.utils.patches":
        if getattr(original, "__module__", "") == "ultralytics.utils.patches":  # imported before us
            original = getattr(patches, "_image_open", original)
        Image.open = original
    return mod


def ensure_torchvision() -> bool:
    """Make ``import torchvision`` usable for ultralytics' inference path.

    Returns True when the real torchvision imports; otherwise installs the minimal
    stand-in described in the module docstring and returns False.
    """
    existing = sys.modules.get("torchvision")
    if existing is not None:
        return not getattr(existing, "__lunarloc_stub__", False)
    try:
        import torchvision  # noqa: F401

        return True
    except (ImportError, OSError, RuntimeError) as exc:
        for name in [m for m in sys.modules if m == "torchvision" or m.startswith("torchvision.")]:
            del sys.modules[name]
        logger.info(
            "torchvision unusable with this torch (%s); using a pure-torch NMS stand-in", exc
        )
    import_ultralytics()
    from importlib.metadata import PackageNotFoundError, version

    from ultralytics.utils.nms import TorchNMS

    try:
        tv_version = version("torchvision")
    except PackageNotFoundError:  # pragma: no cover - ultralytics itself would have failed
        tv_version = "0.0.0"
    stub = types.ModuleType("torchvision")
    stub.__version__ = tv_version
    stub.__lunarloc_stub__ = True
    ops = types.ModuleType("torchvision.ops")
    ops.nms = TorchNMS.nms
    stub.ops = ops
    sys.modules["torchvision"] = stub
    sys.modules["torchvision.ops"] = ops
    return False


# FastSAM-s is a YOLOv8s-seg and FastSAM-x a YOLOv8x-seg, each with one class ("object").
FASTSAM_SCALES = {"s": "FastSAM-s", "x": "FastSAM-x", "n": "YOLOv8n-seg (tests only)"}


def build_untrained_checkpoint(path: str | os.PathLike, scale: str = "s", *, seed: int = 0) -> Path:
    """Save a FastSAM-shaped network with random weights as an ultralytics ``.pt`` checkpoint.

    The network is built from ultralytics' packaged ``yolov8{scale}-seg.yaml`` with one
    class, FastSAM's architecture (``s``: FastSAM-s, ``x``: FastSAM-x; ``n`` is a smaller
    sibling for tests). Nothing is downloaded. Random weights find no rocks: use it to
    time the network and to test the inference path, never to detect.
    """
    if scale not in FASTSAM_SCALES:
        raise InputError(f"unknown network scale {scale!r}; choose one of {sorted(FASTSAM_SCALES)}")
    configure_offline()
    torch = require("torch", "fastsam", _HINT)
    import_ultralytics()
    from ultralytics import YOLO
    from ultralytics.nn.tasks import SegmentationModel, yaml_model_load

    torch.manual_seed(seed)
    yolo = YOLO(
        f"yolov8{scale}-seg.yaml", task="segment", verbose=False
    )  # 80 classes; replaced below
    cfg = yaml_model_load(f"yolov8{scale}-seg.yaml")
    cfg["nc"] = 1
    net = SegmentationModel(cfg, nc=1, verbose=False)
    net.args, net.task, net.names = yolo.model.args, "segment", {0: "object"}
    yolo.model = net
    out = Path(path).expanduser()
    out.parent.mkdir(parents=True, exist_ok=True)
    yolo.save(str(out))
    return out


def point_grid(width: int, height: int, n: int = 32) -> np.ndarray:
    """(n*n, 2) int pixel coordinates (u, v) of a uniform n x n grid of cell centres."""
    if n < 1:
        raise InputError("grid size must be >= 1")
    us = ((np.arange(n) + 0.5) * width / n).astype(int)
    vs = ((np.arange(n) + 0.5) * height / n).astype(int)
    U, V = np.meshgrid(us, vs)
    return np.stack([U.ravel(), V.ravel()], axis=1)


class FastSamSegmenter:
    """FastSAM instance segmentation of a grayscale image, prompted by a point grid.

    Parameters
    ----------
    weights : path to a FastSAM checkpoint (FastSAM-s.pt / FastSAM-x.pt), any
        ultralytics YOLOv8-seg checkpoint, or its ONNX export (``.onnx``, see
        :func:`export_onnx`; runs on onnxruntime). Must exist; never downloaded.
    imgsz : network input size in pixels (long side); FastSAM's default is 1024.
        A fixed-shape ONNX export runs at its own size.
    conf, iou : confidence and NMS IoU thresholds (FastSAM defaults 0.4, 0.9).
    grid : points per side of the prompt grid (paper: 32).
    device : torch device string ("cpu" by default).
    """

    def __init__(
        self,
        weights: str | os.PathLike,
        *,
        imgsz: int = 1024,
        conf: float = 0.4,
        iou: float = 0.9,
        grid: int = 32,
        device: str = "cpu",
    ) -> None:
        if weights is None or str(weights) == "":
            raise InputError("the fastsam segmenter needs a weights file (--weights PATH)")
        path = Path(weights).expanduser()
        if not path.is_file():
            raise InputError(
                f"FastSAM weights not found: {path} (lunarloc never downloads weights; "
                "pass the path of a local FastSAM-s.pt or FastSAM-x.pt, or its .onnx export)"
            )
        configure_offline()
        require("torch", "fastsam", _HINT)
        import_ultralytics()
        if path.suffix.lower() == ".onnx":
            require("onnxruntime", "fastsam-onnx", _HINT)
        ensure_torchvision()
        from ultralytics import FastSAM

        try:
            self._model = FastSAM(str(path))
        except Exception as exc:  # ultralytics raises many types for a bad checkpoint
            raise InputError(f"cannot load FastSAM weights {path}: {exc}") from exc
        self.weights = path
        self.imgsz = int(imgsz)
        self.conf = float(conf)
        self.iou = float(iou)
        self.grid = int(grid)
        self.device = device

    def predict(self, image: np.ndarray):
        """ultralytics' result of the network and its postprocessing (NMS, masks at image
        resolution, the point prompt) for one (H, W) grayscale or (H, W, 3) uint8 image."""
        cv2 = import_cv2()
        img = np.asarray(image)
        if img.ndim == 2:
            img = cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)
        elif img.ndim != 3 or img.shape[2] != 3:
            raise InputError(f"expected (H, W) or (H, W, 3) image, got {img.shape}")
        H, W = img.shape[:2]
        pts = point_grid(W, H, self.grid)
        try:
            results = self._model(
                img,
                device=self.device,
                imgsz=self.imgsz,
                conf=self.conf,
                iou=self.iou,
                retina_masks=True,
                verbose=False,
                points=pts.tolist(),
                labels=[1] * len(pts),
            )
        except ImportError as exc:  # pragma: no cover
            raise DependencyError(
                f"FastSAM inference needs a missing module: {exc} ({_HINT})"
            ) from exc
        return results[0] if results else None

    @staticmethod
    def masks_from(result, image_shape: tuple[int, int]) -> InstanceMasks:
        """InstanceMasks of an ultralytics result (empty masks dropped)."""
        cv2 = import_cv2()
        H, W = image_shape
        out = InstanceMasks((H, W))
        if result is None or result.masks is None:
            return out
        data = result.masks.data.cpu().numpy().astype(bool)
        boxes = result.boxes
        scores = boxes.conf.cpu().numpy() if boxes is not None and len(boxes) == len(data) else None
        for k, m in enumerate(data):
            if m.shape != (H, W):
                m = cv2.resize(m.astype(np.uint8), (W, H), interpolation=cv2.INTER_NEAREST).astype(
                    bool
                )
            if not m.any():
                continue
            out.masks.append(
                InstanceMask.from_full(m, float(scores[k]) if scores is not None else 1.0)
            )
        return out

    def segment(self, image: np.ndarray) -> InstanceMasks:
        """Masks of the image (H, W) grayscale or (H, W, 3) RGB uint8."""
        return self.masks_from(self.predict(image), np.asarray(image).shape[:2])


def export_onnx(weights: str | os.PathLike, *, imgsz: int = 1024) -> Path:
    """Export a local FastSAM checkpoint to ONNX next to it (``FastSAM-s.pt`` ->
    ``FastSAM-s.onnx``) and return the new file's path. Run once; nothing is downloaded.

    The export has dynamic input shapes, so one file serves any ``imgsz`` and keeps
    ultralytics' rectangular letterbox (1280x720 runs at 1024x576, not 1024x1024).
    Needs the ``fastsam-onnx`` extra (onnx, onnxslim, onnxruntime).
    """
    path = Path(weights).expanduser()
    if path.suffix.lower() != ".pt" or not path.is_file():
        raise InputError(f"ONNX export needs a local .pt checkpoint, got {path}")
    configure_offline()
    require("torch", "fastsam", _HINT)
    import_ultralytics()
    for mod in ("onnx", "onnxslim", "onnxruntime"):
        require(mod, "fastsam-onnx", _HINT)
    ensure_torchvision()
    from ultralytics import FastSAM

    try:
        out = FastSAM(str(path)).export(
            format="onnx", imgsz=int(imgsz), dynamic=True, simplify=True, device="cpu"
        )
    except Exception as exc:  # ultralytics raises many types for a bad checkpoint
        raise InputError(f"cannot export {path} to ONNX: {exc}") from exc
    return Path(out)
