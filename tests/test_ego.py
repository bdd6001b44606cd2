"""The camera's own motion and the static-structure test (app.decision.ego), on exact
synthetic geometry: static structure seen from a camera flying forward, objects on a
collision course and crossing, with pixel noise; and what the decision does with it."""

from __future__ import annotations

import math

import numpy as np
import pytest

from app.camera import CameraModel
from app.config import DecisionConfig
from app.decision.ego import EgoMotion, camera_velocity, derotation, mounted, static_fit
from app.decision.policy import NONE, DecisionMaker, ObjectState
from app.flight.engagement import VehicleState
from app.perception.recognition import Cluster
from app.perception.tracking import TrackReport
from tests.test_looming import K, box_of, fly


def test_camera_velocity_turns_ned_into_the_cameras_axes() -> None:
    # level, facing north, flying north: straight along the optical axis
    assert camera_velocity((3.0, 0.0, 0.0), 0.0, 0.0, 0.0) == pytest.approx((0.0, 0.0, 3.0))
    # facing east (yaw 90°), flying north: the world moves to the camera's left
    east = camera_velocity((3.0, 0.0, 0.0), 0.0, 0.0, math.pi / 2)
    assert east == pytest.approx((-3.0, 0.0, 0.0), abs=1e-9)
    # climbing: up is the camera's -Y
    assert camera_velocity((0.0, 0.0, -1.0), 0.0, 0.0, 0.0) == pytest.approx((0.0, -1.0, 0.0))
    # nose down 10° (PX4: negative pitch), flying level north: the line of flight lies above
    # the optical axis, so the velocity has an upward (-Y) part in the camera
    x, y, z = camera_velocity((3.0, 0.0, 0.0), 0.0, math.radians(-10.0), 0.0)
    assert x == pytest.approx(0.0, abs=1e-9)
    assert y == pytest.approx(-3.0 * math.sin(math.radians(10.0)))
    assert z == pytest.approx(3.0 * math.cos(math.radians(10.0)))
    # rolled right 20°, flying east: part of "right" becomes the camera's down
    x, y, _ = camera_velocity((0.0, 2.0, 0.0), math.radians(20.0), 0.0, 0.0)
    assert x == pytest.approx(2.0 * math.cos(math.radians(20.0)))
    assert y == pytest.approx(-2.0 * math.sin(math.radians(20.0)))


def _static_point(point: tuple[float, float, float], cam_vel: tuple[float, float, float],
                  seconds: float = 1.0, noise_px: float = 0.0, seed: int = 0, d_m: float = 0.5):
    """A static blob of ``d_m`` at ``point`` (camera axes at the end) seen from a camera
    flying at ``cam_vel``: relative to the camera it moves at -cam_vel."""
    v = -np.array(cam_vel, float)
    start = np.array(point, float) - v * seconds
    return fly(tuple(start), tuple(v), seconds, d_m=d_m, noise_px=noise_px, seed=seed)


@pytest.mark.parametrize("seed", range(4))
def test_static_structure_beside_the_line_of_flight_is_found_and_placed(seed: int) -> None:
    # a patch of ground or a tree 6 m ahead, 2.5 m right and 1.5 m below, camera at 3 m/s:
    # it grows and drifts outwards; as static structure it passes 2.9 m off the line of flight
    ego = EgoMotion((0.0, 0.0, 3.0), 0.1)
    est, t, p, _ = _static_point((2.5, 1.5, 6.0), ego.velocity_mps, noise_px=0.3, seed=seed)
    e = est.estimate(t)
    assert e is not None and e.tau_s is not None
    fit = static_fit(e, ego, 0.02)
    assert fit is not None and fit.fits
    assert 1.0 / fit.inverse_range == pytest.approx(p[2], rel=0.15)
    assert fit.miss_m == pytest.approx(math.hypot(2.5, 1.5), rel=0.15)
    assert fit.miss_std_m < 0.5 * fit.miss_m


@pytest.mark.parametrize("seed", range(4))
def test_a_collision_course_is_never_read_as_static_structure(seed: int) -> None:
    # a ball at 6 m/s head-on, off to the side of the line of flight, with the camera flying
    # at 3 m/s: its bearing holds, which static structure there would not do
    ego = EgoMotion((0.0, 0.0, 3.0), 0.1)
    est, t, _p, _v = fly((2.0, 1.0, 14.0), (-2.0 / 14 * 9, -1.0 / 14 * 9, -9.0), 1.0,
                         noise_px=0.3, seed=seed)
    e = est.estimate(t)
    assert e is not None and e.tau_s is not None
    fit = static_fit(e, ego, 0.02)
    assert fit is None or not fit.fits


