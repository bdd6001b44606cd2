from __future__ import annotations

from typing import Any, cast

import cv2
import numpy as np
import pytest

from app.config import DetectionConfig
from app.errors import SourceError
from app.perception.detection import (
    SHIFT_TOLERANCE_PX,
    MotionDetector,
    _shift_tiles,
    _warp_onto,
    border_windows,
)
from tests.conftest import textured


def _shift(img: np.ndarray, h: np.ndarray) -> np.ndarray:
    return cv2.warpPerspective(img, h, (img.shape[1], img.shape[0]), flags=cv2.INTER_LINEAR,
                               borderMode=cv2.BORDER_REFLECT)


def _camera(k: int) -> np.ndarray:
    """A known camera motion: image of frame k = base warped by this (pan + slight roll)."""
    a = 0.002 * k
    return np.array([[np.cos(a), -np.sin(a), 2.0 * k], [np.sin(a), np.cos(a), 1.2 * k], [0, 0, 1]])


def test_border_windows_follow_the_paper_layout() -> None:
    wins = border_windows(640, 480, 70, 6)
    assert wins[:4] == [(0, 0, 70, 70), (570, 0, 640, 70), (0, 410, 70, 480), (570, 410, 640, 480)]
    assert wins[4:] == [(285, 0, 355, 70), (285, 410, 355, 480)]
    assert len(border_windows(640, 480, 70, 8)) == 8


def test_frames_smaller_than_the_windows_are_a_clear_error() -> None:
    det = MotionDetector(DetectionConfig())
    with pytest.raises(SourceError, match=r"frame 160x120 is too small .*window_px = 70"):
        det.push(np.zeros((120, 160), np.uint8))


def test_known_homography_is_recovered() -> None:
    base = textured()
    det = MotionDetector(DetectionConfig())
    results = [det.push(_shift(base, _camera(k))) for k in range(4)]
    h = results[-1].homography  # H_{1,2}: frame 1 px -> frame 2 px
    assert h is not None and results[-1].status == "ok"
    truth = _camera(2) @ np.linalg.inv(_camera(1))
    pts = np.array([[[50.0, 50.0]], [[600.0, 60.0]], [[320.0, 240.0]], [[40.0, 450.0]]])
    err = cv2.perspectiveTransform(pts, h) - cv2.perspectiveTransform(pts, truth)
    assert np.abs(err).max() < 0.3  # px


def test_moving_object_is_in_the_mask_and_background_is_not() -> None:
    base = textured(seed=1)
    det = MotionDetector(DetectionConfig())
    masks = []
    for k in range(5):
        img = _shift(base, _camera(k))
        cv2.circle(img, (300 + 6 * k, 200 + 3 * k), 9, 20, -1)  # its own motion
        masks.append(det.push(img).mask)
    mask = masks[-1]  # mask of frame 3
    assert mask is not None
    cx, cy = 300 + 6 * 3, 200 + 3 * 3
    ys, xs = np.nonzero(mask[cy - 25:cy + 26, cx - 25:cx + 26])
    assert len(xs) > 150  # the disc has 250 px; a uniform disc differs at its rim
    assert abs(xs.mean() - 25) < 3 and abs(ys.mean() - 25) < 3  # centred on frame 3's disc
    far = mask.copy()
    cv2.circle(far, (cx, cy), 40, 0, -1)
    assert (far > 0).mean() < 0.002  # background: at most 0.2 % of pixels


def test_a_tracked_object_in_a_window_does_not_vote() -> None:
    base = textured(seed=2)
    det = MotionDetector(DetectionConfig())
    det.push(_shift(base, _camera(0)))
    r = det.push(_shift(base, _camera(1)), exclude=[(10.0, 10.0, 30.0, 30.0)])
    assert r.excluded_windows == 1


