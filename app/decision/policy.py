"""Stage 4 — decision: distance per object, threat assessment, the evasive command
(paper Alg. 4, §4-D, eq. 4.3), safe by construction.

Coordinate frames: objects are in *colour-camera* XYZ, metres (X right, Y down, Z forward).
Commands are *body* velocities (forward, right, down) in m/s; the camera looks forward,
mounted level, so camera X = body right and camera Y = body down. PX4 applies body
velocities yaw-aligned and horizontal, which is what an evasion wants.

Rules, in order of precedence:

1. Only a *fresh* distance (measured this frame or within ``max_depth_age_s``) can start
   anything: no depth, depth 0, NaN or a stale distance never means "close".
2. Emergency stop (zero velocity) when a fresh object is closer than ``emergency_m`` and
   is not the object already being dodged (the paper's stop is for an object first seen
   that close; stopping mid-evasion would put the vehicle back in its path).
3. An object inside the safe window (lateral distance < ``safe_window_m``) is hostile; a
   hostile object closer than the avoidance distance (``avoid_m`` or eq. 4.3), or with
   ``trigger: ttc`` one whose time-to-collision is under ``ttc_avoid_s``, is a threat.
4. Evade diagonally away from the most urgent threat's image quadrant at
   ``evade_speed_mps``. With several threats, the direction must not close on any of them
   (a direction closes on an object when it moves towards its lateral position); if no
   direction qualifies, stop.
5. Hysteresis: the direction is latched; the evasion ends when its object is outside the
   window by ``release_margin_m`` (or farther than the avoidance distance by that margin,
   or unmeasured for ``max_hold_s``). An emergency stop ends likewise.
6. Limits: speed never above ``max_speed_mps``; no downward component below
   ``min_altitude_m`` or with the altitude unknown (the escape turns horizontal).
"""

from __future__ import annotations

import dataclasses
import math
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from filterpy.common import Q_discrete_white_noise
from filterpy.kalman import KalmanFilter

from app.camera import CameraModel
from app.config import DecisionConfig, DetectionConfig, avoid_distance_m
from app.decision.depth import blob_points, object_depth, range_error_m
from app.decision.ego import EgoMotion, static_fit
from app.decision.looming import ImageEstimate, InnerEdge, LoomingEstimator
from app.decision.response import ResponseModel
from app.perception.tracking import TrackReport

NONE, EVADE, STOP = "none", "evade", "emergency_stop"
# trigger: response acts on a time to the passage known to within this fraction (1 std)
MAX_TAU_REL_STD = 0.3
# ... and an object seen in the image only, to within this, whatever its urgency (clutter's
# looming in object-free flight: 0.08-0.11 s +- 0.09-0.12 s, a real ball's 0.6 +- 0.19 s)
MAX_TAU_REL_STD_IMAGE = 0.5
# Faster than this no object closes on a small multirotor (the campaigns' fastest: a 14 m/s
# object head-on to a vehicle at 4 m/s, 18 m/s): a fused track whose looming says more (range
# over τ) has a blob that changed size, not an object that came nearer (seen: τ 0.24 s at 11 m,
# 47 m/s, 1.8 s before the passage, and an escape towards it), m/s
MAX_CLOSING_MPS = 30.0
# a fused track's looming must be urgent in consecutive frames, each consistent with the last,
# the first this long before the latest (two frames at 30 fps, as when it was counted in frames;
# three at 60), s
FUSED_CONFIRM_S = 0.03
# the fewest such frames whatever the frame rate (their counts at 30 fps: a frame the perception
# thread skipped does not shorten the evidence to two estimates)
IMAGE_CONFIRM_FRAMES, FUSED_CONFIRM_FRAMES = 3, 2
# A fused object that perception does not report must have its image's closing speed (Z / τ)
# confirmed by the depth measurements' own: the range rate over this long at most, s ...
RANGE_RATE_WINDOW_S = 0.5
# ... whose standard error is at most this share of the image's closing speed
RANGE_RATE_MAX_REL_STD = 0.5
# An object's depth track speaks for it only while it was measured in at least this share of
# the frames over RANGE_RATE_WINDOW_S in which its blob was matched and read in depth (else the
# object is seen in the image only): a real surface within range returns depth frame after
# frame; a track that follows a stereo camera's wrong matches finds some on its blob now and
# then, each at another distance
MIN_MEASURED_SHARE = 0.5
CLOSING_SIGMAS = 3.0  # image and depth closing speeds further apart than this: the image's is not used
# the image's passage and the depth track's further apart than this many of their combined
# standard errors: the image's is not used
PASSAGE_CONFLICT_SIGMAS = 2.0
# A depth measurement whose innovation's squared Mahalanobis distance exceeds this is not the
# track's (chi-square, 3 degrees of freedom: exceeded with probability 1e-4 by a measurement
# that is), and after this many such in a row the 3-D track starts again from the newest
GATE_CHI2 = 21.1
GATE_RESTART = 3
COURSE_STEPS = 24  # an escape is judged at this many instants along each threat's course
# An image-only object that moves as static structure (app.decision.ego) is cleared when its
# passage misses the largest plausible object's clearance by this many standard errors
STATIC_CLEAR_SIGMAS = 2.0
# An object seen in the image only is the surface behind its blob when the blob's depth lies
# farther than the largest plausible object of its angular size could be, by this many of the
# depth's standard errors (in inverse depth, where a stereo camera's error is constant)
SURFACE_SIGMAS = 3.0
# Escapes whose worst-case misses differ by less than this are equal: then one that does not
# move towards any threat's best estimate of its passage, then the one that passes behind a
# crossing object (against its lateral motion) is taken, m
EQUAL_MISS_M = 0.05


@dataclass(frozen=True)
class Command:
    """What the flight side should do now. Velocities are body frame (FRD), m/s."""

    action: str  # none | evade | emergency_stop
    forward_mps: float = 0.0
    right_mps: float = 0.0
    down_mps: float = 0.0
    object_id: int | None = None
    reason: str = ""

    @property
    def speed_mps(self) -> float:
        return math.sqrt(self.forward_mps**2 + self.right_mps**2 + self.down_mps**2)


@dataclass(frozen=True)
class EdgeCourse:
    """Where an object whose box the frame's corner cuts crosses the camera plane, from the
    uncut sides' motion: per axis (X, Y), ``offset_m`` + ``side`` x its diameter / 2, m, each
    within ``std_m``."""

    offset_m: tuple[float, float]
    side: tuple[int, int]
    std_m: float

    def at(self, diameter_m: float) -> tuple[float, float]:
        return (self.offset_m[0] + self.side[0] * diameter_m / 2,
                self.offset_m[1] + self.side[1] * diameter_m / 2)


def edge_passage(edges: tuple[InnerEdge | None, InnerEdge | None], z_m: float, tau_s: float,
                 tau_std_s: float) -> EdgeCourse | None:
    """The passage of an object whose box is cut on both axes (entering past a corner of the
    frame), ``z_m`` ahead and ``tau_s`` from the camera plane.

    On a straight relative course the bearing b = X/Z moves at b' with X_c = b'·Z·τ where
    it crosses the plane: the side it passes on is the side its bearing moves to, at every
    instant (the sign of b' never changes along the course). The cut hides the centre, but
    the uncut side's bearing moves at e = b' - side·θ'/2 (the box grows away from the
    cutting edge as it nears), and θ' = θ/τ = D/(Z·τ); so X_c = e·Z·τ + side·D/2 for a
    diameter D. An object crossing into the frame moves its uncut side inwards, and passes
    on the far side of the axis from where it is seen, unless within D/2 of the axis (where
    it loomed in rather than moved in): the way the paper's rule (away from where it is) is
    wrong for it (open loop, seed 41's crossing set: an object entering the corner 0.97 m
    off, escaped away from where it was, passed 0.1 m along the escape)."""
    ex, ey = edges
    if ex is None or ey is None or z_m <= 0 or tau_s <= 0:
        return None
    zt = z_m * tau_s
    std = max(math.hypot(e.rate_std * zt, e.rate * z_m * tau_std_s) for e in (ex, ey))
    return EdgeCourse((ex.rate * zt, ey.rate * zt), (ex.side, ey.side), std)


