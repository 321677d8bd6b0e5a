"""FastSAM backend: offline guards and the real inference path on an untrained checkpoint.

The inference tests need the `fastsam` extra (torch + ultralytics; the ONNX test also
`fastsam-onnx`) and skip cleanly without it. The checkpoint is a one-class YOLOv8n-seg
(FastSAM-s/-x are its s/x siblings) built from ultralytics' packaged yaml with random
weights: nothing is downloaded.
"""

from __future__ import annotations

import os

import numpy as np
import pytest

from lunarloc.core.errors import ConfigError, DependencyError, InputError
from lunarloc.perception.fastsam import build_untrained_checkpoint, export_onnx, point_grid
from lunarloc.perception.segment import SegmenterKind, make_segmenter


def test_point_grid_is_uniform_32x32():
    g = point_grid(1280, 720, 32)
    assert g.shape == (1024, 2)
    assert g[:, 0].min() == 20 and g[:, 0].max() == 1260
    assert len(np.unique(g[:, 1])) == 32 and g[:, 1].max() < 720


def test_missing_weights_is_a_clear_error_and_no_download(tmp_path, monkeypatch):
    # must fail before ultralytics is even imported (so it cannot try to download)
    with pytest.raises(InputError, match="not found"):
        make_segmenter(SegmenterKind.FASTSAM, weights=str(tmp_path / "FastSAM-s.pt"))
    with pytest.raises(ConfigError):
        make_segmenter("fastsam")
    with pytest.raises(ConfigError):
        make_segmenter("nope")


def test_bad_arguments_fail_before_any_heavy_import(tmp_path, monkeypatch):
    with pytest.raises(InputError, match="scale"):
        build_untrained_checkpoint(tmp_path / "a.pt", "q")
    with pytest.raises(InputError, match=r"\.pt checkpoint"):
        export_onnx(tmp_path / "missing.pt")
    onnx = tmp_path / "FastSAM-s.onnx"
    onnx.write_bytes(b"not a model")
    monkeypatch.setenv(
        "YOLO_CONFIG_DIR", str(tmp_path / "cfg")
    )  # ultralytics' settings, if it is imported here
    monkeypatch.setitem(__import__("sys").modules, "onnxruntime", None)  # as if not installed
    with pytest.raises(
        DependencyError, match=r"lunarloc\[fastsam"
    ):  # torch, ultralytics or onnxruntime missing
        make_segmenter("fastsam", weights=str(onnx))


@pytest.fixture(scope="module")
def untrained_checkpoint(tmp_path_factory):
    pytest.importorskip("torch")
    d = tmp_path_factory.mktemp("fastsam")
    os.environ.setdefault(
        "YOLO_CONFIG_DIR", str(d / "cfg")
    )  # keep ultralytics' settings out of $HOME
    pytest.importorskip("ultralytics")
    return build_untrained_checkpoint(
        d / "untrained-yolov8n-seg.pt", "n", seed=0
    )  # random init, same every run


def test_fastsam_inference_path_on_cpu(untrained_checkpoint):
    seg = make_segmenter(
        "fastsam", weights=str(untrained_checkpoint), imgsz=320, conf=0.0, iou=0.9, device="cpu"
    )
    rng = np.random.default_rng(0)
    img = (rng.uniform(0, 255, (180, 320))).astype(np.uint8)
    out = seg.segment(img)
    assert out.image_shape == (180, 320)
    assert len(out) > 0  # random weights + conf 0 still give masks through the whole pipeline
    for m in out:
        assert m.crop.dtype == bool and m.area > 0
        u0, v0, u1, v1 = m.bbox
        assert 0 <= u0 < u1 <= 320 and 0 <= v0 < v1 <= 180
    # every returned mask contains at least one grid point (point prompting)
    g = point_grid(320, 180, 32)
    for m in out:
        full = m.to_full((180, 320))
        assert full[g[:, 1], g[:, 0]].any()


def _union(masks, shape):
    full = np.zeros(shape, bool)
    for m in masks:
        full |= m.to_full(shape)
    return full


