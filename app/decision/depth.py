"""Distance of a recognised object from the depth frame, without aligning whole frames.

``rs.align`` re-projects every depth pixel every frame and costs a Pi 4 most of its frame
rate (about 28 → 6 fps reported by RealSense users). Only the object's pixels matter, so:
the object's colour box is mapped into the depth image for the nearest and farthest
trusted depth (a small region of interest), the valid depth pixels there are projected into
the colour image with the calibration, and those landing on the object's *blob* pixels
(not its whole box) give the distance by a low percentile (the near surface; background
bleeding through a loose blob is farther and is discounted), and the bearing by where those
of them at that distance lie (not the blob's centre: a frame difference's blob holds the
object's old place too, and a blob merged with the ground or a tree behind it is centred
between the two).

Depth 0 is "no data", never "zero metres". The near surface is taken over the blob's depths
to the trusted range's end and its error band beyond it (``NEAR_BAND_SIGMAS`` range errors), and
farther than the trusted range it gives no distance: taken over the trusted range alone, a
surface just beyond it gave its noise's near tail as a distance (a building 17.7 m off "at
15 m": object-free flight, seed 43), and taken over every depth the frame holds, the ground
30-40 m behind a ball outnumbered the ball in a blob merged with the horizon (open loop).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from app.camera import CameraModel
from app.perception.near import patch_floor_px
from app.perception.recognition import Cluster

# The near surface: depth points within this many range errors of the object's distance ...
NEAR_BAND_SIGMAS = 3.0
# ... the error being at least this near by, where z² is small: an object's own near surface
# spans a few centimetres of depth, and the D435i errs by under 2 % at 2 m (Intel's D400
# datasheet), m
NEAR_BAND_FLOOR_M = 0.1
# The farthest depth a D435i frame holds: uint16 millimetres, m
DEPTH_FAR_M = 65.535


def range_error_m(z_m: float, rms_per_m2: float, floor_m: float) -> float:
    """The D435i's range error at ``z_m`` (it grows as ``rms_per_m2`` · z², Intel's D400 RMS
    error formula), never below ``floor_m``, m."""
    return max(floor_m, rms_per_m2 * z_m * z_m)


@dataclass(frozen=True)
class ObjectDepth:
    z_m: float  # distance along the colour camera's optical axis, m
    xyz_m: tuple[float, float, float]  # the near surface's centre at z_m, colour camera XYZ, m
    pixels: int  # depth pixels that landed on the blob
    near_pixels: int = 0  # of them, those at the object's distance (the bearing's)


def blob_points(cluster: Cluster, depth: np.ndarray, cam: CameraModel, min_m: float,
                min_pixels: int, max_m: float = DEPTH_FAR_M) -> np.ndarray | None:
    """The depth points (colour-camera XYZ, m; N x 3) that land on the cluster's blob, at
    depths from ``min_m`` to ``max_m`` (by default any the frame holds); None when fewer than
    ``min_pixels``."""
    roi = _depth_roi(cluster.box, cam, min_m, max_m, depth.shape)
    if roi is None:
        return None
    x0, y0, x1, y1 = roi
    patch = depth[y0:y1, x0:x1].astype(np.float64) * cam.depth_scale_m
    vs, us = np.nonzero((patch >= min_m) & (patch <= max_m))
    if len(us) < min_pixels:
        return None
    z = patch[vs, us]
    pts_d = cam.depth.deproject(us + x0, vs + y0, z)
    pts_c = cam.depth_to_color_points(pts_d)
    pts_c = pts_c[pts_c[:, 2] > 0]
    uv = np.round(cam.color.project(pts_c)).astype(np.int64)
    mask, (bx, by) = cluster.pixel_mask()
    mu, mv = uv[:, 0] - bx, uv[:, 1] - by
    inside = (mu >= 0) & (mv >= 0) & (mu < mask.shape[1]) & (mv < mask.shape[0])
    on_blob = np.zeros(len(uv), bool)
    on_blob[inside] = mask[mv[inside], mu[inside]] > 0
    if on_blob.sum() < min_pixels:
        return None
    return pts_c[on_blob]


def object_depth(
    cluster: Cluster,
    depth: np.ndarray,
    cam: CameraModel,
    min_m: float,
    max_m: float,
    percentile: float,
    min_pixels: int,
    rms_per_m2: float = 0.0,
    max_width_m: float = math.inf,
    min_size_m: float = 0.0,
    min_cover: float = 0.0,
) -> ObjectDepth | None:
    """The object's distance, or None when too few depth pixels land on its blob, when their
    near surface (the ``percentile`` of their depths to ``max_m`` and its error band beyond)
    is farther than ``max_m``, or when fewer than ``min_pixels`` of them lie within the range
    error of it (no surface: scattered wrong matches), or fewer than ``min_cover`` of the
    depth pixels a disc ``min_size_m`` across (the smallest plausible object) would cover at
    that distance (a surface too small to be any object there: wrong matches in a clump).

    Its position: the mean bearing of the blob's depth points within the range error of that
    distance (``NEAR_BAND_SIGMAS`` x max(``NEAR_BAND_FLOOR_M``, ``rms_per_m2`` · z²)), at that
    distance; the blob's centre when they spread wider than ``max_width_m`` (between their 5th
    and 95th percentiles across or down): then they are not one object's surface either (a
    blob spread over the frame by the ground's parallax has near points metres apart, whose
    mean jumps from frame to frame as they come and go: in an object-free flight, seed 43,
    that read as a 27 m/s approach and an emergency stop)."""
    band_end = max_m + NEAR_BAND_SIGMAS * range_error_m(max_m, rms_per_m2, NEAR_BAND_FLOOR_M)
    pts = blob_points(cluster, depth, cam, min_m, min_pixels, band_end)
    if pts is None:
        return None
    z_obj = float(np.percentile(pts[:, 2], percentile))
    if z_obj > max_m:
        return None
    band = NEAR_BAND_SIGMAS * range_error_m(z_obj, rms_per_m2, NEAR_BAND_FLOOR_M)
    near = pts[np.abs(pts[:, 2] - z_obj) <= band]
    if len(near) < min_pixels:
        # No surface there: a few depths that agree with nothing, as a stereo camera's wrong
        # matches do, scattered over a blob whose real depth is past the trusted range (the
        # `stereo` world, object-free: 8 of a cluster's 4 784 depth points were 3.2-9.5 m off
        # where the rest lay at 28-65 m, and the 25th percentile of those 8 read 3.6 m)
        return None
    if len(near) < patch_floor_px(cam.depth.fx, cam.depth.fy, min_size_m, min_cover) / (z_obj * z_obj):
        # A surface smaller than any object could be at that distance: a stereo camera's wrong
        # matches come in clumps of a few pixels too (3 x 3 clumps over 1.8 % of the frame:
        # 126 false evasions in 10 object-free minutes, seed 43, from clumps read as 9-point
        # surfaces 2.6-5 m off). In the open loop (seed 11, `stereo` world) real objects held
        # 0.96 of that disc's pixels or more (1st percentile of 828 readings), clumps 0.01-0.2.
        return None
    xyz = None
    bear = near[:, :2] / near[:, 2:3]
    lo, hi = np.percentile(bear, [5.0, 95.0], axis=0)
    if float(np.max(hi - lo)) * z_obj <= max_width_m:
        xyz = (float(np.mean(bear[:, 0])) * z_obj, float(np.mean(bear[:, 1])) * z_obj, z_obj)
    if xyz is None:
        c = cam.color.deproject(np.array([cluster.x]), np.array([cluster.y]), np.array([z_obj]))[0]
        xyz = (float(c[0]), float(c[1]), float(c[2]))
    return ObjectDepth(z_obj, xyz, len(pts), len(near))


def _depth_roi(
    box: tuple[int, int, int, int], cam: CameraModel, min_m: float, max_m: float,
    shape: tuple[int, ...],
) -> tuple[int, int, int, int] | None:
    """Depth-image region that can hold the colour box's pixels at any trusted depth."""
    x, y, w, h = box
    u = np.array([x, x + w, x, x + w], float)
    v = np.array([y, y, y + h, y + h], float)
    corners = []
    for z in (min_m, max_m):
        pc = cam.color.deproject(u, v, np.full(4, z))
        pd = (pc - cam.translation_m) @ cam.rotation  # colour -> depth frame (R orthonormal)
        corners.append(cam.depth.project(pd))
    c = np.concatenate(corners)
    x0 = max(0, int(np.floor(c[:, 0].min())) - 1)
    y0 = max(0, int(np.floor(c[:, 1].min())) - 1)
    x1 = min(shape[1], int(np.ceil(c[:, 0].max())) + 2)
    y1 = min(shape[0], int(np.ceil(c[:, 1].max())) + 2)
    if x1 <= x0 or y1 <= y0:
        return None
    return x0, y0, x1, y1
