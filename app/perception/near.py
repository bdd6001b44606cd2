"""Objects that stand out in depth, not in grey: the depth path of detection (issue 19, item 1).

An object as bright as the ground behind it (a mid-grey bird climbing towards the vehicle
over fields) leaves almost nothing in the frame difference, and on a collision course it
holds its bearing, so its rim grows by a fraction of a pixel a frame: the closed loop's
campaign at 1af4426 first tracked 21 of its 81 birds under 1.0 s before the closest approach
(6 of 65 balls and 2 of 71 drones, which are dark), and lost 19 of them. The stereo camera
sees such a bird plainly: 19 m in front of ground 35 m away is 6.6 standard errors of the
D435i's inverse depth (a frame of docs/campaign-bearings, encounter 4100219).

So, where the depth is registered to the image (the infrared imager's own lens; in simulation
too only with that stream, see :func:`depth_lens`), a pixel is marked when its inverse depth
exceeds that of the valid depth beside it on its own image row by ``near_sigmas`` of the stereo
camera's inverse-depth error (constant for a stereo pair: the RMS error 0.0036 z² of Intel's
D400 formula is 0.0036 /m in 1/z). Along a row, not around the pixel: a level camera sees flat
ground at one range along each row (its inverse depth is linear in the row), so the ground
cancels to the frame's edges, where a window around the pixel would be cut and biased; banked,
the ground's inverse depth is linear along the row too, and a symmetric window cancels it (25
degrees, an evasion's bank, marks nothing: tests/test_near.py). What has no valid depth beside
it (an object against the sky, where depth is empty) marks nothing: the grey difference sees it
there. Static structure nearer than what is behind it (a tree in front of far ground) is marked
too; it is the decision's depth track, not this mask, that tells whether it closes.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import cv2
import numpy as np

from app.camera import CameraModel

MIN_M = 0.2  # the D435i's nearest depth at 848 x 480 is ~0.2-0.3 m (Intel's datasheet): nearer is noise
MAX_M = 65.535  # what a uint16 millimetre frame holds
# A marked patch holding fewer pixels than this share of a disc as wide as the smallest object
# (``near_min_size_m``) at the patch's distance is dropped: as decision.min_depth_cover, whose
# measurement it shares (real objects' near surfaces held >= 0.96 of that disc in the open loop,
# seed 11, `stereo` world; clumps of wrong matches 0.01-0.2)
MIN_COVER = 0.25
# How far a marked patch may have moved since the frame before and still count as there a frame
# ago (grow_persistent), px: a threat on a collision course holds its bearing and only grows (its
# rim by under a pixel a frame until its last half second)
REACH_PX = 8
# ... and how much its mean inverse depth may have changed (a share of it): a threat closing at
# 25 m/s changes its range by 0.83 m a frame at 30 fps, 15 % of it at 5.5 m, nearer than which
# its marks make a cluster by themselves (a 0.25 m ball there is 19 px across)
SAME_RANGE = 0.15


def patch_floor_px(fx_px: float, fy_px: float, size_m: float, cover: float = MIN_COVER) -> float:
    """The fewest depth pixels a surface 1 m off must hold (``cover`` of a disc ``size_m``
    across, in a depth lens of focal lengths ``fx_px``, ``fy_px``); at z m, this over z²; 0
    when ``size_m`` or ``cover`` is 0 (no floor)."""
    return cover * math.pi / 4.0 * (size_m * fx_px) * (size_m * fy_px)


def depth_lens(camera: CameraModel, stream: str) -> CameraModel | None:
    """The calibration the depth path may use with ``capture.stream`` = ``stream``: the
    camera's for the infrared imager, None for the colour camera. A D435i computes depth in
    its left infrared imager's frame, so only that stream has depth in its own pixels; the
    simulation draws depth in whichever lens it renders, and would otherwise give the colour
    stream a depth path the hardware cannot have."""
    return camera if stream == "infrared" else None


def registered(camera: CameraModel | None, shape: tuple[int, int]) -> bool:
    """Is ``camera``'s depth in the image's own pixels (same lens, no offset), for frames
    of ``shape`` (rows, cols)? Only then does a depth pixel sit under the image pixel of the
    same index."""
    if camera is None:
        return False
    c, d = camera.color, camera.depth
    # (tolerances: a hundredth of a pixel, a tenth of a millimetre, as the SDK's floats give
    # the left infrared imager and the depth computed in its frame)
    return ((c.width, c.height) == (d.width, d.height) == (shape[1], shape[0])
            and max(abs(c.fx - d.fx), abs(c.fy - d.fy), abs(c.ppx - d.ppx), abs(c.ppy - d.ppy)) < 0.01
            and np.allclose(camera.rotation, np.eye(3), atol=1e-4)
            and np.allclose(camera.translation_m, 0.0, atol=1e-4))


def _second_nearest_of_blocks(depth: np.ndarray) -> np.ndarray:
    """``depth`` (uint16, 0 = no data) at half resolution, each pixel the second nearest valid
    depth of its 2 x 2 block (0 where the block has fewer than two). Not every other pixel: a
    bird seen head-on is a line of wing one or two rows tall, which every other row misses half
    the time (the shaped world, seed 43: birds 10-20 m off in front of ground 30 m off, first
    marked at 11 m); not the nearest either: a stereo camera's lone wrong matches, some far
    nearer than the ground, would be kept four times as often. Two pixels of a block hold a
    line one pixel thick in either direction, and one pixel of data beside no data is no data,
    as before: one value of the block, never a mixture."""
    if depth.dtype != np.uint16:
        raise ValueError(f"near_mask: expected uint16 depth, got {depth.dtype}")
    h, w = depth.shape
    shifted = depth - np.uint16(1)  # no data (0) wraps to 65535: never nearer than data
    if h % 2 or w % 2:  # (odd sizes: the last row or column pairs with itself)
        shifted = np.pad(shifted, ((0, h % 2), (0, w % 2)), mode="edge")
    top, bottom = shifted[0::2], shifted[1::2]
    a, b = top[:, 0::2], top[:, 1::2]
    c, d = bottom[:, 0::2], bottom[:, 1::2]
    low1, high1 = np.minimum(a, b), np.maximum(a, b)
    low2, high2 = np.minimum(c, d), np.maximum(c, d)
    second = np.minimum(np.maximum(low1, low2), np.minimum(high1, high2))
    return second + np.uint16(1)  # 65535 (fewer than two with data) wraps back to 0


def near_mask(depth: np.ndarray, scale_m: float, sigmas: float, noise_per_m: float,
              window_px: int, min_m: float, max_m: float, floor_px: float = 0.0) -> np.ndarray:
    """The pixels (uint8 0/255, ``depth``'s shape) whose inverse depth exceeds the mean
    inverse depth of the valid pixels within ``window_px`` on their row (worked at half
    resolution) by ``sigmas`` x ``noise_per_m`` (1/m), with at least a third of that
    window valid. ``depth`` in units of ``scale_m``; depths outside [``min_m``, ``max_m``]
    are no data. A connected patch of marks at mean inverse depth 1/z holding fewer than
    ``floor_px`` / z² pixels (:func:`patch_floor_px`) is dropped: smaller than any object
    could be at that distance."""
    if depth.ndim != 2:
        raise ValueError(f"near_mask: expected a single-channel depth image, got shape {depth.shape}")
    h, w = depth.shape
    half = _second_nearest_of_blocks(depth)
    lo, hi = min_m / scale_m, max_m / scale_m  # in depth units
    valid = cv2.inRange(half, math.ceil(lo), min(math.floor(hi), 65535))  # 255 where valid
    ones = cv2.convertScaleAbs(valid, alpha=1.0 / 255.0).astype(np.float32)  # 1.0 where valid
    # 1/z in 1/m, 0 where no data (no data, 0, is divided as 1 unit so that nothing is infinite)
    inv = cv2.multiply(cv2.divide(1.0 / scale_m, cv2.max(half.astype(np.float32), 1.0)), ones)
    k = max(3, (window_px // 2) | 1)
    total = cv2.boxFilter(inv, -1, (k, 1), normalize=False, borderType=cv2.BORDER_CONSTANT)
    count = cv2.boxFilter(ones, -1, (k, 1), normalize=False, borderType=cv2.BORDER_CONSTANT)
    # the pixel's own value is left out of its background: with n valid pixels beside it
    # (count less itself) summing to s, it stands out when inv - s / n > bar, that is when
    # inv * n - s > bar * n (no division)
    count = cv2.subtract(count, ones)
    total = cv2.subtract(total, inv)
    excess = cv2.subtract(cv2.multiply(inv, count), total)
    stands = cv2.compare(excess, cv2.multiply(count, sigmas * noise_per_m), cv2.CMP_GT)
    small = np.where((count >= k / 3.0) & (valid > 0), stands, np.uint8(0)).astype(np.uint8)
    # A mark needs another beside it (at half resolution, 2 px in the frame): a stereo camera's
    # wrong matches are single pixels at random depths, some far nearer than the ground around
    # them, and marked alone they became most of a blob whose depth was then theirs (the
    # `stereo` world, open loop: a cluster over far ground read 2.9 m closing at 18 m/s and
    # evaded). An object worth a range covers several: 4 px of the frame are 2 here.
    beside = cv2.boxFilter(cv2.convertScaleAbs(small, alpha=1.0 / 255.0), -1, (3, 3), normalize=False,
                           borderType=cv2.BORDER_CONSTANT)
    small[beside < 2] = 0
    out = np.zeros((h, w), np.uint8)
    x, y, bw, bh = cv2.boundingRect(small)  # mostly nothing is marked: only that box is worked on
    if bw and bh and floor_px > 0:
        # Patches too small for an object at their distance: stereo's wrong matches come in
        # clumps too, and 3 x 3 clumps over 1.8 % of the frame were marked, merged into blobs
        # and read as surfaces 2.6-5 m off (126 false evasions in 10 object-free minutes)
        sub = small[y:y + bh, x:x + bw]
        n, labels, stats, _ = cv2.connectedComponentsWithStats(sub, connectivity=8)
        area = stats[:, cv2.CC_STAT_AREA].astype(np.float64)
        inv_z = np.bincount(labels.ravel(), weights=inv[y:y + bh, x:x + bw].ravel(),
                            minlength=n) / np.maximum(area, 1.0)  # (the background may be empty)
        small_px = area * 4.0  # (half resolution: each mark stands for 2 x 2 pixels)
        drop = small_px < floor_px * inv_z * inv_z
        drop[0] = False  # (the unmarked background)
        if drop.any():
            sub[drop[labels]] = 0
            x, y, bw, bh = cv2.boundingRect(small)
    if bw and bh:
        up = np.repeat(np.repeat(small[y:y + bh, x:x + bw], 2, axis=0), 2, axis=1)
        x0, y0 = 2 * x, 2 * y
        out[y0:y0 + 2 * bh, x0:x0 + 2 * bw] = up[:h - y0, :w - x0]
    return out


class Patches(NamedTuple):
    """One frame's marked patches, for the next frame's :func:`grow_persistent`: each marked
    pixel's patch mean inverse depth (1/m, float32, 0 unmarked) over a box of the frame whose
    top-left pixel is (``x``, ``y``); nothing is marked outside it."""

    x: int
    y: int
    inverse_m: np.ndarray


def grow_persistent(marks: np.ndarray, depth: np.ndarray, scale_m: float, before: Patches | None,
                    reach_px: int, dilate_px: int) -> tuple[np.ndarray, Patches | None]:
    """``marks`` (uint8 0/255) with each connected patch that was there a frame ago dilated by
    a ``dilate_px`` square; and what the next frame's call takes as ``before`` (None when
    nothing is marked).

    There a frame ago: within ``reach_px`` of a patch of the frame before whose mean range
    is within ``SAME_RANGE`` of its own. Dilated as the grey difference is before its threshold
    (``detection.dilate_ksize``), so that an object is as large a blob in either mask: the
    recognizer's smallest cluster (``recognition.area_px``) is set for dilated blobs, and a
    bird seen head-on, a wing line of 20 marked px at 20 m, made a cluster only from 9 m on
    (the shaped world, seed 43). Only patches that were there: an object on a collision course
    holds its bearing and its range, while a stereo camera's wrong matches come and go at
    random ranges, and grown they became clusters, tracks and commands (the `stereo_clumps`
    world, seed 43: object-free flights whose fast run would command, 1 -> 21 of 40 when
    every patch was grown, 3 when those within reach of one of the frame before were, 1 with
    the range checked too)."""
    x, y, bw, bh = cv2.boundingRect(marks)
    if not (bw and bh):
        return marks, None
    h, w = marks.shape
    m = max(reach_px, dilate_px // 2 + 1)  # a margin the dilations cannot cross
    ya, yb, xa, xb = max(0, y - m), min(h, y + bh + m), max(0, x - m), min(w, x + bw + m)
    box = marks[ya:yb, xa:xb]
    n, labels = cv2.connectedComponents(box, connectivity=8)
    d = depth[ya:yb, xa:xb]
    with_data = (box > 0) & (d > 0)
    inv = 1.0 / (d[with_data].astype(np.float64) * scale_m)
    count = np.bincount(labels[with_data], minlength=n)
    # (label 0, the unmarked background, has no pixel with data: its mean is 0)
    mean = np.bincount(labels[with_data], weights=inv, minlength=n) / np.maximum(count, 1)
    here = mean[labels].astype(np.float32)
    patches = Patches(xa, ya, here)
    if before is None or dilate_px <= 1:
        return marks, patches
    prev = np.zeros_like(here)  # the frame before's patches, in this box
    bx, by = before.x, before.y
    rows, cols = before.inverse_m.shape
    ox0, oy0, ox1, oy1 = max(xa, bx), max(ya, by), min(xb, bx + cols), min(yb, by + rows)
    if ox1 <= ox0 or oy1 <= oy0:
        return marks, patches
    prev[oy0 - ya:oy1 - ya, ox0 - xa:ox1 - xa] = before.inverse_m[oy0 - by:oy1 - by, ox0 - bx:ox1 - bx]
    reach = cv2.getStructuringElement(cv2.MORPH_RECT, (2 * reach_px + 1, 2 * reach_px + 1))
    nearest = cv2.dilate(prev, reach)  # the nearest patch of the frame before within reach
    farthest = cv2.erode(np.where(prev > 0, prev, np.float32(np.inf)), reach)
    same = (here > 0) & (nearest > 0) & (here <= nearest * (1.0 + SAME_RANGE)) & (
        here >= farthest * (1.0 - SAME_RANGE))
    seen = np.zeros(n, bool)
    seen[labels[same]] = True  # (never the background: its ``here`` is 0)
    if not seen.any():
        return marks, patches
    out = marks.copy()
    grown = cv2.dilate(np.where(seen[labels], np.uint8(255), np.uint8(0)),
                       cv2.getStructuringElement(cv2.MORPH_RECT, (dilate_px, dilate_px)))
    out[ya:yb, xa:xb] |= grown
    return out, patches