@dataclass(frozen=True)
class ObjectState:
    """One confirmed object in 3-D (colour-camera XYZ, m)."""

    track_id: int
    xyz_m: tuple[float, float, float]  # Kalman-filtered position
    measured_s: float  # time of the newest depth measurement, s
    fresh: bool  # measured within max_depth_age_s
    closing_mps: float  # -dZ/dt: positive while approaching, m/s
    ttc_s: float | None  # Z / closing speed, when closing
    # where it will cross the camera plane (X, Y at Z = 0) on its current course, when closing
    crossing_m: tuple[float, float] | None = None
    # the predicted passage (trigger: response), from the image, the depth track or both
    source: str = "depth"  # image | depth | fused
    tau_s: float | None = None  # time to the passage (camera plane), s
    tau_std_s: float | None = None
    miss_sizes: tuple[float, float] | None = None  # passage (X, Y at Z = 0), object diameters
    miss_sizes_std: float | None = None
    diameter_m: float | None = None  # known once depth gives the range (Z x angular size), m
    seen_s: float = -math.inf  # newest frame the object was matched in (image or depth), s
    reported: bool = True  # perception's confidence reports it as an object (not clutter)
    crossing_std_m: float = 0.5  # standard error of crossing_m (the depth track's), m
    # the image's course in object diameters: position P/D now, relative velocity (dP/dt)/D
    course_sizes: tuple[tuple[float, float, float], tuple[float, float, float]] | None = None
    closing_std_mps: float | None = None  # the depth track's closing speed's standard error, m/s
    # seen in the image only and moving as static structure does from the moving camera
    # (app.decision.ego): where that structure passes the camera's line of flight, m
    static_miss_m: float | None = None
    static_miss_std_m: float | None = None
    # the closing speed the depth measurements alone give (a line through the newest ranges,
    # whatever the 3-D track was started from) and its standard error, m/s; None: too few
    range_rate_mps: float | None = None
    range_rate_std_mps: float | None = None
    # seen in the image only: the depth of what its blob shows (its near surface, as
    # object_depth takes it, at any range the camera returns), m
    surface_m: float | None = None
    # a depth track whose box a corner of the frame cuts (no side of it whole, no image
    # course): its passage from the uncut sides' motion (see edge_passage), when that is
    # more precise than the depth track's own crossing; the escape's direction only
    edge_course: EdgeCourse | None = None

    def passages(self, d_min: float, d_max: float
                 ) -> list[tuple[float, tuple[float, float, float], float]]:
        """The passage for each plausible size: (diameter m, where it passes relative to the
        camera at the closest approach in 3-D, m, that point's std m). With depth the size is
        known; else the configured range's two ends (the miss and the clearance are both
        linear in the size, so the worst case lies at one of them). Without the image's course,
        the depth track's crossing of the camera plane."""
        if self.course_sizes is None and self.miss_sizes is None:
            if self.crossing_m is None:
                return []
            return [(self.diameter_m or d_min, (*self.crossing_m, 0.0), self.crossing_std_m)]
        sizes = [self.diameter_m] if self.diameter_m is not None else [d_min, d_max]
        ms = self.miss_sizes_std or 0.0
        if self.course_sizes is None:
            assert self.miss_sizes is not None  # where it crosses the camera plane
            mx, my = self.miss_sizes
            return [(d, (mx * d, my * d, 0.0), ms * d) for d in sizes]
        q, w = self.course_sizes
        t = _cpa_time(q, w)
        cpa = (q[0] + w[0] * t, q[1] + w[1] * t, q[2] + w[2] * t)
        return [(d, (cpa[0] * d, cpa[1] * d, cpa[2] * d), ms * d) for d in sizes]

    def escape_passages(self, d_min: float, d_max: float
                        ) -> list[tuple[float, tuple[float, float, float], float]]:
        """The passages an escape's direction is chosen by: :meth:`passages`, or those of the
        edge course where there is one. (The trigger keeps to :meth:`passages`: the cut box
        tells on which side the object passes better than how far, and must not clear it.)"""
        if self.edge_course is None:
            return self.passages(d_min, d_max)
        sizes = [self.diameter_m] if self.diameter_m is not None else [d_min, d_max]
        return [(d, (*self.edge_course.at(d), 0.0), self.edge_course.std_m) for d in sizes]

    @property
    def z_m(self) -> float:
        return self.xyz_m[2]

    @property
    def lateral_m(self) -> float:
        return math.hypot(self.xyz_m[0], self.xyz_m[1])

    @property
    def range_m(self) -> float:
        """Straight-line distance, m: what 'very close' means (an object abeam has Z ~ 0)."""
        return math.hypot(*self.xyz_m)


@dataclass
class _Engagement:
    kind: str  # evade | emergency_stop
    object_id: int
    direction: tuple[float, float]  # unit (right, down)


_POS = [0, 2, 4]  # the positions' indices in a 3-D track's state [X, vX, Y, vY, Z, vZ]

# Escape directions (right, down), unit length: diagonals first (the paper's), then the
# four axes for when diagonals conflict or the altitude floor forbids going down.
_S = 1 / math.sqrt(2)
_DIRECTIONS = [(_S, _S), (-_S, _S), (_S, -_S), (-_S, -_S), (1.0, 0.0), (-1.0, 0.0), (0.0, -1.0), (0.0, 1.0)]


def away_from(x: float, y: float) -> tuple[float, float]:
    """Diagonal away from an object at camera (X, Y): upper-left → down-right,
    upper-right → down-left, lower-left → up-right, lower-right → up-left. On an axis,
    go right and up."""
    return (-_S if x > 0 else _S, -_S if y >= 0 else _S)


def closes_on(direction: tuple[float, float], x: float, y: float) -> bool:
    """Moving along ``direction`` brings the vehicle laterally towards (X, Y)."""
    return direction[0] * x + direction[1] * y > 1e-9


