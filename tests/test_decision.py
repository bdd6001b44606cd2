"""Stage 4: property-based checks of the decision rules, depth lookup, and a replay of a
generated recording with depth in which an object flies at the camera."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from app.camera import CameraModel, Intrinsics
from app.config import Config, DecisionConfig, avoid_distance_m, config_from_mapping, explain
from app.decision.depth import object_depth
from app.decision.policy import EVADE, NONE, STOP, DecisionMaker, ObjectState, away_from, closes_on
from app.errors import ConfigError
from app.perception.recognition import Cluster
from app.runtime.sources import open_source
from app.sim.synthetic import approach_scene, write_recording
from app.tools.replay import run_replay

CAM = CameraModel(Intrinsics(640, 480, 615.0, 615.0, 319.5, 239.5),
                  Intrinsics(640, 480, 385.0, 385.0, 319.5, 239.5),
                  np.eye(3), np.array([0.015, 0.0, 0.0]))
CFG = DecisionConfig()
PAPER = DecisionConfig(trigger="distance")  # the paper's fixed thresholds only
ALT = 10.0  # m, above the altitude floor


def obj(x: float, y: float, z: float, tid: int = 1, fresh: bool = True, t: float = 0.0,
        closing: float = 0.0) -> ObjectState:
    ttc = z / closing if closing > 0.05 else None
    return ObjectState(tid, (x, y, z), t if fresh else t - 10.0, fresh, closing, ttc)


coord = st.floats(-1.4, 1.4, allow_nan=False)


@settings(max_examples=300, deadline=None)
@given(x=coord, y=coord, z=st.floats(CFG.emergency_m + 0.01, 0.99))
def test_threat_in_any_quadrant_is_evaded_away_in_both_axes(x: float, y: float, z: float) -> None:
    assume(math.hypot(x, y) < CFG.safe_window_m and abs(x) > 1e-3 and abs(y) > 1e-3)
    cmd = DecisionMaker(CFG, CAM).decide([obj(x, y, z)], 0.0, ALT)
    assert cmd.action == EVADE
    assert cmd.right_mps * x < 0 and cmd.down_mps * y < 0  # away from it on both axes
    assert cmd.forward_mps == 0.0
    assert cmd.speed_mps <= CFG.max_speed_mps + 1e-9


def test_the_four_quadrants_of_the_paper() -> None:
    cases = {(-0.5, -0.5): (1, 1), (0.5, -0.5): (-1, 1), (-0.5, 0.5): (1, -1), (0.5, 0.5): (-1, -1)}
    for (x, y), (r, d) in cases.items():  # upper-left -> down-right, ..., lower-right -> up-left
        cmd = DecisionMaker(CFG, CAM).decide([obj(x, y, 0.8)], 0.0, ALT)
        assert (np.sign(cmd.right_mps), np.sign(cmd.down_mps)) == (r, d)
        assert math.isclose(cmd.speed_mps, CFG.evade_speed_mps)


@settings(max_examples=200, deadline=None)
@given(x=coord, y=coord, z=st.one_of(st.just(float("nan")), st.floats(0.01, 20.0)))
def test_stale_or_missing_depth_never_triggers(x: float, y: float, z: float) -> None:
    cmd = DecisionMaker(CFG, CAM).decide([obj(x, y, z, fresh=False)], 0.0, ALT)
    assert cmd.action == NONE
    if math.isnan(z):
        assert DecisionMaker(CFG, CAM).decide([obj(x, y, z)], 0.0, ALT).action == NONE


def test_no_depth_pixels_mean_no_distance() -> None:
    cl = Cluster(320.0, 240.0, (310, 230, 20, 20), 400, (np.array([[[310, 230]], [[329, 230]],
                                                                   [[329, 249]], [[310, 249]]]),))
    zeros = np.zeros((480, 640), np.uint16)
    assert object_depth(cl, zeros, CAM, 0.2, 10.0, 25, 6) is None
    far = np.full((480, 640), 15000, np.uint16)  # 15 m: beyond the trusted range
    assert object_depth(cl, far, CAM, 0.2, 10.0, 25, 6) is None
    # a surface just beyond it, with a D435i's error: not its noise's near tail as a distance
    rng = np.random.default_rng(0)
    noisy = np.clip(rng.normal(10_600, 0.0036 * 10.6**2 * 1000, (480, 640)), 0, 65_535).astype(np.uint16)
    assert (noisy[230:250, 310:330] <= 10_000).sum() >= 6  # enough of the blob's nearer than 10 m
    assert object_depth(cl, noisy, CAM, 0.2, 10.0, 25, 6, CFG.depth_rms_per_m2) is None
    dm = DecisionMaker(CFG, CAM)
    from app.perception.tracking import TrackReport
    tr = TrackReport(1, 320.0, 240.0, 0, 0, (310, 230, 20, 20), True, 0.0, 10, cl, ())
    cmd, objects = dm.step([tr], zeros, 0.0, ALT)
    assert cmd.action == NONE and objects == []


def test_scattered_wrong_matches_are_no_distance_but_a_small_surface_is() -> None:
    """A blob over ground 30-60 m off (past the trusted range) holding 8 of a stereo camera's
    wrong matches, 3-9.5 m off each on its own: no surface agrees with them, so no distance
    (their 25th percentile read 3.6 m, a near object closing at the vehicle's speed: the
    `stereo` world, object-free). Six depths of one surface at 3.5 m in the same blob are one."""
    cl = Cluster(320.0, 240.0, (200, 230, 240, 40), 9600, (np.array([[[200, 230]], [[439, 230]],
                                                                    [[439, 269]], [[200, 269]]]),))
    rng = np.random.default_rng(3)
    depth = rng.integers(30_000, 60_000, (480, 640)).astype(np.uint16)

    def put(u: float, v: float, z: float) -> None:  # a depth at colour pixel (u, v), via the calibration
        p = CAM.color.deproject(np.array([u]), np.array([v]), np.array([z])) - CAM.translation_m
        du, dv = np.round(CAM.depth.project(p)[0]).astype(int)
        depth[dv, du] = int(z * 1000)

    spots = [(210, 235), (260, 262), (300, 240), (330, 250), (360, 233), (380, 266), (420, 245), (230, 255)]
    for (u, v), z in zip(spots, (3.16, 3.47, 3.67, 3.69, 4.48, 6.6, 9.16, 9.47), strict=True):
        put(u, v, z)
    assert object_depth(cl, depth, CAM, 0.2, 16.0, 25, 6, CFG.depth_rms_per_m2) is None
    for du in range(4):  # a small surface 3.5 m off: 8 depth pixels of it
        for dv in range(2):
            put(300 + 1.6 * du, 250 + 1.6 * dv, 3.5)
    found = object_depth(cl, depth, CAM, 0.2, 16.0, 25, 6, CFG.depth_rms_per_m2)
    assert found is not None and found.z_m == pytest.approx(3.5, abs=0.2)


def test_a_clump_of_wrong_matches_is_no_distance_but_the_smallest_object_is() -> None:
    """A stereo camera's wrong matches also come in clumps: 3 x 3 depth pixels agreeing on
    3.5 m in a blob over ground 30-60 m off are a surface, but one far smaller than any object
    could be there, so no distance (clumps read as surfaces 2.6-5 m off evaded 126 times in
    10 object-free minutes). The smallest plausible object at 3.5 m, with depth on its rim only
    (a uniform ball's inside has no texture to match), is one."""
    cl = Cluster(320.0, 240.0, (200, 200, 240, 80), 19200, (np.array([[[200, 200]], [[439, 200]],
                                                                     [[439, 279]], [[200, 279]]]),))
    rng = np.random.default_rng(5)
    depth = rng.integers(30_000, 60_000, (480, 640)).astype(np.uint16)
    z = 3.5
    args = (CAM, 0.2, 16.0, 25, 6, CFG.depth_rms_per_m2, CFG.object_diameter_max_m,
            CFG.object_diameter_min_m, CFG.min_depth_cover)
    centre = CAM.depth.project(CAM.color.deproject(np.array([320.0]), np.array([240.0]), np.array([z]))
                               - CAM.translation_m)[0]
    du, dv = np.round(centre).astype(int)
    clump = depth.copy()
    clump[dv - 1:dv + 2, du - 1:du + 2] = int(z * 1000)
    assert object_depth(cl, clump, *args) is None
    assert object_depth(cl, clump, *args[:7]) is not None  # (without the rule: a 3.5 m surface)
    r_px = CFG.object_diameter_min_m / 2 * CAM.depth.fx / z
    uu, vv = np.meshgrid(np.arange(640), np.arange(480))
    dist = np.hypot(uu - centre[0], vv - centre[1])
    ball = depth.copy()
    ball[(dist <= r_px) & (dist > r_px - 3)] = int(z * 1000)  # a 3 px rim
    found = object_depth(cl, ball, *args)
    assert found is not None and found.z_m == pytest.approx(z, abs=0.2)


def test_depth_is_read_on_the_blob_through_the_calibration() -> None:
    """A 2 m object seen by a depth camera 15 mm to the left of the colour camera, with
    another focal length: the lookup must find its depth pixels, not the 6 m wall."""
    depth = np.full((480, 640), 6000, np.uint16)
    z = 2.0
    # the object's colour pixels: a disc of radius 20 px around (400, 200)
    uu, vv = np.meshgrid(np.arange(640), np.arange(480))
    disc = (uu - 400) ** 2 + (vv - 200) ** 2 <= 20**2
    pts_c = CAM.color.deproject(uu[disc], vv[disc], np.full(disc.sum(), z))
    pts_d = pts_c - CAM.translation_m
    uv_d = np.round(CAM.depth.project(pts_d)).astype(int)
    depth[uv_d[:, 1], uv_d[:, 0]] = int(z * 1000)
    import cv2
    mask = disc.astype(np.uint8) * 255
    contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    bx, by, bw, bh = cv2.boundingRect(contours[0])
    cl = Cluster(400.0, 200.0, (bx, by, bw, bh), int(disc.sum()), tuple(contours))
    d = object_depth(cl, depth, CAM, 0.2, 10.0, 25, 6)
    assert d is not None and abs(d.z_m - 2.0) < 0.01
    x, y, zz = d.xyz_m
    assert abs(x - (400 - 319.5) / 615 * 2) < 0.01 and abs(y - (200 - 239.5) / 615 * 2) < 0.01


def test_the_bearing_is_the_near_surface_s_not_the_blob_s_centre() -> None:
    """A 0.3 m ball 6 m off whose blob merged with a 40 px patch of ground 18 m off (a frame
    difference's blob does: the ground's parallax, or the ball's own ghost): the distance is the
    ball's, and so must the bearing be. The blob's centre lies 12 px off the ball's, 0.12 m
    sideways at 6 m: a third of the miss that decides which way to escape."""
    depth = np.full((480, 640), 18000, np.uint16)  # the ground behind, 18 m
    uu, vv = np.meshgrid(np.arange(640), np.arange(480))
    ball = (uu - 400) ** 2 + (vv - 200) ** 2 <= 15**2  # 0.3 m at 6 m, 615 px focal: r 15 px
    ground = (uu >= 400) & (uu < 440) & (vv >= 185) & (vv < 215)
    pts_c = CAM.color.deproject(uu[ball], vv[ball], np.full(int(ball.sum()), 6.0))
    uv_d = np.round(CAM.depth.project(pts_c - CAM.translation_m)).astype(int)
    depth[uv_d[:, 1], uv_d[:, 0]] = 6000
    import cv2
    blob = (ball | ground).astype(np.uint8) * 255
    contours, _ = cv2.findContours(blob, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    bx, by, bw, bh = cv2.boundingRect(contours[0])
    ys, xs = np.nonzero(blob)
    cl = Cluster(float(xs.mean()), float(ys.mean()), (bx, by, bw, bh), int(blob.astype(bool).sum()),
                 tuple(contours))
    assert cl.x - 400 > 10  # the blob's centre is well off the ball's
    d = object_depth(cl, depth, CAM, 0.2, 20.0, 25, 6, CFG.depth_rms_per_m2, CFG.object_diameter_max_m)
    assert d is not None and abs(d.z_m - 6.0) < 0.01
    x_true, y_true = (400 - 319.5) / 615 * 6, (200 - 239.5) / 615 * 6
    assert abs(d.xyz_m[0] - x_true) < 0.02 and abs(d.xyz_m[1] - y_true) < 0.02
    assert d.near_pixels < d.pixels  # the ground's pixels on the blob were left out
    # Two balls 2.4 m apart at the same range in one blob are not one object's surface: the
    # mean of their points would be neither's place; the blob's centre is taken, as before
    depth2 = depth.copy()
    other = (uu - 150) ** 2 + (vv - 200) ** 2 <= 25**2
    pts2 = CAM.color.deproject(uu[other], vv[other], np.full(int(other.sum()), 6.0))
    uv2 = np.round(CAM.depth.project(pts2 - CAM.translation_m)).astype(int)
    depth2[uv2[:, 1], uv2[:, 0]] = 6000
    wide = ((uu >= 150) & (uu < 400) & (vv >= 198) & (vv < 203)) | ball | other  # joined by a thin strip
    blob2 = wide.astype(np.uint8) * 255
    contours2, _ = cv2.findContours(blob2, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    ys2, xs2 = np.nonzero(blob2)
    bx2, by2, bw2, bh2 = cv2.boundingRect(contours2[0])
    cl2 = Cluster(float(xs2.mean()), float(ys2.mean()), (bx2, by2, bw2, bh2), int(wide.sum()),
                  tuple(contours2))
    d2 = object_depth(cl2, depth2, CAM, 0.2, 20.0, 25, 6, CFG.depth_rms_per_m2, CFG.object_diameter_max_m)
    assert d2 is not None and abs(d2.z_m - 6.0) < 0.01
    centre = CAM.color.deproject(np.array([cl2.x]), np.array([cl2.y]), np.array([d2.z_m]))[0]
    assert d2.xyz_m == pytest.approx(tuple(centre))


@settings(max_examples=200, deadline=None)
@given(x=coord, y=coord, z=st.floats(0.05, 12.0), alt=st.one_of(st.none(), st.floats(0, 1.99)))
def test_altitude_floor_removes_the_downward_component(x: float, y: float, z: float,
                                                       alt: float | None) -> None:
    cmd = DecisionMaker(CFG, CAM).decide([obj(x, y, z)], 0.0, alt)
    assert cmd.down_mps <= 0.0
    assert cmd.speed_mps <= CFG.max_speed_mps + 1e-9


def test_altitude_floor_turns_a_downward_escape_horizontal() -> None:
    cmd = DecisionMaker(CFG, CAM).decide([obj(-0.5, -0.5, 0.8)], 0.0, 1.0)  # upper-left, low
    assert cmd.action == EVADE and cmd.down_mps == 0.0 and cmd.right_mps > 0
    assert math.isclose(cmd.speed_mps, CFG.evade_speed_mps)


@settings(max_examples=200, deadline=None)
@given(objs=st.lists(st.tuples(coord, coord, st.floats(0.05, 12.0)), min_size=1, max_size=4),
       speed=st.floats(0.5, 10.0), vmax=st.floats(0.5, 10.0))
def test_no_command_exceeds_the_speed_limit(objs: list, speed: float, vmax: float) -> None:
    assume(speed <= vmax)
    cfg = DecisionConfig(evade_speed_mps=speed, max_speed_mps=vmax)
    dm = DecisionMaker(cfg, CAM)
    states = [obj(x, y, z, tid=i + 1) for i, (x, y, z) in enumerate(objs)]
    for k in range(3):
        cmd = dm.decide(states, k * 0.03, ALT)
        assert cmd.speed_mps <= vmax + 1e-9
        if cmd.action == EVADE:
            assert not any(closes_on((cmd.right_mps, cmd.down_mps), s.xyz_m[0], s.xyz_m[1])
                           for s in states if s.lateral_m < cfg.safe_window_m
                           and 0 < s.z_m < avoid_distance_m(cfg))


def test_emergency_outranks_evade_and_nearest_object_wins() -> None:
    dm = DecisionMaker(CFG, CAM)
    cmd = dm.decide([obj(0.5, 0.5, 0.9, tid=1), obj(0.3, 0.0, 0.4, tid=2), obj(0.0, 0.5, 0.2, tid=3)],
                    0.0, ALT)
    assert cmd.action == STOP and cmd.object_id == 2  # 0.50 m away; object 3 is 0.54 m
    assert (cmd.forward_mps, cmd.right_mps, cmd.down_mps) == (0.0, 0.0, 0.0)


def test_an_object_abeam_is_not_an_emergency_however_small_its_z() -> None:
    """'Very close' is the distance: an object 3 m to the side with Z 0.3 m is passing,
    and stopping then avoids nothing."""
    assert DecisionMaker(CFG, CAM).decide([obj(3.0, 0.0, 0.3)], 0.0, ALT).action == NONE
    assert DecisionMaker(CFG, CAM).decide([obj(0.2, 0.3, 0.3)], 0.0, ALT).action == STOP  # 0.47 m


def test_outside_the_window_or_far_is_not_a_threat() -> None:
    dm = DecisionMaker(CFG, CAM)
    assert dm.decide([obj(1.2, 1.2, 0.8)], 0.0, ALT).action == NONE  # lateral 1.7 m > 1.5 m
    assert dm.decide([obj(0.2, 0.2, 3.0)], 0.0, ALT).action == NONE  # inside, but 3 m > 1 m


def test_opposite_threats_choose_a_direction_that_closes_on_neither_or_stop() -> None:
    dm = DecisionMaker(CFG, CAM)
    # upper-left wants down-right, which closes on the lower-right one: up-right clears both
    a, b = obj(-0.5, -0.3, 0.8, 1), obj(0.3, 0.5, 0.9, 2)
    cmd = dm.decide([a, b], 0.0, ALT)
    assert cmd.action == EVADE and cmd.right_mps > 0 and cmd.down_mps < 0
    assert not any(closes_on((cmd.right_mps, cmd.down_mps), o.xyz_m[0], o.xyz_m[1]) for o in (a, b))
    # surrounded on all four sides: no direction clears them all
    ring = [obj(0.6, 0.0, 0.8, 1), obj(-0.6, 0.0, 0.8, 2), obj(0.0, 0.6, 0.8, 3), obj(0.0, -0.6, 0.8, 4)]
    cmd = DecisionMaker(CFG, CAM).decide(ring, 0.0, ALT)
    assert cmd.action == STOP and "no escape direction" in cmd.reason


def test_hysteresis_keeps_direction_and_releases_past_the_margin() -> None:
    dm = DecisionMaker(CFG, CAM)
    first = dm.decide([obj(-0.1, -0.1, 0.9, t=0.0)], 0.0, ALT)
    assert first.action == EVADE and first.right_mps > 0 and first.down_mps > 0
    # noise flips the object across the centre: the direction stays latched
    flip = dm.decide([obj(0.05, 0.05, 0.85, t=0.03)], 0.03, ALT)
    assert (flip.right_mps, flip.down_mps) == (first.right_mps, first.down_mps)
    # just outside the window but inside the margin: still evading
    assert dm.decide([obj(1.6, 0.0, 0.8, t=0.06)], 0.06, ALT).action == EVADE
    # beyond window + margin: released
    assert dm.decide([obj(1.9, 0.0, 0.8, t=0.09)], 0.09, ALT).action == NONE


def test_eq_4_3_round_trips_and_is_explained() -> None:
    paper = {"safe_window_m": 1.5, "evade_speed_mps": 3.0, "max_speed_mps": 3.0}  # §5-C's figures
    cfg = config_from_mapping({"decision": {"avoid_m": None, "object_speed_mps": 2.0, **paper}})
    assert math.isclose(avoid_distance_m(cfg.decision), 1.0)
    # and back: the given avoid_m implies v_obj = avoid * v_max / R_safe
    given_cfg = config_from_mapping({"decision": paper})
    text = explain(given_cfg)
    assert "v_obj = avoidThresh * v_max / R_safe = 2 m/s" in text
    assert "= 1.5 * 2 / 3 = 1 m (derived)" in explain(cfg)
    with pytest.raises(ConfigError, match="decision.emergency_m = 1.2: must be < the avoidance"):
        config_from_mapping({"decision": {"emergency_m": 1.2}})


def test_away_from_and_closes_on() -> None:
    assert away_from(-1, -1)[0] > 0 and away_from(-1, -1)[1] > 0
    assert closes_on((1.0, 0.0), 0.5, 0.0) and not closes_on((1.0, 0.0), -0.5, 0.3)


def test_ttc_trigger_evades_earlier_than_the_fixed_distance() -> None:
    ttc_cfg = DecisionConfig(trigger="ttc", ttc_avoid_s=1.0)
    approaching = obj(0.3, 0.3, 2.5, closing=4.0)  # ttc 0.6 s, still 2.5 m away
    assert DecisionMaker(PAPER, CAM).decide([approaching], 0.0, ALT).action == NONE
    assert DecisionMaker(ttc_cfg, CAM).decide([approaching], 0.0, ALT).action == EVADE


def test_ttc_trigger_sees_a_crossing_object_before_it_is_in_the_window() -> None:
    ttc_cfg = DecisionConfig(trigger="ttc", ttc_avoid_s=1.5)
    # 2.4 m to the right at 5 m, coming in at 5 m/s and sliding left at 2.2 m/s: it crosses
    # the camera plane 0.2 m right of the axis in 1 s. Now it is outside the 1.5 m window.
    crossing = ObjectState(1, (2.4, 0.0, 5.0), 0.0, True, 5.0, 1.0, (0.2, 0.0))
    assert crossing.lateral_m > ttc_cfg.safe_window_m
    assert DecisionMaker(PAPER, CAM).decide([crossing], 0.0, ALT).action == NONE  # the paper's rule
    cmd = DecisionMaker(ttc_cfg, CAM).decide([crossing], 0.0, ALT)
    assert cmd.action == EVADE and cmd.right_mps < 0  # away from where it will cross, not
    # from where it is (it is on the right now and will still be right of the axis)
    passing = ObjectState(1, (2.4, 0.0, 5.0), 0.0, True, 5.0, 1.0, (2.3, 0.0))  # stays wide
    assert DecisionMaker(ttc_cfg, CAM).decide([passing], 0.0, ALT).action == NONE
    # one that will cross on the left of the axis: escape right, although it is on the right now
    across = ObjectState(1, (1.6, 0.3, 5.0), 0.0, True, 5.0, 1.0, (-0.4, 0.3))
    assert DecisionMaker(ttc_cfg, CAM).decide([across], 0.0, ALT).right_mps > 0


def _run_noisy_depth(cfg: DecisionConfig, z0: float, closing: float, seed: int) -> float | None:
    """Feed one object straight ahead, first measured at ``z0`` m and closing at ``closing``
    m/s, with D435i-like depth noise (RMS 0.0036 z², Intel's D400 formula) for 3 s at 30 fps;
    return how long after its first depth an evasion began (None: never)."""
    cl = Cluster(320.0, 240.0, (310, 230, 20, 20), 400,
                 (np.array([[[310, 230]], [[329, 230]], [[329, 249]], [[310, 249]]]),))
    from app.perception.tracking import TrackReport
    tr = TrackReport(1, 320.0, 240.0, 0, 0, (310, 230, 20, 20), True, 0.0, 10, cl, ())
    rng = np.random.default_rng(seed)
    dm = DecisionMaker(cfg, CAM)
    for k in range(90):
        t = k / 30
        z = z0 - closing * t
        if z < 1.0:
            break
        measured = z + rng.normal(0.0, 0.0036 * z * z)
        cmd, _ = dm.step([tr], np.full((480, 640), int(measured * 1000), np.uint16), t, ALT)
        if cmd.action == EVADE:
            return t
    return None


def test_noisy_far_depth_neither_invents_a_collision_nor_delays_a_real_one() -> None:
    # A hovering object 9 m ahead (depth noise 0.29 m): the time-to-collision from noise
    # alone must never fall under ttc_avoid_s.
    assert all(_run_noisy_depth(CFG, 9.0, 0.0, seed) is None for seed in range(20))
    # One closing at 12 m/s, first measured at the end of the depth range (10 m, 0.83 s
    # away): the 3-D track must settle on its speed within a few frames.
    starts = [_run_noisy_depth(CFG, 10.0, 12.0, seed) for seed in range(20)]
    assert all(s is not None and s <= 0.3 for s in starts)


@pytest.fixture(scope="module")
def approach(tmp_path_factory: pytest.TempPathFactory) -> Path:
    # a 0.3 m ball from 8 m, upper-left of the axis, closing at 4 m/s
    return write_recording(approach_scene((-0.4, -0.3, 8.0)), tmp_path_factory.mktemp("a") / "rec")


def test_replay_with_depth_evades_an_approaching_object(approach: Path, tmp_path: Path) -> None:
    paper = Config(decision=PAPER)
    stats = run_replay(open_source(approach), paper, tmp_path, video=False, altitude_m=ALT)
    rows = (tmp_path / "decisions.csv").read_text().splitlines()
    assert rows[0] == "frame,action,forward_mps,right_mps,down_mps,object_id"
    assert len(rows) - 1 == len(stats.decisions)
    evades = [(f, c) for f, c in stats.decisions if c.action == EVADE]
    assert evades, "no evasion"
    f0, c0 = evades[0]
    # the ball is at z = 8 - 4 * (f - 1) / 30 m: the evasion starts inside the avoidance
    # distance but before it is closer than the emergency distance
    z_at_start = 8.0 - 4.0 * (f0 - 1) / 30.0
    assert PAPER.avoid_m is not None and PAPER.emergency_m < z_at_start <= PAPER.avoid_m + 0.15
    assert c0.right_mps > 0 and c0.down_mps > 0  # upper-left ball: down-right
    assert not any(c.action == STOP for f, c in stats.decisions if f < f0)
    assert all(c.action == NONE for f, c in stats.decisions if f < f0)
    # the default (time-to-collision, 1.5 s) starts the same evasion far earlier: at about
    # 4 m/s x 1.5 s = 6 m, once the 3-D track has its closing speed
    ttc_cfg = Config(decision=DecisionConfig(trigger="ttc"))
    ttc = run_replay(open_source(approach), ttc_cfg, tmp_path / "ttc", video=False, altitude_m=ALT)
    f1, c1 = next((f, c) for f, c in ttc.decisions if c.action == EVADE)
    z_ttc = 8.0 - 4.0 * (f1 - 1) / 30.0
    assert 3.0 < z_ttc <= 4.0 * CFG.ttc_avoid_s + 0.3 and f1 < f0
    assert c1.right_mps > 0 and c1.down_mps > 0
    # the default (response: looming and the vehicle's need) acts in time for the vehicle
    # to move what the ball's passage leaves of its clearance (it passes 0.5 m off, at
    # (-0.4, -0.3) m: the scene's geometry), with most of trigger_margin_s to spare, and away
    # from that passage (up-left of it: never up, left)
    resp = run_replay(open_source(approach), Config(), tmp_path / "resp", video=False, altitude_m=ALT)
    f2, c2 = next((f, c) for f, c in resp.decisions if c.action == EVADE)
    left_s = (8.0 - 4.0 * (f2 - 1) / 30.0) / 4.0  # time to the camera plane when it began
    clearance = CFG.vehicle_radius_m + 0.15 + CFG.clearance_margin_m
    need = DecisionMaker(CFG, CAM).response.time_to_move_s(clearance - 0.5)
    assert left_s >= need + 0.5 * CFG.trigger_margin_s and f2 < f0
    assert c2.right_mps >= 0 and c2.down_mps >= 0 and c2.speed_mps > 0


def test_min_track_confidence_keeps_unbelieved_tracks_out_of_depth() -> None:
    """Only with ``min_track_confidence`` raised does a low-confidence track go unmeasured."""
    import dataclasses

    from app.perception.tracking import TrackReport
    cl = Cluster(320.0, 240.0, (310, 230, 20, 20), 400, (np.array([[[310, 230]], [[329, 230]],
                                                                   [[329, 249]], [[310, 249]]]),))
    depth = np.full((480, 640), 3000, np.uint16)  # 3 m everywhere
    tr = TrackReport(1, 320.0, 240.0, 0, 0, (310, 230, 20, 20), True, 0.0, 10, cl, (), confidence=0.1)
    _, objects = DecisionMaker(CFG, CAM).step([tr], depth, 0.0, ALT)
    assert [round(o.z_m, 1) for o in objects] == [3.0]  # the default measures every track
    strict = dataclasses.replace(CFG, min_track_confidence=0.35)
    _, objects = DecisionMaker(strict, CAM).step([tr], depth, 0.0, ALT)
    assert objects == []
    _, objects = DecisionMaker(strict, CAM).step([dataclasses.replace(tr, confidence=0.5)], depth, 0.0, ALT)
    assert len(objects) == 1


def _crossing_errors(seed: int) -> list[tuple[float, float]]:
    """A 3-D track of an object on a collision course from 20 m, 19° right of the axis
    (constant bearing 0.35, closing at 8 m/s, 30 fps), measured as the D435i measures it: the
    range with its error σ(z) = depth_rms_per_m2 · z², the point on the ray through the
    (exact) bearing. Per frame from 16 m in: (the passage's lateral error, its stated std), m."""
    from app.decision.policy import _Track3D

    rng = np.random.default_rng(seed)
    b, speed, fps = 0.35, 8.0, 30.0
    out = []
    track = None
    for k in range(int(12.0 / speed * fps)):  # 20 m -> 8 m
        t = k / fps
        z = 20.0 - speed * t
        zm = z + rng.normal(0.0, CFG.depth_rms_per_m2 * z * z)
        xyz = (b * zm, 0.0, zm)
        if track is None:
            track = _Track3D(xyz, t, CFG)
            continue
        track.advance(t)
        track.update(xyz, t)
        s = track.state(1, t)
        if z <= 16.0 and s.crossing_m is not None:
            out.append((s.crossing_m[0], s.crossing_std_m))  # the truth crosses at X = 0
    return out


def test_a_far_range_error_runs_along_the_ray_not_sideways() -> None:
    # Beyond 10 m the D435i's range errs by 0.4-1.4 m; on an object off the axis that error
    # moves the measured point along its ray, which a track taking X, Y and Z as independent
    # reads as lateral motion (a collision course passing metres off, with a stated error a
    # fraction of that). The passage must stay within its stated error.
    errs = [e for seed in range(10) for e in _crossing_errors(seed)]
    inside = sum(abs(x) <= 2.0 * std for x, std in errs) / len(errs)
    assert inside >= 0.9, f"passage outside 2 stated errors in {1 - inside:.0%} of frames"
    # and where it passes is known: a median error of 0.30 m with the three taken as
    # independent, 0.02 m along the ray
    assert np.median([abs(x) for x, _ in errs]) < 0.1


def test_a_measurement_metres_off_the_track_is_not_taken_for_motion() -> None:
    """A hovering thing 15.7 m ahead, 5 m to the left, measured for 10 frames with the D435i's
    noise; then its blob's nearest structure jumps 6 m sideways and 3 m down for two frames
    (a blob spread by parallax, measured wherever its nearest part is) and back. The jumps
    lie far beyond the gate: the track does not take them, and its closing speed stays within
    what the noise allows (taken, they made it 28-31 m/s). Three in a row restart it."""
    from app.decision.policy import GATE_RESTART, _Track3D

    rng = np.random.default_rng(3)
    here = np.array([-5.0, 1.0, 15.7])

    def noisy(p: np.ndarray) -> tuple[float, float, float]:
        sz = CFG.depth_rms_per_m2 * p[2] ** 2
        q = p * (1.0 + rng.normal(0.0, sz) / p[2]) + np.r_[rng.normal(0.0, 0.05, 2), 0.0]
        return (float(q[0]), float(q[1]), float(q[2]))

    tr = _Track3D(noisy(here), 0.0, CFG)
    t = 0.0
    for _ in range(10):
        t += 1 / 30
        tr.advance(t)
        assert tr.update(noisy(here), t)
    for _ in range(2):
        t += 1 / 30
        tr.advance(t)
        assert not tr.update(noisy(here + np.array([-6.0, 3.0, 0.0])), t)
    t += 1 / 30
    tr.advance(t)
    assert tr.update(noisy(here), t) and tr.rejected == 0
    assert abs(tr.state(1, t).closing_mps) < 3.0
    for _ in range(GATE_RESTART):
        t += 1 / 30
        tr.advance(t)
        assert not tr.update(noisy(here + np.array([6.0, 0.0, 0.0])), t)
    assert tr.rejected == GATE_RESTART  # the decision starts a new track from here


def _depth_only_start(ranges: list[float | None], reported: bool) -> float | None:
    """An object straight ahead measured in depth only (its blob the same every frame, so no
    looming), one range a frame at 30 fps (None: no depth on it); when an evasion began (None:
    never)."""
    from app.perception.tracking import TrackReport

    cl = Cluster(320.0, 240.0, (310, 230, 20, 20), 400,
                 (np.array([[[310, 230]], [[329, 230]], [[329, 249]], [[310, 249]]]),))
    tr = TrackReport(1, 320.0, 240.0, 0, 0, (310, 230, 20, 20), True, 0.0, 10, cl, (), reported=reported)
    dm = DecisionMaker(CFG, CAM)
    for k, z in enumerate(ranges):
        depth = np.full((480, 640), 0 if z is None else int(z * 1000), np.uint16)
        cmd, _ = dm.step([tr], depth, k / 30, ALT)
        if cmd.action == EVADE:
            return k / 30
    return None


def test_depth_speaks_for_an_object_only_where_it_finds_it_in_most_looks(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """A track following wrong matches: its blob read in depth every frame, measured at 15.2
    and 14.9 m, then nothing for 10 frames, then 9.2 and 8.9 m, 'closing' at 13 m/s (the
    `stereo_clumps` world: the tree behind them stood 46 m off). Measured in under half its
    looks, its depth does not speak for it, reported or not: no evasion (with the share
    at 0, it is evaded). One truly closing at 12 m/s from 10 m, with the D435i's noise and a
    range missing in one frame of four, still is, within 0.3 s, unreported."""
    import app.decision.policy as policy

    jumpy: list[float | None] = [15.2, None, None, None, 14.9] + [None] * 10 + [9.2, None, None, None, 8.9]
    jumpy += [None] * 10
    assert _depth_only_start(jumpy, reported=False) is None
    assert _depth_only_start(jumpy, reported=True) is None
    monkeypatch.setattr(policy, "MIN_MEASURED_SHARE", 0.0)
    assert _depth_only_start(jumpy, reported=False) is not None
    monkeypatch.undo()
    rng = np.random.default_rng(4)
    for _ in range(10):
        zs = 10.0 - 12.0 * np.arange(60) / 30
        straight = [None if k % 4 == 3 else float(z + rng.normal(0.0, 0.0036 * z * z))
                    for k, z in enumerate(zs) if z > 1.0]
        start = _depth_only_start(straight, reported=False)
        assert start is not None and start <= 0.3


def _fused_commands(reported: bool, range_rate: float | None, rate_std: float = 1.0) -> list[str]:
    """An object fused from the image's looming and a range, from 15 m ahead on a collision
    course at 18.75 m/s (τ 0.8 s, shrinking with the clock), decided frame by frame."""
    import dataclasses

    dm = DecisionMaker(CFG, CAM)
    actions = []
    for k in range(8):
        t = k / 30.0
        tau = 0.8 - t
        o = ObjectState(7, (0.0, 0.0, 15.0 * tau / 0.8), t, True, 15.0 / 0.8, tau, (0.0, 0.0), source="fused",
                        tau_s=tau, tau_std_s=0.1, miss_sizes=(0.0, 0.0), miss_sizes_std=0.2,
                        diameter_m=0.4, seen_s=t, reported=reported,
                        range_rate_mps=range_rate,
                        range_rate_std_mps=None if range_rate is None else rate_std)
        actions.append(dm.decide_response([dataclasses.replace(o)], t, ALT).action)
    return actions


def test_an_unreported_object_triggers_once_its_ranges_close_as_its_image_says() -> None:
    # perception reports it: the image's τ with a range is enough, as before
    assert EVADE in _fused_commands(reported=True, range_rate=None)
    # perception calls it clutter: its ranges must close about as fast as the image says
    # (a tree whose blob filled in read τ 0.68 s at 15 m while its ranges held still)
    assert EVADE not in _fused_commands(reported=False, range_rate=None)
    assert EVADE not in _fused_commands(reported=False, range_rate=0.6, rate_std=1.9)
    assert EVADE not in _fused_commands(reported=False, range_rate=18.0, rate_std=12.0)  # not known yet
    assert EVADE in _fused_commands(reported=False, range_rate=17.0, rate_std=3.0)