def test_onnx_export_runs_like_the_checkpoint(untrained_checkpoint):
    for mod in ("onnx", "onnxslim", "onnxruntime"):
        pytest.importorskip(mod)
    onnx = export_onnx(untrained_checkpoint, imgsz=320)
    assert onnx.suffix == ".onnx" and onnx.is_file()
    img = (np.random.default_rng(1).uniform(0, 255, (180, 320))).astype(np.uint8)
    kw = dict(imgsz=320, conf=0.0, iou=0.9, device="cpu")
    a = make_segmenter("fastsam", weights=str(untrained_checkpoint), **kw).segment(img)
    b = make_segmenter("fastsam", weights=str(onnx), **kw).segment(img)
    assert len(a) > 0 and abs(len(a) - len(b)) <= max(2, len(a) // 10)
    ua, ub = _union(a, (180, 320)), _union(b, (180, 320))
    assert np.count_nonzero(ua & ub) >= 0.9 * np.count_nonzero(ua | ub)


def test_detector_runs_fastsam_masks_through_its_filters(untrained_checkpoint):
    from lunarloc.perception.camera import PinholeCamera, ipex_rig
    from lunarloc.perception.detector import Detector, DetectorConfig

    cam = PinholeCamera(320, 180, 70.0)
    seg = make_segmenter("fastsam", weights=str(untrained_checkpoint), imgsz=320, conf=0.0)
    det = Detector(
        DetectorConfig(segmenter="fastsam", weights=str(untrained_checkpoint)), cam, segmenter=seg
    )
    rng = np.random.default_rng(2)
    left = rng.uniform(0, 255, (180, 320)).astype(np.uint8)
    res = det.detect_pair(
        left, np.roll(left, -4, axis=1), ipex_rig(cam)["FrontLeft"].T_rover_optical
    )
    assert len(res.masks) > 0 and len(res.records) == len(res.masks)
    # every mask was judged: rejected with a reason, or kept as one finite detection
    assert sum(r.reason is None for r in res.records) == len(res.detections)
    assert all(np.all(np.isfinite(d.p_rover)) for d in res.detections)


def test_detect_cli_with_fastsam_weights_end_to_end(untrained_checkpoint, tmp_path):
    import json

    from lunarloc.cli import main
    from lunarloc.sim.simulate import SimulationConfig, simulate_dataset

    cfg = SimulationConfig(
        duration_s=2.0,
        image_rate_hz=2.0,
        width=320,
        height=180,
        cameras=("FrontLeft", "FrontRight"),
        semantic=False,
    )
    simulate_dataset(0, 1, tmp_path, cfg)
    out = tmp_path / "det.csv"
    rc = main(
        [
            "detect",
            str(tmp_path / "traverse_0.lac"),
            "-o",
            str(out),
            "--segmenter",
            "fastsam",
            "--weights",
            str(untrained_checkpoint),
        ]
    )
    assert rc == 0
    assert out.read_text().startswith("frame,x,y,z,detections")
    rec = json.loads(out.with_name("det.csv.config.json").read_text())
    assert rec["detector"]["segmenter"] == "fastsam"
    assert rec["detector"]["weights"] == str(untrained_checkpoint)


def test_ultralytics_leaves_pil_image_open_alone(untrained_checkpoint, tmp_path):
    """ultralytics patches PIL.Image.open on import (a corrupt image then tries to load
    pi_heif); after lunarloc has loaded FastSAM a corrupt PNG is still PIL's own error,
    which the archive reader reports as a clear one."""
    from PIL import Image, UnidentifiedImageError

    make_segmenter("fastsam", weights=str(untrained_checkpoint), imgsz=320)
    bad = tmp_path / "corrupt.png"
    bad.write_bytes(b"\x89PNG\r\n\x1a\nbroken")
    assert getattr(Image.open, "__module__", "") != "ultralytics.utils.patches"
    with pytest.raises(UnidentifiedImageError):
        Image.open(bad)


def test_fastsam_input_size_is_a_validated_config_field():
    from lunarloc.core.errors import ConfigError
    from lunarloc.perception.detector import DetectorConfig

    assert DetectorConfig().fastsam_imgsz_px == 1024
    assert DetectorConfig(fastsam_imgsz_px=640).to_dict()["fastsam_imgsz_px"] == 640
    for bad in (0, 100, 8192, 640.0, True):
        with pytest.raises(ConfigError, match="fastsam_imgsz_px"):
            DetectorConfig(fastsam_imgsz_px=bad)


def test_detector_builds_fastsam_at_the_configured_size(untrained_checkpoint):
    from lunarloc.perception.detector import Detector, DetectorConfig

    det = Detector(
        DetectorConfig(segmenter="fastsam", weights=str(untrained_checkpoint), fastsam_imgsz_px=320)
    )
    assert det.segmenter.imgsz == 320
