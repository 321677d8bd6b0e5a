"""Stereo visual odometry from a rectified stereo pair (the rover's front IPEx cameras).

Method (keyframe-to-frame, OpenCV)
----------------------------------
1. **Keyframe**: Shi-Tomasi corners (``goodFeaturesToTrack``) in the left image,
   outside the sky mask (near-black pixels, dilated, so the horizon silhouette
   is left out too) and an optional band of rows hiding the rover's body. Each
   corner is matched into the right image by pyramidal Lucas-Kanade along the
   row (rectified pair: the match must stay on the same row, have a positive
   disparity and pass a right-to-left check) and triangulated,
   ``z = fx * baseline / disparity`` (metres, left optical frame).
2. **Tracking**: the keyframe corners are followed frame to frame in the left
   images by pyramidal LK, seeded with the positions predicted from the motion
   prior (IMU/wheels: the gyro makes fast turns trackable) or, without one, a
   constant-velocity model; a forward-backward check drops bad tracks.
3. **Pose**: ``solvePnPRansac`` between the keyframe's 3D points and their
   current pixels gives the current camera pose relative to the keyframe
   (tracking relative to the keyframe, not chained frame to frame, keeps the
   drift of a stationary or slow rover from growing every frame); the inliers
   are refined with Levenberg-Marquardt (``solvePnPRefineLM``).
4. **Checks and fallback**: too few inliers, a low inlier ratio, an implausible
   step, or a rotation that disagrees with the prior's (gyro) rotation reject the
   estimate; the pose then advances by the prior (or holds without one),
   ``last_ok`` is False and a new keyframe is started. A new keyframe is also
   started when the tracked inliers thin out.
5. **Step covariance**: each visual step's 6x6 covariance from its PnP inliers (track noise
   and keyframe depth error through the pose Jacobian), ``last_step_covariance``, for a
   pose graph to weigh the step by.

Frames: the camera optical frame is OpenCV's (z forward, x right, y down); the
rover frame is the LAC's (x forward, y left, z up). ``T_rover_left`` maps
left-optical points into the rover frame. The odometry frame ``odo`` is the
rover pose at the first pair (or at the last :meth:`StereoVisualOdometry.reset`).
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import asdict, dataclass, fields

import numpy as np

from lunarloc.core.errors import ConfigError, InputError, import_cv2
from lunarloc.core.geometry import invert_transform, make_transform, rotation_angle
from lunarloc.perception.camera import PinholeCamera
from lunarloc.perception.images import ImageNormalization, normalize_image

__all__ = [
    "VisualOdometryConfig",
    "StereoVisualOdometry",
    "front_pair_setup",
    "visual_odometry_frames",
]

logger = logging.getLogger(__name__)
logger.addHandler(logging.NullHandler())


@dataclass(frozen=True)
class VisualOdometryConfig:
    """Tuning constants of :class:`StereoVisualOdometry` (pixels at the images' resolution)."""

    # -- features (keyframes)
    max_features: int = 600  # corners detected per keyframe
    feature_quality: float = 0.001  # goodFeaturesToTrack qualityLevel (fraction of the best corner)
    min_feature_distance_frac: float = (
        0.012  # min distance between corners, fraction of the image width
    )
    border_px: int = 8  # corners closer than this to the image border are not used
    # applied before detection, stereo and tracking
    normalization: ImageNormalization = ImageNormalization.LOCAL_CONTRAST
    normalization_sigma_frac: float = (
        0.01  # local-contrast: Gaussian sigma, fraction of the image width ...
    )
    normalization_min_sigma_px: float = (
        6.0  # ... and at least this (small images: a tiny sigma keeps only noise)
    )
    normalization_gain: float = (
        255.0  # local-contrast: grey levels per unit of relative contrast (centred on 128)
    )
    detect_max_width_px: int = (
        640  # corners are detected on the image reduced to at most this width
    )
    sky_threshold: int = 6  # pixels at or below this grey level are sky (or unlit void)
    sky_dilate_frac: float = 0.01  # grow the sky mask by this fraction of the width (horizon edge)
    body_mask_bottom_frac: float = (
        0.0  # rows hidden at the image bottom (rover body), fraction of height
    )
    # -- stereo (LK along the row; a flat window because the ground's disparity grows
    # ~0.5 px per image row at the IPEx camera height, which a square window smears)
    stereo_window_width_px: int = 21
    stereo_window_height_px: int = 7
    stereo_max_level: int = 3
    stereo_max_row_error_px: float = 1.0  # a rectified match stays on its row
    stereo_check_px: float = 0.5  # right-to-left LK must return within this
    min_disparity_px: float = 1.0  # smaller disparities (far points) are not triangulated
    max_depth_m: float = 40.0  # points farther than this are dropped
    min_depth_m: float = 0.3  # and nearer than this
    # -- tracking
    lk_window_px: int = (
        15  # Lucas-Kanade window side (larger windows smear the ground's perspective change)
    )
    lk_max_level: int = 4  # pyramid levels above the full image
    lk_iterations: int = 30
    fb_check_px: float = 1.0  # forward-backward tracking error allowed
    # -- pose
    ransac_reprojection_px: float = 2.5  # PnP RANSAC inlier threshold
    ransac_iterations: int = 200
    ransac_confidence: float = 0.999
    min_inliers: int = 25  # fewer PnP inliers: fall back to the prior
    min_inlier_ratio: float = 0.35  # inliers / tracked points below this: fall back
    max_translation_per_frame_m: float = 1.0  # larger steps are rejected as failures
    max_rotation_per_frame_deg: float = 45.0
    max_prior_rotation_gap_deg: float = (
        5.0  # visual vs prior rotation disagreement that rejects the visual step
    )
    # the step's covariance (last_step_covariance): track noise floor and stereo disparity noise
    step_sigma_floor_px: float = 0.3
    stereo_disparity_sigma_px: float = 0.2
    step_sigma_scale: float = 2.0  # x the modelled sigma (errors the model leaves out, measured)
    # -- keyframes
    keyframe_min_tracked: int = 120  # re-detect when fewer keyframe points remain inliers
    keyframe_min_fraction: float = 0.5  # ... or fewer than this fraction of the keyframe's points
    keyframe_max_translation_m: float = (
        1.5  # ... or the rover moved farther than this from the keyframe
    )
    constant_velocity: bool = True  # without a prior, predict the next pose by the last motion
    # -- fusion with the IMU (lunarloc.odometry.tilt.GravityAlignedChain, used where an IMU
    # attitude exists: archive odometry and the online component; the class itself ignores it)
    gravity_tilt_gain: float = 1.0  # 1: roll and pitch from gravity at every pair; 0: purely visual

    def __post_init__(self) -> None:
        try:
            object.__setattr__(self, "normalization", ImageNormalization(self.normalization))
        except ValueError:
            raise ConfigError(
                f"VisualOdometryConfig: normalization={self.normalization!r}; choose one of "
                f"{', '.join(m.value for m in ImageNormalization)}"
            ) from None
        checks = {
            "normalization_sigma_frac": 0 < self.normalization_sigma_frac < 0.5,
            "normalization_min_sigma_px": 0 < self.normalization_min_sigma_px < 1e3,
            "normalization_gain": 0 < self.normalization_gain < 1e4,
            "max_features": self.max_features >= 8,
            "feature_quality": 0 < self.feature_quality < 1,
            "min_feature_distance_frac": 0 <= self.min_feature_distance_frac < 0.5,
            "border_px": self.border_px >= 0,
            "detect_max_width_px": self.detect_max_width_px >= 64,
            "sky_threshold": 0 <= self.sky_threshold < 255,
            "sky_dilate_frac": 0 <= self.sky_dilate_frac < 0.5,
            "body_mask_bottom_frac": 0 <= self.body_mask_bottom_frac < 1,
            "stereo_max_row_error_px": self.stereo_max_row_error_px > 0,
            "stereo_check_px": self.stereo_check_px > 0,
            "min_disparity_px": self.min_disparity_px > 0,
            "max_depth_m": self.max_depth_m > self.min_depth_m > 0,
            "lk_window_px": self.lk_window_px >= 5,
            "stereo_window_width_px": self.stereo_window_width_px >= 3,
            "stereo_window_height_px": self.stereo_window_height_px >= 3,
            "stereo_max_level": 0 <= self.stereo_max_level <= 8,
            "lk_max_level": 0 <= self.lk_max_level <= 8,
            "lk_iterations": self.lk_iterations >= 1,
            "fb_check_px": self.fb_check_px > 0,
            "ransac_reprojection_px": self.ransac_reprojection_px > 0,
            "ransac_iterations": self.ransac_iterations >= 1,
            "ransac_confidence": 0 < self.ransac_confidence < 1,
            "min_inliers": self.min_inliers >= 6,
            "min_inlier_ratio": 0 <= self.min_inlier_ratio <= 1,
            "max_translation_per_frame_m": self.max_translation_per_frame_m > 0,
            "max_rotation_per_frame_deg": 0 < self.max_rotation_per_frame_deg <= 180,
            "max_prior_rotation_gap_deg": self.max_prior_rotation_gap_deg > 0,
            "step_sigma_floor_px": self.step_sigma_floor_px > 0,
            "stereo_disparity_sigma_px": self.stereo_disparity_sigma_px >= 0,
            "step_sigma_scale": self.step_sigma_scale > 0,
            "keyframe_min_tracked": self.keyframe_min_tracked >= self.min_inliers,
            "keyframe_min_fraction": 0 <= self.keyframe_min_fraction <= 1,
            "keyframe_max_translation_m": self.keyframe_max_translation_m > 0,
            "gravity_tilt_gain": 0 <= self.gravity_tilt_gain <= 1,
        }
        bad = [k for k, ok in checks.items() if not ok]
        if bad:
            raise ConfigError(
                "VisualOdometryConfig: invalid "
                f"{', '.join(f'{k}={getattr(self, k)!r}' for k in bad)}"
            )

    def to_dict(self) -> dict:
        return {**asdict(self), "normalization": self.normalization.value}

    @classmethod
    def from_dict(cls, data: dict) -> VisualOdometryConfig:
        names = {f.name for f in fields(cls)}
        unknown = sorted(set(data) - names)
        if unknown:
            raise ConfigError(f"VisualOdometryConfig: unknown key(s) {', '.join(unknown)}")
        return cls(**data)


def _as_transform(T, name: str) -> np.ndarray:
    arr = np.asarray(T, dtype=float) if T is not None else None
    if arr is None or arr.shape != (4, 4):
        raise InputError(
            f"{name} must be a 4x4 transform, got {None if arr is None else arr.shape}"
        )
    if not np.all(np.isfinite(arr)):
        raise InputError(f"{name} contains NaN or infinite values")
    R = arr[:3, :3]
    if (
        not np.allclose(R.T @ R, np.eye(3), atol=1e-5)
        or np.linalg.det(R) < 0
        or not np.allclose(arr[3], [0, 0, 0, 1])
    ):
        raise InputError(
            f"{name} is not a rigid transform (rotation not orthonormal or bottom row not 0 0 0 1)"
        )
    return arr


def _orthonormal(R: np.ndarray) -> np.ndarray:
    """Nearest rotation matrix (SVD)."""
    U, _, Vt = np.linalg.svd(R)
    return U @ np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))]) @ Vt


