"""The depth path of detection (app.perception.near): what stands out in range, not in grey."""

from __future__ import annotations

import math
from dataclasses import replace

import cv2
import numpy as np
import pytest

from app.camera import CameraModel, Intrinsics
from app.config import Config
from app.perception.near import REACH_PX, grow_persistent, near_mask, patch_floor_px, registered
from app.perception.recognition import Recognizer
from app.sim.openloop import fly_open_loop
from app.sim.simulate import Encounter

W, H = 848, 480
F = 425.0  # the D435i's depth lens at 848 x 480 (app.sim.world.D435I_DEPTH_FX_PX)
NOISE = 0.0036  # 1/m: Intel's D400 RMS error 0.0036 z^2, in inverse depth
LENS = Intrinsics(W, H, F, F, (W - 1) / 2, (H - 1) / 2)


def ground_depth(altitude_m: float, roll_deg: float = 0.0, seed: int = 0) -> np.ndarray:
    """uint16 mm: flat ground seen by a camera ``altitude_m`` up, banked by ``roll_deg``,
    with the stereo error in inverse depth; no data above the horizon and past 65 m."""
    rng = np.random.default_rng(seed)
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    r = math.radians(roll_deg)
    # the camera's down axis tilted by the roll: height below the camera of the ray's point
    down = ((v - LENS.ppy) * math.cos(r) + (u - LENS.ppx) * math.sin(r)) / F
    inv = down / altitude_m  # 1/z of the ground along each ray (z = altitude / down)
    inv = inv + rng.normal(0.0, NOISE, inv.shape)
    depth = np.zeros((H, W), np.uint16)
    ok = inv > 1.0 / 65.0
    depth[ok] = np.round(1000.0 / inv[ok]).astype(np.uint16)
    return depth


def disc(depth: np.ndarray, u: float, v: float, radius_px: float, z_m: float, seed: int = 1) -> np.ndarray:
    """``depth`` with a disc at ``z_m`` (and its stereo error) drawn in."""
    rng = np.random.default_rng(seed)
    vv, uu = np.mgrid[0:H, 0:W]
    inside = (uu - u) ** 2 + (vv - v) ** 2 <= radius_px**2
    out = depth.copy()
    inv = 1.0 / z_m + rng.normal(0.0, NOISE, int(inside.sum()))
    out[inside] = np.round(1000.0 / inv).astype(np.uint16)
    return out


def mask_of(depth: np.ndarray) -> np.ndarray:
    return near_mask(depth, 0.001, 5.0, NOISE, 80, 0.2, 65.535) > 0


@pytest.mark.parametrize("altitude, roll", [(3.0, 0.0), (6.0, 0.0), (15.0, 0.0), (6.0, 10.0), (3.0, 25.0)])
def test_flat_ground_marks_almost_nothing_to_the_frame_edges(altitude: float, roll: float) -> None:
    """Ground cancels along each row, at any height and with the vehicle banked (25 degrees:
    an evasion at 4 m/s² banks it 22): under 0.1 % of the pixels with depth are marked (the
    noise's tail at 5 standard errors)."""
    depth = ground_depth(altitude, roll)
    marked = mask_of(depth)
    assert marked.sum() <= 0.001 * np.count_nonzero(depth)


@pytest.mark.parametrize("z_m, radius_px", [(10.0, 10.0), (19.0, 6.0)])
def test_an_object_nearer_than_the_ground_behind_it_is_marked(z_m: float, radius_px: float) -> None:
    """A 0.45 m bird at 10 m and at 19 m, 6 m up over ground some 35 m behind it (the campaign's
    encounter 4100219, whose grey is the ground's): most of its pixels are marked, and
    almost nothing off it."""
    ground = ground_depth(6.0)
    u, v = 500.0, 310.0
    depth = disc(ground, u, v, radius_px, z_m)
    marked = mask_of(depth)
    vv, uu = np.mgrid[0:H, 0:W]
    on = (uu - u) ** 2 + (vv - v) ** 2 <= radius_px**2
    assert marked[on].mean() > 0.7
    near_it = (uu - u) ** 2 + (vv - v) ** 2 <= (radius_px + 3) ** 2
    assert marked[~near_it].sum() <= 0.001 * np.count_nonzero(depth)