@pytest.mark.parametrize("seed", range(4))
def test_a_crossing_object_does_not_fit_the_static_flow(seed: int) -> None:
    # crossing from right to left in front of a camera flying forward: its bearing moves
    # against the flow field's direction there
    ego = EgoMotion((0.0, 0.0, 3.0), 0.1)
    est, t, _p, _v = fly((3.0, 0.5, 12.0), (-4.0, 0.0, -6.0), 1.0, noise_px=0.3, seed=seed)
    e = est.estimate(t)
    assert e is not None and e.tau_s is not None
    fit = static_fit(e, ego, 0.02)
    assert fit is None or not fit.fits


def test_without_forward_motion_there_is_no_flow_field_to_fit() -> None:
    est, t, _p, _v = fly((1.0, 0.5, 12.0), (0.0, 0.0, -6.0), 1.0)
    e = est.estimate(t)
    assert e is not None
    assert static_fit(e, EgoMotion((0.0, 0.0, 0.0)), 0.02) is None
    assert static_fit(e, EgoMotion((0.0, 0.0, -2.0)), 0.02) is None  # flying backwards


def _track(tid: int, box: tuple[float, float, float, float], t_s: float) -> TrackReport:
    """A confirmed track matched to a blob of ``box``, reported by the confidence."""
    x, y, w, h = box
    ib = (int(round(x)), int(round(y)), max(1, int(round(w))), max(1, int(round(h))))
    corners = np.array([[[ib[0], ib[1]]], [[ib[0] + ib[2], ib[1]]], [[ib[0] + ib[2], ib[1] + ib[3]]],
                        [[ib[0], ib[1] + ib[3]]]])
    cluster = Cluster(x + w / 2, y + h / 2, ib, ib[2] * ib[3], (corners,))
    return TrackReport(tid, x + w / 2, y + h / 2, 0.0, 0.0, ib, True, t_s, 10, cluster, ())


CAM = CameraModel(K, K, np.eye(3), np.array([0.015, 0.0, 0.0]))


def _decide(boxes: list[tuple[float, float, float, float]], ego: EgoMotion | None,
            reported: bool = True, unreported_sigmas: float = 0.0) -> list[str]:
    dm = DecisionMaker(DecisionConfig(trigger="response", unreported_looming_sigmas=unreported_sigmas), CAM)
    actions = []
    for i, box in enumerate(boxes):
        track = _track(7, box, i / 30.0)
        if not reported:
            track = track.scored(0.1, (), False)
        cmd, _ = dm.step([track], None, i / 30.0, 10.0, ego=ego)
        actions.append(cmd.action)
    return actions


def _boxes(start: tuple[float, float, float], vel: tuple[float, float, float], seconds: float,
           d_m: float) -> list[tuple[float, float, float, float]]:
    from tests.test_looming import box_of

    p0, v = np.array(start, float), np.array(vel, float)
    return [box_of(p0 + v * (i / 30.0), d_m) for i in range(int(seconds * 30) + 1)]


def test_the_decision_clears_static_structure_only_with_the_cameras_velocity() -> None:
    # a 1 m tree crown 2.5 m right of the line of flight, coming up at 4 m/s from 10 m: 2.5
    # of its own sizes off, and without the camera's velocity the image cannot tell it from a
    # 0.15 m ball 0.4 m off (the worst case, a hit); with it, it is placed 2.5 m off
    boxes = _boxes((2.5, 0.3, 10.0), (0.0, 0.0, -4.0), 2.2, 1.0)
    without = _decide(boxes, None)
    assert "evade" in without
    with_ego = _decide(boxes, EgoMotion((0.0, 0.0, 4.0), 0.1))
    assert set(with_ego) == {NONE}


def test_a_ball_on_a_collision_course_is_evaded_with_or_without_the_cameras_velocity() -> None:
    boxes = _boxes((1.0, 0.5, 18.0), (-1.0 / 18 * 8, -0.5 / 18 * 8, -8.0), 2.2, 0.3)
    for ego in (None, EgoMotion((0.0, 0.0, 3.0), 0.1)):
        assert "evade" in _decide(boxes, ego)


