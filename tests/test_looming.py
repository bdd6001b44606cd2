"""Looming time to contact and predicted passage, on exact synthetic geometry: an object of
known size and course projected through a pinhole camera, with pixel noise, cut by the
frame edge, or seen from a rotating camera."""

from __future__ import annotations

import math

import numpy as np
import pytest

from app.camera import Intrinsics
from app.decision.looming import LoomingEstimator

K = Intrinsics(640, 480, 615.0, 615.0, 319.5, 239.5)
FPS = 30.0


def box_of(xyz: np.ndarray, d_m: float, k: Intrinsics = K) -> tuple[float, float, float, float]:
    """The object's box (x, y, w, h px), cut by the frame like a motion mask's blob."""
    x, y, z = xyz
    u, v = k.fx * x / z + k.ppx, k.fy * y / z + k.ppy
    s = k.fx * d_m / z
    x0, y0 = max(0.0, u - s / 2), max(0.0, v - s / 2)
    x1, y1 = min(float(k.width), u + s / 2), min(float(k.height), v + s / 2)
    return x0, y0, x1 - x0, y1 - y0


def fly(start: tuple[float, float, float], vel: tuple[float, float, float], seconds: float,
        d_m: float = 0.3, noise_px: float = 0.0, seed: int = 0,
        est: LoomingEstimator | None = None):
    """Feed the estimator for ``seconds``; return it, the last time and the true state."""
    rng = np.random.default_rng(seed)
    est = est or LoomingEstimator(K)
    p0, v = np.array(start, float), np.array(vel, float)
    n = int(round(seconds * FPS))
    for i in range(n + 1):
        t = i / FPS
        x, y, w, h = box_of(p0 + v * t, d_m)
        if noise_px:
            x, y = x + rng.normal(0, noise_px), y + rng.normal(0, noise_px)
            w, h = max(1.0, w + rng.normal(0, noise_px)), max(1.0, h + rng.normal(0, noise_px))
        est.add(t, (x, y, w, h))
    t = n / FPS
    return est, t, p0 + v * t, v


def truth(p: np.ndarray, v: np.ndarray, d_m: float) -> tuple[float, tuple[float, float]]:
    tau = p[2] / -v[2]
    return tau, ((p[0] + v[0] * tau) / d_m, (p[1] + v[1] * tau) / d_m)


def test_time_to_contact_and_passage_exact_without_noise() -> None:
    est, t, p, v = fly((1.2, -0.6, 14.0), (-0.2, 0.15, -6.0), 1.0)
    e = est.estimate(t)
    assert e is not None and e.tau_s is not None and e.miss_sizes is not None
    tau, miss = truth(p, v, 0.3)
    assert e.tau_s == pytest.approx(tau, rel=0.03)
    assert e.miss_sizes[0] == pytest.approx(miss[0], abs=0.3)
    assert e.miss_sizes[1] == pytest.approx(miss[1], abs=0.3)
    assert e.range_m(0.3) == pytest.approx(p[2], rel=0.02)  # with the true size, the range


@pytest.mark.parametrize("seed", range(5))
def test_with_pixel_noise_the_estimate_holds_within_its_uncertainty(seed: int) -> None:
    """1 px of noise on every box side and the centre: τ within 15 %, the passage within
    0.25 m, and the truth inside 3 standard errors."""
    d = 0.3
    est, t, p, v = fly((0.8, 0.4, 12.0), (0.25, -0.3, -7.0), 1.0, d, noise_px=1.0, seed=seed)
    e = est.estimate(t)
    assert e is not None and e.tau_s is not None and e.miss_sizes is not None
    assert e.tau_std_s is not None and e.miss_sizes_std is not None
    tau, miss = truth(p, v, d)
    assert abs(e.tau_s - tau) <= max(0.15 * tau, 3 * e.tau_std_s)
    for a in (0, 1):
        assert abs(e.miss_sizes[a] - miss[a]) * d <= max(0.25, 3 * e.miss_sizes_std * d)


def test_a_collision_course_has_a_constant_bearing_and_a_passage_at_the_camera() -> None:
    est, t, p, v = fly((1.0, -0.5, 12.0), (-0.5, 0.25, -6.0), 1.0)  # aimed at the camera
    e = est.estimate(t)
    assert e is not None and e.miss_sizes is not None
    assert math.hypot(*e.bearing_rate) < 1e-3
    assert math.hypot(*e.miss_sizes) * 0.3 < 0.02


