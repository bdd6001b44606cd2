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

The estimator fits the course in object diameters, (b_x, b_y, 1) / θ, which is linear in
time on any straight approach, over a sliding window (weighted least squares, so a few
pixels of blob noise average out; the residuals give the uncertainty). The size is the
object's core area where perception measured one for enough samples, the newest among them,
else its contrast flux likewise (the square root of either is proportional to θ to a
fraction of a pixel: app.perception.photometry), else the box's larger side, which steps
by whole pixels and carries the motion mask's smear. Samples whose box touches the frame
edge are partially occluded: their cut dimension is not used for the size, nor the cut
axis's centre for the bearing. Past samples are carried into the newest frame's pixels
through the camera's rotation between frames (K·R·K⁻¹, from the attitude or a gyro), so
the vehicle's own rotation does not read as bearing rate. Its translation must stay in:
it is relative motion, so the background's homography (which holds the parallax of near
ground) is not the thing to carry them through.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from scipy.stats import chi2 as chi2_distribution

from app.camera import Intrinsics

FLUX_MIN_SIGMAS = 5.0  # a flux this many of its std above zero measures a size
# A photometric size states its own error, so its fit to a course is a goodness-of-fit test:
# rejected when its chi-square is one that a constant-velocity approach gives this rarely.
# At their first image-only evasions (open loop, seeds 11 and 23), the fits whose time left was
# right had reduced chi-squares 0.08-2.2; the flux fits that were 1.5-2 s early 3.9-8.5, and
# the flux fits of the ground clutter that evaded in object-free flight 1.9-7.9
PHOTOMETRIC_FIT_P = 1e-3
# A box's size that jumps to a new level and stays there (a blob merged with the structure
# beside it, or split from it) is no approach: when one level shift explains the window's sizes
# better than a straight course by more than this F ratio, the samples before it are not used.
# (A straight course with Gaussian noise exceeds it by chance with probability under 1e-3 at
# 20-30 samples and under 1e-2 at 10: the max F over the splits has its 99.9th percentile at
# 27 and 20 for 20 and 30 samples, and its 99th at 23, its 99.9th at 43, for 10; Monte Carlo,
# 2 000 windows each.)
STEP_F = 30.0


@lru_cache(maxsize=128)
def _chi2_bound(dof: int) -> float:
    """The reduced chi-square that a fit with ``dof`` degrees of freedom exceeds with
    probability PHOTOMETRIC_FIT_P when its errors are as stated."""
    return float(chi2_distribution.ppf(1.0 - PHOTOMETRIC_FIT_P, max(1, dof))) / max(1, dof)


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
    # the course in object diameters: position P/D now and relative velocity (dP/dt)/D, 1/s
    position_sizes: tuple[float, float, float] | None = None
    velocity_sizes: tuple[float, float, float] | None = None
    size_chi2: float = 1.0  # how far the size's samples stray from a constant-velocity course

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
    flux: tuple[float, float] | None = None  # contrast flux and its std (photometry), grey x px²
    core: tuple[float, float] | None = None  # core area and its std (photometry), px²
    # the frame edge that cuts the box on each axis: -1 left / top, +1 right / bottom, 0 none
    # (or both: a box wider than the frame)
    cut_u: int = 0
    cut_v: int = 0


@dataclass(frozen=True)
class InnerEdge:
    """The uncut side of a box that one frame edge cuts, over the window: which edge cuts
    it (-1 left / top, +1 right / bottom) and how fast the uncut side's bearing moves
    (d/dt of X/Z or Y/Z, 1/s, in the image's direction) with its standard error."""

    side: int
    rate: float
    rate_std: float