def test_the_vehicles_motion_reaches_the_decision_only_when_known_and_young() -> None:
    v = VehicleState(10.0, True, True, True, "position", 12.0, velocity_ned_mps=(3.0, 0.0, 0.0),
                     attitude_rad=(0.0, 0.0, 0.0), motion_t_s=9.9)
    ego = v.ego(0.3)
    assert ego is not None and ego.velocity_mps == pytest.approx((0.0, 0.0, 3.0))
    assert VehicleState(10.0, True, True, True, "position", 12.0, velocity_ned_mps=(3.0, 0.0, 0.0),
                        attitude_rad=(0.0, 0.0, 0.0), motion_t_s=9.5).ego(0.3) is None  # stale
    assert VehicleState(10.0, True, True, True, "position", 12.0, velocity_ned_mps=(3.0, 0.0, 0.0),
                        motion_t_s=9.9).ego(0.3) is None  # no attitude: no camera axes
    assert VehicleState(10.0, True, True, True, "position", 12.0, attitude_rad=(0.0, 0.0, 0.0),
                        motion_t_s=9.9).ego(0.3) is None  # no velocity


def test_an_unreported_object_that_clearly_looms_triggers_only_when_configured() -> None:
    # the same ball, scored as clutter by perception's confidence: by default the image alone
    # never acts on it; with unreported_looming_sigmas its growth beyond doubt is enough
    boxes = _boxes((1.0, 0.5, 18.0), (-1.0 / 18 * 8, -0.5 / 18 * 8, -8.0), 2.2, 0.3)
    assert set(_decide(boxes, None, reported=False)) == {NONE}
    assert "evade" in _decide(boxes, None, reported=False, unreported_sigmas=4.0)
    # the gate is the fit's own significance: no ball's growth is 1000 standard errors
    assert set(_decide(boxes, None, reported=False, unreported_sigmas=1000.0)) == {NONE}


def test_unreported_static_structure_is_cleared_by_the_cameras_velocity() -> None:
    # the tree crown of the test above, unreported: with unreported looming allowed it
    # would trigger without the camera's velocity, and is cleared with it
    boxes = _boxes((2.5, 0.3, 10.0), (0.0, 0.0, -4.0), 2.2, 1.0)
    assert "evade" in _decide(boxes, None, reported=False, unreported_sigmas=4.0)
    ego = EgoMotion((0.0, 0.0, 4.0), 0.1)
    assert set(_decide(boxes, ego, reported=False, unreported_sigmas=4.0)) == {NONE}


KM = K.matrix()


def _moved(h: np.ndarray, u: float, v: float) -> tuple[float, float]:
    q = h @ np.array([u, v, 1.0])
    return float(q[0] / q[2]), float(q[1] / q[2])


def test_derotation_moves_far_points_as_the_cameras_turn_does() -> None:
    # yawing right by 10°: a point straight ahead moves left by f·tan 10°
    u, v = _moved(derotation((0.0, 0.0, 0.0), (0.0, 0.0, math.radians(10.0)), KM), K.ppx, K.ppy)
    assert u == pytest.approx(K.ppx - K.fx * math.tan(math.radians(10.0)))
    assert v == pytest.approx(K.ppy)
    # pitching the nose up by 8° (positive pitch): the horizon ahead moves down
    u, v = _moved(derotation((0.0, 0.0, 0.0), (0.0, math.radians(8.0), 0.0), KM), K.ppx, K.ppy)
    assert (u, v) == pytest.approx((K.ppx, K.ppy + K.fy * math.tan(math.radians(8.0))))
    # rolling right by 20°: a point on the horizon to the right ends up above the camera's
    # (tilted) right axis; the image turns about the principal point
    phi = math.radians(20.0)
    x = 0.4  # X/Z level
    u, v = _moved(derotation((0.0, 0.0, 0.0), (phi, 0.0, 0.0), KM), K.ppx + K.fx * x, K.ppy)
    assert u == pytest.approx(K.ppx + K.fx * x * math.cos(phi))
    assert v == pytest.approx(K.ppy - K.fy * x * math.sin(phi))
    # composed turns compose, and turning back undoes them
    a, b, c = (0.1, -0.2, 0.3), (-0.15, 0.05, 0.5), (0.3, 0.1, -0.2)
    ab, bc, ac = derotation(a, b, KM), derotation(b, c, KM), derotation(a, c, KM)
    assert _moved(bc @ ab, 100.0, 50.0) == pytest.approx(_moved(ac, 100.0, 50.0))
    assert _moved(derotation(b, a, KM) @ ab, 100.0, 50.0) == pytest.approx((100.0, 50.0))


