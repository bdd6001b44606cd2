"""A 3-D world seen by a forward D435i on a multirotor: colour and depth for a camera pose.

Pure code (numpy + OpenCV on arrays). World frame: local NED in metres, home at 0, the ground
the plane down = 0. The camera sits at the vehicle's position looking along its heading,
level (PX4 holds a multirotor within a few degrees of level at these speeds; attitude is left
out, which makes the image motion of the background a little easier than in flight).

What is drawn, far to near, and why:

- **sky**: a brightness gradient with clouds on a cylinder around the vehicle (no parallax,
  turns with the heading), no depth (the D435i sees nothing there);
- **ground**: a textured plane drawn through the homography a plane induces, with its true
  depth per pixel, with the D435i's error (1.4 m at 20 m), to the 65.5 m a uint16 frame holds;
- **clutter**: trees (vertical slabs) at fixed places, which move against the ground and
  the sky as the vehicle moves: the parallax a single homography cannot explain;
- **objects**: spheres (ball, bird, drone sized) with their depth;
- sensor noise.
"""

from __future__ import annotations

import importlib
import math
from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

import cv2
import numpy as np

from app.camera import CameraModel, Intrinsics
from app.errors import UsageError

Vec3 = tuple[float, float, float]

# body (forward, right, down) -> camera (right, down, forward)
_BODY_TO_CAM = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])


@dataclass(frozen=True)
class Tree:
    north_m: float
    east_m: float
    height_m: float = 8.0
    width_m: float = 3.0
    grey: int = 60


@dataclass(frozen=True)
class Sphere:
    object_id: int
    position_m: Vec3  # NED
    diameter_m: float
    grey: int  # 0..255
    kind: str = "ball"  # ball, bird or drone: its silhouette when the style draws shapes


@dataclass(frozen=True)
class WorldStyle:
    """The look of one world; everything random comes from ``seed``."""

    seed: int = 0
    ground_grey: float = 100.0
    ground_contrast: float = 30.0
    sky_top: float = 215.0
    sky_bottom: float = 175.0
    cloud_contrast: float = 25.0
    trees: int = 24
    noise_std: float = 1.5
    # Depth noise of a D400 stereo camera: RMS error = z² × subpixel / (focal px × baseline)
    # (Intel, "Best-Known-Methods for Tuning Intel RealSense D400 Depth Cameras", formula for
    # depth RMS error). D435i: baseline 50 mm; depth stream 848 px wide over an 87° field,
    # focal ≈ 447 px; subpixel 0.08 px is the guide's typical value for a textured target.
    # σ(z) ≈ 0.0036 z²: 0.09 m at 5 m, 0.36 m at 10 m. 0 = perfect depth. Applied as noise
    # in disparity, where stereo errs (see render).
    depth_subpixel: float = 0.08
    # Opt-in (the `shaped` world): objects drawn by kind (a bird's body with flapping wings,
    # a quadrotor's cross of arms and rotors, a ball's disc) instead of every one as a disc;
    # clouds that drift across the sky at this many px per frame.
    shapes: bool = False
    flap_hz: float = 4.0  # wing beats per second (a pigeon flaps at ~5 Hz, gulls ~3 Hz)
    fps: float = 30.0  # frames per second the flapping and drift are timed by
    cloud_drift_px: float = 0.0
    # Opt-in (the `stereo` world): depth with a D435i's failures of stereo matching, as well
    # as its noise: no depth where the scene has no texture to match (uniform objects' and
    # slabs' insides), the nearer side of a depth edge spread over the farther, scattered
    # holes, a few wrong matches, and the left band only the left imager sees (see
    # World._stereo_failures). Off, depth is exact but for its noise.
    stereo_failures: bool = False
    # With them, each wrong match spread over a square this many px wide (1: single pixels; the
    # `stereo_clumps` world: 3, so 1.8 % of the pixels wrong in clumps that agree on a depth, as
    # a matcher's errors along a repetitive or low-contrast patch do)
    stereo_clump_px: int = 1


D435I_BASELINE_M = 0.050  # stereo baseline of the D435/D435i (Intel D400 datasheet)
D435I_DEPTH_FX_PX = 447.0  # depth focal length at 848x480: 424 px / tan(87°/2)
# The `stereo` world's matching failures (World._stereo_failures). A model, not a measurement
# of the D4 processor (whose census window and texture thresholds are not published as
# numbers): a window of 7 px; no match where the noise-free grey varies by under 0.5 levels
# over it (a uniform surface: this world's objects and tree slabs; its near ground, smoother
# than real ground, varies by ~1 level over a window and keeps its depth); an edge where the
# depth jumps by 10 %; 5 % of the pixels in holes, 0.2 % wrong by up to 8 px of disparity
STEREO_WINDOW_PX = 7
STEREO_TEXTURE_MIN = 0.5
STEREO_EDGE_JUMP = 0.10
STEREO_HOLE_SHARE = 0.05
STEREO_OUTLIER_SHARE = 0.002
STEREO_OUTLIER_PX = 8.0