@dataclass(frozen=True)
class _Line:
    """A weighted least-squares line y = mean + slope (t - t_mean)."""

    t_mean: float
    mean: float
    slope: float
    var_mean: float  # variance of ``mean`` (uncorrelated with the slope's at t_mean)
    var_slope: float
    chi2: float = 1.0  # reduced chi-square of the fit at the given errors (1: as noisy as assumed)
    dof: int = 0  # its degrees of freedom (samples fitted less two)

    def at(self, t: float) -> float:
        return self.mean + self.slope * (t - self.t_mean)

    def var_at(self, t: float) -> float:
        return self.var_mean + (t - self.t_mean) ** 2 * self.var_slope


def _wfit(t: np.ndarray, y: np.ndarray, sigma: np.ndarray) -> _Line | None:
    """Weighted line through (t, y) with per-sample standard errors ``sigma``; the errors
    are scaled up by the residuals when those say the noise is larger (never down), and one
    sample more than 4 (robust) standard errors off is dropped once (a merged or split blob)."""
    for _ in range(2):
        if len(t) < 3:
            return None
        w = 1.0 / sigma**2
        sw = float(w.sum())
        tm = float((w * t).sum() / sw)
        dt = t - tm
        stt = float((w * dt * dt).sum())
        if stt <= 0:
            return None
        mean = float((w * y).sum() / sw)
        slope = float((w * dt * y).sum() / stt)
        r = (y - mean - slope * dt) / sigma
        chi2 = float((r * r).sum()) / (len(t) - 2)
        robust = 1.4826 * float(np.median(np.abs(r)))
        worst = int(np.argmax(np.abs(r)))
        if abs(r[worst]) > 4.0 * max(1.0, robust) and len(t) > 4:
            keep = np.arange(len(t)) != worst
            t, y, sigma = t[keep], y[keep], sigma[keep]
            continue
        scale = max(1.0, chi2)
        return _Line(tm, mean, slope, scale / sw, scale / stt, chi2, len(t) - 2)
    return None