def test_derotation_agrees_with_the_cameras_velocity() -> None:
    # a world-fixed vector (the vehicle's velocity) seen in the camera's axes before and after
    # a turn: the rotation that derotation uses carries one into the other
    v_ned = (3.0, -1.0, 0.5)
    before, after = (0.2, -0.1, 0.4), (-0.1, 0.15, 0.6)
    c0 = np.array(camera_velocity(v_ned, *before))
    c1 = np.array(camera_velocity(v_ned, *after))
    rot = np.linalg.inv(KM) @ derotation(before, after, KM) @ KM
    assert rot @ c0 == pytest.approx(c1)


def test_a_gimbal_holds_the_camera_level_and_turns_it_with_the_yaw() -> None:
    assert mounted((0.2, -0.1, 1.0), "body") == (0.2, -0.1, 1.0)
    assert mounted((0.2, -0.1, 1.0), "gimbal") == (0.0, 0.0, 1.0)
    with pytest.raises(ValueError, match="camera mount 'belly'"):
        mounted((0.0, 0.0, 0.0), "belly")
    v = VehicleState(10.0, True, True, True, "position", 12.0, velocity_ned_mps=(3.0, 0.0, 0.0),
                     attitude_rad=(0.0, math.radians(-10.0), 0.0), motion_t_s=9.9)
    body, gimbal = v.ego(0.3, "body"), v.ego(0.3, "gimbal")
    assert body is not None and gimbal is not None
    assert body.velocity_mps[1] < -0.5  # nose down: the line of flight lies above the axis
    assert gimbal.velocity_mps == pytest.approx((0.0, 0.0, 3.0))


def _rolled_boxes(phi_rate: float, seconds: float) -> tuple[list[tuple[float, float, float, float]],
                                                            list[tuple[float, float, float]]]:
    """A ball crossing 1 m right of the camera in 2 s, seen by a camera that rolls right at
    ``phi_rate`` rad/s about its optical axis (a multirotor banking to accelerate), and the
    camera's attitude at each frame."""
    start, vel = np.array([1.0 + 2.0 * 2.0, 0.0, 16.0]), np.array([-2.0, 0.0, -8.0])
    boxes, attitudes = [], []
    for i in range(int(seconds * 30) + 1):
        t = i / 30.0
        phi = phi_rate * t
        x, y, z = start + vel * t
        # the level camera's point in the rolled camera's axes (rolled right: its X axis tilts
        # down, so a point to the right rises in the image)
        xr, yr = math.cos(phi) * x + math.sin(phi) * y, -math.sin(phi) * x + math.cos(phi) * y
        boxes.append(box_of(np.array([xr, yr, z]), 0.3))
        attitudes.append((phi, 0.0, 0.0))
    return boxes, attitudes


def test_the_cameras_roll_is_taken_out_of_the_passage() -> None:
    def passage(rate: float, derotate: bool) -> tuple[float, float]:
        boxes, att = _rolled_boxes(rate, 1.0)
        dm = DecisionMaker(DecisionConfig(trigger="response"), CAM)
        objects: list[ObjectState] = []
        for i, box in enumerate(boxes):
            turn = derotation(att[i - 1], att[i], KM) if derotate and i else None
            _, objects = dm.step([_track(7, box, i / 30.0)], None, i / 30.0, 10.0, derotation=turn)
        (o,) = objects
        assert o.miss_sizes is not None
        phi = att[-1][0]  # the passage in the final camera's axes, turned back to level
        mx, my = o.miss_sizes
        return math.cos(phi) * mx - math.sin(phi) * my, math.sin(phi) * mx + math.cos(phi) * my

    level = passage(0.0, False)
    assert level[0] == pytest.approx(1.0 / 0.3, rel=0.15)  # 1 m right: 3.3 ball sizes
    # banking at 60°/s for the last second: derotated, the passage is the level camera's;
    # not derotated, the roll reads as the ball sweeping round and the passage is far off
    assert passage(math.radians(60.0), True) == pytest.approx(level, abs=0.3)
    off = passage(math.radians(60.0), False)
    assert math.hypot(off[0] - level[0], off[1] - level[1]) > 2.0
