"""Recall changes of the fourth perception pass (night recall, small rocks), on small
synthetic inputs: the stereo's image normalization and its configuration."""

from __future__ import annotations

import json

import numpy as np
import pytest

from lunarloc.config.run import RunConfig
from lunarloc.core.errors import ConfigError
from lunarloc.perception.images import ImageNormalization, normalize_image
from lunarloc.perception.camera import PinholeCamera
from lunarloc.perception.detector import DetectorConfig
from lunarloc.perception.stereo import StereoConfig, StereoMatcher


def _texture(h: int, w: int, seed: int = 0) -> np.ndarray:
    import cv2

    rng = np.random.default_rng(seed)
    tex = cv2.GaussianBlur(rng.uniform(0, 255, size=(h, w)).astype(np.float32), (0, 0), 1.2)
    return cv2.normalize(tex, None, 0, 1, cv2.NORM_MINMAX)


def _lamp_lit_pair(disp: int, h: int = 240, w: int = 480, far_gain: float = 0.06):
    """A textured pair (right = left shifted by `disp`) whose brightness falls off from
    the bottom rows (near, lamp-lit) to the top rows (far, nearly dark) like a lamp's."""
    tex = _texture(h, w + disp)
    gain = np.geomspace(far_gain, 1.0, h, dtype=np.float32)[:, None]
    img = np.clip(np.rint(tex * gain * 250.0), 0, 255).astype(np.uint8)
    return np.ascontiguousarray(img[:, :w]), np.ascontiguousarray(img[:, disp : disp + w])


def test_local_contrast_divides_out_the_lamps_fall_off():
    left, _ = _lamp_lit_pair(0, far_gain=0.06)
    top, bottom = slice(10, 40), slice(-40, -10)
    raw_ratio = left[bottom].std() / left[top].std()
    out = normalize_image(left, ImageNormalization.LOCAL_CONTRAST, sigma_px=24.0, gain=100.0)
    norm_ratio = out[bottom].std() / out[top].std()
    assert raw_ratio > 8.0  # the far rows' texture is a few grey levels
    assert 0.6 < norm_ratio < 1.6  # after: the same contrast near and far
    assert out.dtype == np.uint8 and out.shape == left.shape
    assert normalize_image(left, ImageNormalization.NONE, 24.0, 100.0) is left


def test_lift_brightens_the_dark_far_field_and_leaves_the_lit_near_field():
    left, _ = _lamp_lit_pair(0, far_gain=0.06)
    top, bottom = slice(10, 40), slice(-40, -10)
    out = normalize_image(left, ImageNormalization.LIFT, sigma_px=24.0, gain=100.0, mean_shrink=4)
    assert left[top].mean() < 15 and 60 < out[top].mean() < 140  # lifted to about the target level
    assert out[top].std() > 5 * left[top].std()  # and its texture with it
    # where the image is brighter than the target it is left as it was
    low = normalize_image(left, ImageNormalization.LIFT, sigma_px=24.0, gain=60.0, mean_shrink=4)
    assert np.array_equal(low[bottom], left[bottom])


@pytest.mark.parametrize("method", ["local-contrast", "lift"])
def test_normalized_low_resolution_match_recovers_the_disparity_and_keeps_the_sky_black(method):
    cam = PinholeCamera(width=480, height=240, hfov_deg=70.0)
    left, right = _lamp_lit_pair(24)
    left[:16] = 0  # black sky above the horizon
    right[:16] = 0
    base = dict(
        num_disparities=64,
        block_size=5,
        downscale=2,
        three_way=True,
        p1=200,
        p2=800,
        full_width=True,
    )
    m = StereoMatcher(StereoConfig(**base, normalization=method), cam)
    assert m.config.normalization is ImageNormalization(method)
    d = m.disparity_lowres(left, right, sky_level=6)
    core = d[12:-4, 20:-4]
    assert np.isfinite(core).mean() > 0.9
    assert np.nanmedian(core) == pytest.approx(12.0, abs=0.25)  # low-resolution pixels
    assert np.isnan(d[:8]).all()  # the sky mask comes from the raw image


def test_stereo_normalization_round_trips_and_bad_values_name_the_key():
    cfg = RunConfig()
    assert cfg.detector.height_stereo.normalization is ImageNormalization.LIFT
    d = json.loads(json.dumps(cfg.to_dict()))
    assert d["detector"]["height_stereo"]["normalization"] == "lift"
    d["detector"]["height_stereo"]["normalization"] = "none"
    back = RunConfig.from_dict(d)
    assert back.detector.height_stereo.normalization is ImageNormalization.NONE
    assert back.to_dict() == d
    for key, value in (
        ("normalization", "gamma"),
        ("normalization_gain", 0),
        ("normalization_sigma_frac", 0.7),
    ):
        with pytest.raises(ConfigError, match=f"detector.height_stereo.*{key}"):
            RunConfig.from_dict({"detector": {"height_stereo": {key: value}}})
    with pytest.raises(ConfigError, match="normalization"):
        StereoConfig(normalization="gamma")
    assert (
        DetectorConfig().stereo.normalization is ImageNormalization.NONE
    )  # the full-resolution matcher


