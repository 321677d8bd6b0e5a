"""Pinhole camera model and the LAC / IPEx camera rig.

Frames
------
* Rover frame (LAC): x forward, y left, z up; origin at the rover body centre.
* Camera body frame (LAC): same axes as the rover (x along the optical axis,
  y left, z up). `T_rover_cam` places it in the rover frame.
* Optical frame (OpenCV): z along the optical axis, x right, y down. Pixel
  coordinates (u, v): u to the right, v down, pixel centres on integers (as in
  OpenCV), so the principal point of a W x H image is ((W - 1) / 2, (H - 1) / 2).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from lunarloc.core.geometry import make_transform, pose_to_matrix

__all__ = [
    "PinholeCamera",
    "CameraMount",
    "T_CAM_OPTICAL",
    "IPEX_STEREO_BASELINE_M",
    "ipex_rig",
    "STEREO_PAIRS",
    "camera_from_archive",
    "mounts_from_archive_row",
]

# Optical frame axes expressed in the camera body frame: x_opt = -y_body,
# y_opt = -z_body, z_opt = x_body.
T_CAM_OPTICAL = make_transform(
    np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]]), np.zeros(3)
)

IPEX_STEREO_BASELINE_M = 0.162
"""Distance between the left and right cameras of each IPEx stereo pair."""

STEREO_PAIRS = (("FrontLeft", "FrontRight"), ("BackLeft", "BackRight"))
"""(left, right) camera names of the rover's stereo pairs; left is the reference image."""


@dataclass(frozen=True)
class PinholeCamera:
    """Ideal pinhole camera (the LAC cameras are simulated as perfect pinholes).

    Parameters
    ----------
    width, height : image size in pixels.
    hfov_deg : horizontal field of view in degrees (LAC: 70).
    """

    width: int = 1280
    height: int = 720
    hfov_deg: float = 70.0

    @property
    def fx(self) -> float:
        """Focal length in pixels (square pixels: fy == fx)."""
        return (self.width / 2.0) / np.tan(np.radians(self.hfov_deg) / 2.0)

    @property
    def fy(self) -> float:
        return self.fx

    @property
    def cx(self) -> float:
        return (self.width - 1) / 2.0

    @property
    def cy(self) -> float:
        return (self.height - 1) / 2.0

    @property
    def K(self) -> np.ndarray:
        """3x3 intrinsic matrix."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def alpha(self) -> float:
        """Angular resolution in radians per pixel at the image centre (1 / fx)."""
        return 1.0 / self.fx

    def project(self, points_optical: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Project (N, 3) optical-frame points to pixels. Returns (uv (N, 2), depth z (N,))."""
        P = np.asarray(points_optical, dtype=float).reshape(-1, 3)
        z = P[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = self.fx * P[:, 0] / z + self.cx
            v = self.fy * P[:, 1] / z + self.cy
        return np.stack([u, v], axis=1), z

    def backproject(self, uv: np.ndarray, depth: np.ndarray) -> np.ndarray:
        """Lift pixels with depth (z along the optical axis, metres) to (N, 3) optical-frame
        points."""
        uv = np.asarray(uv, dtype=float).reshape(-1, 2)
        z = np.asarray(depth, dtype=float).reshape(-1)
        x = (uv[:, 0] - self.cx) / self.fx * z
        y = (uv[:, 1] - self.cy) / self.fy * z
        return np.stack([x, y, z], axis=1)

    def rays_optical(self) -> np.ndarray:
        """(H, W, 3) unit ray directions of every pixel centre, optical frame."""
        u, v = np.meshgrid(np.arange(self.width, dtype=float), np.arange(self.height, dtype=float))
        d = np.stack([(u - self.cx) / self.fx, (v - self.cy) / self.fy, np.ones_like(u)], axis=-1)
        return d / np.linalg.norm(d, axis=-1, keepdims=True)


@dataclass(frozen=True)
class CameraMount:
    """A camera on the rover: name, intrinsics and pose of its body frame in the rover frame."""

    name: str
    T_rover_cam: np.ndarray
    camera: PinholeCamera = field(default_factory=PinholeCamera)

    @property
    def T_rover_optical(self) -> np.ndarray:
        """Transform from the optical frame (OpenCV axes) to the rover frame."""
        return self.T_rover_cam @ T_CAM_OPTICAL


def ipex_rig(camera: PinholeCamera | None = None) -> dict[str, CameraMount]:
    """The IPEx stereo cameras as in the LAC: FrontLeft/FrontRight at x = +0.28 m,
    BackLeft/BackRight at x = -0.28 m facing backwards, z = 0.131 m, 0.162 m baseline.

    "Left" is the left camera as seen looking along that camera's optical axis, so
    BackLeft sits on the rover's right-hand side (y < 0).
    """
    cam = camera or PinholeCamera()
    b = IPEX_STEREO_BASELINE_M / 2.0
    z = 0.131
    return {
        "FrontLeft": CameraMount("FrontLeft", pose_to_matrix(0.28, b, z, 0.0, 0.0, 0.0), cam),
        "FrontRight": CameraMount("FrontRight", pose_to_matrix(0.28, -b, z, 0.0, 0.0, 0.0), cam),
        "BackLeft": CameraMount("BackLeft", pose_to_matrix(-0.28, -b, z, 0.0, 0.0, np.pi), cam),
        "BackRight": CameraMount("BackRight", pose_to_matrix(-0.28, b, z, 0.0, 0.0, np.pi), cam),
    }


def mounts_from_archive_row(
    rows: Mapping[str, Mapping], camera: PinholeCamera
) -> dict[str, CameraMount]:
    """Camera mounts from an archive frame's camera-table rows (camera_x..camera_yaw,
    the camera body pose in the rover frame); cameras without a pose use the IPEx rig."""
    rig = ipex_rig(camera)
    out = dict(rig)
    for name, row in rows.items():
        try:
            pose = [float(row[f"camera_{k}"]) for k in ("x", "y", "z", "roll", "pitch", "yaw")]
        except (KeyError, TypeError, ValueError):
            continue
        if np.all(np.isfinite(pose)):
            out[name] = CameraMount(name, pose_to_matrix(*pose), camera)
    return out


def camera_from_archive(archive) -> PinholeCamera:
    """The pinhole camera of an archive's first configured left stereo camera (its width,
    height and field of view; the LAC's 1280x720, 70 degrees when absent)."""
    cams = archive.configured_cameras
    for left, _ in STEREO_PAIRS:
        c = cams.get(left)
        if c:
            try:
                w, h = int(c.get("width", 1280)), int(c.get("height", 720))
                fov = float(c.get("fov", c.get("hfov_deg", 70.0)))
                return PinholeCamera(w, h, fov)
            except (TypeError, ValueError):
                break
    return PinholeCamera()
