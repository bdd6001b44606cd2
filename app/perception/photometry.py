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


def contrast_flux(grey: np.ndarray, box: tuple[int, int, int, int]) -> tuple[float, float] | None:
    """(flux, its standard error), grey levels x px², over ``box`` (x, y, w, h px) grown by
    ``MARGIN_PX``, against the mean of the patch's outer ``RING_PX`` band; None when the
    patch leaves the frame (a cut object's flux is a cut one)."""
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
    # ring with structure in it shows as spread, which the error carries)
    (ma,), (sa,) = (v.ravel() for v in cv2.meanStdDev(patch))
    (mi,), (si,) = (v.ravel() for v in cv2.meanStdDev(inner))
    s_all, s_in = float(ma) * patch.size, float(mi) * inner.size
    q_all = (float(sa) ** 2 + float(ma) ** 2) * patch.size
    q_in = (float(si) ** 2 + float(mi) ** 2) * inner.size
    n, m = inner.size, patch.size - inner.size
    bg = (s_all - s_in) / m
    spread = math.sqrt(max(0.0, (q_all - q_in) / m - bg * bg))
    flux = abs(s_in - bg * n)
    # the sum's own noise plus the background's error spread over the whole inner patch
    std = max(spread, 0.5) * (math.sqrt(n) + n / math.sqrt(m))
    return flux, max(std, REL_FLOOR * flux)