@dataclass
class _Keyframe:
    """Points triangulated at a keyframe, with their tracks in the latest image."""

    T_odo_rover: np.ndarray  # keyframe rover pose in the odometry frame
    points_kf: np.ndarray  # (N, 3) float32 left-optical coordinates at the keyframe, metres
    uv: np.ndarray  # (N, 2) float32 pixel positions in the most recent left image
    n_initial: int


class StereoVisualOdometry:
    """Frame-by-frame stereo visual odometry (see the module docstring for the method).

    Parameters
    ----------
    camera : intrinsics of both (rectified, identical) cameras.
    T_rover_left, T_rover_right : 4x4 optical-frame poses of the left and right
        camera in the rover frame (:attr:`CameraMount.T_rover_optical`); the right
        camera must sit on the left one's +x axis with the same orientation.
    config : tuning constants.
    """

    def __init__(
        self,
        camera: PinholeCamera,
        T_rover_left: np.ndarray,
        T_rover_right: np.ndarray,
        config: VisualOdometryConfig | None = None,
    ):
        cv2 = import_cv2()
        self._cv2 = cv2
        if not isinstance(camera, PinholeCamera):
            raise InputError(f"camera must be a PinholeCamera, got {type(camera).__name__}")
        self.camera = camera
        self.config = config or VisualOdometryConfig()
        self.T_rover_left = _as_transform(T_rover_left, "T_rover_left")
        T_rover_right = _as_transform(T_rover_right, "T_rover_right")
        T_left_right = invert_transform(self.T_rover_left) @ T_rover_right
        self.baseline_m = float(T_left_right[0, 3])
        if (
            rotation_angle(T_left_right[:3, :3]) > np.radians(0.1)
            or self.baseline_m <= 0
            or np.hypot(T_left_right[1, 3], T_left_right[2, 3]) > 1e-3 * max(self.baseline_m, 1e-9)
        ):
            raise InputError(
                "the stereo pair is not rectified: the right camera must be parallel to the left "
                "one and offset along its +x axis (got offset "
                f"{np.round(T_left_right[:3, 3], 4).tolist()} m)"
            )
        self.T_left_rover = invert_transform(self.T_rover_left)
        self.K = camera.K
        c = self.config
        self._lk = {
            "winSize": (c.lk_window_px, c.lk_window_px),
            "maxLevel": c.lk_max_level,
            "criteria": (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, c.lk_iterations, 0.01),
        }
        self._lk_stereo = {
            "winSize": (c.stereo_window_width_px, c.stereo_window_height_px),
            "maxLevel": c.stereo_max_level,
            "criteria": self._lk["criteria"],
        }
        self._dilate = None
        self._clahe = None
        self._raw_left = None
        self.reset()

    # -- public --------------------------------------------------------------------------
    def reset(self) -> None:
        """Forget all state: the next pair starts a new odometry frame."""
        self.T_odo_rover = np.eye(4)
        self.last_ok = False
        self.n_frames = 0
        self.n_keyframes = 0
        self._kf: _Keyframe | None = None
        self._prev_left = None
        self._last_motion = np.eye(4)  # rover motion of the last frame (constant-velocity model)
        self.last_inliers = 0
        # the last visual step's covariance inputs, and the covariance once computed from them
        # (last_step_covariance: computed when read, so trackers that never read it skip it)
        self._step_inputs: tuple | None = None
        self._step_cov: np.ndarray | None = None

    @property
    def last_step_covariance(self) -> np.ndarray | None:
        """6x6 covariance of the last pair's visual step (:meth:`_step_covariance`; None: not a
        visual step)."""
        if self._step_inputs is not None:
            self._step_cov = self._step_covariance(*self._step_inputs)
            self._step_inputs = None
        return self._step_cov

    def update(
        self, left: np.ndarray, right: np.ndarray, prior_T_prev_curr: np.ndarray | None = None
    ) -> np.ndarray:
        """Add one rectified stereo pair; return ``T_odo_rover`` (4x4) at this pair.

        `prior_T_prev_curr` is the rover motion since the previous pair from another
        sensor (IMU/wheels), used to predict the tracks, to check the visual rotation,
        and as the estimate when vision fails. Without it a failed frame holds the pose.
        """
        raw_left, right = self._check_images(left, right)
        prior = (
            None
            if prior_T_prev_curr is None
            else _as_transform(prior_T_prev_curr, "prior_T_prev_curr")
        )
        left, right = self._normalize(raw_left), self._normalize(right)
        self._raw_left = raw_left  # the sky mask is taken from the raw image
        first = self.n_frames == 0
        self.n_frames += 1
        if first:
            self.last_ok = self._new_keyframe(left, right, np.eye(4))
            self._prev_left = left
            return self.T_odo_rover.copy()
        T_prev = self.T_odo_rover
        predicted = (
            prior
            if prior is not None
            else (self._last_motion if self.config.constant_velocity else np.eye(4))
        )
        self._step_inputs = self._step_cov = None
        T_new = self._track(left, T_prev @ predicted, prior)
        if T_new is None:
            T_new = T_prev @ (prior if prior is not None else np.eye(4))
            self.last_ok = False
            self._new_keyframe(left, right, T_new)
        else:
            self.last_ok = True
            kf = self._kf
            if (
                self.last_inliers < self.config.keyframe_min_tracked
                or self.last_inliers < self.config.keyframe_min_fraction * kf.n_initial
                or np.linalg.norm(
                    invert_transform(kf.T_odo_rover)[:3, :3]
                    @ (T_new[:3, 3] - kf.T_odo_rover[:3, 3])
                )
                > self.config.keyframe_max_translation_m
            ):
                self._new_keyframe(left, right, T_new)
        T_new = make_transform(_orthonormal(T_new[:3, :3]), T_new[:3, 3])  # no round-off build-up
        self._last_motion = invert_transform(T_prev) @ T_new
        self.T_odo_rover = T_new
        self._prev_left = left
        return T_new.copy()

    # -- steps -----------------------------------------------------------------------------
    def _check_images(self, left, right) -> tuple[np.ndarray, np.ndarray]:
        H, W = self.camera.height, self.camera.width
        out = []
        for name, img in (("left", left), ("right", right)):
            if not isinstance(img, np.ndarray):
                raise InputError(f"{name} image must be a numpy array, got {type(img).__name__}")
            if img.dtype != np.uint8:
                raise InputError(f"{name} image must be uint8 grayscale, got dtype {img.dtype}")
            if img.shape != (H, W):
                raise InputError(
                    f"{name} image must have shape ({H}, {W}) for this camera, got {img.shape}"
                )
            out.append(np.ascontiguousarray(img))
        return out[0], out[1]

    def _normalize(self, image: np.ndarray) -> np.ndarray:
        """`image` after :class:`ImageNormalization` (uint8, same shape)."""
        c = self.config
        if c.normalization is ImageNormalization.CLAHE and self._clahe is None:
            self._clahe = self._cv2.createCLAHE(clipLimit=2.0, tileGridSize=(8, 8))
        sigma = max(c.normalization_min_sigma_px, c.normalization_sigma_frac * image.shape[1])
        return normalize_image(image, c.normalization, sigma, c.normalization_gain, self._clahe)

    def _feature_mask(self, image: np.ndarray, scale: int) -> np.ndarray:
        """Where corners may be detected in `image` (the left image reduced `scale` times)."""
        cv2, c = self._cv2, self.config
        H, W = image.shape
        sky = (image <= c.sky_threshold).astype(np.uint8)
        r = int(round(c.sky_dilate_frac * W))
        if r > 0:
            if self._dilate is None or self._dilate.shape[0] != 2 * r + 1:
                self._dilate = cv2.getStructuringElement(cv2.MORPH_RECT, (2 * r + 1, 2 * r + 1))
            sky = cv2.dilate(sky, self._dilate)
        mask = (sky == 0).astype(np.uint8) * 255
        b = int(np.ceil(c.border_px / scale))
        if b > 0:
            mask[:b] = 0
            mask[-b:] = 0
            mask[:, :b] = 0
            mask[:, -b:] = 0
        body = int(round(c.body_mask_bottom_frac * H))
        if body > 0:
            mask[H - body :] = 0
        return mask

    def _detect(self, left: np.ndarray) -> np.ndarray | None:
        """(N, 2) float32 corners of the left image, detected at most `detect_max_width_px` wide
        (where a corner lies matters little: LK follows the patch around it)."""
        cv2, c = self._cv2, self.config
        H, W = left.shape
        scale = max(1, int(np.ceil(W / c.detect_max_width_px)))

        def reduce(img):
            return (
                img
                if scale == 1
                else cv2.resize(img, (W // scale, H // scale), interpolation=cv2.INTER_AREA)
            )

        small = reduce(left)
        mask = self._feature_mask(
            reduce(self._raw_left if self._raw_left is not None else left), scale
        )
        corners = cv2.goodFeaturesToTrack(
            small,
            c.max_features,
            c.feature_quality,
            max(1.0, c.min_feature_distance_frac * small.shape[1]),
            mask=mask,
        )
        if corners is None:
            return None
        uv = corners.reshape(-1, 2).astype(np.float32)
        return uv if scale == 1 else uv * scale + (scale - 1) / 2.0

    def _new_keyframe(self, left, right, T_odo_rover) -> bool:
        """Detect and triangulate keyframe points; False (and no keyframe) when too few."""
        cv2, c = self._cv2, self.config
        self.n_keyframes += 1
        self._kf = None
        uv_l = self._detect(left)
        if uv_l is None or len(uv_l) < c.min_inliers:
            return False
        # Right image: same row, shifted left by the disparity; seed with a typical disparity.
        fx, b = self.camera.fx, self.baseline_m
        seed_disp = fx * b / 4.0  # a point 4 m ahead
        guess = uv_l.copy()
        # float64 arithmetic, cast back (numpy 2 does so for a float64 scalar; numpy 1 kept float32)
        guess[:, 0] = guess[:, 0].astype(np.float64) - seed_disp
        uv_r, st, _ = cv2.calcOpticalFlowPyrLK(
            left, right, uv_l, guess.copy(), flags=cv2.OPTFLOW_USE_INITIAL_FLOW, **self._lk_stereo
        )
        back, st2, _ = cv2.calcOpticalFlowPyrLK(
            right, left, uv_r, uv_l.copy(), flags=cv2.OPTFLOW_USE_INITIAL_FLOW, **self._lk_stereo
        )
        disp = uv_l[:, 0] - uv_r[:, 0]
        ok = (
            (st.ravel() == 1)
            & (st2.ravel() == 1)
            & (np.abs(uv_r[:, 1] - uv_l[:, 1]) <= c.stereo_max_row_error_px)
            & (np.linalg.norm(back - uv_l, axis=1) <= c.stereo_check_px)
            & (disp >= c.min_disparity_px)
        )
        # float64 on numpy 1 too
        depth = np.where(ok, fx * b / np.maximum(disp.astype(np.float64), 1e-6), np.inf)
        ok &= (depth >= c.min_depth_m) & (depth <= c.max_depth_m)
        if ok.sum() < c.min_inliers:
            return False
        # Average the row of the two views (rectified: both measure the same row).
        uv = np.column_stack([uv_l[ok, 0], 0.5 * (uv_l[ok, 1] + uv_r[ok, 1])])
        pts = self.camera.backproject(uv, depth[ok]).astype(np.float32)
        self._kf = _Keyframe(T_odo_rover.copy(), pts, uv_l[ok].copy(), int(ok.sum()))
        self.last_inliers = int(ok.sum())
        return True

    def _project(self, points_kf: np.ndarray, T_cur_kf_opt: np.ndarray) -> np.ndarray:
        P = points_kf @ T_cur_kf_opt[:3, :3].T + T_cur_kf_opt[:3, 3]
        z = np.maximum(P[:, 2], 1e-3)
        return np.column_stack(
            [
                self.camera.fx * P[:, 0] / z + self.camera.cx,
                self.camera.fy * P[:, 1] / z + self.camera.cy,
            ]
        )

    def _rover_to_optical(self, T_rover_a_b: np.ndarray) -> np.ndarray:
        """Rover motion (rover frame a -> b) as the left camera's motion (optical a -> b)."""
        return self.T_left_rover @ T_rover_a_b @ self.T_rover_left

    def _track(self, image, T_odo_pred: np.ndarray, prior: np.ndarray | None) -> np.ndarray | None:
        """Track the keyframe points into the new image; the new T_odo_rover or None on failure."""
        cv2, c = self._cv2, self.config
        kf = self._kf
        if kf is None or self._prev_left is None or len(kf.points_kf) < c.min_inliers:
            return None
        # Predicted left-camera pose of the keyframe seen from the current frame.
        T_kf_cur_pred = self._rover_to_optical(invert_transform(kf.T_odo_rover) @ T_odo_pred)
        T_cur_kf_pred = invert_transform(T_kf_cur_pred)
        T_prev_kf = invert_transform(
            self._rover_to_optical(invert_transform(kf.T_odo_rover) @ self.T_odo_rover)
        )
        # Seed each track with its last position plus the predicted image shift (a
        # shift, not an absolute projection, so a point's depth error does not bias it).
        prev_uv = kf.uv
        shift = self._project(kf.points_kf, T_cur_kf_pred) - self._project(kf.points_kf, T_prev_kf)
        guess = (prev_uv + shift).astype(np.float32)
        uv, st, _ = cv2.calcOpticalFlowPyrLK(
            self._prev_left,
            image,
            prev_uv,
            guess.copy(),
            flags=cv2.OPTFLOW_USE_INITIAL_FLOW,
            **self._lk,
        )
        back, st2, _ = cv2.calcOpticalFlowPyrLK(
            image,
            self._prev_left,
            uv,
            prev_uv.copy(),
            flags=cv2.OPTFLOW_USE_INITIAL_FLOW,
            **self._lk,
        )
        H, W = self.camera.height, self.camera.width
        ok = (
            (st.ravel() == 1)
            & (st2.ravel() == 1)
            & (np.linalg.norm(back - prev_uv, axis=1) <= c.fb_check_px)
            & (uv[:, 0] >= 0)
            & (uv[:, 0] <= W - 1)
            & (uv[:, 1] >= 0)
            & (uv[:, 1] <= H - 1)
        )
        n = int(ok.sum())
        if n < c.min_inliers:
            logger.debug("frame %d: %d tracks, too few", self.n_frames, n)
            return None
        obj = kf.points_kf[ok].astype(np.float64)
        img = uv[ok].astype(np.float64)
        rvec0, _ = cv2.Rodrigues(T_cur_kf_pred[:3, :3])
        tvec0 = T_cur_kf_pred[:3, 3].reshape(3, 1).copy()
        found, rvec, tvec, inl = cv2.solvePnPRansac(
            obj,
            img,
            self.K,
            None,
            rvec0.copy(),
            tvec0.copy(),
            useExtrinsicGuess=False,
            iterationsCount=c.ransac_iterations,
            reprojectionError=c.ransac_reprojection_px,
            confidence=c.ransac_confidence,
            flags=cv2.SOLVEPNP_P3P,
        )
        if (
            not found
            or inl is None
            or len(inl) < c.min_inliers
            or len(inl) < c.min_inlier_ratio * n
        ):
            logger.debug(
                "frame %d: PnP failed (%s inliers of %d)",
                self.n_frames,
                None if inl is None else len(inl),
                n,
            )
            return None
        inl = inl.ravel()
        # Refine on the inliers, then re-select them with the refined pose (the RANSAC
        # model comes from a minimal sample and under-counts), and refine once more.
        for _ in range(2):
            rvec, tvec = cv2.solvePnPRefineLM(obj[inl], img[inl], self.K, None, rvec, tvec)
            proj, _ = cv2.projectPoints(obj, rvec, tvec, self.K, None)
            inl = np.flatnonzero(
                np.linalg.norm(proj.reshape(-1, 2) - img, axis=1) <= c.ransac_reprojection_px
            )
            if len(inl) < c.min_inliers:
                return None
        logger.debug(
            "frame %d: %d of %d keyframe points tracked, %d PnP inliers",
            self.n_frames,
            n,
            len(ok),
            len(inl),
        )
        R, _ = cv2.Rodrigues(rvec)
        T_cur_kf = make_transform(R, tvec.ravel())
        T_odo_new = (
            kf.T_odo_rover @ self.T_rover_left @ invert_transform(T_cur_kf) @ self.T_left_rover
        )
        step = invert_transform(self.T_odo_rover) @ T_odo_new
        if (
            np.linalg.norm(step[:3, 3]) > c.max_translation_per_frame_m
            or np.degrees(rotation_angle(step[:3, :3])) > c.max_rotation_per_frame_deg
        ):
            logger.debug("frame %d: implausible step rejected", self.n_frames)
            return None
        if (
            prior is not None
            and np.degrees(rotation_angle(step[:3, :3].T @ prior[:3, :3]))
            > c.max_prior_rotation_gap_deg
        ):
            logger.debug("frame %d: visual rotation disagrees with the prior", self.n_frames)
            return None
        # Keep the inlier tracks only (outliers are moving shadows, bad depths, occlusions).
        keep = np.flatnonzero(ok)[inl]
        kf.points_kf = kf.points_kf[keep]
        kf.uv = uv[keep].astype(np.float32)
        self.last_inliers = len(inl)
        self._step_inputs = (
            obj[inl],
            img[inl],
            rvec,
            tvec,
            kf.T_odo_rover.copy(),
            invert_transform(self.T_odo_rover),
        )
        return T_odo_new

    def _step_covariance(self, obj, img, rvec, tvec, T_odo_kf, T_rover_prev) -> np.ndarray | None:
        """6x6 covariance of this pair's rover motion since the previous pair (translation x,
        y, z in m, then rotation vector in rad, both in the previous rover frame), from the
        PnP inliers: each track's pixel noise (their residuals' spread, at least
        `step_sigma_floor_px`) plus its keyframe depth's error along the ray (disparity
        error `stereo_disparity_sigma_px`: far points weigh little), through the pose's
        Jacobian. The keyframe's pose is taken as exact, so a step from a keyframe older than
        the previous pair carries the whole keyframe-to-pair uncertainty. `T_rover_prev`: the
        previous pair's pose, inverted."""
        cv2, c = self._cv2, self.config
        proj, J = cv2.projectPoints(obj, rvec, tvec, self.K, None)
        J = J[:, :6].reshape(-1, 2, 6)  # per point: d(u, v) / d(rvec, tvec)
        r = proj.reshape(-1, 2) - img
        dof = max(2 * len(obj) - 6, 1)
        s2 = max(float(np.sum(r**2)) / dof, c.step_sigma_floor_px**2)
        R, _ = cv2.Rodrigues(rvec)
        P = obj @ R.T + np.ravel(tvec)  # points in the current left camera, m
        z = np.maximum(P[:, 2], 1e-6)
        fx, fy = self.camera.fx, self.camera.fy
        Jp = np.zeros((len(P), 2, 3))  # d(u, v) / d(point)
        Jp[:, 0, 0], Jp[:, 0, 2] = fx / z, -fx * P[:, 0] / z**2
        Jp[:, 1, 1], Jp[:, 1, 2] = fy / z, -fy * P[:, 1] / z**2
        z_kf = np.maximum(obj[:, 2], 1e-6)
        g = np.einsum("nij,nj->ni", Jp, (obj / z_kf[:, None]) @ R.T)  # pixels per metre of depth
        sz = z_kf**2 / (fx * self.baseline_m) * c.stereo_disparity_sigma_px
        C = s2 * np.eye(2) + (sz**2)[:, None, None] * np.einsum("ni,nj->nij", g, g)
        info = np.einsum("nki,nkl,nlj->ij", J, np.linalg.inv(C), J)
        try:
            cov_pose = np.linalg.inv(info)
        except np.linalg.LinAlgError:
            return None

        def step(x):
            R, _ = cv2.Rodrigues(x[:3].reshape(3, 1))
            T = T_odo_kf @ self.T_rover_left @ invert_transform(make_transform(R, x[3:]))
            S = T_rover_prev @ T @ self.T_left_rover
            w, _ = cv2.Rodrigues(np.ascontiguousarray(S[:3, :3]))
            return np.r_[S[:3, 3], w.ravel()]

        x0 = np.r_[np.ravel(rvec), np.ravel(tvec)].astype(float)
        f0, eps = step(x0), 1e-6
        Js = np.column_stack([(step(x0 + eps * e) - f0) / eps for e in np.eye(6)])
        cov = c.step_sigma_scale**2 * (Js @ cov_pose @ Js.T)
        return 0.5 * (cov + cov.T) if np.all(np.isfinite(cov)) else None


def front_pair_setup(archive) -> tuple[PinholeCamera, np.ndarray, np.ndarray, str, str]:
    """Intrinsics and optical-frame mounts of an archive's front stereo pair.

    `archive` is a :class:`~lunarloc.io.lac.archive.LacArchive` or a
    :class:`~lunarloc.io.lac.playback.PlaybackAgent`. Intrinsics from ``initial.toml``,
    camera poses from each camera's first table row (the IPEx rig where a row has
    none), as the detector reads them. Returns ``(camera, T_rover_left,
    T_rover_right, left_name, right_name)``.
    """
    from lunarloc.perception.camera import STEREO_PAIRS
    from lunarloc.perception.camera import camera_from_archive, mounts_from_archive_row

    archive = getattr(archive, "archive", archive)
    left_name, right_name = STEREO_PAIRS[0]
    rows = {}
    for name in (left_name, right_name):
        table = archive.camera_frames(name) if name in archive.cameras else None
        if table is None or len(table) == 0:
            raise InputError(
                f"{archive.path}: no {name} images, visual odometry needs the front stereo pair"
            )
        rows[name] = table.row(0)
    camera = camera_from_archive(archive)
    mounts = mounts_from_archive_row(rows, camera)
    return (
        camera,
        mounts[left_name].T_rover_optical,
        mounts[right_name].T_rover_optical,
        left_name,
        right_name,
    )


def visual_odometry_frames(
    archive,
    config: VisualOdometryConfig | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Run :class:`StereoVisualOdometry` over the front-pair images of an archive (no prior).

    `archive` is a path, a :class:`~lunarloc.io.lac.archive.LacArchive` or a
    :class:`~lunarloc.io.lac.playback.PlaybackAgent`.
    Returns ``(frames (N,), T_odo_rover (N, 4, 4))`` for the N frames that have both
    a left and a right image; ``odo`` is the rover pose at the first of them.
    `progress(done, total)` is called after each pair.
    """
    import os

    if isinstance(archive, (str, os.PathLike)):
        from lunarloc.io.lac.archive import LacArchive

        with LacArchive(archive) as opened:
            return visual_odometry_frames(opened, config, progress)
    archive = getattr(archive, "archive", archive)
    camera, T_rover_left, T_rover_right, left_name, right_name = front_pair_setup(archive)
    frames = np.intersect1d(
        archive.camera_frames(left_name)["frame"], archive.camera_frames(right_name)["frame"]
    )
    frames = frames.astype(np.int64)
    vo = StereoVisualOdometry(camera, T_rover_left, T_rover_right, config)
    out = np.empty((len(frames), 4, 4))
    requests = [(cam, int(f), "grayscale") for f in frames for cam in (left_name, right_name)]
    # read in archive order, a few pairs at a time (forward-only decompression)
    chunk = 16
    for start in range(0, len(frames), chunk):
        part = frames[start : start + chunk]
        images = archive.read_images([r for r in requests[2 * start : 2 * (start + len(part))]])
        for i, f in enumerate(part):
            left = images.get((left_name, int(f), "grayscale"))
            right = images.get((right_name, int(f), "grayscale"))
            if left is None or right is None:
                raise InputError(
                    f"{archive.path}: frame {int(f)} lists a {left_name}/{right_name} image that "
                    "is missing"
                )
            out[start + i] = vo.update(left, right)
            if progress is not None:
                progress(start + i + 1, len(frames))
    return frames, out
