"""Stages 1–3 chained: frames in, confirmed tracks out (one frame behind, see detection)."""

from __future__ import annotations

import functools
import logging
import time
from dataclasses import dataclass, field

import cv2
import numpy as np

from app.camera import CameraModel
from app.config import PerceptionConfig
from app.perception import near, photometry
from app.perception.confidence import TrackConfidence
from app.perception.detection import MotionDetector
from app.perception.frames import Frame, to_grey
from app.perception.recognition import Blobs, Cluster, Recognizer
from app.perception.tracking import Tracker, TrackReport

log = logging.getLogger(__name__)


@functools.cache
def _say_near_off() -> None:
    """Once a process, not once a perception: ``midair bench`` and ``midair evaluate`` build one
    for every run or clip, and said a dozen times the line buries their output."""
    log.info("depth path off: the depth is not in the image's own pixels (another lens, "
             "another size, or no calibration); objects are seen by their grey alone")


@dataclass
class PerceptionResult:
    """What perception knows about ``frame``."""

    frame: Frame
    status: str  # detector status: ok, one_sided, no_homography, scene_cut, warmup
    mask: np.ndarray | None
    blobs: Blobs | None
    clusters: list[Cluster]
    tracks: list[TrackReport]  # every confirmed track, scored (``reported``: counted as an object)
    homography: np.ndarray | None  # H_{t-1,t}
    timings_ms: dict[str, float] = field(default_factory=dict)


class Perception:
    """Detection → recognition → tracking.

    ``push(frame_t+1)`` returns the result for frame t (None for the first frame).
    """

    def __init__(self, cfg: PerceptionConfig, full_frame_features: bool = False,
                 camera: CameraModel | None = None) -> None:
        self.cfg = cfg
        # the depth path (app.perception.near) needs the lens, to know that depth is
        # registered to the image and in what units
        self.camera = camera
        self._near: bool | None = None  # decided on the first frame with depth
        self._near_floor_px = 0.0  # the depth path's smallest patch 1 m off (near.patch_floor_px), px
        # the depth path's patches of the frame before (near.grow_persistent)
        self._near_before: near.Patches | None = None
        self.detector = MotionDetector(cfg.detection, full_frame=full_frame_features)
        self.recognizer = Recognizer(cfg.recognition)
        self.tracker = Tracker(cfg.tracking)
        self.confidence = TrackConfidence(cfg.confidence)
        self._pending: Frame | None = None  # frame t, waiting for t+1
        self._pending_grey: np.ndarray | None = None

    def reset(self) -> None:
        self.detector.reset()
        self.tracker.reset()
        self.confidence.reset()
        self._pending = None
        self._pending_grey = None
        self._near_before = None

    def push(self, frame: Frame) -> PerceptionResult | None:
        t0 = time.perf_counter()
        grey = to_grey(frame.color)
        exclude = self.tracker.confirmed_boxes()
        det = self.detector.push(grey, exclude, frame.t_s, frame.color)
        t1 = time.perf_counter()
        current, self._pending = self._pending, frame
        current_grey, self._pending_grey = self._pending_grey, grey
        if det.status == "scene_cut":
            self.tracker.reset()
            self.confidence.reset()
        if current is None:
            return None
        clusters: list[Cluster] = []
        blobs: Blobs | None = None
        mask = det.mask
        if mask is not None and current.depth is not None and self.cfg.detection.near_sigmas > 0:
            mask = self._with_near(mask, current.depth)
        if mask is not None:
            clusters, blobs = self.recognizer(mask)
        t2 = time.perf_counter()
        if det.status == "scene_cut":
            tracks: list[TrackReport] = []
        else:
            tracks = self.tracker.step(
                clusters if det.mask is not None else None, current.t_s, det.homography
            )
            if current_grey is not None:
                # each matched object's flux and core area, for looming (a box's size steps by
                # whole pixels, and jumps with what its blob merges with) and the confidence
                tracks = [t.with_photometry(*photometry.measure(current_grey, t.cluster.box))
                          if t.matched and t.cluster is not None else t for t in tracks]
                tracks = self.confidence(current_grey, tracks)
        t3 = time.perf_counter()
        timings = {
            "detection_ms": (t1 - t0) * 1e3,
            "recognition_ms": (t2 - t1) * 1e3,
            "tracking_ms": (t3 - t2) * 1e3,
            "total_ms": (t3 - t0) * 1e3,
        }
        return PerceptionResult(current, det.status, mask, blobs, clusters, tracks,
                                det.homography, timings)

    def _with_near(self, mask: np.ndarray, depth: np.ndarray) -> np.ndarray:
        """``mask`` with what stands out in depth (app.perception.near), where the depth is
        registered to the image; ``mask`` itself otherwise."""
        if self._near is None:
            self._near = near.registered(self.camera, mask.shape[:2])
            if self.camera is not None:
                lens, size = self.camera.depth, self.cfg.detection.near_min_size_m
                self._near_floor_px = near.patch_floor_px(lens.fx, lens.fy, size)
            if not self._near:
                _say_near_off()
        if not self._near or depth.shape != mask.shape:
            return mask
        assert self.camera is not None
        d = self.cfg.detection
        marked = near.near_mask(depth, self.camera.depth_scale_m, d.near_sigmas, d.near_noise_per_m,
                                d.near_window_px, near.MIN_M, near.MAX_M, self._near_floor_px)
        grown, self._near_before = near.grow_persistent(marked, depth, self.camera.depth_scale_m,
                                                        self._near_before, near.REACH_PX, d.dilate_ksize)
        return cv2.bitwise_or(mask, grown)