def _robust_line(t: list[float], y: list[float], sigma: float) -> _Line | None:
    """A line through a few samples (each ``sigma``) that no minority of outliers moves: the
    Theil-Sen slope (the median of the pairwise slopes) picks the samples within 4 robust
    errors of it (at least ``sigma``), and least squares runs through those; the errors are
    scaled up by the residuals, never down. Plain Python: a handful of samples, every frame."""
    n = len(t)
    slopes = sorted((y[j] - y[i]) / (t[j] - t[i]) for i in range(n) for j in range(i + 1, n) if t[j] > t[i])
    if not slopes:
        return None
    slope = slopes[len(slopes) // 2]
    r = sorted(v - slope * u for u, v in zip(t, y, strict=True))
    mid = r[n // 2]
    scale = max(sigma, 1.4826 * sorted(abs(v - mid) for v in r)[n // 2])
    keep = [(u, v) for u, v in zip(t, y, strict=True) if abs(v - slope * u - mid) <= 4.0 * scale]
    if len(keep) < 3:
        return None
    tm = sum(u for u, _ in keep) / len(keep)
    ym = sum(v for _, v in keep) / len(keep)
    stt = sum((u - tm) ** 2 for u, _ in keep)
    if stt <= 0:
        return None
    b = sum((u - tm) * (v - ym) for u, v in keep) / stt
    chi2 = sum((v - ym - b * (u - tm)) ** 2 for u, v in keep) / sigma**2 / max(1, len(keep) - 2)
    var = sigma**2 * max(1.0, chi2)
    return _Line(tm, ym, b, var / len(keep), var / stt, chi2, len(keep) - 2)


def _level_shift(t: np.ndarray, y: np.ndarray, sigma: np.ndarray) -> int | None:
    """The index of the first sample after a level shift in ``y`` (three samples at least on
    either side; ``sigma``: each sample's error) that fits the samples better than a straight
    line by an F ratio over STEP_F; None when there is none."""
    n = len(t)
    if n < 8:
        return None
    # Weighted least squares; the step's gain over the line for every split at once, by
    # partialling the line out of it (Frisch-Waugh): with r the line's residuals and s_k the
    # step's regressor, chi2 falls by (s_k' W r)^2 / (s_k' W s_k - b_k' A^-1 b_k), where
    # A = X' W X and b_k = X' W s_k, all suffix sums
    w = 1.0 / sigma**2
    dt = t - float(np.average(t, weights=w))
    a0, a1, a2 = float(w.sum()), float((w * dt).sum()), float((w * dt * dt).sum())
    det = a0 * a2 - a1 * a1
    if det <= 0:
        return None
    c0 = (a2 * float((w * y).sum()) - a1 * float((w * dt * y).sum())) / det
    c1 = (a0 * float((w * dt * y).sum()) - a1 * float((w * y).sum())) / det
    r = y - c0 - c1 * dt
    line = float((w * r * r).sum())
    s0 = np.cumsum((w)[::-1])[::-1]
    s1 = np.cumsum((w * dt)[::-1])[::-1]
    sr = np.cumsum((w * r)[::-1])[::-1]
    ks = np.arange(3, n - 2)
    b0, b1, rk = s0[ks], s1[ks], sr[ks]
    den = b0 - (a2 * b0 * b0 - 2.0 * a1 * b0 * b1 + a0 * b1 * b1) / det
    gain = np.where(den > 1e-12 * b0, rk * rk / np.maximum(den, 1e-300), 0.0)
    j = int(np.argmax(gain))
    best, at = line - float(gain[j]), int(ks[j])
    # the noise at least as stated (as _wfit scales errors up, never down)
    if (line - best) / max(1.0, best / (n - 3)) <= STEP_F:
        return None
    return at


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
        Per-sample centre and size noise, px: the fit's weights, scaled up when the residuals
        say the noise is larger.
    min_size_px
        No time to contact from fewer than ``min_samples`` samples at least this big (after
        ``size_bias_px``), px; smaller samples are left out of the size fit.
    max_chi2
        No time to contact when the size's samples stray further from a constant-velocity
        course than this (reduced chi-square at ``pixel_noise_px``).
    """

    def __init__(self, intrinsics: Intrinsics, window_s: float = 0.5, min_samples: int = 6,
                 size_bias_px: float = 0.0, edge_px: float = 2.0, min_expansion_sigmas: float = 2.0,
                 pixel_noise_px: float = 1.0, max_chi2: float = 9.0, min_size_px: float = 6.0) -> None:
        self.k = intrinsics
        self.window_s = window_s
        self.min_samples = min_samples
        self.size_bias_px = size_bias_px
        self.edge_px = edge_px
        self.min_expansion_sigmas = min_expansion_sigmas
        self.pixel_noise_px = pixel_noise_px
        self.max_chi2 = max_chi2
        self.min_size_px = min_size_px
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

    def add(self, t_s: float, box: tuple[float, float, float, float],
            flux: tuple[float, float] | None = None, core: tuple[float, float] | None = None) -> None:
        """A measured box (x, y, w, h, px) at ``t_s``, with its contrast flux and core area
        (value, std) when perception measured them (app.perception.photometry)."""
        x, y, w, h = box
        e, W, H = self.edge_px, self.k.width, self.k.height
        left, right = x <= e, x + w >= W - e
        top, bottom = y <= e, y + h >= H - e
        self._samples.append(_Sample(t_s, x + w / 2, y + h / 2, w, h,
                                     not (left or right), not (top or bottom),
                                     not (left or right), not (top or bottom), flux, core,
                                     int(right) - int(left), int(bottom) - int(top)))
        while self._samples and t_s - self._samples[0].t > self.window_s:
            self._samples.popleft()

    def estimate(self, t_s: float) -> ImageEstimate | None:
        """The fit over the window, extrapolated to ``t_s``; None with too few samples."""
        return self._estimate([s for s in self._samples if s.w_ok or s.h_ok], t_s, True)

    def inner_edges(self) -> tuple[InnerEdge | None, InnerEdge | None]:
        """Per axis (x, y), the uncut side's motion of a box that one frame edge has cut for
        the newest samples (at least ``min_samples // 2``, three at the fewest), None where
        the newest box is not cut on that axis or too few are. What an object entering the
        frame past its edge shows of its course while no side of it is whole (see
        :func:`app.decision.policy.edge_passage`)."""
        k = self.k
        out: list[InnerEdge | None] = []
        for axis in (0, 1):
            side = (self._samples[-1].cut_u if axis == 0 else self._samples[-1].cut_v) if self._samples else 0
            run: list[_Sample] = []
            for s in reversed(self._samples if side else ()):
                if (s.cut_u if axis == 0 else s.cut_v) != side:
                    break
                run.append(s)
            if len(run) < max(3, self.min_samples // 2):
                out.append(None)
                continue
            c, fl = (k.ppx, k.fx) if axis == 0 else (k.ppy, k.fy)
            # the uncut side: the centre less half the box towards the cutting edge's far side
            run.reverse()
            edge = [((s.u - side * s.w / 2 if axis == 0 else s.v - side * s.h / 2) - c) / fl for s in run]
            line = _robust_line([s.t for s in run], edge, self.pixel_noise_px / fl)
            out.append(None if line is None else InnerEdge(side, line.slope, math.sqrt(line.var_slope)))
        return out[0], out[1]

    def _estimate(self, ss: list[_Sample], t_s: float, may_restart: bool) -> ImageEstimate | None:
        if len(ss) < self.min_samples:
            return None
        k = self.k
        f = 0.5 * (k.fx + k.fy)
        t = np.array([s.t for s in ss])
        # size: the larger uncut side (a motion mask's blob loses a side's part more often
        # than it gains one: seen in the closed loop, heights halving from frame to frame)
        size = np.array([max(max(d - self.size_bias_px for d, ok in ((s.w, s.w_ok), (s.h, s.h_ok)) if ok),
                             1.0) for s in ss])
        sig = self.pixel_noise_px
        # The course in object diameters, q = P / D = (b_x, b_y, 1) / θ: linear in time for
        # any constant relative velocity (the pinhole's 1/Z cancels), so a straight line fits
        # it exactly over any window, with no bias from the curvature of ln θ or of the bearing.
        # The size from the core area where enough samples of the window have one and it fits
        # a course, else from the contrast flux likewise (the square root of either is
        # proportional to the angular size, to a fraction of a pixel), scaled to the boxes'
        # sizes; else from the boxes.
        fit = self._photometric_fit(t, size, f, [s.core for s in ss])
        if fit is None:
            fit = self._photometric_fit(t, size, f, [s.flux for s in ss])
        if fit is None:
            fit = self._box_fit(t, size, f, sig)
        if fit is None:
            return None
        lz, qz, sizes_sig, sized, on_course = fit
        # Each sample's bearing is carried into sizes at the size's fitted course, not at its
        # own size: a box that merged with the structure beside it for a frame (3 to 8 times
        # its size) moved the course's bearing far off the blob's (open loop, three worlds:
        # 17 of 162 first evasions at 20-50° had it more than 0.1 rad off the newest centre;
        # 2 with this and what follows); on a straight course b·q_z is linear in time
        # whichever way q_z is known
        fitted = lz.mean + lz.slope * (t - lz.t_mean)
        qz = np.where(fitted > 0.25 * qz, fitted, qz)  # (not where the course has passed the plane)
        # A course only when the sizes keep to one: clutter's blobs (a cloud's edge, parallax)
        # change size by jumps that no constant-velocity approach makes (measured in the closed
        # loop: real objects 0.3-3.6, the clutter that evaded in object-free flight 7-820);
        # a time to contact only when it clearly expands.
        holds = lz.chi2 <= self.max_chi2
        looms = (holds and sized and lz.slope < 0
                 and -lz.slope > self.min_expansion_sigmas * math.sqrt(lz.var_slope))
        lines, direct = [], []
        for axis in (0, 1):
            c, fl = (k.ppx, k.fx) if axis == 0 else (k.ppy, k.fy)
            # the bearing's course in sizes over the samples the size's course holds (after a
            # jump in the size, the samples before it are at another scale)
            ok = on_course & np.array([s.u_ok if axis == 0 else s.v_ok for s in ss])
            if ok.sum() < max(3, self.min_samples // 2):
                ok = on_course.copy()  # cut all along: better than nothing
            b = (np.array([s.u if axis == 0 else s.v for s in ss]) - c) / fl
            q = b * qz
            sq = qz * np.sqrt((sig / fl) ** 2 + (b * qz * sizes_sig / f) ** 2)
            if may_restart and looms:
                # the bearing's course jumps to a new level and stays: the track moved to
                # another blob (through a merge with it: a tree's blob 0.2 rad from the ball,
                # then the ball, open loop), and its course starts again after the jump (tested
                # where the course will say when and where it passes)
                idx = np.flatnonzero(ok)
                jump = _level_shift(t[idx], q[idx], sq[idx])
                if jump is not None:
                    after = float(t[idx[jump]])
                    return self._estimate([s for s in ss if s.t >= after], t_s, False)
            line = _wfit(t[ok], q[ok], sq[ok])
            if line is None:
                return None
            lines.append(line)
            if not holds:
                # the sizes keep to no course (a blob that merges with the structure beside it
                # for a frame now and then, 8 times its size, and weighs most in the fit): its
                # bearing from its newest centres alone, not from a course in sizes that does
                # not hold (0.5 rad off the blob's, open loop), nor across a jump to another
                # blob; over min_samples the bearing's curvature is under a pixel
                idx = np.flatnonzero(ok)[-self.min_samples:]
                bline = _robust_line(t[idx].tolist(), b[idx].tolist(), sig / fl)
                if bline is None:
                    return None
                direct.append(bline)
        lx, ly = lines
        z_now = lz.at(t_s)
        vz = lz.slope
        z_ref = z_now if z_now > 0.5 * float(qz[-1]) else float(qz[-1])  # passed: the last seen
        theta = 1.0 / z_ref
        x_now, y_now = lx.at(t_s), ly.at(t_s)
        bearing = (x_now / z_ref, y_now / z_ref)
        rate = ((lx.slope * z_ref - x_now * vz) / z_ref**2, (ly.slope * z_ref - y_now * vz) / z_ref**2)
        rate_se = max(math.sqrt(lx.var_slope), math.sqrt(ly.var_slope)) / z_ref
        if direct:
            bx, by = direct
            bearing, rate = (bx.at(t_s), by.at(t_s)), (bx.slope, by.slope)
            rate_se = max(math.sqrt(bx.var_slope), math.sqrt(by.var_slope))
            theta = float(np.median(size[on_course][-self.min_samples:])) / f
        expansion = -vz / z_ref
        exp_se = math.sqrt(lz.var_slope) / z_ref
        tau = tau_se = miss = miss_se = None
        if looms:
            # time to the camera plane (q_z = 0), from the fit's mean time (where its value
            # and slope are uncorrelated), and where the course crosses that plane
            tau_m = -lz.mean / vz
            var_tau = lz.var_mean / vz**2 + lz.mean**2 * lz.var_slope / vz**4
            tau, tau_se = tau_m - (t_s - lz.t_mean), math.sqrt(var_tau)
            t_c = lz.t_mean + tau_m
            miss = (lx.at(t_c), ly.at(t_c))
            miss_se = max(math.sqrt(ln.var_at(t_c) + ln.slope**2 * var_tau) for ln in (lx, ly))
        return ImageEstimate(t_s, len(ss), bearing, rate, theta, expansion, exp_se, tau, tau_se,
                             miss, miss_se, rate_se, (x_now, y_now, z_now), (lx.slope, ly.slope, vz), lz.chi2)

    def _box_fit(self, t: np.ndarray, size: np.ndarray, f: float, sig: float
                 ) -> tuple[_Line, np.ndarray, np.ndarray, bool, np.ndarray] | None:
        """The line of q_z = f / size through the boxes' sizes: (line, q_z, each size's
        std px, whether enough samples were big enough for a time to contact, which samples
        are on the course: all but those before a jump in the size)."""
        qz = f / size
        # a blob of a few pixels is mostly the motion mask's own margin: its size says little
        # of its range, and one pixel more (a merged blob) reads as a collapse of τ (seen: a
        # ball 45 m off, 3 px, evaded 3.5 s early on "τ 0.25 s"). Its bearing still counts.
        big = size >= self.min_size_px
        sized = int(big.sum()) >= self.min_samples
        keep = big if sized else np.ones_like(big)
        lz = _wfit(t[keep], qz[keep], f * sig / size[keep] ** 2)
        if lz is None:
            return None
        on_course = np.ones_like(big)
        if sized and lz.slope < 0:  # (a jump matters only where it would read as looming)
            idx = np.flatnonzero(keep)
            k = _level_shift(t[idx], qz[idx], f * sig / size[idx] ** 2)
            if k is not None:  # the sizes jumped: the course starts again after the jump
                after = keep & (t >= t[idx[k]])
                refit = (_wfit(t[after], qz[after], f * sig / size[after] ** 2)
                         if int(after.sum()) >= self.min_samples else None)
                if refit is None:  # too little since: no time to contact yet (the bearing stands)
                    sized = False
                else:
                    lz, on_course = refit, t >= t[idx[k]]
        return lz, qz, np.full_like(size, sig), sized, on_course

    def _photometric_fit(self, t: np.ndarray, size: np.ndarray, f: float,
                         measured: list[tuple[float, float] | None]
                         ) -> tuple[_Line, np.ndarray, np.ndarray, bool, np.ndarray] | None:
        """As :meth:`_box_fit` from a photometric size (value, std; its square root is
        proportional to the angular size) of the samples that have one clearly above its
        noise: None unless ``min_samples`` of them, the newest among them, span half the
        window, and the sizes they give keep to a course within their stated errors
        (``max_chi2``, and a chi-square that a course gives with PHOTOMETRIC_FIT_P at most:
        ground texture in the patch moves the flux by more than its error says). The samples without
        one (a patch at the frame's edge, a faint first frame) are left out rather than the
        measure given up for the boxes, whose ghosts and merges bias the expansion high (per
        frame against the truth, open loop seed 11: boxes 1.05-1.31x the true expansion at the
        median, 2.5-3.4x at the 90th percentile; the flux 0.97-0.98x and 0.72-1.41x between
        its 10th and 90th; the core area 0.99x and 0.93-1.07x)."""
        ok = np.array([m is not None and m[0] > FLUX_MIN_SIGMAS * m[1] for m in measured])
        if int(ok.sum()) < self.min_samples or not ok[-1]:
            return None
        if float(t[ok][-1] - t[ok][0]) < 0.5 * min(self.window_s, float(t[-1] - t[0])):
            return None
        value = np.array([m[0] for m, good in zip(measured, ok, strict=True) if good])  # type: ignore[index]
        std = np.array([m[1] for m, good in zip(measured, ok, strict=True) if good])  # type: ignore[index]
        root = np.sqrt(value)
        k = float(np.median(size[ok] / root))  # px per sqrt(measure): the boxes' scale, not their steps
        sz = size.copy()  # the samples without a measure: placed on the fitted course below
        sz_sig = np.full_like(size, self.pixel_noise_px)
        sz[ok] = k * root
        sz_sig[ok] = k * 0.5 * std / root
        qz = f / sz
        lz = _wfit(t[ok], qz[ok], f * sz_sig[ok] / sz[ok] ** 2)
        if lz is None or lz.chi2 > min(self.max_chi2, _chi2_bound(lz.dof)):
            return None
        qz[~ok] = [lz.at(float(v)) for v in t[~ok]]  # the bearing's course, at the fitted size
        return lz, qz, sz_sig, True, np.ones(len(t), bool)

    def reset(self) -> None:
        self._samples.clear()