def test_crossing_object_passes_on_the_other_side_of_where_it_is_now() -> None:
    """Now up-left of the axis, flying down-right: it will pass down-right of the camera."""
    est, t, p, v = fly((-1.0, -0.6, 10.0), (1.3, 0.8, -5.0), 0.5)
    e = est.estimate(t)
    assert e is not None and e.miss_sizes is not None
    assert e.bearing[0] < 0 and e.bearing[1] < 0  # seen up-left
    assert e.miss_sizes[0] > 0 and e.miss_sizes[1] > 0  # passes down-right
    _, miss = truth(p, v, 0.3)
    assert e.miss_sizes[0] == pytest.approx(miss[0], rel=0.1)


def test_partially_cut_by_the_frame_edge_the_uncut_side_keeps_the_size() -> None:
    """The object's box runs off the left edge for the whole window: its width shrinks or
    grows with the cut, its height does not; τ comes from the height, and the cut axis's
    centre (biased inwards) is not taken for the bearing while the other axis has samples."""
    d = 0.6
    start = (-0.53 * 8.0, 0.0, 8.0)  # centre just outside the left edge
    est, t, p, v = fly(start, (0.0, 0.0, -4.0), 0.6, d)
    assert box_of(p, d)[0] == 0.0  # cut at the end too
    e = est.estimate(t)
    assert e is not None and e.tau_s is not None
    assert e.tau_s == pytest.approx(p[2] / 4.0, rel=0.05)



def test_a_box_ending_in_the_detectors_border_band_is_cut_by_the_edge() -> None:
    """Static scenery sliding in at the right edge in forward flight: the detector clears a
    4 px band and its dilation grows blobs 2 px back, so the box ends 3 px short of the edge
    while its width grows. With the decision's margin (border + half the growth + 1) the width
    counts as cut and the steady height says no approach; at the bare 2 px the width's growth
    read as looming (object-free flight, seed 41: τ 0.98 s, evaded)."""
    from app.camera import CameraModel
    from app.config import DecisionConfig
    from app.decision.policy import DecisionMaker

    dm = DecisionMaker(DecisionConfig(), CameraModel(K, K), mask_growth_px=4, border_px=4)
    assert dm.edge_px == 7.0
    bare, margin = LoomingEstimator(K, window_s=1.0), LoomingEstimator(K, window_s=1.0, edge_px=dm.edge_px)
    for i in range(31):
        t = i / FPS
        w = 14.0 / (1.0 - t / 1.5)  # growing inwards from the band as an approach would
        box = (K.width - 3.0 - w, 200.0, w, 14.0)
        bare.add(t, box)
        margin.add(t, box)
    eb, em = bare.estimate(1.0), margin.estimate(1.0)
    assert eb is not None and eb.tau_s is not None and eb.tau_s < 2.0  # the old margin's mistake
    assert em is None or em.tau_s is None


def test_the_camera_rotation_is_carried_out_of_the_bearing_rate() -> None:
    """The camera yaws at 20 deg/s while a ball comes straight at it: through the
    frame-to-frame homography (K R K^-1) the passage stays at the camera."""
    kmat = np.array([[K.fx, 0, K.ppx], [0, K.fy, K.ppy], [0, 0, 1.0]])
    rate = math.radians(20.0)
    est, bare = LoomingEstimator(K), LoomingEstimator(K)
    p0, v = np.array([0.5, 0.2, 12.0]), np.array([-0.5 / 2.0, -0.2 / 2.0, -6.0])  # hits at 2 s
    for i in range(31):
        t = i / FPS
        yaw = rate * t
        c, s = math.cos(yaw), math.sin(yaw)
        world_to_cam = np.array([[c, 0, -s], [0, 1, 0], [s, 0, c]])
        box = box_of(world_to_cam @ (p0 + v * t), 0.3)
        if i:
            step = np.array([[math.cos(rate / FPS), 0, -math.sin(rate / FPS)], [0, 1, 0],
                             [math.sin(rate / FPS), 0, math.cos(rate / FPS)]])
            est.carry(kmat @ step @ np.linalg.inv(kmat))
        est.add(t, box)
        bare.add(t, box)
    e, e_bare = est.estimate(1.0), bare.estimate(1.0)
    assert e is not None and e.miss_sizes is not None
    assert e_bare is not None and e_bare.miss_sizes is not None
    assert math.hypot(*e.miss_sizes) * 0.3 < 0.1  # on course, as it is
    assert math.hypot(*e_bare.miss_sizes) * 0.3 > 0.3  # without: a miss that is not there