@pytest.mark.parametrize("row", [310, 311])
def test_a_bird_seen_head_on_a_line_of_wing_one_pixel_tall_is_marked(row: int) -> None:
    """A 0.45 m bird at 15 m seen head-on, its wings level: a line 13 px long and one pixel
    tall (the shaped world's birds, seed 43, in front of ground ~35 m off), on an even row and
    on an odd one. Every other row of the depth missed it on one of the two."""
    depth = ground_depth(6.0)
    rng = np.random.default_rng(3)
    wing = np.s_[row, 494:507]
    depth[wing] = np.round(1000.0 / (1.0 / 15.0 + rng.normal(0.0, NOISE, 13))).astype(np.uint16)
    marked = mask_of(depth)
    assert marked[wing].mean() > 0.7
    off = np.ones_like(marked)
    off[row - 3:row + 4, 491:510] = False
    assert marked[off].sum() <= 0.001 * np.count_nonzero(depth)
    # grown as the grey difference is dilated (detection.dilate_ksize) once it was there a frame
    # ago, the line is a cluster to the recognizer; as marked, it is under the smallest cluster
    cfg = Config().perception
    recognize = Recognizer(cfg.recognition)
    marks = near_mask(depth, 0.001, 5.0, NOISE, 80, 0.2, 65.535)
    k = cfg.detection.dilate_ksize

    def grown(before_depth: np.ndarray | None, shift: int = 0) -> np.ndarray:
        before = None
        if before_depth is not None:  # the frame before: the same line, ``shift`` rows away
            marks_before = near_mask(before_depth, 0.001, 5.0, NOISE, 80, 0.2, 65.535)
            moved = np.roll(marks_before, shift, axis=0), np.roll(before_depth, shift, axis=0)
            _, before = grow_persistent(*moved, 0.001, None, REACH_PX, k)
        return grow_persistent(marks, depth, 0.001, before, REACH_PX, k)[0]

    assert not recognize(grown(None))[0]
    assert not recognize(grown(depth, REACH_PX + 4))[0]  # farther than its reach
    far = depth.copy()
    far[wing] = np.round(1000.0 / (1.0 / 11.0 + rng.normal(0.0, NOISE, 13))).astype(np.uint16)
    assert not recognize(grown(far, REACH_PX - 2))[0]  # a frame ago, but 11 m off: another surface
    clusters, _ = recognize(grown(depth, REACH_PX - 2))
    assert len(clusters) == 1 and abs(clusters[0].x - 500.0) < 2 and abs(clusters[0].y - row) < 2


def test_single_wrong_matches_are_not_marked_but_a_small_object_is() -> None:
    """Stereo's wrong matches: 0.2 % of the ground's pixels (far ground, 6 m up) take a
    disparity up to 8 px off, many of them metres nearer than the ground around them. Alone
    they mark nothing (a blob of them read a cluster over far ground 2.9 m off: the `stereo`
    world); a 0.2 m ball 12 m off, 3 px across at half resolution, still is."""
    rng = np.random.default_rng(5)
    depth = ground_depth(6.0)
    ys, xs = np.nonzero(depth)
    pick = rng.random(len(ys)) < 0.002
    ys, xs = ys[pick], xs[pick]
    fb = F * 0.05  # the depth lens's focal length x the D435i's baseline, px m
    disparity = fb / (depth[ys, xs] / 1000.0) + rng.uniform(-8.0, 8.0, len(ys))
    good = disparity > fb / 65.0
    depth[ys[good], xs[good]] = np.round(1000.0 * fb / disparity[good]).astype(np.uint16)
    before = ground_depth(6.0)[ys[good], xs[good]] / 1000.0
    nearer = 1.0 / (depth[ys[good], xs[good]] / 1000.0) - 1.0 / before
    assert (nearer > 5 * NOISE * 4).sum() > 100  # plenty that stand far out, each alone
    assert mask_of(depth).sum() <= 0.0001 * np.count_nonzero(depth)  # (148 px marked alone)
    u, v = 300.0, 330.0
    ball = disc(depth, u, v, 3.5, 12.0)
    vv, uu = np.mgrid[0:H, 0:W]
    assert mask_of(ball)[(uu - u) ** 2 + (vv - v) ** 2 <= 3.5**2].mean() > 0.5