@dataclass
class World:
    """Pre-built textures for one style; :meth:`render` draws one frame."""

    style: WorldStyle = field(default_factory=WorldStyle)
    intrinsics: Intrinsics = field(default_factory=lambda: Intrinsics(640, 480, 615.0, 615.0, 319.5, 239.5))
    # Stereo has no range limit of its own (Intel's D400 tuning guide: at disparity shift 0
    # the farthest depth is unbounded); what limits it is the error, σ(z) above, 1.4 m at
    # 20 m, 5.8 m at 40 m. The world returns depth as far as a D435i frame can hold it
    # (uint16 millimetres): a building on the horizon has a depth, far and coarse, as it has
    # through a real D435i, not "no data" (at 20 m, as before, the decision could not tell
    # the parallax on a far roof from an object in front of it).
    max_depth_m: float = 65.535

    def __post_init__(self) -> None:
        rng = np.random.default_rng(self.style.seed)
        s, intr = self.style, self.intrinsics
        # ground: 0.1 m per texel, 102.4 m square, tiled
        self.ground_res_m = 0.1
        g = _periodic_blur(rng.normal(0, 1, (1024, 1024)), 2.0)
        g += 0.5 * cv2.resize(_periodic_blur(rng.normal(0, 1, (64, 64)), 1.5), (1024, 1024))
        self.ground = np.clip(s.ground_grey + s.ground_contrast * g / (np.abs(g).max() + 1e-9), 0, 255
                              ).astype(np.uint8)
        # sky: a cylinder of 2*pi*fx columns, rows of the upper half of the image
        width = int(round(2 * math.pi * intr.fx))
        rows = int(math.ceil(intr.ppy)) + 2
        clouds = _periodic_blur(rng.normal(0, 1, (rows // 8 + 2, width // 8)), 3.0, rows_too=False)
        clouds = cv2.resize(clouds, (width, rows), interpolation=cv2.INTER_CUBIC)
        grad = np.linspace(s.sky_top, s.sky_bottom, rows)[:, None]
        self.sky = np.clip(grad + s.cloud_contrast * clouds / (np.abs(clouds).max() + 1e-9), 0, 255
                           ).astype(np.uint8)
        self.trees = [Tree(float(rng.uniform(-60, 160)), float(side * rng.uniform(12, 60)),
                           float(rng.uniform(5, 12)), float(rng.uniform(2, 5)), int(rng.integers(40, 80)))
                      for side in rng.choice([-1, 1], s.trees)]
        self.noise = [rng.normal(0, s.noise_std, (intr.height, intr.width)).astype(np.float32)
                      for _ in range(7)]
        self._noise_steps = [_noise_steps(n) for n in self.noise]
        self._k = 0
        self._tiled: np.ndarray | None = None  # the ground texture 3 x 3, made on first use
        # Depth noise: one smooth unit field (stereo matching correlates neighbouring pixels),
        # a fresh random window of it each frame.
        field = cv2.GaussianBlur(rng.normal(0, 1, (intr.height + 64, intr.width + 64)), (0, 0), 2.0)
        self._disparity_noise = self.style.depth_subpixel * (field / field.std()).astype(np.float32)  # px
        self._depth_rng = np.random.default_rng(self.style.seed + 1)
        if s.stereo_failures:  # clumps of a few px, and single wrong matches
            shape = (intr.height + 64, intr.width + 64)
            clumps = cv2.GaussianBlur(rng.random(shape, dtype=np.float32), (0, 0), 1.5)
            self._holes = clumps > np.quantile(clumps, 1.0 - STEREO_HOLE_SHARE)
            wrong = rng.random(shape) < STEREO_OUTLIER_SHARE
            self._outliers = np.where(wrong, rng.uniform(-STEREO_OUTLIER_PX, STEREO_OUTLIER_PX, shape), 0.0
                                      ).astype(np.float32)
            if s.stereo_clump_px > 1:  # each over its square (where two meet, the larger error)
                square = np.ones((s.stereo_clump_px, s.stereo_clump_px), np.uint8)
                pos = cv2.dilate(np.maximum(self._outliers, 0.0), square)
                neg = cv2.dilate(np.maximum(-self._outliers, 0.0), square)
                self._outliers = np.where(pos >= neg, pos, -neg).astype(np.float32)

    def _ground_rows(self, texel_to_px: np.ndarray, w: int, rows: int) -> np.ndarray:
        """The tiled ground texture seen through ``texel_to_px`` (texel -> output px), ``rows``
        x ``w``. OpenCV's wrapping border costs 14x its constant one (3.1 against 0.22 ms at
        848 x 240), so the rows whose texels all lie in a 3 x 3 tiling of the texture around
        the nearest ground are drawn from that tiling (the same pixels: the texture is
        periodic), and only the far rows near the horizon wrap."""
        n = self.ground.shape[0]
        if self._tiled is None:
            self._tiled = np.tile(self.ground, (3, 3))
        inv = np.linalg.inv(texel_to_px)
        ys = np.arange(rows, dtype=np.float64)
        ends = []
        for x in (0.0, w - 1.0):
            q = inv @ np.vstack([np.full_like(ys, x), ys, np.ones_like(ys)])
            ends.append(q[:2] / q[2])
        cx, cy = (ends[0][0][-1] + ends[1][0][-1]) / 2, (ends[0][1][-1] + ends[1][1][-1]) / 2
        ox, oy = (math.floor(cx / n) - 1) * n, (math.floor(cy / n) - 1) * n  # nearest in the middle tile
        inside = np.ones(rows, bool)
        for ex, ey in ends:
            inside &= (ex - ox >= 1) & (ex - ox <= 3 * n - 2) & (ey - oy >= 1) & (ey - oy <= 3 * n - 2)
        outside = np.flatnonzero(~inside)
        first = int(outside[-1]) + 1 if len(outside) else 0  # every row from here down is inside
        out = np.empty((rows, w), np.uint8)
        if first < rows:
            shift = texel_to_px @ np.array([[1.0, 0.0, ox], [0.0, 1.0, oy], [0.0, 0.0, 1.0]])
            shift = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, -first], [0.0, 0.0, 1.0]]) @ shift
            out[first:] = cv2.warpPerspective(self._tiled, shift, (w, rows - first), flags=cv2.INTER_LINEAR,
                                              borderMode=cv2.BORDER_CONSTANT)
        if first > 0:
            out[:first] = cv2.warpPerspective(self.ground, texel_to_px, (w, first), flags=cv2.INTER_LINEAR,
                                              borderMode=cv2.BORDER_WRAP)
        return out

    def camera(self) -> CameraModel:
        """Colour and depth share the lens here (depth already in the colour frame)."""
        return CameraModel(self.intrinsics, self.intrinsics)

    def render(self, position_m: Vec3, yaw_rad: float, spheres: list[Sphere]
               ) -> tuple[np.ndarray, np.ndarray, dict[int, tuple[float, float, float, float]]]:
        """Colour (BGR uint8), depth (uint16 mm, 0 = no data) and, per visible sphere, its
        image circle and distance ``(u, v, radius_px, z_m)``."""
        intr = self.intrinsics
        h, w = intr.height, intr.width
        altitude = max(0.05, -position_m[2])
        c, s = math.cos(yaw_rad), math.sin(yaw_rad)
        world_to_body = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])
        rot = _BODY_TO_CAM @ world_to_body  # world -> camera
        pos = np.asarray(position_m, float)
        k = intr.matrix()

        # sky: columns by heading
        horizon = int(math.floor(intr.ppy)) + 1  # rows above see sky (level camera)
        drift = self.style.cloud_drift_px * self._k
        shift = int(round(yaw_rad * intr.fx + drift)) % self.sky.shape[1]
        n_sky = self.sky.shape[1]
        first = (shift - int(intr.ppx) + n_sky // 2) % n_sky  # the columns first, first + 1, ...
        grey = np.empty((h, w), np.uint8)
        run = min(w, n_sky - first)  # up to the cylinder's seam, then on from its start
        grey[:horizon, :run] = self.sky[:horizon, first:first + run]
        if run < w:
            grey[:horizon, run:] = self.sky[:horizon, :w - run]

        # ground: texture (u = east, v = north, 0.1 m texels, tiled) -> image
        res = self.ground_res_m
        t = -rot @ (pos - np.array([37.3, 53.1, 0.0]))  # home away from a tile's corner
        plane = k @ np.column_stack([rot[:, 1] * res, rot[:, 0] * res, t])
        # only the rows below the horizon: the same pixels, half the work
        below = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, -horizon], [0.0, 0.0, 1.0]]) @ plane
        grey[horizon:] = self._ground_rows(below, w, h - horizon)
        depth = np.zeros((h, w), np.float32)
        v = np.arange(horizon, h, dtype=np.float32)
        z_ground = altitude * intr.fy / np.maximum(v - intr.ppy, 1e-3)
        depth[horizon:] = z_ground[:, None]
        depth_top = horizon  # the first row that may hold depth

        # trees, far to near: vertical slabs facing the camera
        def to_cam(p: np.ndarray) -> np.ndarray:
            return rot @ (p - pos)

        slabs = []
        for tree in self.trees:
            base = to_cam(np.array([tree.north_m, tree.east_m, 0.0]))
            if base[2] < 1.0:
                continue
            slabs.append((base[2], tree, base))
        for z, tree, base in sorted(slabs, key=lambda item: -item[0]):
            top = base + rot @ np.array([0.0, 0.0, -tree.height_m])
            u0 = intr.fx * (base[0] - tree.width_m / 2) / z + intr.ppx
            u1 = intr.fx * (base[0] + tree.width_m / 2) / z + intr.ppx
            v0 = intr.fy * top[1] / z + intr.ppy
            v1 = intr.fy * base[1] / z + intr.ppy
            x0, x1 = max(0, int(u0)), min(w, int(math.ceil(u1)))
            y0, y1 = max(0, int(v0)), min(h, int(math.ceil(v1)))
            if x1 <= x0 or y1 <= y0:
                continue
            grey[y0:y1, x0:x1] = tree.grey
            depth[y0:y1, x0:x1] = z
            depth_top = min(depth_top, y0)

        # objects
        seen: dict[int, tuple[float, float, float, float]] = {}
        for sp in sorted(spheres, key=lambda o: -float(to_cam(np.asarray(o.position_m))[2])):
            p = to_cam(np.asarray(sp.position_m, float))
            if p[2] < 0.2:
                continue
            u = intr.fx * p[0] / p[2] + intr.ppx
            vv = intr.fy * p[1] / p[2] + intr.ppy
            r = intr.fx * sp.diameter_m / 2 / p[2]
            if not (-r < u < w + r and -r < vv < h + r):
                continue
            mask = np.zeros((h, w), np.uint8)
            beats = self._k / max(self.style.fps, 1.0) * self.style.flap_hz
            shape = sp.kind if self.style.shapes and sp.kind in ("bird", "drone") else "disc"
            x0, y0, x1, y1 = draw_object(mask, shape, u, vv, r, beats)
            if x1 > x0 and y1 > y0:  # blended in the patch drawn: outside it nothing changes
                alpha = mask[y0:y1, x0:x1].astype(np.float32) / 255.0
                patch = grey[y0:y1, x0:x1]
                grey[y0:y1, x0:x1] = (patch * (1 - alpha) + sp.grey * alpha).astype(np.uint8)
                depth[y0:y1, x0:x1][mask[y0:y1, x0:x1] > 127] = float(p[2])
                depth_top = min(depth_top, y0)
            seen[sp.object_id] = (float(u), float(vv), float(r), float(p[2]))

        if self.style.stereo_failures:
            self._stereo_failures(grey, depth, depth_top)
        colour = cv2.cvtColor(self._add_noise(grey, self._k % len(self.noise)), cv2.COLOR_GRAY2BGR)
        self._k += 1
        # rows above `depth_top` hold no depth (sky): they come back 0 as they are; the rest
        # is worked in place (a frame's temporaries cost as much as the arithmetic here)
        band = depth[depth_top:]
        if self.style.depth_subpixel > 0:
            # Stereo errs in disparity (d = f B / z), by about `subpixel` px: to first order
            # σ_z = z² subpixel / (f B), the formula above; a far surface (d → 0) stays far
            # or has no depth, it never comes out near.
            dy, dx = self._depth_rng.integers(0, 64, 2)
            window = self._disparity_noise[dy + depth_top:dy + h, dx:dx + w]
            # No data (0) has an infinite disparity and comes back 0; a disparity at or below
            # 0 comes back at infinity or behind the camera, out of the range kept below.
            fb = D435I_DEPTH_FX_PX * D435I_BASELINE_M
            with np.errstate(divide="ignore"):
                np.divide(fb, band, out=band)  # disparity
                band += window
                np.divide(fb, band, out=band)  # depth again
        kept = cv2.inRange(band, 0.2, self.max_depth_m)  # the range the D435i returns, 0 elsewhere
        band *= 1000.0
        out = np.zeros((h, w), np.uint16)
        with np.errstate(invalid="ignore"):  # what is out of range (inf, nan) is not kept
            cv2.copyTo(band.astype(np.uint16), kept, out[depth_top:])
        return colour, out, seen

    def _stereo_failures(self, grey: np.ndarray, depth: np.ndarray, top: int) -> None:
        """Puts into ``depth`` (m, 0 = none, rows from ``top``) what stereo matching does to
        it, from the noise-free ``grey`` (the pair's image noise is not texture: it differs
        between the two imagers):

        - **no texture, no match**: no depth where the grey varies by under
          ``STEREO_TEXTURE_MIN`` (standard deviation) over a matching window of
          ``STEREO_WINDOW_PX``: a uniform ball's or tree slab's inside; its rim keeps depth;
        - **edges fattened**: within half a window of a depth edge, the nearer side's depth
          spreads over the farther (the window is matched on the nearer surface's texture);
        - **holes**: ``STEREO_HOLE_SHARE`` of the pixels, in clumps of a few px, have none;
        - **wrong matches**: ``STEREO_OUTLIER_SHARE`` of the pixels take a disparity off by up
          to ``STEREO_OUTLIER_PX`` either way (some come out much nearer);
        - **the left band**: no depth in the leftmost B·f/z columns, which the right imager
          does not see (Intel RealSense D400 datasheet, "invalid depth band": B·F/Z px).
        """
        h, w = depth.shape
        band = depth[top:]
        if band.size == 0:
            return
        g = grey[top:].astype(np.float32)
        win = (STEREO_WINDOW_PX, STEREO_WINDOW_PX)
        mean = cv2.blur(g, win)
        var = cv2.blur(g * g, win) - mean * mean
        flat = var < STEREO_TEXTURE_MIN ** 2
        # the nearer side spreads over the farther by half a window from an edge (a jump between
        # neighbours, not the slope of the ground): a min filter there (no depth is infinitely far)
        far = np.where(band > 0, band, np.float32(np.inf)).astype(np.float32)
        edge = (cv2.erode(far, np.ones((3, 3), np.uint8)) < far * (1.0 - STEREO_EDGE_JUMP)).view(np.uint8)
        reach = np.ones((STEREO_WINDOW_PX, STEREO_WINDOW_PX), np.uint8)
        near = cv2.erode(far, reach)
        spread = cv2.dilate(edge, reach).view(bool) & (near < far)
        band[spread] = near[spread]
        band[flat & ~spread] = 0.0
        # holes and wrong matches: a random window of fields made once (as the noise above)
        dy, dx = self._depth_rng.integers(0, 64, 2)
        rows = slice(dy + top, dy + h)
        band[self._holes[rows, dx:dx + w]] = 0.0
        off = self._outliers[rows, dx:dx + w]
        vs, us = np.nonzero((off != 0) & (band > 0))
        fb = D435I_DEPTH_FX_PX * D435I_BASELINE_M  # disparities in the depth stream's px
        disparity = fb / band[vs, us] + off[vs, us]
        band[vs, us] = np.where(disparity > 0, fb / np.maximum(disparity, 1e-6), 0.0)
        # the left band, in this lens's columns
        with np.errstate(divide="ignore"):
            unseen_px = D435I_BASELINE_M * self.intrinsics.fx / np.where(band > 0, band, np.inf)
        band[np.arange(w, dtype=np.float32)[None, :] < unseen_px] = 0.0

    def _add_noise(self, grey: np.ndarray, i: int) -> np.ndarray:
        """``grey`` plus noise frame ``i``, clipped to 0..255 and truncated: what float32
        addition gives, ``clip(grey + noise).astype(uint8)``, pixel for pixel, in two saturating
        integer additions of the noise's whole part and, for the few pixels whose fraction lies
        so close to 1 that the float sum rounds up to the next integer, the float sum itself."""
        up, down, risky, values = self._noise_steps[i]
        out = cv2.subtract(cv2.add(grey, up), down)
        if len(risky):
            exact = grey.reshape(-1)[risky].astype(np.float32) + values
            out.reshape(-1)[risky] = np.clip(exact, 0, 255).astype(np.uint8)
        return out