def test_too_few_samples_or_no_expansion_give_no_time_to_contact() -> None:
    est = LoomingEstimator(K)
    for i in range(3):
        est.add(i / FPS, (300.0, 200.0, 10.0, 10.0))
    assert est.estimate(3 / FPS) is None
    est, t, _, _ = fly((1.0, 0.0, 20.0), (-2.0, 0.0, 0.0), 0.6)  # crossing, no closing
    e = est.estimate(t)
    assert e is not None and e.tau_s is None and e.miss_sizes is None


def test_the_course_in_object_sizes_is_exact_over_a_long_window() -> None:
    """From 14 m to 4 m in 1.2 s (the size grows 3.5x): ln(size) is far from a straight
    line, 1/size is one; over a 1.2 s window τ, the crossing point and the course in object
    diameters (P/D, V/D) come out as the geometry has them."""
    d = 0.3
    est = LoomingEstimator(K, window_s=1.2)
    est, t, p, v = fly((0.9, -0.4, 14.0), (-0.3, 0.2, -8.3), 1.2, d, est=est)
    e = est.estimate(t)
    assert e is not None and e.tau_s is not None and e.miss_sizes is not None
    assert e.position_sizes is not None and e.velocity_sizes is not None
    tau, miss = truth(p, v, d)
    assert e.tau_s == pytest.approx(tau, rel=0.01)
    assert e.miss_sizes == pytest.approx(miss, abs=0.05)
    # box corners are whole pixels here only where the frame cuts them; the course is in
    # object sizes (metres / D)
    assert e.position_sizes == pytest.approx(tuple(p / d), rel=0.02, abs=0.05)
    assert e.velocity_sizes == pytest.approx(tuple(v / d), rel=0.02, abs=0.1)
    assert e.size_chi2 < 1.0


@pytest.mark.parametrize("seed", range(3))
def test_sizes_that_jump_like_clutter_give_no_time_to_contact(seed: int) -> None:
    """A blob whose size jumps by up to half from frame to frame (a cloud's edge, a merged blob)
    on top of a real approach: no constant-velocity course explains it, so no τ, however
    the straight line through it happens to slope; the same course with 1 px of noise has one."""
    rng = np.random.default_rng(seed)
    jumpy, clean = LoomingEstimator(K, window_s=1.0), LoomingEstimator(K, window_s=1.0)
    p0, v = np.array([0.5, 0.2, 12.0]), np.array([0.0, 0.0, -6.0])
    for i in range(31):
        t = i / FPS
        x, y, w, h = box_of(p0 + v * t, 0.3)
        f = 1.0 + rng.uniform(-0.5, 0.5)
        jumpy.add(t, (x, y, w * f, h * f))
        n = rng.normal(0, 1.0, 4)
        clean.add(t, (x + n[0], y + n[1], w + n[2], h + n[3]))
    ej, ec = jumpy.estimate(1.0), clean.estimate(1.0)
    assert ej is not None and ej.size_chi2 > 9.0 and ej.tau_s is None and ej.miss_sizes is None
    assert ec is not None and ec.tau_s is not None and ec.size_chi2 <= 9.0


@pytest.mark.parametrize("seed", range(3))
def test_a_blob_that_jumps_to_a_new_size_and_stays_there_does_not_loom(seed: int) -> None:
    """A static blob (a roof's edge against the sky) that merges with the structure beside it
    and keeps that size: one level shift, not an approach, however a straight line through
    the window slopes; an approaching object measured as well has its τ; and an approach
    whose box jumps once and keeps its new proportion (merged with its own ghost) is fitted
    again after the jump, with its true τ."""
    rng = np.random.default_rng(seed)
    step, real, merged = (LoomingEstimator(K, window_s=1.0) for _ in range(3))
    p0, v = np.array([0.5, 0.2, 12.0]), np.array([0.0, 0.0, -6.0])
    for i in range(31):
        t = i / FPS
        n = rng.normal(0, 1.0, 4)
        w, h = (10.0, 12.0) if i < 18 else (27.0, 15.0)  # the roof's edge, then the roof
        step.add(t, (300 + n[0], 200 + n[1], w + n[2], h + n[3]))
        x, y, w, h = box_of(p0 + v * t, 0.3)
        real.add(t, (x + n[0], y + n[1], w + n[2], h + n[3]))
        k = 1.6 if i >= 12 else 1.0  # from frame 12 on, with its ghost beside it: 1.6 times as wide
        merged.add(t, (x + n[0], y + n[1], w * k + n[2], h + n[3]))
    es, er, em = step.estimate(1.0), real.estimate(1.0), merged.estimate(1.0)
    assert es is not None and es.tau_s is None
    tau_true = 6.0 / 6.0
    assert er is not None and er.tau_s is not None and er.tau_std_s is not None
    assert er.tau_s == pytest.approx(tau_true, abs=3 * er.tau_std_s)
    assert em is not None and em.tau_s is not None and em.tau_std_s is not None
    assert em.tau_s == pytest.approx(tau_true, abs=3 * em.tau_std_s)


