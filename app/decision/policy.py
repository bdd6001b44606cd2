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

import math
from dataclasses import dataclass

import numpy as np
from filterpy.common import Q_discrete_white_noise
from filterpy.kalman import KalmanFilter

from app.camera import CameraModel
from app.config import DecisionConfig, avoid_distance_m
from app.decision.depth import object_depth
from app.perception.tracking import TrackReport

NONE, EVADE, STOP = "none", "evade", "emergency_stop"


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

    @property
    def z_m(self) -> float:
        return self.xyz_m[2]

    @property
    def lateral_m(self) -> float:
        return math.hypot(self.xyz_m[0], self.xyz_m[1])


@dataclass
class _Engagement:
    kind: str  # evade | emergency_stop
    object_id: int
    direction: tuple[float, float]  # unit (right, down)


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

    def __init__(self, xyz: tuple[float, float, float], t_s: float, cfg: DecisionConfig) -> None:
        self.cfg = cfg
        kf = KalmanFilter(dim_x=6, dim_z=3)
        kf.x = np.array([[xyz[0]], [0.0], [xyz[1]], [0.0], [xyz[2]], [0.0]])
        kf.H = np.zeros((3, 6))
        kf.H[0, 0] = kf.H[1, 2] = kf.H[2, 4] = 1.0
        pos, vel = (2 * cfg.kalman_measurement_std_m) ** 2, cfg.kalman_initial_speed_std_mps**2
        kf.P = np.diag([pos, vel, pos, vel, pos, vel])
        self.kf = kf
        self.t_s = t_s
        self.measured_s = t_s

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

    def update(self, xyz: tuple[float, float, float], t_s: float) -> None:
        s = self.cfg.kalman_measurement_std_m
        sz = max(s, self.cfg.depth_rms_per_m2 * xyz[2] ** 2)  # stereo error grows with z²
        self.kf.update(np.array([[xyz[0]], [xyz[1]], [xyz[2]]]), R=np.diag([s * s, s * s, sz * sz]))
        self.measured_s = t_s

    def state(self, track_id: int, t_s: float) -> ObjectState:
        x = self.kf.x[:, 0]
        closing = -float(x[5])
        z = float(x[4])
        ttc = z / closing if closing > 0.05 and z > 0 else None
        crossing = None if ttc is None else (float(x[0] + x[1] * ttc), float(x[2] + x[3] * ttc))
        return ObjectState(track_id, (float(x[0]), float(x[2]), z), self.measured_s,
                           t_s - self.measured_s <= self.cfg.max_depth_age_s, closing, ttc, crossing)


class DecisionMaker:
    """Depth per confirmed track, 3-D tracks, and the command (one call per frame).

    Parameters
    ----------
    cfg
        Thresholds (m, m/s, s; see :class:`app.config.DecisionConfig`).
    camera
        Colour/depth calibration for the colour → depth pixel correspondence.
    """

    def __init__(self, cfg: DecisionConfig, camera: CameraModel) -> None:
        self.cfg = cfg
        self.camera = camera
        self.avoid_m = avoid_distance_m(cfg)
        self._tracks: dict[int, _Track3D] = {}
        self._engaged: _Engagement | None = None

    def reset(self) -> None:
        self._tracks.clear()
        self._engaged = None

    # ------------------------------------------------------------------ measurement

    def observe(self, tracks: list[TrackReport], depth: np.ndarray | None, t_s: float) -> list[ObjectState]:
        """Update the 3-D tracks from this frame's depth; return every known object."""
        c = self.cfg
        alive = {t.track_id for t in tracks}
        for tid in list(self._tracks):
            if tid not in alive:
                del self._tracks[tid]
        for t in tracks:
            meas = None
            if (depth is not None and t.matched and t.cluster is not None
                    and t.confidence >= c.min_track_confidence):
                meas = object_depth(t.cluster, depth, self.camera, c.min_range_m, c.max_range_m,
                                    c.depth_percentile, c.min_depth_pixels)
            tr = self._tracks.get(t.track_id)
            if meas is not None and all(math.isfinite(v) for v in meas.xyz_m):
                if tr is None:
                    self._tracks[t.track_id] = _Track3D(meas.xyz_m, t_s, c)
                else:
                    tr.advance(t_s)
                    tr.update(meas.xyz_m, t_s)
            elif tr is not None:
                tr.advance(t_s)
        return [tr.state(tid, t_s) for tid, tr in self._tracks.items()]

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
        close = [o for o in fresh if o.z_m < c.emergency_m and o.track_id != evading]
        if close:
            near = min(close, key=lambda o: o.z_m)
            self._engaged = _Engagement(STOP, near.track_id, (0.0, 0.0))
            return Command(STOP, object_id=near.track_id,
                           reason=f"object {near.track_id} at {near.z_m:.2f} m < emergency "
                                  f"{c.emergency_m:g} m")
        if self._engaged is not None and self._engaged.kind == STOP:
            held = by_id.get(self._engaged.object_id)
            if (held is not None and t_s - held.measured_s <= c.max_hold_s
                    and 0 < held.z_m < c.emergency_m + c.release_margin_m):
                return Command(STOP, object_id=held.track_id,
                               reason=f"holding: object {held.track_id} at {held.z_m:.2f} m")
            self._engaged = None

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

    def step(self, tracks: list[TrackReport], depth: np.ndarray | None, t_s: float,
             altitude_m: float | None) -> tuple[Command, list[ObjectState]]:
        objects = self.observe(tracks, depth, t_s)
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


def describe_direction(d: tuple[float, float]) -> str:
    horiz = "right" if d[0] > 0 else "left" if d[0] < 0 else ""
    vert = "down" if d[1] > 0 else "up" if d[1] < 0 else ""
    return "-".join(p for p in (vert, horiz) if p) or "none"
