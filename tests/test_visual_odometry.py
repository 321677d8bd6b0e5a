"""Stereo visual odometry: known-motion recovery on a small simulated traverse,
fallback to the prior on frames without usable texture, and input validation."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("cv2")

from lunarloc.core.errors import ConfigError, InputError  # noqa: E402
from lunarloc.core.geometry import invert_transform, pose_to_matrix, rotation_angle  # noqa: E402
from lunarloc.odometry.visual import (  # noqa: E402
    StereoVisualOdometry,
    VisualOdometryConfig,
    front_pair_setup,
    visual_odometry_frames,
)
from lunarloc.perception.camera import PinholeCamera, ipex_rig  # noqa: E402

W, H = 320, 180
CAMERA = PinholeCamera(W, H)
RIG = ipex_rig(CAMERA)
T_LEFT = RIG["FrontLeft"].T_rover_optical
T_RIGHT = RIG["FrontRight"].T_rover_optical


@pytest.fixture(scope="module")
def traverse(tmp_path_factory):
    """A 12 s traverse (turn in place, then driving) at 320x180 and 2 Hz, as an archive,
    lit by the sun alone (the lamp-lit LAC look is `traverse_lamps`)."""
    return _simulate(tmp_path_factory, "sun")


@pytest.fixture(scope="module")
def traverse_lamps(tmp_path_factory):
    """The same traverse in the default LAC look: sun plus the rover's lamps, whose light
    moves with the camera (brightness constancy no longer holds for tracked patches)."""
    return _simulate(tmp_path_factory, "sun+lamps")


def _simulate(tmp_path_factory, lighting: str):
    pytest.importorskip("embreex")
    from lunarloc.io.lac.archive import LacArchive
    from lunarloc.sim.simulate import SimulationConfig, simulate_site, simulate_traverse
    from lunarloc.sim.site import SiteConfig

    site_cfg = SiteConfig(
        size_m=14.0, terrain_margin_m=3.0, resolution_m=0.2, n_rocks=80, rover_start_xy=(-3.0, -2.0)
    )
    from lunarloc.sim.render import RenderConfig

    cfg = SimulationConfig(
        site=site_cfg,
        duration_s=12.0,
        image_rate_hz=2.0,
        width=W,
        height=H,
        cameras=("FrontLeft", "FrontRight"),
        semantic=False,
        render=RenderConfig(lighting=lighting),
    )
    site = simulate_site(3, cfg)
    path, _ = simulate_traverse(
        site, tmp_path_factory.mktemp("vo") / f"t-{lighting.replace('+', '-')}.lac", 0, cfg
    )
    with LacArchive(path) as a:
        frames = a.camera_frames("FrontLeft")["frame"].astype(int)
        index = {int(f): i for i, f in enumerate(a.frame_numbers)}
        poses = a.poses()
        truth = np.stack([pose_to_matrix(*poses[index[f]]) for f in frames])
        left = [a.grayscale("FrontLeft", f) for f in frames]
        right = [a.grayscale("FrontRight", f) for f in frames]
    return {"path": path, "frames": frames, "truth": truth, "left": left, "right": right}


def _relative(T):
    return np.einsum("ij,njk->nik", invert_transform(T[0]), T)


def _errors(T_est, T_true):
    est, tru = _relative(T_est), _relative(T_true)
    length = float(np.linalg.norm(np.diff(tru[:, :3, 3], axis=0), axis=1).sum())
    final_m = float(np.linalg.norm(est[-1, :3, 3] - tru[-1, :3, 3]))
    rot_deg = float(np.degrees(rotation_angle(est[-1, :3, :3].T @ tru[-1, :3, :3])))
    steps = [
        np.linalg.norm(
            (invert_transform(est[i - 1]) @ est[i])[:3, 3]
            - (invert_transform(tru[i - 1]) @ tru[i])[:3, 3]
        )
        for i in range(1, len(est))
    ]
    return length, final_m, rot_deg, max(steps)


def test_recovers_simulated_motion(traverse):
    vo = StereoVisualOdometry(CAMERA, T_LEFT, T_RIGHT)
    T = np.stack([vo.update(l, r) for l, r in zip(traverse["left"], traverse["right"])])
    length, final_m, rot_deg, worst_step_m = _errors(T, traverse["truth"])
    true_rot = np.degrees(rotation_angle(_relative(traverse["truth"])[-1, :3, :3]))
    assert length > 1.0 and true_rot > 5.0  # the traverse both drives and turns
    assert final_m < 0.05 * length + 0.02
    assert rot_deg < 1.0
    assert worst_step_m < 0.05
    assert vo.last_ok


def test_recovers_motion_under_the_rover_lamps(traverse_lamps):
    """Measured: 0.99 deg of rotation error over this clip under sun+lamps and 0.97 deg in
    sun alone with the default local-contrast images (raw images: 1.22 and 0.93 deg; the lamp
    fall-off moves with the camera). At 320x180 this clip's figure moves by +-0.5 deg with
    any setting (sigma 4-16 px gave 0.7-2.0 deg), so it bounds breakage, not the lamp
    effect; that one is measured by the flow-bias test below and on 100 m traverses."""
    vo = StereoVisualOdometry(CAMERA, T_LEFT, T_RIGHT)
    T = np.stack([vo.update(l, r) for l, r in zip(traverse_lamps["left"], traverse_lamps["right"])])
    length, final_m, rot_deg, worst_step_m = _errors(T, traverse_lamps["truth"])
    assert final_m < 0.05 * length + 0.02
    assert rot_deg < 1.5
    assert worst_step_m < 0.05


def test_archive_convenience_matches_direct_use(traverse):
    frames, T = visual_odometry_frames(traverse["path"])
    assert np.array_equal(frames, traverse["frames"])
    assert T.shape == (len(frames), 4, 4)
    np.testing.assert_allclose(T[0], np.eye(4))
    _, final_m, _, _ = _errors(T, traverse["truth"])
    vo = StereoVisualOdometry(CAMERA, T_LEFT, T_RIGHT)
    T_direct = np.stack([vo.update(l, r) for l, r in zip(traverse["left"], traverse["right"])])
    np.testing.assert_allclose(T, T_direct, atol=1e-9)
    from lunarloc.io.lac.playback import PlaybackAgent

    with PlaybackAgent(traverse["path"]) as agent:
        frames2, T2 = visual_odometry_frames(agent)
    assert np.array_equal(frames2, frames)
    np.testing.assert_allclose(T2, T, atol=1e-9)


def _open(path):
    from lunarloc.io.lac.archive import LacArchive

    return LacArchive(path)


def test_front_pair_setup_reads_the_rig(traverse):
    with _open(traverse["path"]) as a:
        camera, T_l, T_r, left, right = front_pair_setup(a)
    assert (camera.width, camera.height) == (W, H) and (left, right) == ("FrontLeft", "FrontRight")
    np.testing.assert_allclose(T_l, T_LEFT, atol=1e-9)
    np.testing.assert_allclose(T_r, T_RIGHT, atol=1e-9)


def test_black_and_sky_frames_fall_back_to_the_prior(traverse):
    left, right, truth = traverse["left"], traverse["right"], traverse["truth"]
    vo = StereoVisualOdometry(CAMERA, T_LEFT, T_RIGHT)
    for k in range(3):
        T_prev = vo.update(left[k], right[k])
        assert vo.last_ok
    prior = invert_transform(truth[2]) @ truth[3]
    black = np.zeros((H, W), np.uint8)
    T = vo.update(black, black, prior)
    assert not vo.last_ok
    np.testing.assert_allclose(T, T_prev @ prior, atol=1e-12)
    # sky with a distant bright textured object (the lander far away: no disparity)
    sky = np.zeros((H, W), np.uint8)
    sky[60:100, 200:260] = np.random.default_rng(0).integers(40, 255, (40, 60), dtype=np.uint8)
    T2 = vo.update(sky, sky.copy(), prior)
    assert not vo.last_ok
    np.testing.assert_allclose(T2, T @ prior, atol=1e-12)
    # no prior: the pose holds
    T3 = vo.update(black, black)
    assert not vo.last_ok
    np.testing.assert_allclose(T3, T2, atol=1e-12)
    # vision comes back on textured frames
    oks = []
    for k in range(4, 8):
        vo.update(left[k], right[k])
        oks.append(vo.last_ok)
    assert oks[-1]


def test_prior_guides_tracking_and_is_checked(traverse):
    left, right, truth = traverse["left"], traverse["right"], traverse["truth"]
    vo = StereoVisualOdometry(CAMERA, T_LEFT, T_RIGHT)
    vo.update(left[0], right[0])
    # a prior whose rotation is far from the truth makes the visual step fail the check
    wrong = invert_transform(truth[0]) @ truth[1] @ pose_to_matrix(0, 0, 0, 0, 0, np.radians(20))
    T = vo.update(left[1], right[1], wrong)
    assert not vo.last_ok
    np.testing.assert_allclose(T, wrong, atol=1e-12)
    # an accurate prior is accepted and the estimate stays visual
    vo.reset()
    T_est = [vo.update(left[0], right[0])]
    for k in range(1, len(left)):
        T_est.append(vo.update(left[k], right[k], invert_transform(truth[k - 1]) @ truth[k]))
        assert vo.last_ok
    length, final_m, rot_deg, _ = _errors(np.stack(T_est), truth)
    assert final_m < 0.05 * length + 0.02 and rot_deg < 1.0


def test_bad_inputs_raise_input_error(traverse):
    vo = StereoVisualOdometry(CAMERA, T_LEFT, T_RIGHT)
    img = traverse["left"][0]
    with pytest.raises(InputError, match="shape"):
        vo.update(img[:-1], traverse["right"][0][:-1])
    with pytest.raises(InputError, match="shape"):
        vo.update(img, traverse["right"][0][:, :-1])
    with pytest.raises(InputError, match="uint8"):
        vo.update(img.astype(np.float32), traverse["right"][0])
    with pytest.raises(InputError, match="shape"):
        vo.update(np.dstack([img] * 3), traverse["right"][0])
    with pytest.raises(InputError, match="numpy"):
        vo.update(img.tolist(), traverse["right"][0])
    vo.update(img, traverse["right"][0])
    prior = np.eye(4)
    prior[0, 3] = np.nan
    with pytest.raises(InputError, match="NaN"):
        vo.update(img, traverse["right"][0], prior)
    with pytest.raises(InputError, match="4x4"):
        vo.update(img, traverse["right"][0], np.eye(3))
    with pytest.raises(InputError, match="rigid"):
        vo.update(img, traverse["right"][0], 2 * np.eye(4))
    assert vo.n_frames == 1  # rejected calls change nothing


def test_rig_must_be_rectified():
    with pytest.raises(InputError, match="rectified"):
        StereoVisualOdometry(CAMERA, T_LEFT, T_LEFT)
    tilted = T_RIGHT @ pose_to_matrix(0, 0, 0, 0, np.radians(2), 0)
    with pytest.raises(InputError, match="rectified"):
        StereoVisualOdometry(CAMERA, T_LEFT, tilted)
    with pytest.raises(InputError, match="rectified"):
        StereoVisualOdometry(CAMERA, T_RIGHT, T_LEFT)  # swapped: negative baseline
    with pytest.raises(InputError):
        StereoVisualOdometry((W, H), T_LEFT, T_RIGHT)


def test_config_round_trip_and_validation():
    cfg = VisualOdometryConfig(max_features=300, lk_window_px=11)
    assert VisualOdometryConfig.from_dict(cfg.to_dict()) == cfg
    with pytest.raises(ConfigError, match="unknown"):
        VisualOdometryConfig.from_dict({"max_featurez": 3})
    with pytest.raises(ConfigError, match="min_inliers"):
        VisualOdometryConfig(min_inliers=2)
    with pytest.raises(ConfigError, match="max_depth_m"):
        VisualOdometryConfig(max_depth_m=0.1, min_depth_m=0.3)
    with pytest.raises(ConfigError, match="step_sigma_floor_px"):
        VisualOdometryConfig(step_sigma_floor_px=0)


def test_archive_without_front_images_is_refused(tmp_path):
    from lunarloc.io.lac.archive import LacArchive, LacWriter

    cams = {
        n: {"camera_active": False, "width": W, "height": H} for n in ("FrontLeft", "FrontRight")
    }
    path = tmp_path / "noimg.lac"
    with LacWriter(path, {"lander": [0.0] * 6, "rover": [0.0] * 6, "cameras": cams}) as w:
        w.add_frame(0, x=0.0, y=0.0, z=0.0, roll=0.0, pitch=0.0, yaw=0.0)
    with LacArchive(path) as a, pytest.raises(InputError, match="FrontLeft"):
        visual_odometry_frames(a)


def test_local_contrast_removes_the_flow_bias_of_a_camera_fixed_light():
    """A texture moving 3 px down under a light cone fixed to the camera (the rover's lamps):
    raw Lucas-Kanade under-reads the motion (the static brightness gradient pulls the flow
    toward zero); on local-contrast images the bias nearly vanishes."""
    import cv2

    w, h, shift = 640, 360, 3.0
    camera = PinholeCamera(w, h)
    rig = ipex_rig(camera)
    rng = np.random.default_rng(1)
    big = cv2.GaussianBlur(rng.uniform(0, 1, (h + 40, w + 40)).astype(np.float32), (0, 0), 1.5)
    big = (big - big.min()) / (big.max() - big.min())
    y, x = np.mgrid[0:h, 0:w].astype(np.float32)
    cone = np.exp(-((x - w / 2) ** 2 / (2 * 200**2) + (y - h) ** 2 / (2 * 150**2)))
    moved = cv2.warpAffine(
        big, np.float32([[1, 0, 0], [0, 1, shift]]), (w + 40, h + 40), flags=cv2.INTER_CUBIC
    )
    # albedo 150 +- 50 grey levels times the cone: nothing saturates
    a, b = (
        np.clip(10 + cone * (150 + 100 * (t[20 : 20 + h, 20 : 20 + w] - 0.5)), 0, 255).astype(
            np.uint8
        )
        for t in (big, moved)
    )
    pts = cv2.goodFeaturesToTrack(a, 400, 0.01, 10).reshape(-1, 2)
    pts = pts[
        (pts[:, 1] > 40) & (pts[:, 1] < h - 40) & (pts[:, 0] > 40) & (pts[:, 0] < w - 40)
    ].astype(np.float32)
    bias = {}
    for norm in ("none", "local-contrast"):
        vo = StereoVisualOdometry(
            camera,
            rig["FrontLeft"].T_rover_optical,
            rig["FrontRight"].T_rover_optical,
            VisualOdometryConfig(normalization=norm),
        )
        uv, st, _ = cv2.calcOpticalFlowPyrLK(
            vo._normalize(a), vo._normalize(b), pts, None, **vo._lk
        )
        ok = st.ravel() == 1
        assert ok.sum() > 200
        bias[norm] = float((uv - pts)[ok, 1].mean()) - shift
    assert bias["none"] < -0.04  # measured -0.087 px: 3 % of the motion
    assert abs(bias["local-contrast"]) < 0.005  # measured -0.0002 px


def test_normalization_is_a_checked_enum_that_round_trips():
    from lunarloc.perception.images import ImageNormalization

    cfg = VisualOdometryConfig(normalization="clahe")
    assert cfg.normalization is ImageNormalization.CLAHE
    assert VisualOdometryConfig.from_dict(cfg.to_dict()) == cfg
    assert cfg.to_dict()["normalization"] == "clahe"
    with pytest.raises(ConfigError, match="normalization.*local-contrast"):
        VisualOdometryConfig(normalization="histogram")
    with pytest.raises(ConfigError, match="gravity_tilt_gain"):
        VisualOdometryConfig(gravity_tilt_gain=2.0)
    img = np.full((H, W), 90, np.uint8)
    vo = StereoVisualOdometry(CAMERA, T_LEFT, T_RIGHT, VisualOdometryConfig(normalization="none"))
    assert vo._normalize(img) is img
    out = StereoVisualOdometry(CAMERA, T_LEFT, T_RIGHT)._normalize(img)
    assert (
        out.dtype == np.uint8 and out.shape == img.shape and np.all(out == 128)
    )  # flat: no contrast


def test_step_covariance_is_given_for_visual_steps_and_covers_the_errors(traverse):
    """`last_step_covariance` (6x6, previous rover frame) exists exactly for visual steps and
    its translation sigma is of the order of the step's actual error."""
    left, right, truth = traverse["left"], traverse["right"], traverse["truth"]
    vo = StereoVisualOdometry(CAMERA, T_LEFT, T_RIGHT)
    vo.update(left[0], right[0])
    assert vo.last_step_covariance is None  # the first pair has no step
    ratios = []
    T_prev = np.eye(4)
    for k in range(1, len(left)):
        T = vo.update(left[k], right[k])
        assert vo.last_ok
        C = vo.last_step_covariance
        assert C.shape == (6, 6) and np.allclose(C, C.T)
        assert np.all(np.linalg.eigvalsh(C) > 0)
        true_step = invert_transform(truth[k - 1]) @ truth[k]
        err = (invert_transform(T_prev) @ T)[:3, 3] - true_step[:3, 3]
        ratios.append(float(np.sqrt(err @ np.linalg.solve(C[:3, :3], err))))
        T_prev = T
    # Mahalanobis distance of the translation error: neither far too small nor far too large
    assert 0.1 < np.median(ratios) < 10.0
    black = np.zeros((H, W), np.uint8)
    vo.update(black, black)
    assert not vo.last_ok and vo.last_step_covariance is None