def test_clumps_of_wrong_matches_are_not_marked_but_the_smallest_object_is() -> None:
    """Wrong matches in 3 x 3 clumps over 1.8 % of the ground's pixels (far ground, 6 m up),
    each clump one disparity error up to 8 px: with a neighbour beside every mark, the
    neighbour test keeps them, and many are metres nearer than the ground. A patch holding
    under a quarter of a disc 0.15 m wide at its distance is no object: those within 6 m are
    dropped, while
    the smallest object at 3 m (its rim only: a uniform ball's inside has no texture to match)
    and a 0.2 m ball at 12 m are still marked."""
    rng = np.random.default_rng(7)
    depth = ground_depth(6.0)
    ys, xs = np.nonzero(depth[1:-1, 1:-1])
    pick = rng.random(len(ys)) < 0.002
    fb = F * 0.05  # the depth lens's focal length x the D435i's baseline, px m
    for y, x, off in zip(ys[pick] + 1, xs[pick] + 1, rng.uniform(-8.0, 8.0, int(pick.sum())), strict=True):
        patch = depth[y - 1:y + 2, x - 1:x + 2]
        disparity = fb / (np.maximum(patch, 1) / 1000.0) + off
        patch[:] = np.where((patch > 0) & (disparity > fb / 65.0),
                            np.round(1000.0 * fb / np.maximum(disparity, 1e-6)), 0).astype(np.uint16)
    floor = patch_floor_px(F, F, 0.15)

    def marks(d: np.ndarray, floor_px: float) -> np.ndarray:
        return near_mask(d, 0.001, 5.0, NOISE, 80, 0.2, 65.535, floor_px) > 0

    near6 = (depth > 0) & (depth < 6000)  # (the ground 6 m up is 6 m off only at the frame's foot)
    assert (marks(depth, 0.0) & near6).sum() > 300  # kept by the neighbour test alone
    # every patch left reads farther than 6 m over its pixels (its own wrong readings may dip
    # under: a patch is judged by its mean, 1/mean(1/z), as the floor judges it)
    n, labels = cv2.connectedComponents(marks(depth, floor).astype(np.uint8))
    for i in range(1, n):
        inv = 1000.0 / depth[(labels == i) & (depth > 0)]
        assert 1.0 / inv.mean() > 6.0
    # (a clump marked as 2 x 2 at half resolution, 16 px, is a quarter of that disc 7 m off:
    # farther, size cannot tell it from a small object, and the decision's tests take over)
    vv, uu = np.mgrid[0:H, 0:W]
    r = 0.075 * F / 3.0
    dist = np.hypot(uu - 300.0, vv - 330.0)
    ball = disc(depth, 300.0, 330.0, r, 3.0)
    ball[dist <= r - 3] = 0  # depth on its 3 px rim only
    assert marks(ball, floor)[(dist <= r) & (dist > r - 3)].mean() > 0.8
    far = disc(depth, 500.0, 330.0, 3.5, 12.0)
    assert marks(far, floor)[np.hypot(uu - 500.0, vv - 330.0) <= 3.5].mean() > 0.5


def test_an_object_against_the_empty_sky_marks_nothing() -> None:
    """Depth holds nothing around it (the sky): no background to stand out from; the grey
    difference sees objects there."""
    depth = disc(np.zeros((H, W), np.uint16), 424.0, 120.0, 10.0, 8.0)
    assert not mask_of(depth).any()


def test_bad_depth_is_refused_by_shape_and_type() -> None:
    with pytest.raises(ValueError, match="single-channel depth image, got shape"):
        near_mask(np.zeros((H, W, 3), np.uint16), 0.001, 5.0, NOISE, 80, 0.2, 65.535)
    with pytest.raises(ValueError, match="expected uint16 depth, got float32"):
        near_mask(np.zeros((H, W), np.float32), 0.001, 5.0, NOISE, 80, 0.2, 65.535)


