"""An object's contrast flux: its size from the pixels' values, not from the mask's box.

A small object's box in the motion mask is a poor measure of its size: the mask's dilation
and threshold add a few pixels, a merge or split with noise adds or removes whole rows, and
at 5-10 px those steps are as large as the growth that says it is approaching (seen: a drone
of 4.4 px read 9-13 px from frame to frame, and its looming gave a time to contact of 0.5 s
with 3.6 s left). The light it takes away from (or adds to) its background does not step:

    flux = | sum over a patch around it of (grey - background) |

is its area times its contrast, whatever the blur, with the noise of a sum. On one object
against one background the contrast stays the same, so sqrt(flux) is proportional to its
angular size, to a fraction of a pixel, and its looming is exact in the same way. What it
needs is a background that the patch's border ring describes: against sky it is, against
texture its error (which the ring's spread measures) says it is not.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

MARGIN_PX = 3  # the patch is the box grown by this on every side, px
RING_PX = 2  # its outer band of this width gives the background, px
REL_FLOOR = 0.02  # flux error never below this fraction of it (rendering, compression)


def _ring(grey: np.ndarray, box: tuple[int, int, int, int]
          ) -> tuple[np.ndarray, int, float, float, float] | None:
    """Of ``box`` (x, y, w, h px)'s patch grown by ``MARGIN_PX`` and ``RING_PX``: its inner
    part (less the outer ``RING_PX`` band), the band's pixel count, the inner part's sum, and
    the band's mean and spread; None when the patch leaves the frame (a cut object's measure
    is a cut one)."""
    height, width = grey.shape[:2]
    x, y, w, h = box
    g = MARGIN_PX + RING_PX
    x0, y0, x1, y1 = x - g, y - g, x + w + g, y + h + g
    if x0 < 0 or y0 < 0 or x1 > width or y1 > height or w <= 0 or h <= 0:
        return None
    patch = grey[y0:y1, x0:x1]
    inner = patch[RING_PX:-RING_PX, RING_PX:-RING_PX]
    # the ring's mean and spread from the patch's and the inner part's (a median costs 80 us
    # a track; the box already holds the object with the mask's dilation around it, and a
    # ring with structure in it shows as spread, which the errors carry)
    (ma,), (sa,) = (v.ravel() for v in cv2.meanStdDev(patch))
    (mi,), (si,) = (v.ravel() for v in cv2.meanStdDev(inner))
    s_all, s_in = float(ma) * patch.size, float(mi) * inner.size
    q_all = (float(sa) ** 2 + float(ma) ** 2) * patch.size
    q_in = (float(si) ** 2 + float(mi) ** 2) * inner.size
    m = patch.size - inner.size
    bg = (s_all - s_in) / m
    spread = math.sqrt(max(0.0, (q_all - q_in) / m - bg * bg))
    return inner, m, s_in, bg, spread


def _flux(inner: np.ndarray, m: int, s_in: float, bg: float, spread: float) -> tuple[float, float]:
    n = inner.size
    flux = abs(s_in - bg * n)
    # the sum's own noise plus the background's error spread over the whole inner patch
    std = max(spread, 0.5) * (math.sqrt(n) + n / math.sqrt(m))
    return flux, max(std, REL_FLOOR * flux)


def contrast_flux(grey: np.ndarray, box: tuple[int, int, int, int]) -> tuple[float, float] | None:
    """(flux, its standard error), grey levels x px², over ``box`` (x, y, w, h px) grown by
    ``MARGIN_PX``, against the mean of the patch's outer ``RING_PX`` band; None when the
    patch leaves the frame (a cut object's flux is a cut one)."""
    ring = _ring(grey, box)
    if ring is None:
        return None
    return _flux(*ring)


CORE_SIGMAS = 3.0  # half the core's contrast must stand this many ring spreads above the ring
CORE_PEAK_PX = 5  # the core's contrast: the median of this many most extreme pixels


def _core(inner: np.ndarray, m: int, s_in: float, bg: float, spread: float
          ) -> tuple[float, float] | None:
    d = inner.astype(np.float32).ravel() - np.float32(bg)
    if s_in - bg * inner.size < 0:
        d = -d  # a dark object: its pixels below the ring's
    k = min(CORE_PEAK_PX, d.size)
    c = float(np.median(np.partition(d, d.size - k)[-k:]))
    if c / 2 < CORE_SIGMAS * max(spread, 0.5):
        return None
    area = float(np.count_nonzero(d > c / 2))
    # pixels near the half-contrast line flip with the noise: the contour's length times the
    # band the noise moves it by (the edge rises over about two pixels)
    perimeter = 2.0 * math.sqrt(math.pi * area)
    std = math.sqrt(1.0 + perimeter * 2.0 * max(spread, 0.5) / c)
    return area, max(std, REL_FLOOR * area)


def core_area(grey: np.ndarray, box: tuple[int, int, int, int]) -> tuple[float, float] | None:
    """(area, its standard error), px², of the pixels of ``box``'s patch (as
    :func:`contrast_flux`'s) that differ from the ring's mean, in the object's sense, by more
    than half the object's own contrast (its core's: the median of its ``CORE_PEAK_PX`` most
    extreme pixels). sqrt(area) is proportional to the angular size: a half-maximum area,
    which neither the contrast nor the texture around the object inside the patch moves (the
    flux sums that texture in: against ground its square root over the radius ran 8.0-15.1,
    the core area's 1.70-1.82 where a disc gives sqrt(pi) = 1.77). None when the patch
    leaves the frame or half the contrast is within ``CORE_SIGMAS`` ring spreads (texture would
    count as object)."""
    ring = _ring(grey, box)
    if ring is None:
        return None
    return _core(*ring)


def measure(grey: np.ndarray, box: tuple[int, int, int, int]
            ) -> tuple[tuple[float, float] | None, tuple[float, float] | None]:
    """(:func:`contrast_flux`, :func:`core_area`) of one box, its ring measured once."""
    ring = _ring(grey, box)
    if ring is None:
        return None, None
    return _flux(*ring), _core(*ring)