class _Track3D:
    """Constant-velocity Kalman filter over colour-camera XYZ; state [X, vX, Y, vY, Z, vZ]."""

    def __init__(self, xyz: tuple[float, float, float], t_s: float, cfg: DecisionConfig,
                 image: ImageEstimate | None = None) -> None:
        self.cfg = cfg
        kf = KalmanFilter(dim_x=6, dim_z=3)
        vel0 = (0.0, 0.0, 0.0)
        pos, vel = (2 * cfg.kalman_measurement_std_m) ** 2, cfg.kalman_initial_speed_std_mps**2
        var_v = [vel, vel, vel]
        if (image is not None and image.tau_s is not None and image.tau_s > 0
                and xyz[2] / image.tau_s <= MAX_CLOSING_MPS):
            # Start from what the image already knows, not from rest: closing speed Z/τ,
            # lateral speed from the bearing rate (d(bZ)/dt = b'Z + bZ'). Not from a looming no
            # object makes at this range (as _fuse: a blob that changed size; object-free,
            # seed 43 with the depth path: a tree's blob filling in read τ 0.30 s at 15.6 m,
            # and its new track closed at 51 m/s on the image's word)
            z = xyz[2]
            vz = -z / image.tau_s
            vel0 = (image.bearing_rate[0] * z + image.bearing[0] * vz,
                    image.bearing_rate[1] * z + image.bearing[1] * vz, vz)
            sz = z * (image.tau_std_s or 0.0) / image.tau_s**2
            var_v = [vel, vel, max(sz, 0.3) ** 2]
        kf.x = np.array([[xyz[0]], [vel0[0]], [xyz[1]], [vel0[1]], [xyz[2]], [vel0[2]]])
        kf.H = np.zeros((3, 6))
        kf.H[0, 0] = kf.H[1, 2] = kf.H[2, 4] = 1.0
        kf.P = np.diag([0.0, var_v[0], 0.0, var_v[1], 0.0, var_v[2]])
        # the position as uncertain as one measurement of it, along the ray included, and
        # at least the old (2 x kalman_measurement_std_m)² on every axis
        extra = pos - cfg.kalman_measurement_std_m**2
        kf.P[np.ix_(_POS, _POS)] = self.measurement_cov(xyz) + extra * np.eye(3)
        self.kf = kf
        self.t_s = t_s
        self.measured_s = t_s
        self.ranges: deque[tuple[float, float]] = deque([(t_s, xyz[2])])  # (t s, Z m), measured
        self.looks: deque[float] = deque([t_s])  # when its blob was read in depth, s
        self.rejected = 0  # measurements in a row beyond the gate

    def advance(self, t_s: float) -> None:
        dt = t_s - self.t_s
        if dt <= 0:
            return
        f1 = np.array([[1.0, dt], [0.0, 1.0]])
        self.kf.F = np.kron(np.eye(3), f1)
        self.kf.Q = Q_discrete_white_noise(dim=2, dt=dt, var=self.cfg.kalman_accel_std_mps2**2,
                                           block_size=3)
        self.kf.predict()
        self.t_s = t_s

    def looked(self, t_s: float) -> None:
        """Its blob was read in depth at ``t_s`` (measured or not)."""
        self.looks.append(t_s)
        while self.looks[0] < t_s - RANGE_RATE_WINDOW_S:
            self.looks.popleft()

    def measurement_cov(self, xyz: tuple[float, float, float]) -> np.ndarray:
        """Covariance of one depth measurement (X, Y, Z) = Z·(b_x, b_y, 1), m²: stereo errs in
        the range, by max(``kalman_measurement_std_m``, ``depth_rms_per_m2`` · Z²), and that
        error runs *along the ray* through the bearing, so it reaches X and Y in proportion to
        the bearing and is correlated with Z's; the bearing itself (the blob's centre) errs by
        about ``kalman_measurement_std_m`` across the ray. (Taken as independent on X, Y, Z,
        the 1.4 m range error at 20 m, on a point 17° off the axis, moves it 0.4 m sideways
        where the filter allowed 0.15 m, and reads as lateral motion: a far collision course's
        passage erred by 0.30 m, median, against 0.02 m along the ray, tests/test_decision.py.)"""
        s = self.cfg.kalman_measurement_std_m
        z = xyz[2]
        sz = self._range_std(z)
        ray = np.array([xyz[0] / z, xyz[1] / z, 1.0]) if z > 0 else np.array([0.0, 0.0, 1.0])
        return np.diag([s * s, s * s, 0.0]) + sz * sz * np.outer(ray, ray)

    def _range_std(self, z: float) -> float:
        """The D435i's range error at ``z`` m (it grows with z²), never below the floor, m."""
        return range_error_m(z, self.cfg.depth_rms_per_m2, self.cfg.kalman_measurement_std_m)

    def update(self, xyz: tuple[float, float, float], t_s: float) -> bool:
        """Take a measurement, unless it lies beyond the gate (``GATE_CHI2`` on the innovation's
        Mahalanobis distance: not this track's object, or not one object's place); say which.
        A blob spread over the frame by parallax is measured wherever its nearest structure
        is, metres apart from frame to frame, and the filter reads the jumps as motion: in an
        object-free flight (seed 43) a 7 m jump sideways at 15.7 m became a 27 m/s approach."""
        z = np.array([[xyz[0]], [xyz[1]], [xyz[2]]])
        r = self.measurement_cov(xyz)
        innov = z - self.kf.H @ self.kf.x
        s = self.kf.H @ self.kf.P @ self.kf.H.T + r
        if (innov.T @ np.linalg.solve(s, innov)).item() > GATE_CHI2:
            self.rejected += 1
            return False
        self.rejected = 0
        self.kf.update(z, R=r)
        self.measured_s = t_s
        self.ranges.append((t_s, xyz[2]))
        while self.ranges[0][0] < t_s - RANGE_RATE_WINDOW_S:
            self.ranges.popleft()
        return True

    def range_rate(self) -> tuple[float, float] | None:
        """The closing speed from the measured ranges alone (least squares over the newest
        ``RANGE_RATE_WINDOW_S``) and its standard error from the D435i's range error, m/s; None
        with fewer than three. Unlike the track's velocity it owes nothing to the image that
        may have started the track: a tree whose growing blob read τ 0.6 s at 15.7 m started
        its track at 25 m/s, and the track then 'agreed' with the image (object-free, seen)."""
        if len(self.ranges) < 3:
            return None
        ts = np.array([t for t, _ in self.ranges])
        zs = np.array([z for _, z in self.ranges])
        dt = ts - ts.mean()
        sxx = float(dt @ dt)
        if sxx <= 0:
            return None
        slope = float(dt @ (zs - zs.mean())) / sxx
        return -slope, self._range_std(float(zs.mean())) / math.sqrt(sxx)

    def state(self, track_id: int, t_s: float) -> ObjectState:
        x = self.kf.x[:, 0]
        closing = -float(x[5])
        z = float(x[4])
        ttc = z / closing if closing > 0.05 and z > 0 else None
        crossing = None if ttc is None else (float(x[0] + x[1] * ttc), float(x[2] + x[3] * ttc))
        tau_std = None
        crossing_std = 0.5
        if ttc is not None:
            p = self.kf.P
            pz, pv = float(p[4, 4]), float(p[5, 5])
            tau_std = math.sqrt(pz / closing**2 + (z / closing**2) ** 2 * pv)
            # X + vX·τ, per axis, with τ's own error: the depth track's lateral velocity is
            # poorly known for its first frames, and the passage must say so
            crossing_std = max(math.sqrt(float(p[i, i]) + ttc**2 * float(p[i + 1, i + 1])
                                         + (float(x[i + 1]) * tau_std) ** 2) for i in (0, 2))
        rate = self.range_rate()
        return ObjectState(track_id, (float(x[0]), float(x[2]), z), self.measured_s,
                           t_s - self.measured_s <= self.cfg.max_depth_age_s, closing, ttc, crossing,
                           tau_s=ttc, tau_std_s=tau_std, seen_s=self.measured_s,
                           crossing_std_m=crossing_std, closing_std_mps=math.sqrt(float(self.kf.P[5, 5])),
                           range_rate_mps=rate[0] if rate else None,
                           range_rate_std_mps=rate[1] if rate else None)

    def measured_share(self) -> float:
        """Of the looks at its blob in depth over the newest ``RANGE_RATE_WINDOW_S``, the share
        that measured it (every range was taken at a look)."""
        return sum(1 for t, _ in self.ranges if t >= self.looks[0]) / len(self.looks)


