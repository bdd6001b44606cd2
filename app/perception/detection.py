"""Stage 1 — moving-object detection from a moving camera (paper Alg. 1, §3-F).

Camera motion between consecutive frames is modelled as a homography estimated from
Lucas–Kanade flow in a few small windows on the frame border. The previous and next
frames are warped onto the current one; the two absolute differences are merged,
median-filtered, dilated and thresholded into a binary motion mask.

Because the next frame is needed, the mask of frame t exists once frame t+1 has
arrived: one frame of built-in latency.

All images are 8-bit grey, shape (H, W), in image pixel coordinates (x right, y down).
A homography ``H_a_b`` maps pixel coordinates of frame a to those of frame b.
"""

from __future__ import annotations

import logging
import math
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Any, cast

import cv2
import numpy as np

from app.config import DetectionConfig
from app.errors import SourceError
from app.ratelimit import RateLimitedLogger

log = RateLimitedLogger(logging.getLogger(__name__), period_s=5.0)

Box = tuple[float, float, float, float]  # x, y, w, h in image px (top-left corner and size)

# goodFeaturesToTrack over the whole frame: the usual choice of full-frame stabilisers
# (OpenCV's videostab motion estimator defaults to 1000; 500 is a common lighter setting).
FULL_FRAME_CORNERS = 500
_NO_POINTS = np.empty((0, 2), np.float32)
_NO_WINDOWS = np.empty(0, np.intp)
# Below this phase-correlation peak the whole-frame shift is not used to start LK. Measured: a
# 25 px pan of the tests' texture 0.89, Halmstad frame pairs 0.81-1.0, blank sky with sensor
# noise 0.6 at zero shift (harmless: blank sky registers trivially), a broken frame pair -0.01.
MIN_PHASE_RESPONSE = 0.1
# The difference image may be moved into the previous frame's pixels by whole-pixel shifts of
# TILES x TILES tiles when every tile corner lands within SHIFT_TOLERANCE_PX of where the
# homography puts it (px, per axis, including the shift's own rounding, so that any pure
# translation qualifies; the nearest-neighbour warp it stands in for is off by up to 0.5).
# Measured share of frame pairs that qualify: the bench's synthetic flight 95 %, the Halmstad
# clips 1-100 % per clip (mean 59 % over the airplane/bird/helicopter clips, 67 % over all 32);
# the group's recall/precision moved by less than the run-to-run chaos of the tracker
# (0.807/0.830 -> 0.809/0.825; 0.6, 1.0, 1.25 px gave 0.809/0.825, 0.808/0.818, 0.810/0.822).
TILES = 4
SHIFT_TOLERANCE_PX = 0.75