def test_a_track_that_moves_to_another_blob_starts_its_course_again() -> None:
    """A track on a static blob (a tree's top) that passes, through a merge, to an approaching
    ball 0.3 rad away: the course is the ball's from the jump on, its bearing the ball's, not
    a line through both."""
    rng = np.random.default_rng(4)
    est = LoomingEstimator(K, window_s=1.0)
    p0, v = np.array([1.6, 0.1, 12.0]), np.array([0.0, 0.0, -6.0])
    for i in range(31):
        t = i / FPS
        n = rng.normal(0, 1.0, 4)
        if i < 14:
            box = (250 + n[0], 230 + n[1], 12 + n[2], 10 + n[3])  # the tree's top
        else:
            x, y, w, h = box_of(p0 + v * t, 0.3)
            box = (x + n[0], y + n[1], w + n[2], h + n[3])
        est.add(t, box)
    e = est.estimate(1.0)
    p = p0 + v * 1.0
    assert e is not None
    assert e.bearing[0] == pytest.approx(p[0] / p[2], abs=0.01)
    assert e.bearing[1] == pytest.approx(p[1] / p[2], abs=0.01)
    assert e.tau_s is not None and e.tau_std_s is not None
    assert e.tau_s == pytest.approx(1.0, abs=3 * e.tau_std_s)


@pytest.mark.parametrize("seed", range(3))
def test_a_box_merged_with_the_structure_below_for_a_few_frames_keeps_the_bearing(seed: int) -> None:
    """An approaching ball whose blob merges for single frames with a tree below it (a box
    8 times as tall, its centre lower): its sizes no longer keep to a course (no τ), but its
    bearing stays the ball's, to a few pixels, not a ratio of two broken lines."""
    rng = np.random.default_rng(seed)
    est = LoomingEstimator(K, window_s=1.0)
    p0, v = np.array([-2.4, 0.2, 9.0]), np.array([0.0, 0.0, -3.0])
    for i in range(31):
        t = i / FPS
        n = rng.normal(0, 1.0, 4)
        x, y, w, h = box_of(p0 + v * t, 0.3)
        if i in (5, 12, 19, 26, 29):
            y, h = y, 8 * h  # merged with the tree under it
        est.add(t, (x + n[0], y + n[1], w + n[2], h + n[3]))
    e = est.estimate(1.0)
    p = p0 + v * 1.0
    assert e is not None
    assert e.bearing[0] == pytest.approx(p[0] / p[2], abs=0.01)
    assert e.bearing[1] == pytest.approx(p[1] / p[2], abs=0.02)


def test_the_uncut_side_of_a_box_cut_by_one_edge_moves_with_the_objects_near_side() -> None:
    """An object crossing in past the left edge: the box's right side is its own, and its
    bearing moves as the object's right side does (the centre's rate plus half the angular
    size's); the other axis, uncut, has no inner edge, nor has a box cut on neither."""
    d = 0.6
    est, t, p, v = fly((-0.6 * 6.0, 0.2, 6.0), (1.5, 0.0, -3.0), 0.3, d)
    assert box_of(p, d)[0] == 0.0
    ex, ey = est.inner_edges()
    assert ey is None and ex is not None and ex.side == -1

    def right_side(q: np.ndarray) -> float:
        return (q[0] + d / 2) / q[2]

    dt = 0.15  # the window's middle: the fitted line's rate is the mean over it
    rate = (right_side(p) - right_side(p - v * 2 * dt)) / (2 * dt)
    assert ex.rate == pytest.approx(rate, rel=0.05)
    whole, _, _, _ = fly((0.0, 0.0, 6.0), (0.5, 0.0, -3.0), 0.3, d)
    assert whole.inner_edges() == (None, None)
