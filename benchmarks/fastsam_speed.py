"""FastSAM's speed on the CPU: per image and per stereo pair as the detector uses it,
through PyTorch and through its ONNX export on onnxruntime.

No weights are downloaded: FastSAM-s and FastSAM-x are built from ultralytics' packaged
model description (``yolov8s-seg.yaml`` / ``yolov8x-seg.yaml``, one class: FastSAM's
architecture) with random weights and saved as local checkpoints under ``--work``
(:func:`lunarloc.perception.fastsam.build_untrained_checkpoint`); the ONNX files are
exported from those (:func:`~lunarloc.perception.fastsam.export_onnx`, dynamic shapes).
The network's cost does not depend on its weights; what follows it does. Random
weights give (almost) no mask above FastSAM's confidence 0.4, so the table separates:

* **network**: ultralytics' preprocess + forward pass (wall ms, from its ``speed``);
* **post**: NMS, masks at image resolution and the 32x32 point prompt (wall ms) - with
  no mask this is nearly free; ``--mask-load`` adds rows at confidence 0, where the
  random network returns a couple of hundred masks, to show how it grows with masks;
* **image**: the whole ``FastSamSegmenter.predict`` call, wall and process CPU time;
* **lunarloc**: turning the masks into ``InstanceMasks`` (:meth:`FastSamSegmenter.masks_from`), CPU ms;
* **pair**: ``Detector.detect_pair`` on the stereo pair (segment the left image, the
  low-resolution stereo height map, the mask filters), wall and CPU. A LAC frame has two
  pairs (front and rear), so frames/s = 1 / (2 x pair).

CPU time is the process's (all threads). ultralytics runs torch on ``os.cpu_count() - 1``
threads (1 on a 2-core machine); onnxruntime uses its default pool. Wall times depend
on what else the machine runs; say "under load" when quoting them. ``--net-only`` rows
time the bare network forward at one thread for both runtimes (CPU time, the least
load-sensitive comparison of the two).

Usage::

    python benchmarks/fastsam_speed.py [--left L.png --right R.png | --archive X.lac]
        [--scales s x] [--imgsz 1024 640] [--backends torch onnx] [--repeats 3]
        [--mask-load] [--net-only] [--work /tmp/fastsam]

The default frame is the real LAC front pair in ``../shared/data/lac-real/``.
Needs the ``fastsam`` extra (and ``fastsam-onnx`` for the ONNX rows); skips with a
message when they are absent.
"""

from __future__ import annotations

import argparse
import importlib.util
import math
import statistics
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
LAC_REAL = REPO / ".." / "shared" / "data" / "lac-real"


def _load_frame(args) -> tuple[np.ndarray, np.ndarray, str]:
    import cv2

    if args.archive is not None:
        from lunarloc.io.lac.archive import LacArchive

        with LacArchive(args.archive) as arc:
            for f in arc.frame_numbers():
                L, R = arc.grayscale("FrontLeft", int(f)), arc.grayscale("FrontRight", int(f))
                if L is not None and R is not None:
                    return L, R, f"{args.archive} frame {int(f)}"
        sys.exit(f"error: no frame with both front images in {args.archive}")
    L = cv2.imread(str(args.left), cv2.IMREAD_GRAYSCALE)
    R = cv2.imread(str(args.right), cv2.IMREAD_GRAYSCALE)
    if L is None or R is None:
        sys.exit(f"error: cannot read {args.left} / {args.right}")
    return L, R, str(args.left.name)


def _timed(fn):
    t, c = time.perf_counter(), time.process_time()
    out = fn()
    return out, time.perf_counter() - t, time.process_time() - c


def _median(xs):
    return statistics.median(xs) if xs else float("nan")