class DecisionMaker:
    """Depth per confirmed track, 3-D tracks, and the command (one call per frame).

    Parameters
    ----------
    cfg
        Thresholds (m, m/s, s; see :class:`app.config.DecisionConfig`).
    camera
        Colour/depth calibration for the colour → depth pixel correspondence.
    """

    def __init__(self, cfg: DecisionConfig, camera: CameraModel, mask_growth_px: float = 0.0,
                 border_px: float = 0.0) -> None:
        self.cfg = cfg
        self.camera = camera
        self.mask_growth_px = mask_growth_px  # what the motion mask's dilation adds to a blob, px
        # A blob ends this close to the frame's edge when the edge cuts it: the detector clears
        # a border_px band, and the dilation grows it back by half its growth (a tree sliding
        # in at the edge in forward flight, its box 3 px short of the edge, read as looming,
        # τ 0.98 s, and evaded: object-free flight, seed 41)
        self.edge_px = max(2.0, border_px + mask_growth_px / 2 + 1)
        self.avoid_m = avoid_distance_m(cfg)
        self._tracks: dict[int, _Track3D] = {}
        self._looming: dict[int, LoomingEstimator] = {}
        self._seen: dict[int, float] = {}
        # id -> (frames in a row, the latest tau, its time, the first frame's time)
        self._image_votes: dict[int, tuple[int, float, float, float]] = {}
        self._engaged: _Engagement | None = None
        self.response = ResponseModel(cfg.response_dead_time_s, cfg.response_lag_s,
                                      cfg.response_accel_mps2,
                                      min(cfg.response_speed_mps, cfg.evade_speed_mps, cfg.max_speed_mps))

    @classmethod
    def for_perception(cls, cfg: DecisionConfig, camera: CameraModel,
                       detection: DetectionConfig) -> DecisionMaker:
        """A decision that knows what the detector does to a blob's box: its dilation's growth
        and the border band it clears along the frame's edges."""
        return cls(cfg, camera, mask_growth_px=detection.dilate_ksize - 1, border_px=detection.border_px)

    def reset(self) -> None:
        self._tracks.clear()
        self._looming.clear()
        self._seen.clear()
        self._engaged = None

    # ------------------------------------------------------------------ measurement

    def observe(self, tracks: list[TrackReport], depth: np.ndarray | None, t_s: float,
                derotation: np.ndarray | None = None, ego: EgoMotion | None = None) -> list[ObjectState]:
        """Update the image estimates and the 3-D tracks from this frame; return every known
        object: measured in depth, or seen in the image only (reported by perception as an
        object, or the one being evaded).

        ``derotation`` is K·R·K⁻¹ of the camera's *rotation* since the last frame (from the
        vehicle's attitude or the D435i's gyro), which carries the image history through
        it. Not the background's homography: that also holds the parallax of our own
        translation against near ground, which is real relative motion towards or away
        from the object (carried through it, a climbing vehicle saw an object passing
        below it as passing above, and turned back into its path: closed loop, seen)."""
        c = self.cfg
        alive = {t.track_id for t in tracks}
        for store in (self._tracks, self._looming, self._seen):
            for tid in [k for k in store if k not in alive]:
                del store[tid]
        images: dict[int, ImageEstimate | None] = {}

        def image_of(tid: int) -> ImageEstimate | None:  # the fit, once a frame, when used
            if tid not in images:
                images[tid] = self._looming[tid].estimate(t_s)
            return images[tid]

        for t in tracks:
            est = self._looming.get(t.track_id)
            if est is None:
                est = self._looming[t.track_id] = LoomingEstimator(
                    self.camera.color, c.looming_window_s, c.looming_min_samples,
                    size_bias_px=self.mask_growth_px, edge_px=self.edge_px,
                    max_chi2=c.looming_max_chi2, min_size_px=c.looming_min_size_px)
            else:
                est.carry(derotation)
            if t.matched and t.cluster is not None:
                est.add(t_s, tuple(float(v) for v in t.cluster.box), t.flux, t.core)  # type: ignore[arg-type]
                self._seen[t.track_id] = t_s
        for t in tracks:
            meas = None
            read = (depth is not None and t.matched and t.cluster is not None
                    and t.confidence >= c.min_track_confidence)
            if read:
                assert t.cluster is not None and depth is not None
                meas = object_depth(t.cluster, depth, self.camera, c.min_range_m, c.max_range_m,
                                    c.depth_percentile, c.min_depth_pixels, c.depth_rms_per_m2,
                                    c.object_diameter_max_m, c.object_diameter_min_m, c.min_depth_cover)
            tr = self._tracks.get(t.track_id)
            if meas is not None and all(math.isfinite(v) for v in meas.xyz_m):
                if tr is None:
                    self._tracks[t.track_id] = _Track3D(meas.xyz_m, t_s, c, image_of(t.track_id))
                else:
                    tr.advance(t_s)
                    if not tr.update(meas.xyz_m, t_s) and tr.rejected >= GATE_RESTART:
                        # the track follows something else now: start again from here
                        self._tracks[t.track_id] = _Track3D(meas.xyz_m, t_s, c, image_of(t.track_id))
                    else:
                        tr.looked(t_s)
            elif tr is not None:
                tr.advance(t_s)
                if read:
                    tr.looked(t_s)
        out = []
        engaged = self._engaged.object_id if self._engaged is not None else None
        for t in tracks:
            tid = t.track_id
            tr = self._tracks.get(tid)
            if tr is not None and tr.measured_share() >= MIN_MEASURED_SHARE:
                image = image_of(tid)
                state = self._fuse(tr.state(tid, t_s), image, tid)
                if image is None:  # no side of its box whole (or too young a track)
                    state = self._cut_by_corner(state, tid)
                out.append(dataclasses.replace(state, reported=t.reported))
            elif t.reported or tid == engaged or c.unreported_looming_sigmas > 0:
                # (an unreported track seen in the image only is clutter to perception, and the
                # decision acts on it only when it clearly looms, if configured: otherwise its
                # fit is not made, a third of the decision's time in object-free flight)
                image = image_of(tid)
                if image is not None:
                    o = self._image_only(tid, image, t_s, ego)
                    surface = None
                    if depth is not None and o.tau_s is not None and t.matched and t.cluster is not None:
                        # (only where the image says it comes in: what is behind it?)
                        pts = blob_points(t.cluster, depth, self.camera, c.min_range_m, c.min_depth_pixels)
                        if pts is not None:
                            surface = float(np.percentile(pts[:, 2], c.depth_percentile))
                    out.append(dataclasses.replace(o, reported=t.reported, surface_m=surface))
        return out

    def _image_only(self, tid: int, e: ImageEstimate, t_s: float, ego: EgoMotion | None = None
                    ) -> ObjectState:
        """An object seen in the colour image only: placed at the range of the smallest
        plausible size (the nearest it can be); never 'fresh' (no measured distance). With
        the camera's velocity, also where it passes if it is static structure."""
        z = e.range_m(self.cfg.object_diameter_min_m)
        xyz = (e.bearing[0] * z, e.bearing[1] * z, z)
        closing = z / e.tau_s if e.tau_s is not None and e.tau_s > 0 else 0.0
        static = static_fit(e, ego, self.cfg.ego_rate_noise_rad_s) if ego is not None else None
        if static is not None and not static.fits:
            static = None
        return ObjectState(tid, xyz, -math.inf, False, closing, None, None, source="image",
                           tau_s=e.tau_s, tau_std_s=e.tau_std_s, miss_sizes=e.miss_sizes,
                           miss_sizes_std=e.miss_sizes_std, seen_s=self._seen.get(tid, -math.inf),
                           course_sizes=_course(e),
                           static_miss_m=static.miss_m if static is not None else None,
                           static_miss_std_m=static.miss_std_m if static is not None else None)

    def _cut_by_corner(self, o: ObjectState, tid: int) -> ObjectState:
        """A fresh depth track whose box the frame's corner cuts, with its edge course
        (:func:`edge_passage`) where that is more precise than its own crossing."""
        if not o.fresh or o.tau_s is None or o.tau_std_s is None:
            return o
        edge = edge_passage(self._looming[tid].inner_edges(), o.z_m, o.tau_s, o.tau_std_s)
        if edge is None or (o.crossing_m is not None and edge.std_m >= o.crossing_std_m):
            return o
        return dataclasses.replace(o, edge_course=edge)

    def _fuse(self, o: ObjectState, e: ImageEstimate | None, tid: int) -> ObjectState:
        """The depth track's state with the image's looming: the time to the passage from the
        looming's rate (1/τ) and the ranges' own, by inverse variance, the passage from the
        image's bearing rate scaled by the size the range gives (a depth velocity is too noisy
        at range to aim by)."""
        seen = max(o.seen_s, self._seen.get(tid, -math.inf))  # matched in the image counts too
        if e is not None and e.tau_s is not None and e.tau_s > 0 and o.z_m / e.tau_s > MAX_CLOSING_MPS:
            e = None  # the range says its looming is impossible: a blob's size jumped, not the object
        gap = 0.0  # the two closing speeds apart, in their combined standard errors
        if e is not None and o.closing_std_mps is not None and o.z_m > 0:
            # The image's closing speed (Z / τ, or Z x the blob's expansion where it does not
            # loom) against the depth track's, each with its error: further apart than
            # CLOSING_SIGMAS, the blob's size is not the object's, and neither are its centre's
            # motion and its course. A ball straddling the horizon, its patch and box growing
            # with the edge behind it, read τ 0.31 s at 8.8 m, 28 m/s, where depth said
            # 1.6 ± 1.3 m/s, and escaped towards its passage (test_a_crossing_ball_is_passed_behind);
            # a ball crossing in front of a tree, its blob the tree's edge too and 2x its width,
            # kept one size while depth said 4 m/s at 5 m, its centre still while the ball moved
            # right, and escaped right, into its passage (open loop, seed 43's crossing set)
            # (A blob whose sizes keep to no course says nothing by its expansion, and its
            # passage is not taken from it anyway: below.)
            v_img = s_img = None
            if e.tau_s is not None and e.tau_std_s is not None and e.tau_s > 0:
                v_img, s_img = o.z_m / e.tau_s, o.z_m * e.tau_std_s / e.tau_s**2
            elif e.size_chi2 <= self.cfg.looming_max_chi2:
                v_img, s_img = o.z_m * e.expansion_per_s, o.z_m * e.expansion_std
            if v_img is not None and s_img is not None:
                gap = abs(v_img - o.closing_mps) / max(1e-9, math.hypot(s_img, o.closing_std_mps))
                if gap > CLOSING_SIGMAS:
                    e = None
        if e is None or (not o.fresh and seen - o.measured_s > self.cfg.max_hold_s):
            return dataclasses.replace(o, seen_s=seen)
        # (ranges that lapse for a moment, while the image still looms, leave the track fused,
        # its size from the last range, but not fresh: a stale range alone starts nothing, the
        # image's looming can. Dropped to a dead-reckoned depth track, a bird whose blob lost
        # its ranges over the ground 1.3 s before its passage was escaped 0.37 s before it,
        # not 1.03: open loop, the shaped world, seed 11)
        tau, tau_std = o.tau_s, o.tau_std_s
        if e.tau_s is not None and e.tau_std_s is not None:
            # Looming's τ, not the depth track's: the depth velocity starts from rest (or
            # from the image) and its error is biased, not only noisy, for its first frames
            # (an inverse-variance blend pulled τ 0.2-0.4 s late in the closed loop). Its
            # error is scaled up by how far the two closing speeds stray apart beyond their
            # stated errors (as the fits scale theirs by the residuals, never down): a blob
            # of 7 px that grew to 10 in one frame read τ 1.1 ± 0.2 s where depth said
            # 2.6 ± 0.5 (the truth 2.8), and a slow bird was escaped 2.7 s early, the way
            # it would pass (open loop, seed 43's crossing set)
            tau, tau_std = e.tau_s, e.tau_std_s * max(1.0, gap)
            if o.range_rate_mps is not None and o.range_rate_std_mps is not None and o.z_m > 0:
                # the looming's τ weighed against the ranges' own closing (a line through them,
                # owing nothing to the track's start) in rates (1/τ, linear in both measures,
                # where their errors are near normal; in τ a looming of 1.9 ± 1.5 /s reads
                # 0.53 ± 0.42 s and outweighs ranges that say 2.7 s to 0.1 s: a slow ball
                # crossing at 44°, 6.8 m off, was escaped 2.9 s before its passage on the
                # image's τ, on a passage known to 2.4 m, open loop, seed 41's crossing set)
                w_img = (tau**2 / max(1e-9, tau_std)) ** 2
                w_rng = (o.z_m / max(1e-9, o.range_rate_std_mps)) ** 2
                rate = (w_img / tau + w_rng * o.range_rate_mps / o.z_m) / (w_img + w_rng)
                if rate > 0:
                    tau, tau_std = 1.0 / rate, 1.0 / math.sqrt(w_img + w_rng) / rate**2
        diameter = o.z_m * e.size_rad if o.z_m > 0 else None
        if diameter is not None and diameter > self.cfg.object_diameter_max_m:
            # A blob larger at its range than any plausible object is not one object (merged
            # with the ground or a tree behind it, or with its own ghost): its course is the
            # blob's, not the object's; the depth track (bearing from the near surface) stays.
            # Open loop, crossing sets: 6 of the 14 first evasions towards the passage had
            # such a blob (18 of 131 commands), 1.1-14 m "wide".
            return dataclasses.replace(o, source="fused", tau_s=tau, tau_std_s=tau_std,
                                       diameter_m=self.cfg.object_diameter_max_m, seen_s=seen)
        miss, miss_std = e.miss_sizes, e.miss_sizes_std
        if (miss is None and tau is not None and tau > 0 and tau_std is not None
                and e.size_chi2 <= self.cfg.looming_max_chi2):
            # no looming yet (a crossing object closes slowly) but depth gives τ: the passage
            # from the image's bearing rate with the depth's τ (X_c / D = τ · b' / θ), when
            # the blob keeps to one object's size (one that jumps, merged with the horizon or
            # a tree, moves its centre with it: a ball on the horizon read 0.06 rad/s to the
            # right while it moved 0.01 to the left, open loop)
            miss = (tau * e.bearing_rate[0] / e.size_rad, tau * e.bearing_rate[1] / e.size_rad)
            miss_std = math.hypot(tau * e.bearing_rate_std / e.size_rad,
                                  math.hypot(*miss) * tau_std / tau)
        fused = dataclasses.replace(o, source="fused", tau_s=tau, tau_std_s=tau_std,
                                    miss_sizes=miss, miss_sizes_std=miss_std,
                                    diameter_m=diameter, course_sizes=_course(e), seen_s=seen)
        if o.crossing_m is not None and diameter is not None and (miss is not None or fused.course_sizes):
            # Two passages, the image's (its course in sizes at the size the range gives) and
            # the depth track's (bearing x depth, tracked): the more precise is taken, and where
            # they contradict each other, the depth track's. The image's stated error is the
            # overconfident one (open loop, seed 11, first evasions of fused tracks: 16 % of the
            # image's passages off by more than 2 of its standard errors, 2 % of the depth
            # track's), and every contradiction seen there was the image's mistake: 4 passes
            # 2-4 m off that it put at 0.2-0.7 m, an object 1 m away it put 38 m off.
            (_, p_img, s_img), = fused.passages(diameter, diameter)
            gap = math.hypot(p_img[0] - o.crossing_m[0], p_img[1] - o.crossing_m[1])
            both = math.hypot(s_img, o.crossing_std_m)
            if s_img > o.crossing_std_m or gap > PASSAGE_CONFLICT_SIGMAS * both:
                fused = dataclasses.replace(fused, miss_sizes=None, miss_sizes_std=None, course_sizes=None)
        return fused

    # ------------------------------------------------------------------ policy

    def decide(self, objects: list[ObjectState], t_s: float, altitude_m: float | None) -> Command:
        """The command for this frame from the objects' 3-D states."""
        c = self.cfg
        # Z <= 0: the object has passed the camera plane; it is behind us, not close.
        fresh = [o for o in objects if o.fresh and math.isfinite(o.z_m) and o.z_m > 0]
        by_id = {o.track_id: o for o in objects}
        can_descend = altitude_m is not None and math.isfinite(altitude_m) and altitude_m >= c.min_altitude_m
        evading = self._engaged.object_id if self._engaged and self._engaged.kind == EVADE else None

        # 1. Emergency stop: a fresh object inside emergency distance that we are not already
        #    dodging (stopping mid-evasion would put us back into its path; paper §4-D: the
        #    stop is for objects first measured that close, e.g. arriving from the side).
        stop = self._emergency(fresh, by_id, t_s, evading, lambda o: o.measured_s)
        if stop is not None:
            return stop

        # 2. Threats: hostile (inside the window) and close (or, with ttc, soon).
        threats = [o for o in fresh if self._lateral(o) < c.safe_window_m and self._urgent(o)]
        threats.sort(key=self._urgency)

        # 3. A running evasion continues until its object is clear, with its latched direction.
        eng = self._engaged
        if eng is not None:
            cur = by_id.get(eng.object_id)
            if cur is None or t_s - cur.measured_s > c.max_hold_s or cur.z_m <= 0 or self._clear(cur):
                self._engaged = eng = None
            elif eng.object_id not in {t.track_id for t in threats}:
                threats.insert(0, cur)  # still engaged with it (inside the release margin)
        if not threats:
            return Command(NONE)

        primary = threats[0]
        if eng is not None:
            # Latched: the engaged object's own position jitters around the axis from frame to
            # frame; re-deciding against it would flap. Only the other threats can veto.
            preferred = eng.direction
            others = [t for t in threats if t.track_id != eng.object_id]
        else:
            preferred = away_from(*self._aim(primary))
            others = threats
        direction = self._choose(preferred, others, threats, can_descend)
        if direction is None:
            self._engaged = None
            ids = ", ".join(str(t.track_id) for t in threats)
            return Command(STOP, object_id=primary.track_id,
                           reason=f"no escape direction clears objects {ids}: stop")
        engaged = _Engagement(EVADE, eng.object_id if eng else primary.track_id, direction)
        self._engaged = engaged
        speed = min(c.evade_speed_mps, c.max_speed_mps)
        right, down = direction[0] * speed, direction[1] * speed
        return Command(EVADE, 0.0, right, down, engaged.object_id,
                       reason=f"object {primary.track_id} at {primary.z_m:.2f} m, lateral "
                              f"{primary.lateral_m:.2f} m: evade {describe_direction(direction)}")

    def _emergency(self, fresh: list[ObjectState], by_id: dict[int, ObjectState], t_s: float,
                   evading: int | None, last_seen: Callable[[ObjectState], float]) -> Command | None:
        """The emergency stop, or holding one, shared by both policies; None when neither.
        ``fresh`` are the objects measured within max_depth_age_s and in front (Z > 0);
        ``last_seen`` is when a held object last counts as seen (depth, or image too)."""
        c = self.cfg
        # the distance, not Z: a wide lens holds an object passing 2 m abeam until its Z is
        # 0.3 m, and stopping then avoids nothing (open loop, 87° lens: 2 of 20 wide passes)
        close = [o for o in fresh if o.range_m < c.emergency_m and o.track_id != evading]
        if close:
            near = min(close, key=lambda o: o.range_m)
            self._engaged = _Engagement(STOP, near.track_id, (0.0, 0.0))
            return Command(STOP, object_id=near.track_id,
                           reason=f"object {near.track_id} at {near.range_m:.2f} m < emergency "
                                  f"{c.emergency_m:g} m")
        if self._engaged is not None and self._engaged.kind == STOP:
            held = by_id.get(self._engaged.object_id)
            if (held is not None and t_s - last_seen(held) <= c.max_hold_s
                    and 0 < held.z_m and held.range_m < c.emergency_m + c.release_margin_m):
                return Command(STOP, object_id=held.track_id,
                               reason=f"holding: object {held.track_id} at {held.range_m:.2f} m")
            self._engaged = None
        return None

    # ------------------------------------------------------------------ policy: response

    def assess(self, o: ObjectState) -> tuple[float, float] | None:
        """(time to the passage, time the vehicle needs to clear it) for an object on its
        way in, or None when it is not (no looming, passed, or it passes wide of every
        plausible size). The need is the response model's time to move the clearance
        (vehicle + object radius + margin) less the worst-case miss (``passage_sigmas``
        standard errors towards the vehicle), straight away from the passage."""
        c = self.cfg
        if o.tau_s is None or o.tau_s <= 0:
            return None
        if o.tau_std_s is None:
            return None
        if o.source == "depth" and not o.fresh:
            # rule 1: a stale distance starts nothing. With neither the image's estimate nor a
            # range for max_depth_age_s, the depth track only dead-reckons: a bird 2.5 m off
            # that had left the 87° lens, its last range 1.4 s old and its passage known to
            # ±3.7 m, was 'evaded' 0.3 s after it had passed (docs/measurements.md)
            return None
        if o.source == "image" and not o.reported and not (
                c.unreported_looming_sigmas > 0 and o.tau_std_s > 0
                and o.tau_s >= c.unreported_looming_sigmas * o.tau_std_s):
            # no range and perception calls it clutter: the image alone won't do, unless its
            # growth is beyond doubt (τ/σ_τ = expansion/σ_expansion, to first order)
            return None
        if (o.source == "image" and c.image_max_passage_std_m > 0 and o.miss_sizes_std is not None
                and o.miss_sizes_std * c.object_diameter_min_m > c.image_max_passage_std_m):
            return None  # where it passes is unknown to the image alone: wait for a fit or a range
        if o.source == "image" and o.surface_m is not None and o.z_m > 0:
            # Its blob shows a surface farther than an object of its angular size can be (the
            # range of the largest plausible one): the blob is that surface, a building's or a
            # tree's edge against the sky that parallax moves, not an object in front of it
            # (object-free flight, infrared, seeds 43 and 53: 3 of the 8 flights whose fast run
            # evaded, each on the edge of a building that stood above the horizon)
            farthest = c.object_diameter_max_m / c.object_diameter_min_m * o.z_m
            if 1.0 / o.surface_m + SURFACE_SIGMAS * c.depth_rms_per_m2 < 1.0 / farthest:
                return None
        if o.static_miss_m is not None and o.static_miss_std_m is not None:
            widest = c.vehicle_radius_m + c.object_diameter_max_m / 2 + c.clearance_margin_m
            if o.static_miss_m - STATIC_CLEAR_SIGMAS * o.static_miss_std_m > widest:
                return None  # static structure that the vehicle passes wide of
        need_m = -math.inf
        # The passage is predicted on the relative course of now; the vehicle's own wander
        # (a hover in wind) moves it by the time it comes. On PX4 SITL a passage predicted
        # 0.49 m off, 0.02 m sure, came to 0.45 m as the hover drifted towards it, and the
        # evasion it started 0.7 s before cleared 0.55 of 0.64 m (docs/sitl.md).
        own_std = c.own_wander_mps * max(0.0, o.tau_s)
        for d, miss, std in o.passages(c.object_diameter_min_m, c.object_diameter_max_m):
            clearance = c.vehicle_radius_m + d / 2 + c.clearance_margin_m
            worst = max(0.0, math.hypot(*miss) - c.passage_sigmas * math.hypot(std, own_std))
            need_m = max(need_m, clearance - worst)
        if need_m <= 0:
            return None
        need_s = self.response.time_to_move_s(need_m)
        spread = c.passage_sigmas * o.tau_std_s
        if o.tau_s + spread <= need_s + c.trigger_margin_s:
            return o.tau_s + spread, need_s  # urgent even at its latest: act, however unsure
        if o.tau_std_s > MAX_TAU_REL_STD * o.tau_s:
            return None  # too unsure when (a young depth track's velocity): not yet
        # known well enough: the time left judged at its earliest
        return max(0.0, o.tau_s - spread), need_s

    def decide_response(self, objects: list[ObjectState], t_s: float, altitude_m: float | None) -> Command:
        """``trigger: response``: evade each object whose predicted passage is inside its
        clearance once the time left falls to the vehicle's need plus ``trigger_margin_s``;
        the direction maximises the worst-case miss over every such threat."""
        c = self.cfg
        fresh = [o for o in objects if o.fresh and math.isfinite(o.z_m) and o.z_m > 0]
        by_id = {o.track_id: o for o in objects}
        can_descend = altitude_m is not None and math.isfinite(altitude_m) and altitude_m >= c.min_altitude_m
        evading = self._engaged.object_id if self._engaged and self._engaged.kind == EVADE else None

        # 1. Emergency stop, as the paper's (an object first measured this close).
        stop = self._emergency(fresh, by_id, t_s, evading, lambda o: o.seen_s)
        if stop is not None:
            return stop

        # 2. Threats: time left down to the need (+ margin); the paper's distance rule too.
        threats: list[tuple[ObjectState, str]] = []
        votes: dict[int, tuple[int, float, float, float]] = {}
        for o in objects:
            a = self.assess(o)
            urgent = a is not None and a[0] <= a[1] + c.trigger_margin_s
            if urgent and o.source in ("image", "fused"):
                # The image's time left must say so over consecutive frames, each time
                # consistent with the last (shrinking with the clock): image_confirm_s
                # without a range, where nothing else vouches for it (clutter's looming
                # flickers: object-free flights at 2-3 m/s over ground evaded 12 times in 10
                # minutes on single-frame image estimates), two frames' worth with one (a
                # fused track's looming collapsed 1.5 -> 0.01 s for one frame and turned an
                # escape to the wrong side: docs/measurements.md). In time, not only frames: at
                # 60 fps three frames are 33 ms of a blob's flicker (docs/measurements.md).
                assert o.tau_s is not None and o.tau_std_s is not None
                n, tau0, t0, first = self._image_votes.get(o.track_id, (0, math.nan, -math.inf, t_s))
                expect = tau0 - (t_s - t0)
                consistent = abs(o.tau_s - expect) <= 0.3 * max(expect, 0.0) + 0.05
                sure = (o.tau_std_s <= MAX_TAU_REL_STD_IMAGE * o.tau_s if o.source == "image"
                        else o.reported or _depth_confirms(o))
                n = (n + 1 if n and consistent and t_s - t0 < 0.2 else 1) if sure else 0
                first = first if n > 1 else t_s
                votes[o.track_id] = (n, o.tau_s, t_s, first)
                need_s, fewest = ((c.image_confirm_s, IMAGE_CONFIRM_FRAMES) if o.source == "image"
                                  else (FUSED_CONFIRM_S, FUSED_CONFIRM_FRAMES))
                urgent = _held(n, t_s - first, need_s, fewest)
            if urgent:
                assert a is not None
                threats.append((o, f"tau {a[0]:.2f} s <= need {a[1]:.2f} + {c.trigger_margin_s:g} s "
                                   f"({o.source})"))
            elif o in fresh and o.lateral_m < c.safe_window_m and o.z_m < self.avoid_m:
                threats.append((o, f"at {o.z_m:.2f} m < {self.avoid_m:g} m, lateral {o.lateral_m:.2f} m"))
        self._image_votes = votes
        threats.sort(key=lambda ot: ot[0].tau_s if ot[0].tau_s is not None else ot[0].z_m)

        # 3. A running evasion lasts until its object has passed or is lost.
        eng = self._engaged
        if eng is not None:
            cur = by_id.get(eng.object_id)
            passed = cur is not None and ((cur.tau_s is not None and cur.tau_s < -0.1)
                                          or (cur.source != "image" and cur.z_m <= 0))
            if cur is None or passed or t_s - cur.seen_s > c.max_hold_s:
                self._engaged = eng = None
            elif eng.object_id not in {o.track_id for o, _ in threats}:
                threats.insert(0, (cur, "evading until it has passed"))
        if not threats:
            return Command(NONE)

        primary, why = threats[0]
        direction = self._escape([o for o, _ in threats], eng.direction if eng else None, can_descend)
        if direction is None:
            self._engaged = None
            ids = ", ".join(str(o.track_id) for o, _ in threats)
            return Command(STOP, object_id=primary.track_id,
                           reason=f"no escape direction clears objects {ids}: stop")
        self._engaged = _Engagement(EVADE, eng.object_id if eng else primary.track_id, direction)
        right, down = self._flown(direction)
        return Command(EVADE, 0.0, right, down, self._engaged.object_id,
                       reason=f"object {primary.track_id} {why}: evade {describe_direction(direction)}")

    def _velocity(self, d: tuple[float, float]) -> tuple[float, float]:
        """The evasion velocity (right, down m/s) the trigger and the escape count on: along
        ``d`` at ``response_speed_mps``, its vertical part within what PX4 flies in Offboard
        (MPC_Z_VEL_MAX_DN / _UP: a faster descent is commanded but not flown, and the escape
        would be judged on a speed the vehicle does not reach)."""
        c = self.cfg
        speed = self.response.speed_mps
        right, down = d[0] * speed, d[1] * speed
        return right, max(-c.max_climb_mps, min(c.max_descent_mps, down))

    def _flown(self, d: tuple[float, float]) -> tuple[float, float]:
        """The evasion velocity commanded: :meth:`_velocity` scaled up towards
        ``evade_speed_mps`` as far as the vertical caps allow, so that the vehicle moves in
        the direction the escape was chosen for, only further (a down-diagonal, already at
        the descent cap, is flown as planned)."""
        c = self.cfg
        right, down = self._velocity(d)
        plan = math.hypot(right, down)
        if plan <= 0:
            return right, down
        # each ratio >= 1: the plan is at or under every one of these bounds already
        k = min(c.evade_speed_mps, c.max_speed_mps) / plan
        if down > 0:
            k = min(k, c.max_descent_mps / down)
        elif down < 0:
            k = min(k, c.max_climb_mps / -down)
        return right * k, down * k

    def _escape(self, threats: list[ObjectState], latched: tuple[float, float] | None,
                can_descend: bool) -> tuple[float, float] | None:
        """The direction (right, down) that maximises the worst-case miss at each threat's
        passage, over its plausible sizes and ``passage_sigmas`` of its uncertainty, never
        one that moves towards a threat's predicted passage (beyond that uncertainty). A
        latched direction is kept until it would move towards a passage beyond that
        uncertainty (the prediction flipped with confidence)."""
        c = self.cfg
        k = c.passage_sigmas

        def towards(d: tuple[float, float], o: ObjectState) -> bool:
            return any(d[0] * m[0] + d[1] * m[1] > k * std + 1e-9
                       for _, m, std in o.escape_passages(c.object_diameter_min_m, c.object_diameter_max_m))

        def allowed(d: tuple[float, float]) -> bool:
            return (can_descend or d[1] <= 0) and not any(towards(d, o) for o in threats)

        if latched is not None and allowed(latched):
            return latched  # changes only once it moves towards a passage beyond the doubt
        if not any(o.escape_passages(c.object_diameter_min_m, c.object_diameter_max_m) for o in threats):
            # Nothing says where any of them passes (the paper's distance rule on a depth track
            # too young to close): away from where the nearest is now, as the paper does, not
            # the first direction of the list (closed loop, seed 41: an object first measured
            # 0.96 m off, 0.1 s before it passed, was escaped down-right, into its passage)
            x, y = threats[0].xyz_m[0], threats[0].xyz_m[1]
            d = away_from(x, y)
            return d if can_descend or d[1] <= 0 else (math.copysign(1.0, d[0]), 0.0)

        def score(d: tuple[float, float]) -> float:
            worst = math.inf
            vel = self._velocity(d)
            speed = max(1e-9, math.hypot(*vel))
            scale = speed / max(1e-9, self.response.speed_mps)  # a capped descent is slower
            u = (vel[0] / speed, vel[1] / speed)

            def moved(t: float) -> float:
                return self.response.displacement_m(t) * scale

            for o in threats:
                for size, m, std in o.escape_passages(c.object_diameter_min_m, c.object_diameter_max_m):
                    clearance = c.vehicle_radius_m + size / 2 + c.clearance_margin_m
                    miss = _closest_m(o, size, moved, u, m) - k * std
                    worst = min(worst, miss - clearance)
            return worst

        def behind(d: tuple[float, float]) -> float:
            """How much ``d`` runs against the threats' lateral motion (passing behind them)."""
            total = 0.0
            for o in threats:
                if o.course_sizes is not None:
                    w = o.course_sizes[1]
                    total -= (d[0] * w[0] + d[1] * w[1]) / max(1e-9, math.hypot(w[0], w[1], w[2]))
            return total

        # every threat's best estimate of its passage (its centre, not the doubt ``towards``
        # allows); among escapes of equal worst-case miss, one that does not drift towards
        # them: open loop, seed 43's crossing set, a passage fused 0.21 m above (±0.33; the
        # truth 0.21) was escaped up-left, whose miss was 0.02 m short of down-left's,
        # because it ran least with the object's motion
        centres = [m for o in threats
                   for _, m, _ in o.escape_passages(c.object_diameter_min_m, c.object_diameter_max_m)]

        def away(d: tuple[float, float]) -> bool:
            return not any(d[0] * m[0] + d[1] * m[1] > 0.0 for m in centres)

        options = [d for d in _DIRECTIONS if allowed(d)]
        if not options:
            return None
        # Misses equal to within EQUAL_MISS_M are equal; then off the passages' estimates, then
        # behind a crossing object, then (a head-on course: every direction buys the same) the
        # paper's order
        scores = {d: score(d) for d in options}
        best = max(scores.values())
        near = [d for d in options if scores[d] >= best - EQUAL_MISS_M]
        return max(near, key=lambda d: (away(d), round(behind(d), 2), -_DIRECTIONS.index(d)))

    def step(self, tracks: list[TrackReport], depth: np.ndarray | None, t_s: float,
             altitude_m: float | None, derotation: np.ndarray | None = None,
             ego: EgoMotion | None = None) -> tuple[Command, list[ObjectState]]:
        objects = self.observe(tracks, depth, t_s, derotation, ego)
        if self.cfg.trigger == "response":
            return self.decide_response(objects, t_s, altitude_m), objects
        return self.decide(objects, t_s, altitude_m), objects

    # ------------------------------------------------------------------ helpers

    def _predicting(self, o: ObjectState) -> bool:
        return self.cfg.trigger == "ttc" and o.crossing_m is not None

    def _lateral(self, o: ObjectState) -> float:
        """How far off the axis it is: now, or (ttc trigger) where it will cross the camera
        plane on its course, whichever is nearer. The paper's test (now) misses an object
        that is off to the side and on its way in until it is close."""
        if self._predicting(o):
            assert o.crossing_m is not None
            return min(o.lateral_m, math.hypot(*o.crossing_m))
        return o.lateral_m

    def _aim(self, o: ObjectState) -> tuple[float, float]:
        """The point to get away from: where it will cross (ttc trigger), else where it is."""
        if self._predicting(o):
            assert o.crossing_m is not None
            return o.crossing_m
        return o.xyz_m[0], o.xyz_m[1]

    def _urgent(self, o: ObjectState) -> bool:
        if o.z_m < self.avoid_m:
            return True
        return self.cfg.trigger == "ttc" and o.ttc_s is not None and o.ttc_s < self.cfg.ttc_avoid_s

    def _urgency(self, o: ObjectState) -> float:
        """Sort key: time-to-collision when closing, else distance at 1 m/s."""
        return o.ttc_s if o.ttc_s is not None else o.z_m

    def _clear(self, o: ObjectState) -> bool:
        m = self.cfg.release_margin_m
        if self._lateral(o) >= self.cfg.safe_window_m + m:
            return True
        return o.z_m > self.avoid_m + m and not (self.cfg.trigger == "ttc" and o.ttc_s is not None
                                                 and o.ttc_s < self.cfg.ttc_avoid_s)

    def _choose(self, preferred: tuple[float, float], preferred_vetoes: list[ObjectState],
                threats: list[ObjectState], can_descend: bool) -> tuple[float, float] | None:
        """The preferred direction unless it closes on one of ``preferred_vetoes``; else the
        first other direction that closes on none of ``threats`` (each judged where it will
        be, see :meth:`_aim`)."""
        seen: list[tuple[float, float]] = []
        for i, d in enumerate([preferred, *_DIRECTIONS]):
            if not can_descend and d[1] > 0:
                d = (math.copysign(1.0, d[0]), 0.0) if d[0] != 0 else (0.0, 0.0)
            if d == (0.0, 0.0) or d in seen:
                continue
            seen.append(d)
            vetoes = preferred_vetoes if i == 0 else threats
            if not any(closes_on(d, *self._aim(t)) for t in vetoes):
                return d
        return None