def border_windows(width: int, height: int, size: int, count: int) -> list[tuple[int, int, int, int]]:
    """The border windows ``(x0, y0, x1, y1)`` (paper Fig. 20): corners first, then the
    top/bottom middles (count 6), then the left/right middles (count 8)."""
    if width < 3 * size or height < 3 * size:
        raise SourceError(
            f"frame {width}x{height} is too small for the detection windows: "
            f"perception.detection.window_px = {size} needs at least {3 * size}x{3 * size}"
        )
    xs = (0, (width - size) // 2, width - size)
    ys = (0, (height - size) // 2, height - size)
    order = [(0, 0), (2, 0), (0, 2), (2, 2), (1, 0), (1, 2), (0, 1), (2, 1)]
    return [(xs[i], ys[j], xs[i] + size, ys[j] + size) for i, j in order[:count]]


@dataclass
class DetectionResult:
    """The motion mask of one frame (the one *before* the frame just pushed)."""

    mask: np.ndarray | None  # uint8 (H, W), 255 = moving; None when the frame was skipped
    status: str  # ok, one_sided, featureless, no_homography, bad_warp, warmup, scene_cut
    homography: np.ndarray | None  # H_{t-1,t}: previous frame px -> this frame px, or None
    inliers: int  # RANSAC inliers of the newest homography estimate
    excluded_windows: int  # border windows left out because a tracked object overlaps them
    timings_ms: dict[str, float] = field(default_factory=dict)


class MotionDetector:
    """Homography-compensated three-frame differencing.

    Parameters
    ----------
    cfg
        Thresholds and sizes (see :class:`app.config.DetectionConfig`; units in its docs).
    full_frame
        Track features over the whole frame instead of the border windows. Only for the
        benchmark's baseline: it is what the windows are measured against.
    """

    def __init__(self, cfg: DetectionConfig, full_frame: bool = False) -> None:
        self.cfg = cfg
        self.full_frame = full_frame
        self._lk_params: dict[str, Any] = dict(
            winSize=(cfg.lk_window_px, cfg.lk_window_px),
            maxLevel=cfg.lk_pyramid_levels,
            criteria=(cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, cfg.lk_max_iterations, 0.03),
            minEigThreshold=cfg.lk_min_eigen,
        )
        k = cfg.dilate_ksize
        self._dilate_kernel = cv2.getStructuringElement(cv2.MORPH_RECT, (k, k)) if k > 1 else None
        self._shape: tuple[int, int] | None = None
        self._windows: list[tuple[int, int, int, int]] = []
        self._crops: list[tuple[int, int, int, int]] = []  # windows grown by lk_search_px
        # the crops laid out in one image, that LK flows in one call (see _configure): two
        # buffers taken in turn, frame t's and frame t+1's
        self._mosaics: list[np.ndarray] = []
        self._mosaic_cur: np.ndarray | None = None
        self.reset()

    # ------------------------------------------------------------------ state

    def reset(self) -> None:
        """Forget all frames (after a scene cut, or at a new source)."""
        self._has_prev = False  # frame t has a predecessor
        self._diff_cur: np.ndarray | None = None  # |I_t - W(I_{t-1})| in t's pixels
        self._cur: np.ndarray | None = None  # frame t
        self._mosaic_cur = None  # frame t's crops in their mosaic
        self._h_prev_cur: np.ndarray | None = None  # H_{t-1,t}
        self._t_prev: float | None = None  # capture times of frames t-1 and t, s
        self._t_cur: float | None = None
        self._interval_ratio = 1.0  # (t+1 - t) / (t - t-1) in quarters, 0.25-4
        self._hist_cur: np.ndarray | None = None
        # the slow difference's history: (time s, frame at half resolution, H from it to frame t)
        self._slow: deque[tuple[float, np.ndarray, np.ndarray]] = deque()
        self._small_cur: np.ndarray | None = None  # frame t at half resolution
        self._t_slow_cur: float | None = None
        # the last frame's difference against twice the baseline back (half resolution, its
        # pixels) when it was computed fresh: the next frame shifts it on instead (see below)
        self._slow_far: tuple[float, np.ndarray] | None = None
        # the parallax registration's pixel grid and tile centres (half resolution), once
        self._tile_grid: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
        self._frames = 0  # frames pushed (the clock when no capture time is given)
        # the chroma difference (chroma_gain > 0, colour frames): frame t's YCrCb at half
        # resolution, and |C_t - W(C_{t-1})| (the larger over Cr and Cb) in its pixels
        self._chroma_cur: np.ndarray | None = None
        self._chroma_diff_cur: np.ndarray | None = None
        self._clear_points()
        self._clear_shifts()
        # no motion to go on (start, or the last frame failed): the next flow starts from the
        # whole frame's shift instead
        self._lost_motion = True
        self._textureless = np.zeros(len(self._windows), bool)  # per window, newest frame
        self.featureless = False  # the newest H came from the blank-border fallback

    def _configure(self, shape: tuple[int, int]) -> None:
        h, w = shape
        c = self.cfg
        self._windows = border_windows(w, h, c.window_px, c.window_count)  # checks the size too
        if self.full_frame:
            self._windows = [(0, 0, w, h)]
        m = c.lk_search_px
        self._crops = [(max(0, x0 - m), max(0, y0 - m), min(w, x1 + m), min(h, y1 + m))
                       for x0, y0, x1, y1 in self._windows]
        self._shape = shape
        # The crops are laid out in one mosaic image as they lie in the frame, the frame's middle
        # bands cut out (six windows: 402 x 236 px, the crops' pixels and no more): each crop is
        # copied to its place once per frame and LK flows every window's points in one call.
        # Measured on the bench clip: 654 us against 934 us for one call per crop (six crops,
        # 72 points): OpenCV pads every pyramid level of every image by the LK window, which
        # for a small crop is more than its own pixels. Every side of a crop on the frame's edge
        # is on the mosaic's edge, where LK pads as it did for the crop alone; an inner side
        # (lk_search_px from its window) meets another crop's inner side. A crop that is the
        # whole frame (the full-frame variant) is the frame itself.
        cols = [0 if x0 == 0 else 2 if x1 == w else 1 for x0, _, x1, _ in self._windows]
        rows = [0 if y0 == 0 else 2 if y1 == h else 1 for _, y0, _, y1 in self._windows]
        col_w = [max((x1 - x0 for (x0, _, x1, _), c in zip(self._crops, cols, strict=True) if c == k),
                     default=0) for k in range(3)]
        row_h = [max((y1 - y0 for (_, y0, _, y1), r in zip(self._crops, rows, strict=True) if r == k),
                     default=0) for k in range(3)]
        # per crop, its top-left corner in the mosaic
        self._mosaic_at = [(sum(col_w[:c]), sum(row_h[:r])) for c, r in zip(cols, rows, strict=True)]
        whole = self._crops == [(0, 0, w, h)]
        self._mosaics = [] if whole else [np.zeros((sum(row_h), sum(col_w)), np.uint8) for _ in range(2)]
        # per window: image px -> mosaic px (a whole-pixel offset), and its own bounds (image px,
        # float32 like the points)
        self._to_mosaic = np.array([(mx - x0, my - y0) for (x0, y0, _, _), (mx, my)
                                    in zip(self._crops, self._mosaic_at, strict=True)], np.float32)
        self._bounds = np.array(self._windows, np.float32).reshape(-1, 4)
        self._crop_bounds = np.array(self._crops, np.float32).reshape(-1, 4)
        self._textureless = np.zeros(len(self._windows), bool)
        self._clear_points()
        self._clear_shifts()

    def _clear_points(self) -> None:
        # Tracked points in frame t: every border window's in one (N, 2) float32 array of image
        # px, window after window (the order RANSAC sees them in), and the window of each.
        self._pts = _NO_POINTS
        self._wid = _NO_WINDOWS
        self._counts = [0] * len(self._windows)  # points per window

    def _clear_shifts(self) -> None:
        # per border window, the median flow t-1 -> t of its points (image px), where it had any
        self._shift = np.zeros((len(self._windows), 2), np.float32)
        self._has_shift = [False] * len(self._windows)

    # ------------------------------------------------------------------ main step

    def push(self, gray: np.ndarray, exclude: list[Box] | tuple[Box, ...] = (),
             t_s: float | None = None, colour: np.ndarray | None = None) -> DetectionResult:
        """Add frame t+1; return the motion mask of frame t.

        ``exclude`` holds boxes of tracked objects in frame t: border windows that
        overlap them do not vote on the homography. ``t_s`` is frame t+1's capture time
        (s, any clock): with it, LK's start from the last flow is scaled by how much longer
        or shorter this frame interval is than the last one (frames skipped by a busy
        perception thread double the motion between the frames it sees). ``colour`` is the
        same frame in 8-bit BGR: with ``chroma_gain`` > 0 its chroma is differenced too.
        """
        if gray.ndim != 2 or gray.dtype != np.uint8:
            raise ValueError(f"expected an 8-bit grey image, got {gray.dtype} {gray.shape}")
        if self._shape != gray.shape:
            if self._shape is not None:
                raise SourceError(
                    f"frame size changed from {self._shape[1]}x{self._shape[0]} "
                    f"to {gray.shape[1]}x{gray.shape[0]}"
                )
            self._configure(gray.shape)
        t0 = time.perf_counter()
        timings: dict[str, float] = {}

        hist = _grey_histogram(gray)
        chroma = _half_ycrcb(colour, gray.shape) if self.cfg.chroma_gain > 0 else None
        if self._cur is None or self._hist_cur is None or self._mosaic_cur is None:
            self._start(gray, hist, t_s)
            self._chroma_cur = chroma
            return DetectionResult(None, "warmup", None, 0, 0, timings)
        if cv2.compareHist(self._hist_cur, hist, cv2.HISTCMP_CORREL) < self.cfg.scene_cut_correlation:
            log.info("scene_cut", "scene cut detected: detector reset")
            self.reset()
            self._start(gray, hist, t_s)
            self._chroma_cur = chroma
            return DetectionResult(None, "scene_cut", None, 0, 0, timings)

        excluded = self._excluded_windows(exclude)
        self._interval_ratio = 1.0
        if t_s is not None and self._t_cur is not None and self._t_prev is not None:
            last, now = self._t_cur - self._t_prev, t_s - self._t_cur
            if last > 0 and now > 0:
                # In quarters: the start needs no more, clock jitter (a few % at 60 fps) then
                # never changes it, and a replay of the flight record, whose times are rounded
                # to 1 us, starts LK exactly where the flight did.
                self._interval_ratio = min(4.0, max(0.25, round(4.0 * now / last) / 4.0))
        mosaic_next = self._mosaic(gray)
        h_cur_next, inliers = self._estimate(self._cur, gray, (self._mosaic_cur, mosaic_next), excluded)
        t1 = time.perf_counter()
        timings["flow_ms"] = (t1 - t0) * 1e3

        mask, status = self._difference(gray, h_cur_next, chroma)
        self._remember(h_cur_next, t_s)
        if self.featureless and mask is not None:
            status = "featureless"
        timings["difference_ms"] = (time.perf_counter() - t1) * 1e3
        if status == "no_homography":
            log.warning("no_h", "homography not estimated (%d inliers): frame skipped", inliers)
        self._lost_motion = status in ("no_homography", "bad_warp")

        result = DetectionResult(mask, status, self._h_prev_cur, inliers, len(excluded), timings)
        # Shift: t+1 becomes the current frame; H_{t,t+1} becomes next step's H_{t-1,t}.
        self._has_prev = True
        self._cur, self._hist_cur, self._mosaic_cur = gray, hist, mosaic_next
        self._chroma_cur = chroma
        self._t_prev, self._t_cur = self._t_cur, t_s
        self._set_slow_cur(gray, t_s)
        self._h_prev_cur = h_cur_next
        self._reseed(gray)
        return result

    def _remember(self, h_cur_next: np.ndarray | None, t_s: float | None) -> None:
        """Frame t joins the slow difference's history, every stored frame's homography is
        carried on to frame t+1, and what is older than twice the baseline goes. A frame
        without a homography breaks the chain: the history starts again."""
        base = self.cfg.slow_baseline_s
        if base <= 0:
            return
        self._frames += 1
        if h_cur_next is None or self._small_cur is None or self._t_slow_cur is None:
            self._slow.clear()
            self._slow_far = None
        else:
            for i, (t, small, h) in enumerate(self._slow):
                self._slow[i] = (t, small, h_cur_next @ h)
            self._slow.append((self._t_slow_cur, self._small_cur, h_cur_next.copy()))
            while self._slow and self._t_slow_cur - self._slow[0][0] > 2 * base + 0.05:
                self._slow.popleft()

    def _chroma_difference(self, chroma_next: np.ndarray | None,
                           h_cur_next: np.ndarray | None) -> np.ndarray | None:
        """The three-frame difference of the chroma (the larger of |dCr| and |dCb|), as the
        grey one is made but at half resolution, times ``chroma_gain``, in frame t's full
        pixels; None without colour, a homography or a predecessor. The next step's "previous"
        half is kept either way."""
        cur, prev_diff = self._chroma_cur, self._chroma_diff_cur
        self._chroma_diff_cur = None
        if cur is None or chroma_next is None or h_cur_next is None:
            return None
        hh = _HALF @ h_cur_next @ _DOUBLE
        d = _compensated_diff(cur, chroma_next, hh)
        self._chroma_diff_cur = cv2.max(cv2.extractChannel(d, 1), cv2.extractChannel(d, 2))
        if prev_diff is None:
            return None
        next_diff = cv2.warpPerspective(
            self._chroma_diff_cur, hh, (cur.shape[1], cur.shape[0]),
            flags=cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP, borderValue=0)
        if self.cfg.combine == "min":
            merged = cv2.min(prev_diff, next_diff)
        else:
            merged = cv2.addWeighted(prev_diff, 0.5, next_diff, 0.5, 0.0)
        merged = cv2.convertScaleAbs(merged, alpha=self.cfg.chroma_gain)
        assert self._shape is not None
        return cv2.pyrUp(merged, dstsize=(self._shape[1], self._shape[0]))

    def _slow_difference(self) -> np.ndarray | None:
        """Frame t against the registered frames ``slow_baseline_s`` and twice that before it,
        at half resolution: the smaller of the two differences (a moving object's ghost is in
        one of them only), less what the background's misregistration can explain (the image
        gradient times ``slow_registration_px``). Full resolution, or None without history or
        when it is the background that moved (more than ``max_mask_frac`` of the frame)."""
        c = self.cfg
        cur, t_cur = self._small_cur, self._t_slow_cur
        if c.slow_baseline_s <= 0 or cur is None or t_cur is None or len(self._slow) < 2:
            return None
        if t_cur - self._slow[0][0] < 2 * c.slow_baseline_s - 0.02:
            return None  # not enough history yet

        def nearest(t: float) -> tuple[float, np.ndarray, np.ndarray]:
            return min(self._slow, key=lambda e: abs(e[0] - t))

        _, small, h = nearest(t_cur - c.slow_baseline_s)
        near = _compensated_diff(small, cur, _HALF @ h @ _DOUBLE)
        # Against twice the baseline, every other frame shifts the last frame's difference on
        # by tiles instead of warping anew (a warp is a third of the slow difference's cost):
        # its ghost, 0.4 s back, moves by a frame and stays apart from the 0.2 s one's.
        far = None
        t_last, _, h_last = self._slow[-1]
        if self._slow_far is not None and self._slow_far[0] == t_last:
            far = _shift_tiles(self._slow_far[1], np.linalg.inv(_HALF @ h_last @ _DOUBLE))
        if far is None:
            _, small, h = nearest(t_cur - 2 * c.slow_baseline_s)
            far = _compensated_diff(small, cur, _HALF @ h @ _DOUBLE)
            self._slow_far = (t_cur, far)
        else:
            self._slow_far = None  # shifted once: the next frame warps afresh
        diff = cv2.min(near, far)
        tolerance = None
        if c.slow_registration_px > 0:
            # 3x3 max - min spans two pixels; at half resolution a pixel is two
            grad = cv2.morphologyEx(cur, cv2.MORPH_GRADIENT, _KERNEL3)
            tolerance = cv2.convertScaleAbs(grad, alpha=c.slow_registration_px / 4.0)
            diff = cv2.subtract(diff, tolerance)
        moving = cv2.threshold(diff, c.threshold, 255, cv2.THRESH_BINARY)[1]
        if cv2.countNonZero(moving) > c.slow_max_frac * diff.size:
            # the background moved (parallax, a failed chain): registered again tile by tile,
            # what the tiles' shifts explain is not objects; else nothing of it is
            if c.slow_parallax_tile_px <= 0:
                return None
            pairs = [nearest(t_cur - c.slow_baseline_s), nearest(t_cur - 2 * c.slow_baseline_s)]
            olds = [(t_cur - t, sm, _HALF @ hh @ _DOUBLE) for t, sm, hh in pairs]
            parallax = self._slow_parallax(cur, olds, tolerance)
            if parallax is None:
                return None
            diff = parallax
        assert self._shape is not None
        return cv2.pyrUp(diff, dstsize=(self._shape[1], self._shape[0]))  # 0.1 ms; resize: 0.23

    def _slow_parallax(self, cur: np.ndarray, olds: list[tuple[float, np.ndarray, np.ndarray]],
                       tolerance: np.ndarray | None) -> np.ndarray | None:
        """The slow difference with the parallax the homography leaves taken out: each old
        frame (its age s, half-resolution pixels, homography onto frame t), registered by its
        homography, is shifted tile by tile (``slow_parallax_tile_px``) by the residual flow
        Lucas-Kanade finds at the tiles' centres against the first (3 x 3 median over tiles,
        bilinear between centres; the older one's flow scaled by its age, the parallax of a
        steady flight growing with time), the smaller of the differences kept, less the
        misregistration tolerance; tiles still marked over ``slow_parallax_tile_frac`` (near
        ground, whose flow varies within a tile) are left out. None when what is left still
        marks over ``slow_max_frac``. Half resolution in and out."""
        c = self.cfg
        side = max(4, c.slow_parallax_tile_px // 2)
        h, w = cur.shape
        ty, tx = h // side, w // side
        if ty < 3 or tx < 3:
            return None
        if self._tile_grid is None or self._tile_grid[0].shape != (ty * side, tx * side):
            ys = (np.arange(ty, dtype=np.float32) + 0.5) * side
            xs = (np.arange(tx, dtype=np.float32) + 0.5) * side
            centres = np.stack(np.meshgrid(xs - 0.5, ys - 0.5), -1).reshape(-1, 1, 2)
            gx, gy = np.meshgrid(np.arange(tx * side, dtype=np.float32),
                                 np.arange(ty * side, dtype=np.float32))
            self._tile_grid = (gx, gy, centres)
        grid_x, grid_y, centres = self._tile_grid
        core = cur[:ty * side, :tx * side]
        diff: np.ndarray | None = None
        fx = fy = None
        age0 = olds[0][0]
        for age, small, hh in olds:
            warped = _warp_onto(small, hh, cur)
            if fx is None or fy is None:
                # 9 px windows over 3 levels: 1.2 ms for 26 x 15 tiles here, a 17 px one 2.9
                moved, status, _err = cv2.calcOpticalFlowPyrLK(
                    warped, cur, centres, None, winSize=(9, 9), maxLevel=2,
                    criteria=(cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 10, 0.03),
                    minEigThreshold=self.cfg.lk_min_eigen)
                flow = (moved - centres).reshape(ty, tx, 2)
                flow[status.reshape(ty, tx) == 0] = 0.0  # featureless (sky): no parallax to find
                fx = cv2.resize(cv2.medianBlur(np.ascontiguousarray(flow[..., 0]), 3),
                                (tx * side, ty * side), interpolation=cv2.INTER_LINEAR)
                fy = cv2.resize(cv2.medianBlur(np.ascontiguousarray(flow[..., 1]), 3),
                                (tx * side, ty * side), interpolation=cv2.INTER_LINEAR)
            k = age / age0 if age0 > 0 else 1.0
            # LK moved the old frame's point p to p + f in frame t: frame t at q is the old at q - f
            registered = cv2.remap(warped, grid_x - k * fx, grid_y - k * fy, cv2.INTER_LINEAR,
                                   borderMode=cv2.BORDER_REPLICATE)
            d = cv2.absdiff(core, registered)
            diff = d if diff is None else cv2.min(diff, d)
        assert diff is not None
        if tolerance is not None:
            diff = cv2.subtract(diff, tolerance[:ty * side, :tx * side])
        moving = cv2.threshold(diff, c.threshold, 255, cv2.THRESH_BINARY)[1]
        frac = cv2.resize(moving, (tx, ty), interpolation=cv2.INTER_AREA).astype(np.float32) / 255.0
        keep = (frac <= c.slow_parallax_tile_frac).astype(np.uint8)
        keep = np.repeat(np.repeat(keep, side, axis=0), side, axis=1)
        diff = cv2.multiply(diff, keep)
        out = np.zeros_like(cur)
        out[:ty * side, :tx * side] = diff
        marked = cv2.countNonZero(cv2.threshold(out, c.threshold, 255, cv2.THRESH_BINARY)[1])
        if marked > c.slow_max_frac * out.size:
            return None
        return out

    def _set_slow_cur(self, gray: np.ndarray, t_s: float | None) -> None:
        if self.cfg.slow_baseline_s > 0:
            self._small_cur = cv2.pyrDown(gray)
            # without capture times, frames are taken as 30 fps
            self._t_slow_cur = t_s if t_s is not None else self._frames / 30.0

    def _start(self, gray: np.ndarray, hist: np.ndarray, t_s: float | None = None) -> None:
        self._set_slow_cur(gray, t_s)
        self._cur, self._hist_cur, self._mosaic_cur = gray, hist, self._mosaic(gray)
        self._t_prev, self._t_cur = None, t_s
        self._reseed(gray)

    # ------------------------------------------------------------------ homography

    def _excluded_windows(self, boxes: list[Box] | tuple[Box, ...]) -> set[int]:
        if not boxes or self.full_frame:
            return set()
        m = self.cfg.object_margin_px
        out: set[int] = set()
        for i, (x0, y0, x1, y1) in enumerate(self._windows):
            for bx, by, bw, bh in boxes:
                if bx - m < x1 and bx + bw + m > x0 and by - m < y1 and by + bh + m > y0:
                    out.add(i)
                    break
        return out

    def _mosaic(self, gray: np.ndarray) -> np.ndarray:
        """The frame's crops in their mosaic (see _configure), in the buffer frame t's are not in."""
        if not self._mosaics:
            return gray
        out = self._mosaics[1] if self._mosaic_cur is self._mosaics[0] else self._mosaics[0]
        for (x0, y0, x1, y1), (mx, my) in zip(self._crops, self._mosaic_at, strict=True):
            out[my:my + y1 - y0, mx:mx + x1 - x0] = gray[y0:y1, x0:x1]
        return out

    def _estimate(self, cur: np.ndarray, nxt: np.ndarray, mosaics: tuple[np.ndarray, np.ndarray],
                  excluded: set[int]) -> tuple[np.ndarray | None, int]:
        """H_{t,t+1} from LK flow of the tracked points, and its RANSAC inliers. Leaves each
        window with its points that LK followed into t+1 and that stayed inside the window.
        ``mosaics``: frame t's and t+1's crops in their mosaic (see _configure)."""
        self.featureless = False
        n_windows = len(self._windows)
        if len(self._pts) < 4:
            has_points = [k > 0 for k in self._counts]
            self._clear_points()
            if self._featureless_border(has_points):
                self.featureless = True
                return np.eye(3), 0
            return None, 0
        p0, p1, wid, followed = self._flow(cur, nxt, mosaics)
        voting = [i for i in range(n_windows) if followed[i] and i not in excluded]
        n_vote = sum(followed[i] for i in voting)
        if excluded and n_vote < self.cfg.min_inliers:
            # every window is covered: better the object's points than none
            voting = [i for i in range(n_windows) if followed[i]]
            n_vote = len(p0)
        if n_vote == len(p0):
            v0, v1 = p0, p1  # every window votes (the usual case)
        else:
            sel = np.isin(wid, voting)
            v0, v1 = p0[sel], p1[sel]
        h = None
        inliers = 0
        if n_vote >= max(4, self.cfg.min_inliers):
            h, inl = cv2.findHomography(v0, v1, cv2.RANSAC, self.cfg.ransac_reproj_px, maxIters=500)
            inliers = cv2.countNonZero(inl) if inl is not None else 0
            if h is None or inliers < self.cfg.min_inliers or not _plausible(h):
                h = None
        elif self._featureless_border([i in voting for i in range(n_windows)]):
            # Too few points because the border is blank sky, not because the points disagree:
            # a misregistered blank sky differs from itself by nothing, so a translation by
            # the median flow of what points there are (or none) is a safe model.
            shift = np.median(v1 - v0, axis=0) if n_vote >= 3 else np.zeros(2)
            h = np.array([[1, 0, shift[0]], [0, 1, shift[1]], [0, 0, 1]], float)
            self.featureless = True
        # Keep the points that stay inside their own window in frame t+1.
        inside = _in_boxes(p1, self._bounds[wid])
        if inside.all():
            self._pts, self._wid = p1, wid
        else:
            self._pts, self._wid = p1[inside], wid[inside]
        self._counts = np.bincount(self._wid, minlength=n_windows).tolist()
        return h, inliers

    def _flow(self, cur: np.ndarray, nxt: np.ndarray, mosaics: tuple[np.ndarray, np.ndarray]
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[int]]:
        """LK flow of the tracked points, t -> t+1: the points LK could follow, in t and in t+1
        (image px; two (M, 2) float32 arrays, window after window), the window of each, and
        how many each window has.

        Each window is flowed inside its own crop (window + ``lk_search_px``): image pyramids
        of six small crops cost a fraction of two whole frames'. The crops are laid out in one
        mosaic image per frame (see _configure), so that one LK call flows them all.
        """
        n_windows = len(self._windows)
        predict = self.cfg.lk_predict
        scale = np.float32(self._interval_ratio)  # the last flow covered a different interval
        if predict and self._lost_motion:
            # Nothing to predict from, or a prediction that just failed: a coarse phase
            # correlation of the whole frame gives every window its start when the frame
            # moved by more than LK finds from rest (about half its window: at 12 px/frame
            # from rest the homography's error reached 3.4 px p95 on the synthetic flight).
            whole = _global_shift(cur, nxt)
            if whole is not None and float(np.hypot(*whole)) > self.cfg.lk_window_px / 2:
                self._shift[:] = whole
                self._has_shift = [True] * n_windows
                scale = np.float32(1.0)  # measured on this very pair
        pts, wid = self._pts, self._wid
        to_mosaic = self._to_mosaic[wid]
        q0 = (pts + to_mosaic).reshape(-1, 1, 2)  # mosaic px
        guess: np.ndarray | None = None
        if predict and any(self._has_shift):
            # Camera motion changes little from one frame to the next: start LK where the
            # window's own last flow carries its points, so the pyramid only has to find the
            # change of motion (a 2-level pyramid then follows pans of 48 px/frame). A window
            # without a last flow starts at its points, as LK does without a start.
            start = np.where(np.array(self._has_shift)[:, None], self._shift * scale, np.float32(0))
            guess = q0 + start[wid].reshape(-1, 1, 2)
        self._has_shift = [False] * n_windows
        q1, status, _err = cv2.calcOpticalFlowPyrLK(
            *mosaics, q0,
            cast(Any, guess),  # None (LK starts at the points) is accepted; some stubs say no
            flags=cv2.OPTFLOW_USE_INITIAL_FLOW if guess is not None else 0, **self._lk_params,
        )
        if q1 is None:  # LK gave up on every point
            return _NO_POINTS, _NO_POINTS, _NO_WINDOWS, [0] * n_windows
        p1 = q1.reshape(-1, 2) - to_mosaic
        # A point carried out of its crop moved farther than lk_search_px allows: lost. (A crop
        # flowed alone padded its pyramids there; in the mosaic another crop begins there.)
        # Registration error of the tests' fast pans (mean / worst of every frame, px): ramped
        # to 40 px/frame 0.137 / 0.83 -> 0.071 / 0.23, frames skipped 0.197 / 0.54 -> 0.096 / 0.47.
        within = _in_boxes(p1, self._crop_bounds[wid])
        if cv2.countNonZero(status) == len(pts) and within.all():
            followed = self._counts
        else:
            ok = (status.reshape(-1) == 1) & within
            pts, p1, wid = pts[ok], p1[ok], wid[ok]
            followed = np.bincount(wid, minlength=n_windows).tolist()
        if predict and len(pts):
            self._median_flow(p1 - pts, followed)
        return pts, p1, wid, followed

    def _median_flow(self, moves: np.ndarray, counts: list[int]) -> None:
        """Each window's median of ``moves`` per axis (image px; (M, 2), window after window,
        ``counts[i]`` rows of window i), kept as the start of the next LK. A dozen values a
        window: sorted in plain Python (np.median costs 10x, and numpy's per-call cost adds up
        over six windows). Stored as float32, the mean of the two middle values is rounded
        just as float32 arithmetic rounds it."""
        rows = moves.tolist()
        end = 0
        for i, k in enumerate(counts):
            if not k:
                continue
            start, end = end, end + k
            xs = sorted([r[0] for r in rows[start:end]])
            ys = sorted([r[1] for r in rows[start:end]])
            lo, hi = (k - 1) // 2, k // 2
            self._shift[i] = ((xs[lo] + xs[hi]) / 2, (ys[lo] + ys[hi]) / 2)
            self._has_shift[i] = True

    def _featureless_border(self, has_points: list[bool]) -> bool:
        """True when every window without points is blank (and at least one is)."""
        empty = ~np.asarray(has_points, bool)
        return bool(empty.any() and self._textureless[empty].all())

    def _reseed(self, gray: np.ndarray) -> None:
        """Alg. 1 lines 3–7: top up every window that has fewer than n points."""
        c = self.cfg
        if self.full_frame:
            # Baseline: fresh corners over the whole frame every frame.
            pts = cv2.goodFeaturesToTrack(
                gray, FULL_FRAME_CORNERS, c.feature_quality, c.feature_min_distance_px
            )
            self._pts = _NO_POINTS if pts is None else pts.reshape(-1, 2).astype(np.float32)
            self._wid = np.zeros(len(self._pts), np.intp)
            self._counts = [len(self._pts)]
            return
        fresh: dict[int, np.ndarray] = {}
        for i, (x0, y0, x1, y1) in enumerate(self._windows):
            if self._counts[i] >= c.min_points_per_window:
                continue
            patch = gray[y0:y1, x0:x1]
            self._textureless[i] = float(cv2.cornerMinEigenVal(patch, 3).max()) < c.min_texture
            if self._textureless[i]:
                continue
            found = cv2.goodFeaturesToTrack(
                patch, c.max_points_per_window, c.feature_quality, c.feature_min_distance_px
            )
            if found is not None:
                # replaces the window's thin set with a fresh one
                fresh[i] = (found.reshape(-1, 2) + np.array([x0, y0], np.float32)).astype(np.float32)
        if not fresh:
            return
        parts, end = [], 0
        for i, k in enumerate(self._counts):
            start, end = end, end + k
            parts.append(fresh.get(i, self._pts[start:end]))
        self._counts = [len(p) for p in parts]
        self._pts = np.concatenate(parts)
        self._wid = np.repeat(np.arange(len(parts)), self._counts)

    # ------------------------------------------------------------------ differencing

    def _threshold(self, merged: np.ndarray) -> np.ndarray | None:
        """The motion mask of a merged difference (border cleared, median, dilation,
        threshold); None when it covers more than ``max_mask_frac`` of the frame."""
        b = self.cfg.border_px
        if b:
            merged[:b, :] = 0
            merged[-b:, :] = 0
            merged[:, :b] = 0
            merged[:, -b:] = 0
        if self.cfg.median_ksize > 1:
            merged = cv2.medianBlur(merged, self.cfg.median_ksize)
        if self._dilate_kernel is not None:
            merged = cv2.dilate(merged, self._dilate_kernel)
        _, mask = cv2.threshold(merged, self.cfg.threshold, 255, cv2.THRESH_BINARY)
        if cv2.countNonZero(mask) > self.cfg.max_mask_frac * mask.size:
            return None
        return mask

    def _difference(self, nxt: np.ndarray, h_cur_next: np.ndarray | None,
                    chroma_next: np.ndarray | None = None) -> tuple[np.ndarray | None, str]:
        """Motion mask of frame t from frames t-1, t, t+1 (Alg. 1 lines 11–12).

        Each frame is warped once: |I_{t+1} - W(I_t)| is computed in t+1's pixels, kept as
        next step's "previous" difference, and brought back into t's pixels for this step
        by a nearest-neighbour warp of the difference image (a third of a bilinear warp of
        the frame, and the median filter follows anyway), or, when the motion is close
        enough to a translation, by whole-pixel shifts of its tiles (:func:`_shift_tiles`).
        """
        cur = self._cur
        if cur is None:
            return None, "warmup"
        prev_diff = self._diff_cur  # |I_t - W(I_{t-1})| in t's pixels, or None
        self._diff_cur = None
        next_diff = None
        if h_cur_next is not None:
            self._diff_cur = _compensated_diff(cur, nxt, h_cur_next)
            next_diff = _shift_tiles(self._diff_cur, h_cur_next)
            if next_diff is None:  # the frame turned or zoomed too much for tiles to shift
                next_diff = cv2.warpPerspective(
                    self._diff_cur, h_cur_next, (cur.shape[1], cur.shape[0]),
                    flags=cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP, borderValue=0,
                )
        if not self._has_prev:
            return None, "warmup"  # the first frame has no previous frame
        if prev_diff is None or next_diff is None:
            only = prev_diff if prev_diff is not None else next_diff
            if only is None:
                return None, "no_homography"
            merged, status = only, "one_sided"
        elif self.cfg.combine == "min":
            merged, status = cv2.min(prev_diff, next_diff), "ok"
        else:
            merged, status = cv2.addWeighted(prev_diff, 0.5, next_diff, 0.5, 0.0), "ok"
        chroma = self._chroma_difference(chroma_next, h_cur_next)
        if chroma is not None:
            merged = cv2.max(merged, chroma)
        slow = self._slow_difference()
        mask = self._threshold(cv2.max(merged, slow) if slow is not None else merged)
        if mask is None and slow is not None:
            mask = self._threshold(merged)  # the slow difference never costs a frame
        if mask is None:
            # Real objects are small; a mask this large is the background failing to register.
            log.warning("bad_warp", "motion mask covers over %.0f %% of the frame: frame skipped",
                        100 * self.cfg.max_mask_frac)
            return None, "bad_warp"
        return mask, status


_HALF = np.diag([0.5, 0.5, 1.0])  # full-resolution px -> pyrDown's px (pixel centres 2i -> i)
_DOUBLE = np.diag([2.0, 2.0, 1.0])
_KERNEL3 = cv2.getStructuringElement(cv2.MORPH_RECT, (3, 3))


def _half_ycrcb(colour: np.ndarray | None, shape: tuple[int, int]) -> np.ndarray | None:
    """``colour`` (8-bit BGR of the grey frame's size) at half resolution in YCrCb; None for
    no colour or a grey frame. Area averaging is 6x cheaper than pyrDown on three channels;
    its pixel centres sit a quarter of a half-resolution pixel off ``_HALF``'s, which the
    median and dilation that follow do not resolve. A 3-channel warp at this size costs less
    than two single-channel ones (OpenCV's 2-channel warp is slower than either)."""
    if colour is None or colour.ndim != 3 or colour.shape[2] != 3:
        return None
    if colour.shape[:2] != shape:
        raise ValueError(f"colour frame {colour.shape[1]}x{colour.shape[0]} is not the grey "
                         f"frame's {shape[1]}x{shape[0]}")
    h, w = shape
    small = cv2.resize(colour, ((w + 1) // 2, (h + 1) // 2), interpolation=cv2.INTER_AREA)
    return cv2.cvtColor(small, cv2.COLOR_BGR2YCrCb)


def _compensated_diff(src: np.ndarray, dst: np.ndarray, h: np.ndarray) -> np.ndarray:
    """|dst - src warped onto dst|, in dst's pixels; ``h`` maps src px -> dst px.

    Pixels with no source keep dst's value, so their difference is 0, not a false edge.
    """
    return cv2.absdiff(dst, _warp_onto(src, h, dst))


def _warp_onto(src: np.ndarray, h: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """``src`` warped bilinearly by ``h`` (src px -> dst px) onto a copy of ``dst``, with
    OpenCV's transparent border (where a pixel has no source, ``dst``'s own value stays).

    The transparent border takes the whole warp off OpenCV's vectorised path (1.05 against
    0.63 ms at 640 x 480 here, 0.29 against 0.15 at half). So the frame is warped with a
    constant border, which gives the same pixels wherever a pixel's whole bilinear
    neighbourhood lies inside ``src`` (but for the grey level the two paths round differently
    at a few pixels), and only the strips outside the largest upright rectangle where that
    holds (a few px wide for a frame-to-frame motion) are warped with the transparent border.
    A homography that sends a corner behind the camera, or turns the frame so that no such
    rectangle is found, is warped transparently whole.
    """
    rows, cols = src.shape[:2]
    width, height = dst.shape[1], dst.shape[0]
    hom = np.asarray(h, np.float64)
    (a, b, c), (d, e, f), (g, k, m) = hom.tolist()
    # a pixel is interpolated from inside where its source lies in [0, cols - 1) x [0, rows - 1);
    # the rectangle is found from that region shrunk by a pixel, against rounding
    quad: list[tuple[float, float]] = []  # TL, TR, BR, BL of the region, in dst px
    for x, y in ((1.0, 1.0), (cols - 2.0, 1.0), (cols - 2.0, rows - 2.0), (1.0, rows - 2.0)):
        w = g * x + k * y + m
        if w < 1e-6:
            quad = []
            break
        quad.append(((a * x + b * y + c) / w, (d * x + e * y + f) / w))
    x0 = x1 = y0 = y1 = 0
    if quad and cols >= 4 and rows >= 4:
        (tlx, tly), (trx, try_), (brx, bry), (blx, bly) = quad
        x0 = min(width, max(0, math.ceil(max(tlx, blx))))
        x1 = max(x0, min(width, math.floor(min(trx, brx)) + 1))
        y0 = min(height, max(0, math.ceil(max(tly, try_))))
        y1 = max(y0, min(height, math.floor(min(bry, bly)) + 1))
        poly = np.array(quad, np.float32)
        inner = ((x0, y0), (x1 - 1, y0), (x1 - 1, y1 - 1), (x0, y1 - 1))
        if x1 <= x0 or y1 <= y0 or min(cv2.pointPolygonTest(poly, (float(x), float(y)), False)
                                       for x, y in inner) < 0:
            x0 = x1 = y0 = y1 = 0
    if x1 <= x0:
        out = dst.copy()
        cv2.warpPerspective(src, hom, (width, height), dst=out, flags=cv2.INTER_LINEAR,
                            borderMode=cv2.BORDER_TRANSPARENT)
        return out
    out = cv2.warpPerspective(src, hom, (width, height), flags=cv2.INTER_LINEAR,
                              borderMode=cv2.BORDER_CONSTANT)
    strips = ((0, 0, width, y0), (0, y1, width, height), (0, y0, x0, y1), (x1, y0, width, y1))
    for sx0, sy0, sx1, sy1 in strips:
        if sx1 <= sx0 or sy1 <= sy0:
            continue
        strip = dst[sy0:sy1, sx0:sx1].copy()  # a copy: a full-width strip would be a view of dst
        shift = np.array([[1.0, 0.0, -sx0], [0.0, 1.0, -sy0], [0.0, 0.0, 1.0]]) @ hom
        cv2.warpPerspective(src, shift, (sx1 - sx0, sy1 - sy0), dst=strip, flags=cv2.INTER_LINEAR,
                            borderMode=cv2.BORDER_TRANSPARENT)
        out[sy0:sy1, sx0:sx1] = strip
    return out


def _shift_tiles(diff: np.ndarray, h: np.ndarray) -> np.ndarray | None:
    """``diff`` (in t+1's pixels) brought into t's pixels by moving each of ``TILES`` x
    ``TILES`` tiles by one whole-pixel shift; ``h`` maps t px -> t+1 px. None when at some
    tile corner the shift misses ``h`` by more than ``SHIFT_TOLERANCE_PX`` (rotation, zoom):
    then the caller warps.

    Only the difference image is moved this way, never a frame: the background was registered
    by the bilinear warp before differencing, so the tolerance only blurs where a moving blob
    is placed, as the nearest-neighbour warp does by up to half a pixel. In the pipeline it
    costs about a third of that warp (the bench's flight: 4-5 % of a frame's time saved,
    paired runs); plain Python, as numpy's call overhead on a 5 x 5 grid ate the saving.
    """
    height, width = diff.shape
    (a, b, c), (d, e, f), (g, k, m) = h.tolist()
    xs = [width * j // TILES for j in range(TILES + 1)]
    ys = [height * i // TILES for i in range(TILES + 1)]
    moves = []  # per grid corner: where h moves it, relative to itself (px)
    for y in ys:
        row = []
        for x in xs:
            w = g * x + k * y + m
            if w < 1e-6:  # the corner goes through the horizon: no shift comes near (and no /0)
                return None
            row.append(((a * x + b * y + c) / w - x, (d * x + e * y + f) / w - y))
        moves.append(row)
    tol = SHIFT_TOLERANCE_PX
    # Tiles side by side with the same shift are moved as one run, and tile rows with the same
    # runs as one band: a pan moves the whole image in one copy (the union of the tiles'
    # clipped rectangles is the clipped union).
    bands: list[list] = []  # [first tile row, last + 1, runs]; a run is [first tile, last + 1, sx, sy]
    for i in range(TILES):
        top, bottom = moves[i], moves[i + 1]
        runs: list[list[int]] = []
        for j in range(TILES):
            (u0, v0), (u1, v1) = top[j], top[j + 1]
            (u2, v2), (u3, v3) = bottom[j], bottom[j + 1]
            sx = round((u0 + u1 + u2 + u3) / 4)
            sy = round((v0 + v1 + v2 + v3) / 4)
            if (abs(u0 - sx) > tol or abs(u1 - sx) > tol or abs(u2 - sx) > tol or abs(u3 - sx) > tol
                    or abs(v0 - sy) > tol or abs(v1 - sy) > tol or abs(v2 - sy) > tol or abs(v3 - sy) > tol):
                return None
            if runs and runs[-1][2] == sx and runs[-1][3] == sy:
                runs[-1][1] = j + 1
            else:
                runs.append([j, j + 1, sx, sy])
        if bands and bands[-1][2] == runs:
            bands[-1][1] = i + 1
        else:
            bands.append([i, i + 1, runs])
    out = np.zeros_like(diff)  # what comes from outside t+1's frame: no difference
    for i0, i1, runs in bands:
        for j0, j1, sx, sy in runs:
            x0, x1 = max(xs[j0], -sx), min(xs[j1], width - sx)
            y0, y1 = max(ys[i0], -sy), min(ys[i1], height - sy)
            if x1 > x0 and y1 > y0:
                out[y0:y1, x0:x1] = diff[y0 + sy:y1 + sy, x0 + sx:x1 + sx]
    return out


def _in_boxes(points: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    """Which of ``points`` (M, 2: x, y image px) lie in their own box of ``boxes`` (M, 4: x0, y0,
    x1, y1 image px, the far sides excluded); (M,) bool."""
    x, y = points[:, 0], points[:, 1]
    return (x >= boxes[:, 0]) & (y >= boxes[:, 1]) & (x < boxes[:, 2]) & (y < boxes[:, 3])


def _global_shift(src: np.ndarray, dst: np.ndarray, scale: int = 4) -> np.ndarray | None:
    """The translation of ``dst`` against ``src`` (image px, (dx, dy)) by phase correlation of
    1/``scale`` copies, or None when the correlation peak is too weak to trust."""
    size = (src.shape[1] // scale, src.shape[0] // scale)
    a = cv2.resize(src, size, interpolation=cv2.INTER_AREA).astype(np.float32)
    b = cv2.resize(dst, size, interpolation=cv2.INTER_AREA).astype(np.float32)
    (dx, dy), response = cv2.phaseCorrelate(a, b, cv2.createHanningWindow(size, cv2.CV_32F))
    if response < MIN_PHASE_RESPONSE:
        return None
    return np.array([dx * scale, dy * scale], np.float32)


def _plausible(h: np.ndarray) -> bool:
    """Reject degenerate fits: consecutive frames differ by a small motion."""
    (a, b, _), (c, d, _), (p, q, _) = h.tolist()
    det = a * d - b * c
    return 0.5 < det < 2.0 and abs(p) < 1e-2 and abs(q) < 1e-2


def _grey_histogram(gray: np.ndarray) -> np.ndarray:
    """32-bin histogram of every 4th pixel: cheap and blind to camera pans, not to cuts."""
    return cv2.calcHist([gray[::4, ::4]], [0], None, [32], [0, 256])
