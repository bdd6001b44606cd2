"""What perception consumes: a camera frame, a source of frames, and the pixel formats.

A source (a recording, a video, the D435i, a rendered world) yields :class:`Frame` with 8-bit
BGR colour; :class:`FrameSource` is what every source offers (its adapters live in
``app.runtime.sources``, ``hardware.realsense`` and ``app.sim``).
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass

import cv2
import numpy as np

from app.camera import CameraModel
from app.errors import SourceError


@dataclass(frozen=True)
class Frame:
    """One camera frame. Arrays are owned by the frame (never an SDK buffer)."""

    index: int  # 1-based frame number in its source
    t_s: float  # capture time, s (source clock; monotonic for live cameras): perception's time
    color: np.ndarray  # (H, W, 3) uint8 BGR, or (H, W) uint8 grey
    depth: np.ndarray | None = None  # (H', W') uint16 mm, 0 = no data
    # when the flight process took the frame in (monotonic, s): a recording played as the
    # camera keeps its own ``t_s`` for perception (same tracks on every playback) and gets
    # this for latency and decision age; NaN for a live camera, whose ``t_s`` is monotonic
    t_arrived_s: float = math.nan

    @property
    def t_monotonic_s(self) -> float:
        """Monotonic time of the frame's capture (or arrival, for a played recording), s."""
        return self.t_s if math.isnan(self.t_arrived_s) else self.t_arrived_s


def to_grey(image: np.ndarray) -> np.ndarray:
    """8-bit grey from an 8-bit BGR, BGRA or grey image."""
    if image.ndim == 2:
        return image
    if image.ndim == 3 and image.shape[2] == 1:
        return image[:, :, 0]
    if image.ndim == 3 and image.shape[2] == 3:
        return cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    if image.ndim == 3 and image.shape[2] == 4:
        return cv2.cvtColor(image, cv2.COLOR_BGRA2GRAY)
    raise ValueError(f"unsupported image shape {image.shape}")


def to_bgr8(image: np.ndarray, name: str) -> np.ndarray:
    """Normalise a decoded image to 8-bit BGR (H, W, 3)."""
    if image.dtype == np.uint16:
        image = (image >> 8).astype(np.uint8)
    elif image.dtype != np.uint8:
        raise SourceError(f"{name}: unsupported pixel type {image.dtype}")
    if image.ndim == 2:
        return cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
    if image.ndim == 3 and image.shape[2] == 1:
        return cv2.cvtColor(image[:, :, 0], cv2.COLOR_GRAY2BGR)
    if image.ndim == 3 and image.shape[2] == 4:
        return cv2.cvtColor(image, cv2.COLOR_BGRA2BGR)
    if image.ndim == 3 and image.shape[2] == 3:
        return image
    raise SourceError(f"{name}: unsupported image shape {image.shape}")


class FrameSource:
    """Iterable of frames with what replay needs to know up front."""

    name: str
    fps: float
    has_depth: bool = False
    camera: CameraModel | None = None  # calibration that came with the source, if any
    live: bool = False  # a live camera: frames stamped on the monotonic clock, never paced
    # the camera flies on the vehicle being commanded, so its motion is the vehicle's (a
    # recording or a synthetic scene played as the camera is not: the vehicle's velocity and
    # attitude say nothing about how its frames moved)
    carried: bool = False

    def close(self) -> None:
        """Release the device or files (a no-op for sources that hold nothing open)."""

    def __iter__(self) -> Iterator[Frame]:  # pragma: no cover - interface
        raise NotImplementedError

    def __len__(self) -> int:  # pragma: no cover - interface
        raise NotImplementedError