def _held(frames: int, elapsed_s: float, need_s: float, min_frames: int) -> bool:
    """Have ``frames`` consecutive frames (at least ``min_frames``), the first ``elapsed_s``
    before the latest, lasted ``need_s``? A quarter of the run's mean frame interval is spared
    for clock jitter: 0.06 s is 3 frames at 30 fps and 5 at 60, the same 67 ms either way."""
    if frames < max(2, min_frames):
        return False
    return elapsed_s >= need_s - 0.25 * elapsed_s / (frames - 1)


def _depth_confirms(o: ObjectState) -> bool:
    """Do the depth measurements, by themselves, say that ``o`` closes about as fast as its
    image's τ says (Z / τ)? Their range rate known to RANGE_RATE_MAX_REL_STD of that speed,
    at least (1 - RANGE_RATE_MAX_REL_STD) of it, and within CLOSING_SIGMAS of the two errors.
    (For an object perception calls clutter the image alone is not believed: a blob that fills
    in looms; a range that does not close refutes it. A tree 15 m off read τ 0.68 ± 0.28 s,
    22 m/s, with ranges closing at 0.6 ± 1.9 m/s: within three errors, but not closing.)"""
    if o.range_rate_mps is None or o.range_rate_std_mps is None or o.tau_s is None or o.tau_s <= 0:
        return False
    v_img = o.z_m / o.tau_s
    s_img = o.z_m * (o.tau_std_s or 0.0) / o.tau_s**2
    return (o.range_rate_std_mps <= RANGE_RATE_MAX_REL_STD * v_img
            and o.range_rate_mps >= (1.0 - RANGE_RATE_MAX_REL_STD) * v_img
            and abs(v_img - o.range_rate_mps) <= CLOSING_SIGMAS * math.hypot(s_img, o.range_rate_std_mps))


