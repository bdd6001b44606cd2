"""Pinhole camera geometry of the D435i: colour and depth intrinsics, depth→colour extrinsics.

Frames: *camera* coordinates are metres with X right, Y down, Z forward (the RealSense and
OpenCV convention); image pixels have u right, v down. ``depth_to_color`` maps a point in
the depth camera's frame into the colour camera's frame: ``p_c = R @ p_d + t``.

No distortion model: the D435i's colour stream reports Inverse Brown–Conrady with
near-zero coefficients and its depth stream none (librealsense docs, "Projection in
RealSense SDK 2.0"), so the pinhole model is what the SDK's own projection does here.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from app.errors import SourceError

if TYPE_CHECKING:
    from app.config import CameraConfig


@dataclass(frozen=True)
class Intrinsics:
    width: int  # px
    height: int  # px
    fx: float  # focal length, px
    fy: float
    ppx: float  # principal point, px
    ppy: float

    def matrix(self) -> np.ndarray:
        """The pinhole matrix K (3 x 3): camera XYZ -> homogeneous pixels."""
        return np.array([[self.fx, 0.0, self.ppx], [0.0, self.fy, self.ppy], [0.0, 0.0, 1.0]])

    def deproject(self, u: np.ndarray, v: np.ndarray, z: np.ndarray) -> np.ndarray:
        """Pixels and depth (m) → camera XYZ (m), shape (N, 3)."""
        x = (np.asarray(u, float) - self.ppx) / self.fx * z
        y = (np.asarray(v, float) - self.ppy) / self.fy * z
        return np.stack([x, y, np.asarray(z, float)], axis=-1)

    def project(self, xyz: np.ndarray) -> np.ndarray:
        """Camera XYZ (m), shape (N, 3) → pixels (N, 2). Points need Z > 0."""
        xyz = np.asarray(xyz, float).reshape(-1, 3)
        return np.stack([xyz[:, 0] / xyz[:, 2] * self.fx + self.ppx,
                         xyz[:, 1] / xyz[:, 2] * self.fy + self.ppy], axis=-1)

    def scaled_to(self, width: int, height: int) -> Intrinsics:
        """The same lens at another resolution (same field of view)."""
        sx, sy = width / self.width, height / self.height
        return Intrinsics(width, height, self.fx * sx, self.fy * sy,
                          (self.ppx + 0.5) * sx - 0.5, (self.ppy + 0.5) * sy - 0.5)


@dataclass(frozen=True)
class CameraModel:
    color: Intrinsics
    depth: Intrinsics
    rotation: np.ndarray = field(default_factory=lambda: np.eye(3))  # depth -> colour, (3, 3)
    translation_m: np.ndarray = field(default_factory=lambda: np.zeros(3))  # depth -> colour, m
    depth_scale_m: float = 0.001  # metres per depth unit (D435i default: 1 mm)

    def depth_to_color_points(self, xyz_depth: np.ndarray) -> np.ndarray:
        """Points in the depth camera's frame → the colour camera's frame, (N, 3) m."""
        return xyz_depth @ self.rotation.T + self.translation_m

    def to_json(self) -> dict[str, object]:
        return {
            "color": self.color.__dict__, "depth": self.depth.__dict__,
            "depth_to_color": {"rotation": self.rotation.tolist(),
                               "translation_m": self.translation_m.tolist()},
            "depth_scale_m": self.depth_scale_m,
        }

    @staticmethod
    def from_json(data: dict, source: str = "intrinsics") -> CameraModel:
        try:
            ext = data.get("depth_to_color", {})
            rot = np.asarray(ext.get("rotation", np.eye(3).tolist()), float)
            tr = np.asarray(ext.get("translation_m", [0.0, 0.0, 0.0]), float)
            if rot.shape != (3, 3) or tr.shape != (3,):
                raise ValueError("depth_to_color needs a 3x3 rotation and 3 translations")
            return CameraModel(Intrinsics(**data["color"]), Intrinsics(**data["depth"]), rot, tr,
                               float(data.get("depth_scale_m", 0.001)))
        except (KeyError, TypeError, ValueError) as exc:
            raise SourceError(f"{source}: not a camera description ({exc})") from None

    @staticmethod
    def load(path: Path) -> CameraModel:
        try:
            data = json.loads(path.read_text())
        except (OSError, json.JSONDecodeError) as exc:
            raise SourceError(f"{path}: cannot be read as JSON ({exc})") from None
        return CameraModel.from_json(data, str(path))


def camera_from_config(cfg: CameraConfig) -> CameraModel:
    """The calibration written in ``config.yaml`` (``camera`` section)."""
    c, d = cfg.color, cfg.depth
    return CameraModel(
        Intrinsics(c.width, c.height, c.fx, c.fy, c.ppx, c.ppy),
        Intrinsics(d.width, d.height, d.fx, d.fy, d.ppx, d.ppy),
        np.eye(3),
        np.array([cfg.depth_to_color_x_m, cfg.depth_to_color_y_m, cfg.depth_to_color_z_m]),
        cfg.depth_scale_m,
    )