def _noise_steps(noise: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A float32 noise frame as :meth:`World._add_noise` applies it: its whole part, split into
    what it adds and what it takes away (uint8, saturating), and the flat indices and values of
    the pixels whose fraction is within 2^-12 of 1, where a float sum with an integer grey may
    round up (float32 keeps 2^-16 px at 255; the margin is generous)."""
    whole = np.floor(noise.astype(np.float64))
    up = np.clip(whole, 0, 255).astype(np.uint8)
    down = np.clip(-whole, 0, 255).astype(np.uint8)
    risky = np.flatnonzero(noise.astype(np.float64) - whole > 1.0 - 2.0 ** -12)
    return up, down, risky, noise.reshape(-1)[risky].copy()


def draw_object(mask: np.ndarray, kind: str, u: float, v: float, r: float, beats: float
                ) -> tuple[int, int, int, int]:
    """Draw a disc, bird or quadrotor of half-span ``r`` px at (u, v) into ``mask`` (255 =
    covered), each pixel's value its covered fraction: drawn supersampled in a patch around it
    and averaged down, so the image's size and position change continuously with the range
    (OpenCV's anti-aliased discs alone still step: r 2.4 -> 2.5 px covered 21.6 -> 30.3 px²).
    Returns the patch (x0, y0, x1, y1, px; empty when off the image): nothing outside it is
    touched."""
    h, w = mask.shape
    g = r + 3.0
    x0, y0 = max(0, int(math.floor(u - g))), max(0, int(math.floor(v - g)))
    x1, y1 = min(w, int(math.ceil(u + g)) + 1), min(h, int(math.ceil(v + g)) + 1)
    if x1 <= x0 or y1 <= y0:
        return x0, y0, x0, y0
    side = max(x1 - x0, y1 - y0)
    k = 8 if side <= 48 else 4 if side <= 160 else 1  # a large object's pixel steps are small
    sub = np.zeros(((y1 - y0) * k, (x1 - x0) * k), np.uint8)
    su, sv = (u - x0 + 0.5) * k - 0.5, (v - y0 + 0.5) * k - 0.5  # pixel centres at integers
    if kind == "disc":
        cv2.circle(sub, _sub((su, sv)), _sub1(max(0.5, r) * k), 255, -1, cv2.LINE_AA, SUB_BITS)
    else:
        _silhouette(sub, kind, su, sv, r * k, beats)
    patch = sub if k == 1 else cv2.resize(sub, (x1 - x0, y1 - y0), interpolation=cv2.INTER_AREA)
    np.maximum(mask[y0:y1, x0:x1], patch, out=mask[y0:y1, x0:x1])
    return x0, y0, x1, y1


def _silhouette(mask: np.ndarray, kind: str, u: float, v: float, r: float, beats: float) -> None:
    """A bird (body ellipse, two wings whose tips beat up and down ``beats`` cycles in) or a
    quadrotor (two crossed arms and four rotor discs) of half-span ``r`` px centred at (u, v),
    drawn into ``mask`` at 255, to 1/16 px."""
    c = _sub((u, v))
    span = max(0.5, r)
    if kind == "bird":
        cv2.ellipse(mask, c, (_sub1(span * 0.45), _sub1(span * 0.18)), 0, 0, 360, 255, -1,
                    cv2.LINE_AA, SUB_BITS)
        # wing tips on the circle, beating 35 degrees above and below the body
        angle = math.radians(35.0) * math.sin(2 * math.pi * beats)
        for side in (-1, 1):
            tip = (u + side * span * math.cos(angle) * 0.97, v - span * math.sin(angle) * 0.97)
            root = u + side * span * 0.15
            pts = np.array([_sub((root, v - span * 0.1)), _sub(tip), _sub((root, v + span * 0.1))],
                           np.int32)
            cv2.fillConvexPoly(mask, pts, 255, cv2.LINE_AA, SUB_BITS)
    else:  # drone: an X of arms with a rotor at each end (seen from the front, foreshortened)
        half = span * 0.06  # each arm a bar span x 0.12 thick (a polygon: OpenCV's line widths are whole px)
        for dx, dy in ((1, 0.35), (1, -0.35)):
            ex, ey = dx * span * 0.75, dy * span * 0.75
            n = half / math.hypot(ex, ey)
            nx, ny = -ey * n, ex * n
            bar = [(u - ex + nx, v - ey + ny), (u + ex + nx, v + ey + ny),
                   (u + ex - nx, v + ey - ny), (u - ex - nx, v - ey - ny)]
            cv2.fillConvexPoly(mask, np.array([_sub(p) for p in bar], np.int32), 255, cv2.LINE_AA, SUB_BITS)
        for sx in (-1, 1):
            for sy in (-1, 1):
                rotor = _sub((u + sx * span * 0.75, v + sy * span * 0.27))
                axes = (_sub1(span * 0.25), _sub1(span * 0.08))
                cv2.ellipse(mask, rotor, axes, 0, 0, 360, 255, -1, cv2.LINE_AA, SUB_BITS)
        cv2.circle(mask, c, _sub1(span * 0.18), 255, -1, cv2.LINE_AA, SUB_BITS)


# Objects are drawn to 1/16 px (OpenCV's fractional bits): whole-pixel radii and centres made a
# far object's image size step by a pixel at a time (a 4.4 px drone read 2 360 -> 5 935 grey px²
# of contrast in one frame), which no camera sees and which looming then reads as approach.
SUB_BITS = 4


def _sub(p: tuple[float, float]) -> tuple[int, int]:
    return int(round(p[0] * (1 << SUB_BITS))), int(round(p[1] * (1 << SUB_BITS)))


def _sub1(v: float) -> int:
    return max(1, int(round(v * (1 << SUB_BITS))))


def shaped(seed: int, lens: Intrinsics) -> World:
    """The built-in world with birds and quadrotors drawn as such (not discs) and clouds that
    drift (``--world app.sim.world:shaped``): perception not tuned to balls against a still sky."""
    return World(WorldStyle(seed=seed, shapes=True, cloud_drift_px=0.4), intrinsics=lens)


def stereo(seed: int, lens: Intrinsics) -> World:
    """The built-in world whose depth fails as stereo matching does (``--world
    app.sim.world:stereo``): no depth inside uniform objects and slabs, fattened edges, holes,
    a few wrong matches and the left invalid band (:meth:`World._stereo_failures`)."""
    return World(WorldStyle(seed=seed, stereo_failures=True), intrinsics=lens)


def stereo_clumps(seed: int, lens: Intrinsics) -> World:
    """The `stereo` world with its wrong matches in 3 x 3 clumps (``--world
    app.sim.world:stereo_clumps``): 1.8 % of the pixels wrong, nine at a time at one depth, a
    harsher model than `stereo`'s single pixels (the D4's own rates are not published)."""
    return World(WorldStyle(seed=seed, stereo_failures=True, stereo_clump_px=3), intrinsics=lens)


def _periodic_blur(noise: np.ndarray, sigma: float, rows_too: bool = True) -> np.ndarray:
    """Gaussian-blurred noise that tiles without a seam: blurred with a wrapped margin wider
    than the kernel (the same pixels as blurring a 3 x 3 tiling and keeping its centre,
    without blurring nine times the texture)."""
    h, w = noise.shape
    m = int(math.ceil(4 * sigma)) + 1  # OpenCV's kernel for a float image reaches 4 sigma
    mr = min(m, h) if rows_too else 0
    mc = min(m, w)
    # the margin wraps (rows only with rows_too), up to one period each side
    padded = np.concatenate([noise[:, w - mc:], noise, noise[:, :mc]], axis=1)
    if mr:
        padded = np.concatenate([padded[h - mr:], padded, padded[:mr]], axis=0)
    blurred = cv2.GaussianBlur(padded, (0, 0), sigma)
    return np.ascontiguousarray(blurred[mr:mr + h, mc:mc + w])


# ---------------------------------------------------------------------------- other worlds


@runtime_checkable
class Renderer(Protocol):
    """What the closed loop needs of a world (``--world package.module:factory``).

    ``camera()`` is the lens the frames are drawn with (colour; depth registered to it).
    ``render(position_m, yaw_rad, spheres)`` draws one frame from the vehicle at
    ``position_m`` (NED, m) facing ``yaw_rad``, camera level, with the objects ``spheres``
    (NED centre, diameter, brightness) in it, and returns colour (H x W x 3 BGR uint8),
    depth (H x W uint16, mm, 0 where there is none) and, per object in view, its image
    circle and distance ``(u px, v px, radius px, z m)`` (the truth the score uses). It may
    draw an object as anything it likes (a bird, a quadrotor) as long as it reports its
    circle. It is called once per frame, in order, from one thread.
    """

    def camera(self) -> CameraModel: ...

    def render(self, position_m: Vec3, yaw_rad: float, spheres: list[Sphere]
               ) -> tuple[np.ndarray, np.ndarray, dict[int, tuple[float, float, float, float]]]: ...


# The D435i's colour lens: factory calibrations at 640x480 read fx ~ 615 px (the CameraConfig
# defaults, app/config.py), i.e. 55 degrees across. Its 4:3 modes are a centre crop of the
# 16:9 sensor at the same vertical scale, so fx ~ 615 * height / 480 in every mode; at 848x480
# that gives 2 atan(424 / 615) = 69 degrees across, the datasheet's 69 x 42 degree RGB field
# (Intel RealSense D400 series datasheet, RGB sensor FOV).
D435I_COLOR_FX_PER_ROW = 615.0 / 480.0


def d435i_color(width: int, height: int) -> Intrinsics:
    """The colour lens of a D435i streaming ``width`` x ``height`` (pinhole, centred)."""
    f = D435I_COLOR_FX_PER_ROW * height
    return Intrinsics(width, height, f, f, (width - 1) / 2.0, (height - 1) / 2.0)


def d435i_infrared(width: int, height: int) -> Intrinsics:
    """The left infrared imager of a D435i streaming ``width`` x ``height`` (pinhole,
    centred): the depth pair's lens, 87 degrees across at 848x480 (D435I_DEPTH_FX_PX), the
    same field at 1280x720 (its 16:9 modes scale the sensor), and depth is registered to it."""
    f = D435I_DEPTH_FX_PX * width / 848.0
    return Intrinsics(width, height, f, f, (width - 1) / 2.0, (height - 1) / 2.0)


class Monochrome:
    """A world seen by a monochrome imager (the D435i's infrared pair, whose sensors have no
    colour filter and, outdoors with the projector off, see visible light and near infrared
    alike): the inner world's frames as 8-bit grey (H x W), the rest unchanged. Near-infrared
    brightness is not modelled (foliage is brighter there than in grey): a grey rendering of
    the colour world, which is what the geometry of the wider lens needs."""

    def __init__(self, world: Renderer) -> None:
        self.world = world
        self.tilts = isinstance(world, Tilted)

    def camera(self) -> CameraModel:
        return self.world.camera()

    def render(self, position_m: Vec3, yaw_rad: float, spheres: list[Sphere],
               rotation: np.ndarray | None = None
               ) -> tuple[np.ndarray, np.ndarray, dict[int, tuple[float, float, float, float]]]:
        if rotation is None:
            colour, depth, seen = self.world.render(position_m, yaw_rad, spheres)
        else:
            colour, depth, seen = self.world.render(position_m, yaw_rad, spheres, rotation=rotation)  # type: ignore[call-arg]
        grey = colour if colour.ndim == 2 else cv2.cvtColor(colour, cv2.COLOR_BGR2GRAY)
        return grey, depth, seen


def load_world(spec: str, seed: int, lens: Intrinsics) -> Renderer:
    """The world for one encounter: the built-in one (``spec`` empty) or ``factory(seed,
    lens)`` from ``spec`` = "package.module:factory" (importable where the encounter runs);
    ``lens`` is the colour lens the configuration streams, which a world may follow or not
    (its ``camera()`` says which it drew with)."""
    if not spec:
        return World(WorldStyle(seed=seed), intrinsics=lens)
    module_name, sep, attr = spec.partition(":")
    if not sep or not module_name or not attr:
        raise UsageError(f"--world {spec!r}: expected package.module:factory")
    try:
        module = importlib.import_module(module_name)
    except ImportError as exc:
        raise UsageError(f"--world {spec!r}: cannot import {module_name} ({exc})") from None
    factory = getattr(module, attr, None)
    if not callable(factory):
        raise UsageError(f"--world {spec!r}: {module_name} has no callable {attr}")
    world = factory(seed, lens)
    if not isinstance(world, Renderer):
        raise UsageError(f"--world {spec!r}: {attr}({seed}, lens) returned {type(world).__name__}, which "
                         "lacks camera() and render() (app.sim.world.Renderer)")
    return world


class Tilted:
    """A camera fixed to a multirotor's body, which banks and pitches to accelerate: the
    world drawn level (its yaw only) through a lens wider by ``margin`` on every side, then
    turned to the camera's roll and pitch. A turn about the camera's centre has no parallax,
    so one homography (K·R·K_wide⁻¹) turns the whole frame exactly; each depth is rescaled to
    the turned camera's Z. Needs a world that draws with the lens it is given."""

    def __init__(self, spec: str, seed: int, lens: Intrinsics, margin: tuple[int, int] | None = None) -> None:
        # up to ~25° of roll and ~22° of pitch (4 m/s², the stand-in's limit, is 22°) without
        # reaching the wide frame's edge (beyond it, its border is repeated)
        mx, my = margin or (int(0.2 * lens.width), int(0.55 * lens.height))
        self.wide = Intrinsics(lens.width + 2 * mx, lens.height + 2 * my, lens.fx, lens.fy,
                               lens.ppx + mx, lens.ppy + my)
        self.world = load_world(spec, seed, self.wide)
        drawn = self.world.camera().color
        if (drawn.width, drawn.height, drawn.fx, drawn.ppx) != (self.wide.width, self.wide.height,
                                                                self.wide.fx, self.wide.ppx):
            raise UsageError(f"--tilt: the world {spec or 'built-in'} draws with its own lens "
                             f"({drawn.width}x{drawn.height}), not the wider one it is given")
        self.lens = lens
        self._k = lens.matrix()
        self._k_wide_inv = np.linalg.inv(self.wide.matrix())
        u = (np.arange(lens.width, dtype=np.float32) - lens.ppx) / lens.fx
        v = (np.arange(lens.height, dtype=np.float32) - lens.ppy) / lens.fy
        self._xn, self._yn = np.meshgrid(u, v)

    def camera(self) -> CameraModel:
        return CameraModel(self.lens, self.lens)

    def render(self, position_m: Vec3, yaw_rad: float, spheres: list[Sphere],
               rotation: np.ndarray | None = None
               ) -> tuple[np.ndarray, np.ndarray, dict[int, tuple[float, float, float, float]]]:
        """As :meth:`World.render`, the camera turned by ``rotation`` (level camera's axes ->
        the tilted camera's; None: level)."""
        colour, depth, seen = self.world.render(position_m, yaw_rad, spheres)
        r = np.eye(3) if rotation is None else np.asarray(rotation, float)
        h = self._k @ r @ self._k_wide_inv
        size = (self.lens.width, self.lens.height)
        colour = cv2.warpPerspective(colour, h, size, flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        depth = cv2.warpPerspective(depth, h, size, flags=cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT)
        # Z in the turned camera = Z level / (third row of Rᵀ · the turned ray), R[:, 2] · ray
        scale = 1.0 / (r[0, 2] * self._xn + r[1, 2] * self._yn + r[2, 2])
        depth = np.clip(depth.astype(np.float32) * scale, 0, 65535).astype(np.uint16)
        turned = {}
        for oid, (u, v, radius, z) in seen.items():
            q = h @ np.array([u, v, 1.0])
            uu, vv = float(q[0] / q[2]), float(q[1] / q[2])
            ray = np.array([(uu - self.lens.ppx) / self.lens.fx, (vv - self.lens.ppy) / self.lens.fy, 1.0])
            turned[oid] = (uu, vv, radius, float(z / (r[:, 2] @ ray)))
        return colour, depth, turned