def _cpa_time(q: tuple[float, float, float], w: tuple[float, float, float]) -> float:
    """When a course from ``q`` at velocity ``w`` comes closest to the camera, from now (s, >= 0)."""
    ww = w[0] ** 2 + w[1] ** 2 + w[2] ** 2
    return max(0.0, -(q[0] * w[0] + q[1] * w[1] + q[2] * w[2]) / ww) if ww > 0 else 0.0


def _course(e: ImageEstimate) -> tuple[tuple[float, float, float], tuple[float, float, float]] | None:
    """The image's course in object sizes, when it gives a time to contact (its sizes keep
    to a constant-velocity approach: :class:`LoomingEstimator`)."""
    if e.tau_s is None or e.position_sizes is None or e.velocity_sizes is None:
        return None
    return e.position_sizes, e.velocity_sizes


def _closest_m(o: ObjectState, d: float, s_of_t: Callable[[float], float], u: tuple[float, float],
               fallback: tuple[float, float, float]) -> float:
    """How near ``o`` (of diameter ``d``) comes to the vehicle moving ``s_of_t(t)`` m along
    ``u`` (right, down) from now: along the image's course when there is one (its closest
    approach in 3-D, which for an object crossing at an angle is not where it crosses the
    camera plane), else at the passage ``fallback`` when it is due."""
    if o.course_sizes is None:
        s = s_of_t(max(0.0, o.tau_s or 0.0))
        return math.hypot(fallback[0] - s * u[0], fallback[1] - s * u[1], fallback[2])
    q, w = o.course_sizes
    t_cpa = _cpa_time(q, w)
    best = math.inf
    for i in range(COURSE_STEPS + 1):
        t = (t_cpa + 0.5) * i / COURSE_STEPS
        s = s_of_t(t)
        best = min(best, math.hypot(d * (q[0] + w[0] * t) - s * u[0], d * (q[1] + w[1] * t) - s * u[1],
                                    d * (q[2] + w[2] * t)))
    return best


def passage_fields(o: ObjectState) -> dict[str, object]:
    """The predicted passage of one object, for the flight record: its source (image, depth,
    fused), time to it, and where (m: the known size, or the range of plausible ones; for a
    box the frame's corner cuts, its edge course)."""
    def r(v: float | None, n: int = 3) -> float | None:
        return None if v is None or not math.isfinite(v) else round(v, n)

    return {"source": o.source, "tau_s": r(o.tau_s), "tau_std_s": r(o.tau_std_s),
            "miss_sizes": None if o.miss_sizes is None else [r(v, 2) for v in o.miss_sizes],
            "miss_sizes_std": r(o.miss_sizes_std, 2), "diameter_m": r(o.diameter_m),
            "static_miss_m": r(o.static_miss_m, 2),
            "edge_course": None if o.edge_course is None else {
                "offset_m": [r(v) for v in o.edge_course.offset_m], "side": list(o.edge_course.side),
                "std_m": r(o.edge_course.std_m)}}


def describe_direction(d: tuple[float, float]) -> str:
    horiz = "right" if d[0] > 0 else "left" if d[0] < 0 else ""
    vert = "down" if d[1] > 0 else "up" if d[1] < 0 else ""
    return "-".join(p for p in (vert, horiz) if p) or "none"