def _height_map(H: np.ndarray):
    from lunarloc.perception.stereo import HeightMap

    h, w = H.shape
    return HeightMap(
        np.full((h, w), 10.0, np.float32),
        np.full((h, w), 3.0, np.float32),
        np.zeros((h, w, 3), np.float32),
        H.astype(np.float32),
        2,
        0,
        np.eye(4),
    )


def _dome(shape, cu: float, cv: float, top_m: float, radius_px: float) -> np.ndarray:
    yy, xx = np.mgrid[0 : shape[0], 0 : shape[1]]
    return top_m * np.clip(1 - ((xx - cu) ** 2 + (yy - cv) ** 2) / radius_px**2, 0, 1)


def _labels(H: np.ndarray, **kw) -> np.ndarray:
    from lunarloc.perception.segment import ClassicalConfig, ClassicalSegmenter

    return ClassicalSegmenter(ClassicalConfig(**kw)).height_labels(_height_map(H))


def _blobs(lab: np.ndarray) -> list[tuple[int, int, int, int]]:
    """(u0, v0, u1, v1) inclusive boxes of the labels."""
    out = []
    for i in np.unique(lab[lab > 0]):
        vv, uu = np.nonzero(lab == i)
        out.append((int(uu.min()), int(vv.min()), int(uu.max()), int(vv.max())))
    return sorted(out)


def test_an_elongated_blob_is_split_at_its_saddle_into_rocks():
    shape = (60, 120)
    H = np.zeros(shape)
    H[28:33, 20:101] = 0.035  # a raised streak 3.5 cm high joins two rock tops 8 cm high
    H = np.maximum(H, np.maximum(_dome(shape, 30, 30, 0.08, 6), _dome(shape, 85, 30, 0.08, 6)))
    assert len(_blobs(_labels(H, height_split_step_m=0.0))) == 1  # split off: one streak
    boxes = _blobs(_labels(H, height_split_step_m=0.01))
    assert len(boxes) == 2
    (a0, _, a1, _), (b0, _, b1, _) = boxes
    assert a0 <= 30 <= a1 < b0 <= 85 <= b1  # one part per rock, the streak shared out


def test_a_blob_without_a_saddle_or_not_rejected_is_left_whole():
    shape = (60, 120)
    strip = np.zeros(shape)
    strip[28:33, 20:101] = 0.06  # a flat elongated strip: no saddle to split at
    assert len(_blobs(_labels(strip, height_split_step_m=0.01))) == 1
    # a round blob with two tops (a knobbly rock) is not elongated: not split
    knobs = np.maximum(_dome(shape, 55, 30, 0.08, 12), _dome(shape, 65, 30, 0.08, 12))
    assert len(_blobs(_labels(knobs, height_split_step_m=0.01))) == 1


def test_a_rock_merged_with_a_streak_cut_by_the_border_becomes_a_mask_of_its_own():
    from lunarloc.perception.masks import MaskFilterConfig, image_reject_reason, mask_stats
    from lunarloc.perception.segment import ClassicalConfig, ClassicalSegmenter

    shape = (60, 120)
    H = np.zeros(shape)
    H[24:36, 0:72] = 0.035  # raised ground running out of the image on the left, up to the rock
    H = np.maximum(H, _dome(shape, 75, 30, 0.10, 12))  # a rock on its end
    seg = ClassicalSegmenter(ClassicalConfig(height_split_step_m=0.01))
    masks = seg.segment(np.full((120, 240), 128, np.uint8), height=_height_map(H))
    fc = MaskFilterConfig(tau_elong=20.0)
    kept = [m for m in masks if image_reject_reason(mask_stats(m, masks.image_shape), fc) is None]
    assert len(kept) == 1
    u0, _, u1, _ = kept[0].bbox
    assert 2 * 60 <= u0 and u1 <= 2 * 90  # the rock (low-resolution columns 63-87), full resolution
    whole = ClassicalSegmenter(ClassicalConfig(height_split_step_m=0.0)).segment(
        np.full((120, 240), 128, np.uint8), height=_height_map(H)
    )
    # unsplit, the one blob runs out of the image (dropped, or rejected as cut by the border)
    assert not [
        m for m in whole if image_reject_reason(mask_stats(m, whole.image_shape), fc) is None
    ]


def test_split_settings_round_trip_and_bad_values_name_the_key():
    d = json.loads(json.dumps(RunConfig().to_dict()))
    # on by default, with the learned verifier that removes the terrain parts it makes
    assert d["detector"]["classical"]["height_split_step_m"] == 0.01
    assert d["detector"]["rules"]["verifier_min_score"] > 0
    d["detector"]["classical"]["height_split_step_m"] = 0.02
    assert RunConfig.from_dict(d).detector.classical.height_split_step_m == pytest.approx(0.02)
    for key, value in (
        ("height_split_step_m", -0.01),
        ("height_split_eig_ratio", 0.5),
        ("height_split_grow_px", -1),
    ):
        with pytest.raises(ConfigError, match=f"detector.classical.*{key}"):
            RunConfig.from_dict({"detector": {"classical": {key: value}}})