def measure_image(seg, L: np.ndarray, repeats: int) -> dict:
    """Median timings of FastSamSegmenter.predict and masks_from on one image."""
    seg.segment(L)  # warm-up: predictor set-up, first-call allocations
    rows = []
    for _ in range(repeats):
        res, w, c = _timed(lambda: seg.predict(L))
        masks, _, cm = _timed(lambda: seg.masks_from(res, L.shape))
        sp = res.speed if res is not None else {}
        rows.append(
            (
                sp.get("preprocess", 0) + sp.get("inference", 0),
                sp.get("postprocess", 0),
                w,
                c,
                cm,
                len(masks),
            )
        )
    cols = list(zip(*rows))
    return {
        "net_ms": _median(cols[0]),
        "post_ms": _median(cols[1]),
        "image_s": _median(cols[2]),
        "image_cpu_s": _median(cols[3]),
        "lunarloc_cpu_ms": 1e3 * _median(cols[4]),
        "masks": int(_median(cols[5])),
    }


def measure_pair(seg, L: np.ndarray, R: np.ndarray, repeats: int) -> dict:
    """Median wall and CPU time of Detector.detect_pair with this segmenter."""
    from lunarloc.perception.camera import PinholeCamera, ipex_rig
    from lunarloc.perception.detector import Detector, DetectorConfig

    det = Detector(
        DetectorConfig(segmenter="fastsam", weights=str(seg.weights)),
        PinholeCamera(1280, 720, 70.0),
        segmenter=seg,
    )
    T = ipex_rig(det.camera)["FrontLeft"].T_rover_optical
    det.detect_pair(L, R, T)
    walls, cpus = [], []
    for _ in range(repeats):
        _, w, c = _timed(lambda: det.detect_pair(L, R, T))
        walls.append(w)
        cpus.append(c)
    return {"pair_s": _median(walls), "pair_cpu_s": _median(cpus)}


