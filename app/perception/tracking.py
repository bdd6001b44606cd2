"""Stage 3 — tracking: stable identities and smoothed trajectories (paper Alg. 3, §4-B/C).

Clusters are associated to tracks by distance to each track's predicted position (one
cluster per track, gated at ``dist_px``; confirmed tracks choose first). Unmatched clusters
start *candidates*; a candidate seen in more than ``noise_frames`` frames becomes
*confirmed* and receives a stable ID; a confirmed track without a match is *lost* and
coasts on its Kalman prediction until deleted after ``lost_s``. Candidates that miss
``candidate_max_misses`` frames in a row are noise and vanish.

Each track carries a linear constant-velocity Kalman filter (filterpy), state
``[x, vx, y, vy]`` in image px and px/frame (paper eq. 4.1/4.2). Beyond the paper, the
prediction can be moved through the frame's homography H_{t-1,t} so that the camera's
own motion does not read as the object's (``predict_with_homography``).
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field

import cv2
import numpy as np
from filterpy.common import Q_discrete_white_noise
from filterpy.kalman import KalmanFilter
from scipy.optimize import linear_sum_assignment

from app.config import TrackingConfig
from app.perception.recognition import Cluster

TRAIL_LEN = 30  # positions kept per track for drawing, frames

# State transition and measurement matrices of the paper, eq. 4.1 and 4.2 (dt = 1 frame).
_F = np.array([[1, 1, 0, 0], [0, 1, 0, 0], [0, 0, 1, 1], [0, 0, 0, 1]], float)
_H = np.array([[1, 0, 0, 0], [0, 0, 1, 0]], float)


@dataclass
class _Track:
    kf: KalmanFilter
    box_wh: tuple[float, float]
    last_seen_s: float
    track_id: int = 0  # 0 while a candidate; a stable ID from confirmation on
    hits: int = 1
    misses: int = 0
    cluster: Cluster | None = None  # the cluster matched in the newest frame
    trail: deque[tuple[float, float]] = field(default_factory=lambda: deque(maxlen=TRAIL_LEN))

    @property
    def xy(self) -> tuple[float, float]:
        return float(self.kf.x[0, 0]), float(self.kf.x[2, 0])


@dataclass(frozen=True)
class TrackReport:
    """A confirmed object in one frame (image px of that frame)."""

    track_id: int
    x: float  # Kalman-filtered centre, px
    y: float
    vx: float  # px/frame, relative to the background when homography prediction is on
    vy: float
    box: tuple[float, float, float, float]  # x, y, w, h px, centred on (x, y)
    matched: bool  # False while lost (coasting on the prediction)
    last_seen_s: float  # time of the newest matched frame, s (source clock)
    hits: int
    cluster: Cluster | None
    trail: tuple[tuple[float, float], ...]
    confidence: float = 1.0  # 0-1, from app.perception.confidence (1 until scored)
    features: tuple[float, ...] = ()  # what the confidence was computed from (app.perception.confidence)
    reported: bool = True  # counted as an object in this frame (tracks.csv, evaluation)
    # matched, or coasting where its last matched look is still found (app.perception.confidence)
    in_sight: bool = True
    # the matched cluster's contrast flux and its std (app.perception.photometry), grey x px²
    flux: tuple[float, float] | None = None
    # its core's area (pixels beyond half its contrast) and that's std, px² (photometry)
    core: tuple[float, float] | None = None

    def scored(self, confidence: float, features: tuple[float, ...], reported: bool,
               in_sight: bool = True) -> TrackReport:
        """This report with its confidence filled in (as ``dataclasses.replace``, which looks the
        fields up on every call: 5x the cost, once per track and frame)."""
        return TrackReport(
            track_id=self.track_id, x=self.x, y=self.y, vx=self.vx, vy=self.vy, box=self.box,
            matched=self.matched, last_seen_s=self.last_seen_s, hits=self.hits, cluster=self.cluster,
            trail=self.trail, confidence=confidence, features=features, reported=reported,
            flux=self.flux, core=self.core, in_sight=in_sight,
        )

    def with_photometry(self, flux: tuple[float, float] | None,
                        core: tuple[float, float] | None) -> TrackReport:
        """This report with its contrast flux and core area filled in."""
        return TrackReport(
            track_id=self.track_id, x=self.x, y=self.y, vx=self.vx, vy=self.vy, box=self.box,
            matched=self.matched, last_seen_s=self.last_seen_s, hits=self.hits, cluster=self.cluster,
            trail=self.trail, confidence=self.confidence, features=self.features,
            reported=self.reported, flux=flux, core=core, in_sight=self.in_sight,
        )


class Tracker:
    """Distance-gated association with a candidate → confirmed → lost life cycle.

    Parameters
    ----------
    cfg
        ``dist_px`` (px), ``noise_frames`` (frames), ``candidate_max_misses`` (frames),
        ``lost_s`` (s), ``measurement_std_px`` (px), ``process_accel_std_px``
        (px/frame²), ``predict_with_homography``.
    """

    def __init__(self, cfg: TrackingConfig) -> None:
        self.cfg = cfg
        self._tracks: list[_Track] = []
        self._next_id = 1
        self._q = Q_discrete_white_noise(dim=2, dt=1.0, var=cfg.process_accel_std_px**2, block_size=2)

    def reset(self) -> None:
        """Drop every track (scene cut). IDs keep counting up: a new shot has new objects."""
        self._tracks.clear()

    def confirmed_boxes(self) -> list[tuple[float, float, float, float]]:
        """Boxes (x, y, w, h px) of the confirmed tracks, cheaply (no reports built)."""
        return [_box(t) for t in self._tracks if t.track_id]

    @property
    def confirmed(self) -> list[TrackReport]:
        return [self._report(t) for t in self._tracks if t.track_id]

    def step(
        self, clusters: list[Cluster] | None, t_s: float, homography: np.ndarray | None = None
    ) -> list[TrackReport]:
        """Advance one frame with its clusters; return the confirmed tracks.

        ``clusters`` is None for a frame the detector had to skip: tracks coast on their
        prediction and no one is counted as missed, but the lost timeout still runs.
        ``homography`` is H_{t-1,t} (previous frame px -> this frame px), if known.
        """
        if homography is not None and self.cfg.predict_with_homography and self._tracks:
            self._warp_tracks(homography)
        for t in self._tracks:
            t.kf.predict()
            t.cluster = None

        if clusters is None:
            self._tracks = [t for t in self._tracks if t_s - t.last_seen_s <= self._timeout(t)]
            for t in self._tracks:
                t.trail.append(t.xy)
            return self.confirmed
        unmatched = list(range(len(clusters)))
        for group in ([t for t in self._tracks if t.track_id], [t for t in self._tracks if not t.track_id]):
            unmatched = self._associate(group, clusters, unmatched, t_s)

        survivors: list[_Track] = []
        for t in self._tracks:
            if t.cluster is None:
                t.misses += 1
                if not t.track_id and t.misses >= self.cfg.candidate_max_misses:
                    continue
                if t.track_id and t_s - t.last_seen_s > self.cfg.lost_s:
                    continue
            survivors.append(t)
        self._tracks = survivors
        for j in unmatched:
            self._tracks.append(self._new_track(clusters[j], t_s))
        for t in self._tracks:
            t.trail.append(t.xy)
        return self.confirmed

    # ------------------------------------------------------------------ internals

    def _timeout(self, t: _Track) -> float:
        return self.cfg.lost_s if t.track_id else 2 * self.cfg.lost_s

    def _associate(
        self, tracks: list[_Track], clusters: list[Cluster], free: list[int], t_s: float
    ) -> list[int]:
        if not tracks or not free:
            return free
        gate = self.cfg.dist_px
        pairs: list[tuple[int, int]]
        if len(tracks) == 1 or len(free) == 1:
            # One track or one cluster (the usual case): the assignment is the nearest pair.
            # Plain Python, the same distances as numpy's norm (the same IEEE operations:
            # products, their sum, the root; ** 2 would go through pow()).
            dist_list = [[_hypot(tx - clusters[j].x, ty - clusters[j].y) for j in free]
                         for tx, ty in (t.xy for t in tracks)]
            best = min(((d, r, c) for r, row in enumerate(dist_list) for c, d in enumerate(row)),
                       key=lambda e: e[0])
            pairs = [(best[1], best[2])] if best[0] < gate else []
        else:
            pred = np.array([t.xy for t in tracks])
            pts = np.array([(clusters[j].x, clusters[j].y) for j in free])
            dist = np.linalg.norm(pred[:, None, :] - pts[None, :, :], axis=2)
            rows, cols = linear_sum_assignment(np.where(dist < gate, dist, 1e9))
            pairs = [(r, c) for r, c in zip(rows.tolist(), cols.tolist(), strict=True) if dist[r, c] < gate]
        taken: set[int] = set()
        for r, c in pairs:
            t, cl = tracks[r], clusters[free[c]]
            t.kf.update(np.array([[cl.x], [cl.y]]))
            t.cluster = cl
            t.box_wh = (float(cl.box[2]), float(cl.box[3]))
            t.hits += 1
            t.misses = 0
            t.last_seen_s = t_s
            if not t.track_id and t.hits > self.cfg.noise_frames:
                t.track_id = self._next_id
                self._next_id += 1
            taken.add(c)
        return [j for k, j in enumerate(free) if k not in taken]

    def _new_track(self, cl: Cluster, t_s: float) -> _Track:
        kf = KalmanFilter(dim_x=4, dim_z=2)
        kf.F = _F.copy()
        kf.H = _H.copy()
        kf.R = np.eye(2) * self.cfg.measurement_std_px**2
        kf.Q = self._q
        kf.x = np.array([[cl.x], [0.0], [cl.y], [0.0]])
        v_var = (self.cfg.dist_px / 2) ** 2  # unknown velocity: up to about the gate per frame
        kf.P = np.diag([self.cfg.measurement_std_px**2, v_var, self.cfg.measurement_std_px**2, v_var])
        t = _Track(kf=kf, box_wh=(float(cl.box[2]), float(cl.box[3])), last_seen_s=t_s, cluster=cl)
        if self.cfg.noise_frames == 0:
            t.track_id = self._next_id
            self._next_id += 1
        return t

    def _warp_tracks(self, h: np.ndarray) -> None:
        """Express every track in the new frame's pixels: position through H, velocity
        through H's local linearisation, trail points through H."""
        pos = np.array([t.xy for t in self._tracks])
        vel = np.array([(t.kf.x[1, 0], t.kf.x[3, 0]) for t in self._tracks])
        both = np.concatenate([pos, pos + vel]).reshape(-1, 1, 2)
        moved = cv2.perspectiveTransform(both, h).reshape(-1, 2)
        n = len(pos)
        new_pos, new_vel = moved[:n], moved[n:] - moved[:n]
        for t, p, v in zip(self._tracks, new_pos, new_vel, strict=True):
            t.kf.x[0, 0], t.kf.x[1, 0], t.kf.x[2, 0], t.kf.x[3, 0] = p[0], v[0], p[1], v[1]
            if t.trail:
                tr = cv2.perspectiveTransform(np.array(t.trail, float).reshape(-1, 1, 2), h)
                t.trail = deque(map(tuple, tr.reshape(-1, 2)), maxlen=TRAIL_LEN)

    @staticmethod
    def _report(t: _Track) -> TrackReport:
        x, y = t.xy
        return TrackReport(
            track_id=t.track_id, x=x, y=y, vx=float(t.kf.x[1, 0]), vy=float(t.kf.x[3, 0]),
            box=_box(t), matched=t.cluster is not None,
            last_seen_s=t.last_seen_s, hits=t.hits,
            cluster=t.cluster, trail=tuple(t.trail), reported=t.cluster is not None,
        )


def _hypot(dx: float, dy: float) -> float:
    return math.sqrt(dx * dx + dy * dy)


def _box(t: _Track) -> tuple[float, float, float, float]:
    """The track's box (x, y, w, h px): its last cluster's size, centred on the filter."""
    x, y = t.xy
    w, h = t.box_wh
    return (x - w / 2, y - h / 2, w, h)

