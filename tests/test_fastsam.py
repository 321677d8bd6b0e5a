"""FastSAM backend: offline guards and the real inference path on an untrained checkpoint.

The inference test needs the `fastsam` extra (torch + ultralytics) and skips cleanly
without it. The checkpoint is a YOLOv8n-seg (FastSAM's architecture) built from
ultralytics' packaged yaml with random weights: nothing is downloaded.
"""

from __future__ import annotations

import os

import numpy as np
import pytest

from lunarloc.errors import ConfigError, InputError
from lunarloc.perception.fastsam import point_grid
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


@pytest.fixture(scope="module")
def untrained_checkpoint(tmp_path_factory):
    pytest.importorskip("torch")
    d = tmp_path_factory.mktemp("fastsam")
    os.environ.setdefault("YOLO_CONFIG_DIR", str(d / "cfg"))  # keep ultralytics' settings out of $HOME
    from lunarloc.perception.fastsam import configure_offline

    configure_offline()
    pytest.importorskip("ultralytics")
    import torch
    from ultralytics import YOLO

    torch.manual_seed(0)  # random init, but the same every run
    model = YOLO("yolov8n-seg.yaml", task="segment")  # built from the packaged yaml: random weights
    path = d / "untrained-yolov8n-seg.pt"
    model.save(str(path))
    return path


def test_fastsam_inference_path_on_cpu(untrained_checkpoint):
    seg = make_segmenter("fastsam", weights=str(untrained_checkpoint), imgsz=320, conf=0.0, iou=0.9, device="cpu")
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