def net_only(pt: Path, onnx: Path | None, imgsz: int, shape: tuple[int, int], repeats: int) -> dict:
    """CPU seconds of the bare forward pass at one thread: torch and onnxruntime."""
    import torch
    from ultralytics.nn.tasks import load_checkpoint

    H, W = shape
    r = imgsz / max(H, W)
    h, w = (
        int(math.ceil(round(v * r) / 32) * 32) for v in (H, W)
    )  # ultralytics' rectangular letterbox
    x = np.random.default_rng(0).uniform(0, 1, (1, 3, h, w)).astype(np.float32)
    out = {"input": f"{w}x{h}"}
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        model = load_checkpoint(str(pt))[0].float().fuse().eval()
        with torch.inference_mode():
            xt = torch.from_numpy(x)
            model(xt)
            out["torch_cpu_s"] = _median([_timed(lambda: model(xt))[2] for _ in range(repeats)])
    finally:
        torch.set_num_threads(threads)
    if onnx is not None:
        import onnxruntime as ort

        so = ort.SessionOptions()
        so.intra_op_num_threads = so.inter_op_num_threads = 1
        sess = ort.InferenceSession(str(onnx), so, providers=["CPUExecutionProvider"])
        feed = {sess.get_inputs()[0].name: x}
        sess.run(None, feed)
        out["onnx_cpu_s"] = _median(
            [_timed(lambda: sess.run(None, feed))[2] for _ in range(repeats)]
        )
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--left", type=Path, default=LAC_REAL / "FrontLeft_99.png")
    ap.add_argument("--right", type=Path, default=LAC_REAL / "FrontRight_99.png")
    ap.add_argument(
        "--archive", type=Path, default=None, help="take the first front pair of this .lac instead"
    )
    ap.add_argument("--scales", nargs="+", default=["s", "x"], choices=["n", "s", "x"])
    ap.add_argument("--imgsz", nargs="+", type=int, default=[1024, 640])
    ap.add_argument("--backends", nargs="+", default=["torch", "onnx"], choices=["torch", "onnx"])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument(
        "--mask-load", action="store_true", help="add per-image rows at confidence 0 (many masks)"
    )
    ap.add_argument(
        "--net-only", action="store_true", help="add the one-thread forward-pass comparison"
    )
    ap.add_argument("--no-pair", action="store_true", help="skip the detector's per-pair timing")
    ap.add_argument(
        "--work", type=Path, default=Path("/tmp/fastsam"), help="where the weightless networks go"
    )
    args = ap.parse_args(argv)

    missing = [m for m in ("torch", "ultralytics") if importlib.util.find_spec(m) is None]
    if missing:
        print(
            f"skipped: {', '.join(missing)} not installed (pip install torch==2.13.0, then "
            "pip install torchvision==0.28.0 --no-deps and -e '.[fastsam-onnx]'; see docs/perception.md)"
        )
        return 0
    backends = list(args.backends)
    no_onnx = [
        m for m in ("onnx", "onnxslim", "onnxruntime") if importlib.util.find_spec(m) is None
    ]
    if "onnx" in backends and no_onnx:
        print(
            f"ONNX rows skipped: {', '.join(no_onnx)} not installed (pip install -e '.[fastsam-onnx]')"
        )
        backends.remove("onnx")
    import os

    args.work.mkdir(parents=True, exist_ok=True)
    os.environ.setdefault("YOLO_CONFIG_DIR", str(args.work / "ultralytics-settings"))
    import torch

    from lunarloc.perception.fastsam import (
        FastSamSegmenter,
        build_untrained_checkpoint,
        export_onnx,
    )

    L, R, source = _load_frame(args)
    weights: dict[tuple[str, str], Path] = {}
    for s in args.scales:
        pt = args.work / f"untrained-FastSAM-{s}.pt"
        if not pt.is_file():
            build_untrained_checkpoint(pt, s, seed=0)
        weights["torch", s] = pt
        if "onnx" in backends or (args.net_only and not no_onnx):
            onnx = pt.with_suffix(".onnx")
            if not onnx.is_file():
                export_onnx(pt)
            weights["onnx", s] = onnx

    print(
        f"# FastSAM on the CPU: {source} {L.shape[1]}x{L.shape[0]}, torch {torch.__version__}, "
        f"os.cpu_count() {os.cpu_count()}, median of {args.repeats}, load average {os.getloadavg()[0]:.1f}"
    )
    print(
        "| runtime | net | imgsz | conf | masks | network ms | post ms | image wall s | image CPU s | lunarloc CPU ms "
        "| pair wall s | pair CPU s |"
    )
    print("|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    runs = [(b, s, z, 0.4, True) for b in backends for s in args.scales for z in args.imgsz]
    if args.mask_load:
        runs += [(b, args.scales[0], z, 0.0, False) for b in backends for z in args.imgsz]
    for b, s, z, conf, pair in runs:
        seg = FastSamSegmenter(weights[b, s], imgsz=z, conf=conf)
        m = measure_image(seg, L, args.repeats)
        p = measure_pair(seg, L, R, args.repeats) if pair and not args.no_pair else {}
        print(
            f"| {b} | FastSAM-{s} | {z} | {conf:g} | {m['masks']} | {m['net_ms']:.0f} | {m['post_ms']:.0f} "
            f"| {m['image_s']:.2f} | {m['image_cpu_s']:.2f} | {m['lunarloc_cpu_ms']:.0f} "
            f"| {p.get('pair_s', float('nan')):.2f} | {p.get('pair_cpu_s', float('nan')):.2f} |",
            flush=True,
        )
    if args.net_only:
        print("\n| net | imgsz | input | torch CPU s (1 thread) | onnxruntime CPU s (1 thread) |")
        print("|---|---:|---|---:|---:|")
        for s in args.scales:
            for z in args.imgsz:
                r = net_only(
                    weights["torch", s], weights.get(("onnx", s)), z, L.shape, args.repeats
                )
                print(
                    f"| FastSAM-{s} | {z} | {r['input']} | {r['torch_cpu_s']:.2f} | {r.get('onnx_cpu_s', float('nan')):.2f} |",
                    flush=True,
                )
    print(f"# load average at the end {os.getloadavg()[0]:.1f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
