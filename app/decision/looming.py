"""Time to contact and predicted passage from the colour image alone (monocular), per track.

Geometry (colour-camera frame: X right, Y down, Z forward, m). An object of diameter D at
(X, Y, Z) moving at constant relative velocity is seen at the bearing b = (X/Z, Y/Z) with
the angular size θ = D/Z. Then, exactly:

- time to contact with the camera plane: τ = Z / (-dZ/dt) = θ / (dθ/dt) = 1 / (d ln θ/dt)
  (looming; Lee 1976, "A theory of visual control of braking based on information about
  time-to-collision"); no range, no size needed;
- where it crosses the camera plane (Z = 0), in object diameters: X_c/D = τ · (db/dt) / θ,
  the bearing rate relative to the angular size — a constant bearing with a growing size
  (db/dt = 0) is a collision course. The direction of the passage needs no size at all; its
  distance in metres needs D (a configured plausible range until stereo depth gives Z).

The estimator fits ln(size) and the bearing over a sliding window (least squares, so a few
pixels of blob noise average out; the residuals give the uncertainty). Samples whose box
touches the frame edge are partially occluded: their cut dimension is not used for the size,
nor the cut axis's centre for the bearing. Past samples are carried into the newest frame's
pixels through the camera's rotation between frames (K·R·K⁻¹, from the attitude or a gyro),
so the vehicle's own rotation does not read as bearing rate. Its translation must stay in:
it is relative motion, so the background's homography (which holds the parallax of near
ground) is not the thing to carry them through.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np

from app.camera import Intrinsics


@dataclass(frozen=True)
class ImageEstimate:
    """What the image alone says about one object, at time ``t_s``."""

    t_s: float
    samples: int  # samples the size fit used
    bearing: tuple[float, float]  # (X/Z, Y/Z) now
    bearing_rate: tuple[float, float]  # d/dt of the bearing, 1/s
    size_rad: float  # angular size θ = D/Z now
    expansion_per_s: float  # d ln θ / dt, 1/s (positive: approaching)
    expansion_std: float  # its standard error, 1/s
    tau_s: float | None  # time to contact = 1 / expansion, when clearly expanding, s
    tau_std_s: float | None  # its standard error (first order), s
    miss_sizes: tuple[float, float] | None  # crossing point (X_c/D, Y_c/D), object diameters
    miss_sizes_std: float | None  # its standard error per axis, object diameters
    bearing_rate_std: float = 0.0  # standard error of the bearing rate (the larger axis), 1/s

    def miss_m(self, diameter_m: float) -> tuple[float, float] | None:
        """The crossing point in metres for an object of ``diameter_m``."""
        if self.miss_sizes is None:
            return None
        return self.miss_sizes[0] * diameter_m, self.miss_sizes[1] * diameter_m

    def range_m(self, diameter_m: float) -> float:
        """Z for an object of ``diameter_m``, m."""
        return diameter_m / self.size_rad


@dataclass
class _Sample:
    t: float
    u: float  # centre px (in the newest frame's pixels after carrying)
    v: float
    w: float  # box size px
    h: float
    u_ok: bool  # the centre's x is not cut by the frame edge
    v_ok: bool
    w_ok: bool  # the width is not cut by the frame edge
    h_ok: bool


def _fit(t: np.ndarray, y: np.ndarray) -> tuple[float, float, float]:
    """Least-squares line y = a + b (t - t[-1]): value now, slope, slope's standard error."""
    tc = t - t[-1]
    n = len(t)
    tm = tc.mean()
    stt = float(((tc - tm) ** 2).sum())
    if n < 2 or stt <= 0:
        return float(y[-1]), 0.0, math.inf
    b = float(((tc - tm) * (y - y.mean())).sum() / stt)
    a = float(y.mean() - b * tm)
    if n > 2:
        resid = y - (a + b * tc)
        s2 = float((resid**2).sum()) / (n - 2)
        se = math.sqrt(s2 / stt)
    else:
        se = math.inf
    return a, b, se