def test_featureless_sky_falls_back_to_a_safe_model_and_sees_the_object() -> None:
    sky = np.full((480, 640), 180, np.uint8)
    det = MotionDetector(DetectionConfig())
    out = []
    for k in range(5):
        img = sky.copy()
        cv2.circle(img, (320 + 5 * k, 240), 8, 60, -1)
        out.append(det.push(img))
    assert out[-1].status == "featureless"
    mask = out[-1].mask  # frame 3: the disc is at x = 335
    assert mask is not None
    assert mask[230:251, 320:351].any()
    mask[220:261, 300:371] = 0
    assert not mask.any()  # the blank sky itself never differs


def test_frames_that_do_not_register_are_skipped_not_diffed() -> None:
    """Unrelated frames: either RANSAC finds no consistent motion or the warp leaves a
    mask far larger than any object; in both cases no mask comes out."""
    det = MotionDetector(DetectionConfig())
    a, b = textured(seed=3), textured(seed=4)  # unrelated frames with the same histogram shape
    r1 = det.push(a)
    r2 = det.push(b)
    r3 = det.push(a)
    assert r1.status == "warmup"
    assert r2.mask is None and r3.mask is None
    assert r2.status == "warmup" and r3.status in ("no_homography", "bad_warp")


def test_scene_cut_resets_instead_of_flagging_the_whole_frame() -> None:
    det = MotionDetector(DetectionConfig())
    for k in range(3):
        det.push(_shift(textured(seed=5), _camera(k)))
    dark = (textured(seed=6) // 4).astype(np.uint8)
    r = det.push(dark)
    assert r.status == "scene_cut" and r.mask is None
    assert det.push(dark).status == "warmup"


def _ramped_pan(k: int, accel: float, top_speed: float) -> np.ndarray:
    """Frame k's camera: a pan that speeds up by ``accel`` px/frame each frame to ``top_speed``
    (a multirotor's yaw cannot jump), with a slight roll and tilt."""
    x = sum(min(top_speed, accel * (i + 1)) for i in range(k))
    a = 0.001 * k
    return np.array([[np.cos(a), -np.sin(a), -x], [np.sin(a), np.cos(a), 0.3 * k], [0, 0, 1]])


def _registration_errors(cameras: list[np.ndarray], times: list[float] | None = None,
                         cfg: DetectionConfig | None = None) -> list[float]:
    """Film a wide texture through ``cameras`` (world px -> image px, one per frame) and return,
    for every estimated H_{k-2,k-1}, the largest misplacement (px) of nine points spread over
    the frame against the truth; inf where no homography came out."""
    base = textured(480, 640 + 2200, seed=3)
    probe = np.array([[[x, y]] for x in (20.0, 320.0, 620.0) for y in (20.0, 240.0, 460.0)])
    det = MotionDetector(cfg or DetectionConfig())
    errors = []
    for k, cam in enumerate(cameras):
        img = cv2.warpPerspective(base, cam, (640, 480), flags=cv2.INTER_LINEAR,
                                  borderMode=cv2.BORDER_REFLECT)
        r = det.push(img, t_s=None if times is None else times[k])
        if k < 2:
            continue
        if r.homography is None:
            errors.append(float("inf"))
            continue
        truth = cameras[k - 1] @ np.linalg.inv(cameras[k - 2])
        errors.append(float(np.abs(cv2.perspectiveTransform(probe, r.homography)
                                   - cv2.perspectiveTransform(probe, truth)).max()))
    return errors


@pytest.mark.parametrize("predict", [True, False])
def test_fast_camera_pans_are_registered_when_lk_starts_from_the_last_flow(predict: bool) -> None:
    """Up to 40 px/frame (140 deg/s of yaw at 60 fps with a 615 px lens). Without the start
    from each window's last flow, the 2-level pyramid loses pans beyond 12-25 px/frame and,
    worse, agrees on a wrong shift that RANSAC accepts."""
    errors = _registration_errors([_ramped_pan(k, 2.0, 40.0) for k in range(50)],
                                  cfg=DetectionConfig(lk_predict=predict))
    fast = np.array(errors[20:])  # from frame 20 on the pan runs at 40 px/frame
    if predict:
        assert max(errors) < 1.0  # px, everywhere in the frame, the whole way up
    else:
        assert (fast > 5.0).mean() > 0.5  # most fast frames misregistered


def test_pyramid_levels_held_agree_with_opencv() -> None:
    from app.config import pyramid_levels_held

    for win in (5, 11, 13, 15, 21, 31):
        for side in range(win, 400, 7):
            built, _ = cv2.buildOpticalFlowPyramid(np.zeros((side, side + 40), np.uint8), (win, win), 10,
                                                   withDerivatives=False)
            assert pyramid_levels_held(side, win) == built, (side, win)


def test_a_pan_already_fast_at_the_start_is_registered_from_a_whole_frame_shift() -> None:
    """After a start or a reset (camera restarted mid-yaw) there is no last flow to start
    from: a phase correlation of the whole frame supplies it."""
    errors = _registration_errors([_ramped_pan(k, 25.0, 25.0) for k in range(8)])  # 25 px/frame at once
    assert max(errors) < 1.0, errors  # from the first estimate on


def test_whole_frame_shift_has_the_flow_sign() -> None:
    from app.perception.detection import _global_shift

    base = textured(480, 700, seed=1)
    shift = _global_shift(base[:, 30:670], base[:, 10:650])  # content moves 20 px to the right
    assert shift is not None and np.allclose(shift, (20.0, 0.0), atol=1.0)
    sky = np.full((480, 640), 180, np.uint8)
    blank = _global_shift(sky, sky)  # nothing to correlate: no peak, or no motion
    assert blank is None or np.abs(blank).max() < 1.0


@pytest.mark.parametrize("with_times", [True, False])
def test_frames_skipped_by_a_busy_perception_thread_are_registered_with_their_times(with_times: bool) -> None:
    """A perception thread slower than the camera sees every 2nd or 3rd frame now and then:
    the motion between the frames it sees jumps, and the start from the last flow must be
    scaled by the interval (a pan of 12 px per 1/60 s)."""
    ticks = np.cumsum([0, 1, 1, 1, 2, 1, 3, 1, 1, 2, 2, 1, 3, 3, 1, 1, 2, 1, 1, 3, 1, 2, 1, 1, 1, 2, 3, 1, 1])
    cameras = [np.array([[1, 0, -12.0 * t], [0, 1, 0.2 * t], [0, 0, 1.0]]) for t in ticks]
    errors = _registration_errors(cameras, [t / 60.0 for t in ticks] if with_times else None)
    bad = sum(e > 1.0 for e in errors)
    if with_times:
        assert bad == 0, errors
    else:
        assert bad >= 3  # without the times the start is off by a whole frame's motion


def _dots(shape: tuple[int, int], seed: int) -> tuple[np.ndarray, np.ndarray]:
    """A difference image of isolated bright pixels, and their (x, y) positions."""
    rng = np.random.default_rng(seed)
    pts = np.stack([rng.integers(10, shape[1] - 10, 300), rng.integers(10, shape[0] - 10, 300)], 1)
    img = np.zeros(shape, np.uint8)
    img[pts[:, 1], pts[:, 0]] = 200
    return img, pts


def test_tile_shifts_move_the_difference_as_the_nearest_neighbour_warp_does() -> None:
    """A pure translation (whole or fractional): the tiles give exactly the warp's image."""
    diff = textured(480, 640, seed=5)
    for tx, ty in ((3.0, -2.0), (-7.3, 4.6), (0.2, 0.49), (30.0, 12.0)):
        h = np.array([[1, 0, tx], [0, 1, ty], [0, 0, 1]], float)  # frame t px -> t+1 px
        ref = cv2.warpPerspective(diff, h, (640, 480), flags=cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP,
                                  borderValue=0)
        got = _shift_tiles(diff, h)
        assert got is not None
        assert np.array_equal(got, ref), (tx, ty)


def test_tile_shifts_place_every_pixel_within_the_tolerance_or_decline() -> None:
    """A slight turn and zoom: every dot lands within SHIFT_TOLERANCE_PX (+ the dot's own
    rounding) of where the homography puts it; a turn of 1 degree is declined."""
    shape = (480, 640)
    diff_next, pts_next = _dots(shape, seed=3)  # dots in t+1's pixels
    a = np.deg2rad(0.05)
    h = np.array([[1.0005 * np.cos(a), -np.sin(a), 2.4], [np.sin(a), 1.0005 * np.cos(a), -1.2], [0, 0, 1]])
    got = _shift_tiles(diff_next, h)
    assert got is not None
    ys, xs = np.nonzero(got)
    assert len(xs) > 250  # the dots near the border may leave the frame
    # where each found dot truly belongs in t: the inverse homography of its t+1 position
    true_t = cv2.perspectiveTransform(pts_next.reshape(-1, 1, 2).astype(float), np.linalg.inv(h))
    true_t = true_t.reshape(-1, 2)
    for x, y in zip(xs, ys, strict=True):
        err = np.abs(true_t - (x, y)).max(axis=1).min()
        assert err <= SHIFT_TOLERANCE_PX + 0.5, (x, y, err)
    turn = np.deg2rad(1.0)
    h_turn = np.array([[np.cos(turn), -np.sin(turn), 0], [np.sin(turn), np.cos(turn), 0], [0, 0, 1]])
    assert _shift_tiles(diff_next, h_turn) is None
    # a homography that sends a grid corner through the horizon (w = 0 at x = 320, y = 0)
    assert _shift_tiles(diff_next, np.array([[1, 0, 0], [0, 1, 0], [-1 / 320, 0, 1.0]])) is None


@pytest.mark.parametrize("count", [4, 6, 8])
@pytest.mark.parametrize("shape", [(480, 640), (512, 640)])
def test_the_crops_mosaic_holds_every_crop_with_the_frame_edges_on_its_edges(
        count: int, shape: tuple[int, int]) -> None:
    """LK runs once over all border windows' crops laid out in one image: each crop is copied
    exactly, no two overlap, and a crop side on the frame's edge is on the mosaic's edge (LK
    pads there as it did for the crop alone; inner sides may meet other crops)."""
    det = MotionDetector(DetectionConfig(window_count=count))
    frame = textured(*shape, seed=4)
    det.push(frame)
    mosaic = det._mosaic_cur
    assert mosaic is not None
    height, width = shape
    covered = np.zeros(mosaic.shape, int)
    for (x0, y0, x1, y1), (mx, my) in zip(det._crops, det._mosaic_at, strict=True):
        assert np.array_equal(mosaic[my:my + y1 - y0, mx:mx + x1 - x0], frame[y0:y1, x0:x1])
        covered[my:my + y1 - y0, mx:mx + x1 - x0] += 1
        assert (x0 == 0) == (mx == 0) and (y0 == 0) == (my == 0)
        assert (x1 == width) == (mx + x1 - x0 == mosaic.shape[1])
        assert (y1 == height) == (my + y1 - y0 == mosaic.shape[0])
    assert covered.max() == 1


def test_one_lk_call_over_the_mosaic_follows_the_points_as_each_crop_alone() -> None:
    """Points in the windows lie lk_search_px from any other crop: at every pyramid level LK
    sees their own crop, so the one call gives what a call per crop gave."""
    base = textured(480, 700, seed=8)
    cur, nxt = base[:, 20:660], base[:, 17:657]  # the camera turned: the scene moves 3 px right
    det = MotionDetector(DetectionConfig(lk_predict=False))
    det.push(np.ascontiguousarray(cur))
    pts, wid = det._pts.copy(), det._wid.copy()
    det.push(np.ascontiguousarray(nxt))
    lk = det._lk_params
    alone = np.empty_like(pts)
    for i, (x0, y0, x1, y1) in enumerate(det._crops):
        q1, status, _ = cv2.calcOpticalFlowPyrLK(
            np.ascontiguousarray(cur[y0:y1, x0:x1]), np.ascontiguousarray(nxt[y0:y1, x0:x1]),
            (pts[wid == i] - (x0, y0)).astype(np.float32).reshape(-1, 1, 2),
            cast(Any, None), **lk)  # None (no start) is accepted; some stubs say no
        assert status.all()
        alone[wid == i] = q1.reshape(-1, 2) + (x0, y0)
    # the points kept (those still inside their windows) against the same points flowed alone
    kept = [int(np.flatnonzero((np.abs(alone - p) < 0.5).all(axis=1))[0]) for p in det._pts]
    assert len(kept) > 0.8 * len(pts)
    assert np.abs(det._pts - alone[kept]).max() < 1e-3
    assert np.abs(det._pts - pts[kept] - (3.0, 0.0)).max() < 0.25  # and it is the scene's motion


def test_a_point_carried_out_of_its_crop_is_not_followed() -> None:
    """lk_search_px is how far a point may move beyond its window: a pan of 70 px carries the
    points of the windows on the frame's left edge out of the frame, and with them out of their
    crops; none of them may vote for the homography."""
    base = textured(480, 820, seed=9)
    det = MotionDetector(DetectionConfig(lk_predict=False))
    cur, nxt = base[:, 100:740], base[:, 170:810]  # the scene moves 70 px left
    det.push(np.ascontiguousarray(cur))
    mosaics = (det._mosaic_cur, det._mosaic(np.ascontiguousarray(nxt)))
    assert mosaics[0] is not None
    n_before = len(det._pts)
    _, p1, wid, followed = det._flow(cur, np.ascontiguousarray(nxt), mosaics)  # type: ignore[arg-type]
    crops = np.array(det._crops, np.float32)[wid]
    assert ((p1 >= crops[:, :2]) & (p1 < crops[:, 2:])).all()
    assert len(p1) < n_before and sum(followed) == len(p1)


def _looming(det: MotionDetector, frames: int, r0: float, growth_px: float,
             fps: float = 30.0) -> list[np.ndarray | None]:
    """A dark disc that only grows (a collision course: constant bearing, camera hovering),
    ``growth_px`` of radius per frame, over a textured scene with sensor noise; the masks."""
    base = textured(seed=3)
    rng = np.random.default_rng(0)
    masks = []
    for k in range(frames):
        img = cv2.add(base, rng.integers(0, 3, base.shape, dtype=np.uint8))
        r = r0 + growth_px * k
        cv2.circle(img, (320 * 16, 200 * 16), int(round(r * 16)), 25, -1, cv2.LINE_AA, shift=4)
        masks.append(det.push(img, t_s=k / fps).mask)
    return masks


def _hits_disc(mask: np.ndarray | None, r: float) -> int:
    assert mask is not None
    m = np.zeros_like(mask)
    cv2.circle(m, (320, 200), int(r + 4), 255, -1)
    return int(cv2.countNonZero(cv2.bitwise_and(mask, m)))


def test_an_object_that_only_grows_is_seen_by_the_slow_difference() -> None:
    """0.2 px of radius a frame (a 0.25 m ball at 9.6 m closing at 7.2 m/s, 30 fps, f = 615
    px): frame to frame it is below the noise, over 0.2 s it is a ring. With the slow
    difference off, the same frames show nothing there."""
    r0, g = 8.0, 0.2
    slow = _looming(MotionDetector(DetectionConfig()), 20, r0, g)
    fast = _looming(MotionDetector(DetectionConfig(slow_baseline_s=0.0)), 20, r0, g)
    r_last = r0 + g * 18  # the newest mask is frame 18's
    assert _hits_disc(fast[-1], r_last) == 0
    assert _hits_disc(slow[-1], r_last) >= 20
    # and only there: the noisy textured background stays out of the mask
    mask = slow[-1]
    assert mask is not None
    outside = mask.copy()
    cv2.circle(outside, (320, 200), int(r_last + 8), 0, -1)
    assert cv2.countNonZero(outside) == 0


def test_the_slow_difference_waits_for_its_history_and_restarts_after_a_skipped_frame() -> None:
    det = MotionDetector(DetectionConfig())
    masks = _looming(det, 8, 8.0, 0.1)  # 0.27 s: less than twice the 0.2 s baseline
    assert all(m is None or _hits_disc(m, 9.0) == 0 for m in masks)
    assert det._slow_difference() is None
    det.push(np.zeros((480, 640), np.uint8), t_s=0.3)  # a scene cut: everything starts again
    assert len(det._slow) == 0


def test_a_slow_change_over_a_large_area_is_left_out_and_the_frame_keeps_its_mask() -> None:
    """A 110 x 110 px patch (4 % of the frame) brightening by 4 grey levels a frame: below the
    threshold frame to frame, above it over 0.2 s. The slow difference marks that much only
    when its long baseline fails to register (a cloud, parallax, a followed object), so it is
    left out: the patch is not in the mask, and the frame still has one. Without the limit
    the patch is marked."""
    base = textured(seed=5)
    rng = np.random.default_rng(1)

    def run(cfg: DetectionConfig) -> list:
        det = MotionDetector(cfg)
        out = []
        for k in range(20):
            img = cv2.add(base, rng.integers(0, 3, base.shape, dtype=np.uint8))
            patch = img[150:260, 250:360].astype(np.int16) + 4 * k
            img[150:260, 250:360] = np.clip(patch, 0, 255).astype(np.uint8)
            out.append(det.push(img, t_s=k / 30.0))
        return out

    limited = run(DetectionConfig())
    unlimited = run(DetectionConfig(slow_max_frac=1.0))
    inside = np.zeros((480, 640), np.uint8)
    inside[160:250, 260:350] = 255
    last, free = limited[-1], unlimited[-1]
    assert last.mask is not None and last.status == "ok"
    assert cv2.countNonZero(cv2.bitwise_and(last.mask, inside)) == 0
    assert free.mask is not None and cv2.countNonZero(cv2.bitwise_and(free.mask, inside)) > 1000


class _SlowProbe(MotionDetector):
    """The detector, keeping what its slow difference gave each frame."""

    def __init__(self, cfg: DetectionConfig) -> None:
        super().__init__(cfg)
        self.slow: list[np.ndarray | None] = []

    def _slow_difference(self) -> np.ndarray | None:
        out = super()._slow_difference()
        self.slow.append(out)
        return out


def test_in_forward_flight_the_slow_difference_registers_the_grounds_parallax_tile_by_tile() -> None:
    """Flying forward at 4 m/s, 6 m over the built-in world's textured ground, a bird (0.47 m)
    closes head-on at 10.5 m/s and only grows. Over 0.2-0.4 s the ground's parallax defeats one
    homography, so the slow difference marks too much and is left out of every frame; with the
    tiles' residual shifts taken out it is kept in most frames, the ground is not in it, and
    the bird's rim is while it is still under 8 px across in radius. Through the colour lens,
    where it was measured (the scene's sizes and parallax are the 69° lens's)."""
    from dataclasses import replace

    from app.config import CaptureConfig, Config
    from app.sim.fast import _Script
    from app.sim.simulate import Encounter, SimulatedCamera, world_for

    colour = replace(Config(), capture=replace(CaptureConfig(), stream="color"))

    enc = Encounter(seed=1100116, kind="bird", object_speed_mps=10.53, approach_deg=-1.9, climb_deg=-2.8,
                    miss_dir_deg=102.0, size_m=0.47, grey=67, own_speed_mps=4.0, altitude_m=6.0)

    def fly(cfg: DetectionConfig) -> tuple[_SlowProbe, list[tuple[float, float, float, float] | None]]:
        cam = SimulatedCamera(enc, _Script(enc.altitude_m, enc.own_speed_mps), world=world_for(colour, enc),
                              paced=False)
        det, truth = _SlowProbe(cfg), []
        for frame in cam:
            det.push(cv2.cvtColor(frame.color, cv2.COLOR_BGR2GRAY), t_s=frame.t_s)
            truth.append(cam.truth[frame.index - 2].pixel if frame.index >= 2 else None)
        return det, truth

    plain, _ = fly(DetectionConfig(slow_parallax_tile_px=0))
    tiled, truth = fly(DetectionConfig())
    warm = 15  # twice the baseline of history first
    assert sum(s is not None for s in plain.slow[warm:]) == 0
    kept = [(s, t) for s, t in zip(tiled.slow[warm:], truth[warm + 1:], strict=False) if s is not None]
    assert len(kept) >= 0.7 * len(tiled.slow[warm:])
    rim_seen = 0
    for slow, t in kept:
        marked = slow > DetectionConfig().threshold
        assert cv2.countNonZero(marked.astype(np.uint8)) <= 0.005 * marked.size
        if t is not None and t[2] < 8.0:
            u, v = int(t[0]), int(t[1])
            rim_seen += bool(marked[max(0, v - 12):v + 13, max(0, u - 12):u + 13].any())
    assert rim_seen >= 10


def _colour_ground(seed: int) -> np.ndarray:
    """Green-brown textured ground (BGR): luma texture and a milder chroma texture."""
    y = textured(seed=seed)
    rng = np.random.default_rng(seed + 1)
    tint = cv2.resize(rng.normal(0, 1, (30, 40)), (640, 480), interpolation=cv2.INTER_CUBIC)
    ycrcb = np.dstack([y, np.clip(115 + 6 * tint, 0, 255), np.clip(110 - 4 * tint, 0, 255)]).astype(np.uint8)
    return cv2.cvtColor(ycrcb, cv2.COLOR_YCrCb2BGR)


def _isoluminant_disc(img: np.ndarray, centre: tuple[int, int], radius: int) -> np.ndarray:
    """``img`` with a disc as bright as what it covers, pixel by pixel, but reddish-brown."""
    ycrcb = cv2.cvtColor(img, cv2.COLOR_BGR2YCrCb)
    disc = np.zeros(img.shape[:2], np.uint8)
    cv2.circle(disc, centre, radius, 255, -1)
    ycrcb[disc > 0, 1] = 150
    ycrcb[disc > 0, 2] = 100
    return cv2.cvtColor(ycrcb, cv2.COLOR_YCrCb2BGR)


@pytest.mark.parametrize("gain", [0.0, 1.0])
def test_an_object_as_bright_as_the_ground_is_seen_only_in_colour(gain: float) -> None:
    base = _colour_ground(seed=4)
    det = MotionDetector(DetectionConfig(chroma_gain=gain))
    masks = []
    for k in range(5):
        img = _isoluminant_disc(_shift(base, _camera(k)), (300 + 6 * k, 200 + 3 * k), 10)
        masks.append(det.push(cv2.cvtColor(img, cv2.COLOR_BGR2GRAY), t_s=k / 30, colour=img).mask)
    mask = masks[-1]
    assert mask is not None
    cx, cy = 300 + 6 * 3, 200 + 3 * 3
    near = int((mask[cy - 25:cy + 26, cx - 25:cx + 26] > 0).sum())
    far = mask.copy()
    cv2.circle(far, (cx, cy), 40, 0, -1)
    assert (far > 0).mean() < 0.002  # the ground's colour texture is registered away too
    if gain == 0:
        assert near < 30  # grey only: the disc hardly differs from the ground it covers
    else:
        ys, xs = np.nonzero(mask[cy - 25:cy + 26, cx - 25:cx + 26])
        assert len(xs) > 150  # the disc's 314 px, by its colour
        assert abs(xs.mean() - 25) < 3 and abs(ys.mean() - 25) < 3


def test_a_grey_frame_or_none_leaves_the_chroma_difference_out() -> None:
    base = textured(seed=2)
    with_gain, without = MotionDetector(DetectionConfig(chroma_gain=2.0)), MotionDetector(DetectionConfig())
    for k in range(4):
        img = _shift(base, _camera(k))
        cv2.circle(img, (300 + 6 * k, 200 + 3 * k), 9, 20, -1)
        a = with_gain.push(img, t_s=k / 30, colour=img if k % 2 else None).mask
        b = without.push(img, t_s=k / 30).mask
    assert a is not None and b is not None and np.array_equal(a, b)


def test_a_colour_frame_of_another_size_is_a_clear_error() -> None:
    det = MotionDetector(DetectionConfig(chroma_gain=1.0))
    img = textured(seed=3)
    with pytest.raises(ValueError, match="colour frame 320x240"):
        det.push(img, colour=np.zeros((240, 320, 3), np.uint8))


def _source_px(h: np.ndarray, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Where each pixel of a frame of ``shape`` comes from under ``h`` (src px -> dst px)."""
    ys, xs = np.mgrid[0:shape[0], 0:shape[1]].astype(np.float64)
    inv = np.linalg.inv(h)
    w = inv[2, 0] * xs + inv[2, 1] * ys + inv[2, 2]
    sx = (inv[0, 0] * xs + inv[0, 1] * ys + inv[0, 2]) / w
    return sx, (inv[1, 0] * xs + inv[1, 1] * ys + inv[1, 2]) / w


@pytest.mark.parametrize("h", [
    np.array([[1.0, 0.0, 3.37], [0.0, 1.0, -2.21], [0.0, 0.0, 1.0]]),  # a pan
    np.array([[1.001, 0.002, -9.3], [0.001, 0.999, 6.7], [1e-6, 2e-6, 1.0]]),  # a pan with perspective
    np.array([[0.98, 0.05, 10.4], [-0.04, 1.01, -7.2], [1e-5, -2e-5, 1.0]]),  # a turn
    np.array([[1.2, 0.0, -60.0], [0.0, 1.2, -50.0], [0.0, 0.0, 1.0]]),  # a zoom: no source outside
    np.array([[0.0, -1.0, 300.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]),  # a quarter turn: no upright rectangle
])
def test_warp_onto_is_the_transparent_warp(h: np.ndarray) -> None:
    """OpenCV's bilinear warp with a transparent border: ``dst`` where a pixel has no source,
    the warp elsewhere, to the one grey level its vectorised path rounds differently at a few
    pixels."""
    rng = np.random.default_rng(3)
    src = cv2.GaussianBlur(rng.integers(0, 256, (240, 320), dtype=np.uint8), (0, 0), 1.0)
    dst = cv2.GaussianBlur(rng.integers(0, 256, (240, 320), dtype=np.uint8), (0, 0), 1.0)
    transparent = dst.copy()
    cv2.warpPerspective(src, h, (320, 240), dst=transparent, flags=cv2.INTER_LINEAR,
                        borderMode=cv2.BORDER_TRANSPARENT)
    before = dst.copy()
    got = _warp_onto(src, h, dst)
    np.testing.assert_array_equal(dst, before)  # dst is the caller's frame: never written
    diff = np.abs(got.astype(int) - transparent)
    assert diff.max() <= 1
    assert (diff > 0).mean() < 0.2  # a zoom: 13 % here; a pan or turn: under 0.2 %
    sx, sy = _source_px(h, dst.shape)
    outside = (sx < -1.0) | (sx > 320.0) | (sy < -1.0) | (sy > 240.0)
    np.testing.assert_array_equal(got[outside], dst[outside])


def test_warp_onto_through_the_horizon_falls_back_to_the_transparent_warp() -> None:
    """A homography that sends a corner of ``src`` behind the camera: no quadrilateral, so the
    transparent warp itself."""
    rng = np.random.default_rng(4)
    src = rng.integers(0, 256, (120, 160), dtype=np.uint8)
    dst = rng.integers(0, 256, (120, 160), dtype=np.uint8)
    h = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, -1 / 60, 1.0]])  # rows below 60 go behind
    want = dst.copy()
    cv2.warpPerspective(src, h, (160, 120), dst=want, flags=cv2.INTER_LINEAR,
                        borderMode=cv2.BORDER_TRANSPARENT)
    np.testing.assert_array_equal(_warp_onto(src, h, dst), want)


def test_warp_onto_keeps_colour_channels() -> None:
    rng = np.random.default_rng(5)
    src = rng.integers(0, 256, (60, 80, 3), dtype=np.uint8)
    dst = rng.integers(0, 256, (60, 80, 3), dtype=np.uint8)
    h = np.array([[1.0, 0.0, 5.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    got = _warp_onto(src, h, dst)
    assert got.shape == dst.shape
    np.testing.assert_array_equal(got[:, :4], dst[:, :4])  # no source left of x = 4.5
    np.testing.assert_array_equal(got[1:-1, 10:70], src[1:-1, 5:65])  # a whole-px shift: the pixels