def test_only_depth_in_the_image_s_own_pixels_counts_as_registered() -> None:
    """The infrared imager's depth (one lens) is registered; the colour camera's (another lens,
    2-3 cm beside it) is not, nor depth at another resolution, nor no lens at all."""
    assert registered(CameraModel(LENS, LENS), (H, W))
    colour = Intrinsics(W, H, 615.0, 615.0, 424.0, 240.0)
    assert not registered(CameraModel(colour, LENS), (H, W))
    assert not registered(CameraModel(LENS, LENS, translation_m=np.array([0.015, 0.0, 0.0])), (H, W))
    assert not registered(CameraModel(LENS, LENS), (240, 424))
    assert not registered(None, (H, W))


def test_a_bird_as_grey_as_the_ground_climbing_at_the_vehicle_is_tracked_by_its_range() -> None:
    """The closed loop's encounter 4100219 (docs/campaign-bearings): a 0.48 m bird of grey 81
    climbing at 7.6 m/s towards a vehicle flying at 2 m/s, 6 m up, over ground of grey ~97. By
    grey alone it is tracked 0.77 s before its passage and not cleared; with the depth path it
    is tracked over 1.5 s before, and the first evasion clears it."""
    enc = Encounter(seed=4100219, kind="bird", object_speed_mps=7.6, approach_deg=6.1, climb_deg=10.9,
                    miss_m=0.31, miss_dir_deg=40.0, size_m=0.48, grey=81, own_speed_mps=2.0)
    cfg = Config()
    with_depth = replace(cfg, perception=replace(cfg.perception, detection=replace(
        cfg.perception.detection, near_sigmas=5.0)))
    grey_only = replace(cfg, perception=replace(cfg.perception, detection=replace(
        cfg.perception.detection, near_sigmas=0.0)))
    seen = fly_open_loop(with_depth, enc)
    unseen = fly_open_loop(grey_only, enc)
    assert seen.tracked_before_cpa_s is not None and seen.tracked_before_cpa_s > 1.5
    assert (unseen.tracked_before_cpa_s is None
            or unseen.tracked_before_cpa_s < seen.tracked_before_cpa_s - 0.5)
    assert seen.commanded and seen.cleared


def test_an_odd_sized_frame_keeps_its_size_and_marks_in_place() -> None:
    """Worked at half resolution, drawn back at the frame's own size: an object in the
    bottom-right corner of a 847 x 479 frame is marked where it is."""
    depth = disc(ground_depth(6.0), 840.0, 470.0, 6.0, 8.0)[:479, :847]
    marked = mask_of(depth)
    assert marked.shape == (479, 847)
    ys, xs = np.nonzero(marked)
    assert len(xs) > 50 and abs(xs.mean() - 840.0) < 3 and abs(ys.mean() - 470.0) < 3


def test_the_colour_stream_has_no_depth_path_even_where_the_simulation_draws_depth_in_it(
        caplog: pytest.LogCaptureFixture) -> None:
    """A D435i computes depth in its left infrared imager's frame: the depth path is for that
    stream. The simulation draws depth in the colour lens too, so it is told by the stream,
    and a perception given no registered depth says once that the path is off."""
    from app.perception.frames import Frame
    from app.perception.near import depth_lens
    from app.perception.pipeline import Perception, _say_near_off

    _say_near_off.cache_clear()  # said once a process: another test may have said it
    cam = CameraModel(LENS, LENS)
    assert depth_lens(cam, "infrared") is cam and depth_lens(cam, "color") is None
    cfg = Config()
    p = Perception(cfg.perception, camera=depth_lens(cam, "color"))
    rng = np.random.default_rng(0)
    grey = rng.integers(60, 140, (H, W), dtype=np.uint8)
    depth = disc(ground_depth(6.0), 500.0, 310.0, 10.0, 10.0)
    with caplog.at_level("INFO", logger="app.perception.pipeline"):
        for i in range(3):
            result = p.push(Frame(i + 1, i / 30.0, np.dstack([grey] * 3), depth))
    assert result is not None and result.mask is not None
    assert not result.mask[300:320, 490:510].any()  # the disc stands in depth only: unmarked
    assert sum("depth path off" in r.getMessage() for r in caplog.records) == 1
    with_depth = Perception(cfg.perception, camera=depth_lens(cam, "infrared"))
    for i in range(3):
        result = with_depth.push(Frame(i + 1, i / 30.0, np.dstack([grey] * 3), depth))
    assert result is not None and result.mask is not None and (result.mask[302:318, 492:508] > 0).mean() > 0.7