class LoomingEstimator:
    """Sliding-window looming and bearing fit for one track.

    Parameters
    ----------
    intrinsics
        Colour camera intrinsics (px).
    window_s
        Length of the fit window, s.
    min_samples
        Fewest samples for an estimate.
    size_bias_px
        Subtracted from every box side before the fit: what the motion mask adds around an
        object (its dilation), px.
    edge_px
        A box side within this of the frame edge is cut by it, px.
    min_expansion_sigmas
        τ is given only when the expansion exceeds this many standard errors.
    pixel_noise_px
        Floor on the per-sample centre and size noise, px (the fit's residuals on a few
        samples can be implausibly small).
    """

    def __init__(self, intrinsics: Intrinsics, window_s: float = 0.5, min_samples: int = 6,
                 size_bias_px: float = 0.0, edge_px: float = 2.0, min_expansion_sigmas: float = 2.0,
                 pixel_noise_px: float = 1.0) -> None:
        self.k = intrinsics
        self.window_s = window_s
        self.min_samples = min_samples
        self.size_bias_px = size_bias_px
        self.edge_px = edge_px
        self.min_expansion_sigmas = min_expansion_sigmas
        self.pixel_noise_px = pixel_noise_px
        self._samples: deque[_Sample] = deque()

    def carry(self, homography: np.ndarray | None) -> None:
        """Move the stored samples into the next frame's pixels through the camera's
        rotation since the last frame (K·R·K⁻¹)."""
        if homography is None or not self._samples:
            return
        pts = np.array([[s.u, s.v, 1.0] for s in self._samples]).T  # (3, N)
        q = homography @ pts
        q = q[:2] / q[2]
        for s, (u, v) in zip(self._samples, q.T, strict=True):
            s.u, s.v = float(u), float(v)

    def add(self, t_s: float, box: tuple[float, float, float, float]) -> None:
        """A measured box (x, y, w, h, px) at ``t_s``."""
        x, y, w, h = box
        e, W, H = self.edge_px, self.k.width, self.k.height
        left, right = x <= e, x + w >= W - e
        top, bottom = y <= e, y + h >= H - e
        self._samples.append(_Sample(t_s, x + w / 2, y + h / 2, w, h,
                                     not (left or right), not (top or bottom),
                                     not (left or right), not (top or bottom)))
        while self._samples and t_s - self._samples[0].t > self.window_s:
            self._samples.popleft()

    def estimate(self, t_s: float) -> ImageEstimate | None:
        """The fit over the window, extrapolated to ``t_s``; None with too few samples."""
        ss = [s for s in self._samples if s.w_ok or s.h_ok]
        if len(ss) < self.min_samples:
            return None
        t = np.array([s.t for s in ss])
        # size: the larger uncut side (a motion mask's blob loses a side's part more often
        # than it gains one: seen in the closed loop, heights halving from frame to frame)
        sizes = []
        for s in ss:
            sides = [d - self.size_bias_px for d, ok in ((s.w, s.w_ok), (s.h, s.h_ok)) if ok]
            sizes.append(max(max(sides), 1.0))
        size = np.array(sizes)
        ln_size, expansion, exp_se = _fit(t, np.log(size))
        # a floor on the noise: pixel_noise_px on the size, over the window
        n = len(ss)
        span = float(t[-1] - t[0]) or 1e-3
        floor = (self.pixel_noise_px / float(size.mean())) * math.sqrt(12.0 / n) / span
        exp_se = max(exp_se, floor) if math.isfinite(exp_se) else floor
        dt = t_s - float(t[-1])
        size_px = math.exp(ln_size + expansion * dt)
        f = 0.5 * (self.k.fx + self.k.fy)
        theta = size_px / f
        bearing, rate, rate_se = [], [], []
        for axis, (c, fl) in enumerate(((self.k.ppx, self.k.fx), (self.k.ppy, self.k.fy))):
            rows = [(s.t, (s.u if axis == 0 else s.v)) for s in ss if (s.u_ok if axis == 0 else s.v_ok)]
            if len(rows) < max(3, self.min_samples // 2):
                rows = [(s.t, (s.u if axis == 0 else s.v)) for s in ss]  # cut: better than none
            tt = np.array([r[0] for r in rows])
            bb = (np.array([r[1] for r in rows]) - c) / fl
            now, slope, se = _fit(tt, bb)
            floor_b = (self.pixel_noise_px / fl) * math.sqrt(12.0 / len(rows)) / span
            bearing.append(now + slope * (t_s - float(tt[-1])))
            rate.append(slope)
            rate_se.append(max(se, floor_b) if math.isfinite(se) else floor_b)
        tau = tau_se = miss = miss_se = None
        if expansion > self.min_expansion_sigmas * exp_se and expansion > 0:
            # A straight-line fit's slope is the rate at the window's mean time (ln θ is
            # convex in t on an approach): τ there is 1/slope, and τ now is that less the
            # time since. The crossing point is a constant of the course, so it is taken
            # at the mean time too, with θ there.
            t_mean = float(t.mean())
            tau_mid = 1.0 / expansion
            tau = tau_mid - (t_s - t_mean)
            tau_se = exp_se / expansion**2
            theta_mid = math.exp(ln_size + expansion * (t_mean - float(t[-1]))) / f
            # crossing point in diameters: τ · bearing rate / θ (first-order error of both)
            miss = (tau_mid * rate[0] / theta_mid, tau_mid * rate[1] / theta_mid)
            rel_tau = tau_se / tau_mid
            miss_se = max(math.hypot(tau_mid * rate_se[a] / theta_mid, abs(miss[a]) * rel_tau)
                          for a in (0, 1))
        return ImageEstimate(t_s, n, (bearing[0], bearing[1]), (rate[0], rate[1]), theta, expansion,
                             exp_se, tau, tau_se, miss, miss_se, max(rate_se))

    def reset(self) -> None:
        self._samples.clear()
