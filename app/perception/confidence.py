"""Track confidence: is a confirmed track an object, or moving clutter? (beyond the paper)

Frame differencing cannot tell a bird from a swaying branch or from ground that parallax
moves: both leave a blob that persists. What can tell them apart is *where* the blob is and
*how* it behaves. Measured on the Halmstad clips (docs/measurements.md, "Track confidence"): objects sit in
plain surroundings (sky: ring gradient 75th percentile ~4 grey levels/px, median) while false
tracks sit in texture (trees, ground: ~17), and objects move steadily while clutter jitters.

Each confirmed track gets eleven causal features, updated every frame it is reported:

============== ==========================================================================
matched         1 if a cluster was matched in this frame, 0 while coasting
log_hits        log(1 + frames matched since the track was born)
ring_gradient   log(1 + median over the last ``history_frames`` matched frames of the 75th
                percentile of the grey gradient magnitude in a ``ring_px`` band around the
                cluster, outside its blobs), grey levels/px
ring_std        log(1 + the same median of the grey standard deviation in that band)
straightness    net displacement / path length of the last ``straightness_frames`` trail
                points (1 = a straight line, 0 = back and forth)
match_fraction  fraction of the last ``match_frames`` frames in which the track was matched
elongation      median over the last ``history_frames`` matched frames of log(long side /
                short side) of the cluster's box (flyers are compact; parallax edges, poles
                and trunks are long)
fill            the same median of the cluster's blob area / box area
bottom_edge     how long the ``ring_px`` band below the cluster's box has crossed the
                frame's bottom edge: the newest matched frames in a row that it did, over
                ``edge_frames``, at most 1 (ground, masts and tree tops that the bottom edge
                cuts off stay there; an object passing through it is 0 once above it)
contrast        the same median of how far the grey of the cluster's pixels stands from its
                ring's: |mean inside - mean of the ring| / (ring's grey std + 1), in units of
                the ring's own variation (an object stands out from whatever is behind it;
                texture that parallax moves is the ring's texture)
core            the fraction of the last ``history_frames`` matched frames in which
                photometry found the cluster a core (pixels beyond half its own contrast
                against the ring: app.perception.photometry): a solid body, not an edge
============== ==========================================================================

and a confidence ``sigmoid(bias + sum(weight * feature))``. The weights are fitted by
logistic regression (``midair fit-confidence``) and live in ``config.yaml``; a track is
*reported* as an object in the frames its confidence reaches ``min_confidence``. A track that
coasts on its prediction (no cluster matched this frame) is reported only while what it last
looked like is still found there (``coast_match``: the grey patch of its newest matched box,
searched for within ``coast_search_px`` of the prediction by normalised cross-correlation): a
hovering drone that the frame difference stops seeing is still there; a prediction that ran on
into empty sky or a tree after the object was lost is not. With ``min_confidence: 0`` every
matched confirmed track is reported (the paper).

The two ring-texture features say what the background is (plain sky or texture); fitted on
the Halmstad clips, they make ground behind an object read as clutter. ``contrast`` and
``core`` ask instead how the track stands against its background, whatever that is. Measured
leave-one-dataset-out (docs/measurements.md, "A confidence that does not ask what the
background is"), weights fitted on them in place of the ring's texture carry better to ground
flights and DAVIS, but never report a head-on ball on the horizon (its ring straddles sky
and ground, it has no core), which the ring-texture weights report in part: the shipped
weights are the nine features', ``w_contrast`` and ``w_core`` 0.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field
from statistics import median

import cv2
import numpy as np

from app.config import ConfidenceConfig
from app.perception.tracking import TrackReport

FEATURES = ("matched", "log_hits", "ring_gradient", "ring_std", "straightness", "match_fraction",
            "elongation", "fill", "bottom_edge", "contrast", "core")


@dataclass
class _Evidence:
    """What one track has shown so far (the running part of its features)."""

    gradient: deque[float]
    std: deque[float]
    elongation: deque[float]
    fill: deque[float]
    matched: deque[bool]
    contrast: deque[float]
    core: deque[bool]
    edge_run: int = field(default=0)  # newest matched frames in a row with the ring across the bottom edge
    seen: bool = field(default=False)  # updated in the current frame
    look: np.ndarray | None = field(default=None)  # grey patch of the newest matched frame's box


def ring_texture(grey: np.ndarray, box: tuple[int, int, int, int], contours: tuple[np.ndarray, ...],
                 ring_px: int) -> tuple[float, float, float] | None:
    """75th percentile of the gradient magnitude and standard deviation of grey in a
    ``ring_px`` band around ``box`` (x, y, w, h px), outside the object's pixels: the inside
    of its outer ``contours`` (image px, as a Cluster holds them); and the object's contrast
    against that band, |mean inside - mean of the band| / (the band's std + 1). None if the
    band is empty (box off the frame)."""
    height, width = grey.shape
    x, y, w, h = box
    x0, y0 = max(0, x - ring_px), max(0, y - ring_px)
    x1, y1 = min(width, x + w + ring_px), min(height, y + h + ring_px)
    if x1 - x0 < 3 or y1 - y0 < 3:
        return None
    # one pixel more on each side so that the gradient kernel sees real neighbours at the edge
    ex0, ey0, ex1, ey1 = max(0, x0 - 1), max(0, y0 - 1), min(width, x1 + 1), min(height, y1 + 1)
    # Both 3x3 Sobel derivatives in one pass (int16; identical to two cv2.Sobel calls, at a
    # third of their cost). The crop is copied: the kernel then borders it by reflection, which
    # only the extra pixel sees, except at the frame's own edges (where Sobel reflects too).
    gx, gy = cv2.spatialGradient(np.ascontiguousarray(grey[ey0:ey1, ex0:ex1]), ksize=3)
    band = np.full((y1 - y0, x1 - x0), 255, np.uint8)
    cv2.drawContours(band, list(contours), -1, 0, cv2.FILLED, offset=(-x0, -y0))  # clipped to the band
    sel = band != 0
    gxs = gx[y0 - ey0:y1 - ey0, x0 - ex0:x1 - ex0][sel].astype(np.int32)
    gys = gy[y0 - ey0:y1 - ey0, x0 - ex0:x1 - ex0][sel].astype(np.int32)
    # Squared magnitude in integers: exact, so the same on every run. (cv2.magnitude's vector
    # and scalar paths round differently, and which pixels take which path follows the
    # buffer's address: the same clip replayed twice gave confidences differing in the 8th
    # digit, enough to flip a report now and then.) The percentile is taken of the squares,
    # then rooted.
    squares = gxs * gxs + gys * gys
    if squares.size == 0:
        return None
    crop = grey[y0:y1, x0:x1]
    mean, std = cv2.meanStdDev(crop, mask=band)
    inside = cv2.bitwise_not(band)
    contrast = 0.0
    if cv2.countNonZero(inside):
        contrast = abs(cv2.mean(crop, mask=inside)[0] - float(mean[0, 0])) / (float(std[0, 0]) + 1.0)
    return _percentile_of_root(squares, 75.0), float(std[0, 0]), contrast


# the margin kept around a matched cluster's box in its look, px (a bit of what it stands against)
LOOK_MARGIN_PX = 2


def _patch(grey: np.ndarray, box: tuple[int, int, int, int], margin: int) -> np.ndarray | None:
    """A copy of ``grey`` in ``box`` (x, y, w, h px) grown by ``margin``, clipped to the frame;
    None when under 3 px a side or flat (grey std under 1: nothing to find it by)."""
    height, width = grey.shape
    x, y, w, h = box
    x0, y0 = max(0, int(x) - margin), max(0, int(y) - margin)
    x1, y1 = min(width, int(x) + int(w) + margin), min(height, int(y) + int(h) + margin)
    if x1 - x0 < 3 or y1 - y0 < 3:
        return None
    patch = grey[y0:y1, x0:x1]
    _, sd = cv2.meanStdDev(patch)
    return patch.copy() if float(sd[0, 0]) >= 1.0 else None


def still_there(grey: np.ndarray, box: tuple[float, float, float, float], look: np.ndarray,
                search_px: int) -> float:
    """How well ``look`` (a grey patch, not flat: :func:`_patch`) is found within ``search_px``
    of ``box``'s centre in ``grey``: the best normalised cross-correlation (-1 to 1). 0 when the
    search would leave the frame."""
    height, width = grey.shape
    x, y, w, h = box
    ph, pw = look.shape
    x0 = int(round(x + w / 2 - pw / 2)) - search_px
    y0 = int(round(y + h / 2 - ph / 2)) - search_px
    x1, y1 = x0 + pw + 2 * search_px, y0 + ph + 2 * search_px
    if x0 < 0 or y0 < 0 or x1 > width or y1 > height:
        return 0.0
    scores = cv2.matchTemplate(grey[y0:y1, x0:x1], look, cv2.TM_CCOEFF_NORMED)
    # a flat window of the search divides by ~0: not a match
    return float(np.nan_to_num(scores, nan=0.0, posinf=0.0, neginf=0.0).max())


def _percentile_of_root(squares: np.ndarray, q: float) -> float:
    """``np.percentile(np.sqrt(squares), q)`` (linear interpolation) by partial sorting of
    the squares (the root is monotonic, so the order statistics are the same): one partition
    at the lower rank, the upper one is the least above it (measured: 26 -> 17 us on the
    bench's rings, whose squares are 96 % repeats; np.percentile is 5-10x slower)."""
    pos = (squares.size - 1) * q / 100.0
    lo = int(pos)
    part = np.partition(squares, lo)
    a = math.sqrt(float(part[lo]))
    b = math.sqrt(float(part[lo + 1:].min())) if lo + 1 < squares.size else a
    return a + (b - a) * (pos - lo)


def straightness(trail: tuple[tuple[float, float], ...], n: int) -> float:
    """Net displacement over path length of the last ``n`` trail points (0-1; 0 if < 3)."""
    if len(trail) < 3:
        return 0.0
    pts = trail[-n:]
    path = sum(math.hypot(b[0] - a[0], b[1] - a[1]) for a, b in zip(pts[:-1], pts[1:], strict=True))
    if path < 1e-6:
        return 0.0
    return min(1.0, math.hypot(pts[-1][0] - pts[0][0], pts[-1][1] - pts[0][1]) / path)


def logistic(bias: float, weights: tuple[float, ...], features: tuple[float, ...]) -> float:
    z = bias + sum(w * f for w, f in zip(weights, features, strict=True))
    return 1.0 / (1.0 + math.exp(-max(-60.0, min(60.0, z))))


class TrackConfidence:
    """Scores the confirmed tracks of each frame; keeps each track's running evidence.

    Parameters
    ----------
    cfg
        ``min_confidence`` (0-1), ``ring_px`` (px), ``history_frames``,
        ``straightness_frames``, ``match_frames`` (frames), ``bias`` and the ``w_*``
        weights (one per feature, see the module doc).
    """

    def __init__(self, cfg: ConfidenceConfig) -> None:
        self.cfg = cfg
        self.weights = tuple(getattr(cfg, f"w_{name}") for name in FEATURES)
        self._evidence: dict[int, _Evidence] = {}

    def reset(self) -> None:
        self._evidence.clear()

    def __call__(self, grey: np.ndarray, tracks: list[TrackReport]) -> list[TrackReport]:
        """The tracks of the frame ``grey`` with ``confidence``, ``features`` and
        ``reported`` filled in. Call once per frame, with every confirmed track."""
        cfg = self.cfg
        height = grey.shape[0]
        for old in self._evidence.values():
            old.seen = False
        out = []
        for t in tracks:
            ev = self._evidence.get(t.track_id)
            if ev is None:
                n = cfg.history_frames
                ev = _Evidence(deque(maxlen=n), deque(maxlen=n), deque(maxlen=n), deque(maxlen=n),
                               deque(maxlen=cfg.match_frames), deque(maxlen=n), deque(maxlen=n))
                self._evidence[t.track_id] = ev
            ev.seen = True
            ev.matched.append(t.matched)
            if t.matched and t.cluster is not None:
                _, y, w, h = t.cluster.box
                ev.edge_run = ev.edge_run + 1 if y + h + cfg.ring_px > height else 0
                ev.elongation.append(math.log(max(w, h) / max(1, min(w, h))))
                ev.fill.append(t.cluster.area / max(1, w * h))
                tex = ring_texture(grey, t.cluster.box, t.cluster.contours, cfg.ring_px)
                if tex is not None:
                    ev.gradient.append(tex[0])
                    ev.std.append(tex[1])
                    ev.contrast.append(tex[2])
                ev.core.append(t.core is not None)
                if cfg.coast_match > 0:
                    ev.look = _patch(grey, t.cluster.box, LOOK_MARGIN_PX)
            features = (
                1.0 if t.matched else 0.0,
                math.log1p(t.hits),
                math.log1p(median(ev.gradient)) if ev.gradient else 0.0,
                math.log1p(median(ev.std)) if ev.std else 0.0,
                straightness(t.trail, cfg.straightness_frames),
                sum(ev.matched) / len(ev.matched),
                median(ev.elongation) if ev.elongation else 0.0,
                median(ev.fill) if ev.fill else 1.0,
                min(1.0, ev.edge_run / cfg.edge_frames),
                median(ev.contrast) if ev.contrast else 0.0,
                sum(ev.core) / len(ev.core) if ev.core else 0.0,
            )
            conf = logistic(cfg.bias, self.weights, features)
            in_sight = t.matched or cfg.coast_match <= 0 or (
                ev.look is not None
                and still_there(grey, t.box, ev.look, cfg.coast_search_px) >= cfg.coast_match)
            reported = (conf >= cfg.min_confidence if cfg.min_confidence > 0 else t.matched) and in_sight
            out.append(t.scored(conf, features, reported, in_sight))
        # a track that was not handed in is gone (deleted or reset): forget it
        for tid in [tid for tid, ev in self._evidence.items() if not ev.seen]:
            del self._evidence[tid]
        return out
