"""Fitting the track confidence (app/perception/confidence.py) on clips with ground truth.

``midair fit-confidence DATA``: every clip is replayed once; each confirmed track in each
frame becomes one example — its features, and whether its centre lies within the
evaluation gate of a labelled object (the matching rule of app/tools/evaluate.py). A logistic
regression (Newton's method, a small L2 penalty, no extra dependency) is fitted on all of
them. Because the confidence only decides what is *reported* and never feeds back into the
stages, the features do not depend on the weights: the same examples also give an honest
*leave-one-clip-out* estimate — each clip scored with weights fitted on the other clips,
then counted with the evaluation's own scorer (py-motmetrics).
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass

import numpy as np

from app.config import Config
from app.perception.confidence import FEATURES
from app.perception.pipeline import Perception
from app.runtime.sources import open_source
from app.tools.evaluate import GATE_PX, GATE_SCALE, Clip, read_boxes, score

L2 = 1e-5  # ridge penalty per example on the standardised weights (keeps separable data finite)


@dataclass
class ClipExamples:
    """Every confirmed track report of one clip."""

    clip: Clip
    frames: int
    gt: dict[int, list[tuple[int, float, float, float, float]]]
    keys: np.ndarray  # (n, 2) int: frame, track id
    boxes: np.ndarray  # (n, 4) float: x, y, w, h px
    x: np.ndarray  # (n, len(FEATURES)) float
    y: np.ndarray  # (n,) bool: centre within the gate of a labelled object
    in_sight: np.ndarray | None = None  # (n,) bool: TrackReport.in_sight (None: every row)


def collect(clip: Clip, cfg: Config) -> ClipExamples:
    """Replay ``clip`` and label every confirmed track report."""
    import cv2

    cv2.setNumThreads(1)
    gt = read_boxes(clip.gt)
    source = open_source(clip.video)
    p = Perception(cfg.perception)
    keys, boxes, xs, ys, sight = [], [], [], [], []
    for frame in source:
        r = p.push(frame)
        if r is None:
            continue
        objects = gt.get(r.frame.index, [])
        for t in r.tracks:
            x, y, w, h = t.box
            cx, cy = x + w / 2, y + h / 2
            hit = any(np.hypot(gx + gw / 2 - cx, gy + gh / 2 - cy) <= max(GATE_PX, GATE_SCALE * max(gw, gh))
                      for _, gx, gy, gw, gh in objects)
            keys.append((r.frame.index, t.track_id))
            boxes.append(t.box)
            xs.append(t.features)
            ys.append(hit)
            sight.append(t.in_sight)
    n = len(keys)
    return ClipExamples(
        clip, len(source), gt,
        np.array(keys, int).reshape(n, 2), np.array(boxes, float).reshape(n, 4),
        np.array(xs, float).reshape(n, len(FEATURES)), np.array(ys, bool), np.array(sight, bool),
    )


def collect_all(clips: Sequence[Clip], cfg: Config, workers: int | None = None) -> list[ClipExamples]:
    workers = workers or os.cpu_count() or 1
    if workers == 1 or len(clips) == 1:
        return [collect(c, cfg) for c in clips]
    with ProcessPoolExecutor(max_workers=workers) as pool:
        return list(pool.map(collect, clips, [cfg] * len(clips)))


# What the shipped weights are fitted on: the first nine features. Contrast and core (how a
# track stands against whatever is behind it) generalise better from the Halmstad clips to the
# ground flights and DAVIS when they replace the ring's texture, but the head-on ball on the
# horizon that the closed loop must avoid is then never reported (its ring straddles sky and
# ground, it has no core): docs/measurements.md, "A confidence that does not ask what the
# background is"
DEFAULT_FEATURES = tuple(f for f in FEATURES if f not in ("contrast", "core"))


def feature_columns(names: Sequence[str]) -> list[int]:
    """The columns of ``names`` in FEATURES; a clear error for a name that is not one."""
    unknown = [n for n in names if n not in FEATURES]
    if unknown or not names:
        raise ValueError(f"features {', '.join(unknown) or '(none)'}: expected some of {', '.join(FEATURES)}")
    return [FEATURES.index(n) for n in names]


def fit_logistic(x: np.ndarray, y: np.ndarray, l2: float = L2,
                 iterations: int = 50, columns: Sequence[int] | None = None) -> tuple[float, np.ndarray]:
    """Intercept and weights (in the units of ``x``) of a ridge-penalised logistic regression;
    with ``columns``, fitted on those features only, the others' weights 0."""
    if columns is not None:
        bias, w = fit_logistic(x[:, list(columns)], y, l2, iterations)
        full = np.zeros(x.shape[1])
        full[list(columns)] = w
        return bias, full
    if len(y) == 0 or y.all() or not y.any():
        raise ValueError("need examples of both classes to fit a confidence")
    mu, sd = x.mean(0), x.std(0)
    sd[sd < 1e-9] = 1.0
    z = np.hstack([np.ones((len(x), 1)), (x - mu) / sd])
    beta = np.zeros(z.shape[1])
    penalty = np.full(z.shape[1], l2 * len(y))
    penalty[0] = 0.0  # the intercept is not penalised
    for _ in range(iterations):
        p = 1 / (1 + np.exp(-np.clip(z @ beta, -60, 60)))
        grad = z.T @ (p - y) + penalty * beta
        hess = (z * (p * (1 - p))[:, None]).T @ z + np.diag(penalty + 1e-9)
        step = np.linalg.solve(hess, grad)
        beta -= step
        if np.max(np.abs(step)) < 1e-8:
            break
    w = beta[1:] / sd
    return float(beta[0] - np.sum(w * mu)), w


def confidence(bias: float, w: np.ndarray, x: np.ndarray) -> np.ndarray:
    return 1 / (1 + np.exp(-np.clip(bias + x @ w, -60, 60)))


def score_clip(ex: ClipExamples, conf: np.ndarray, min_confidence: float) -> dict[str, float]:
    """The evaluation's counts for ``ex`` reporting the rows whose confidence reaches the
    threshold (0: the matched rows, as ``min_confidence: 0`` does at run time), and coasting
    only where its look was still found (``coast_match``, as at run time)."""
    if min_confidence > 0:
        keep = conf >= min_confidence
    else:
        keep = ex.x[:, FEATURES.index("matched")] > 0.5
    if ex.in_sight is not None:
        keep = keep & ex.in_sight
    rows = [(int(f), int(i), *map(float, b), float(c))
            for (f, i), b, c in zip(ex.keys[keep], ex.boxes[keep], conf[keep], strict=True)]
    return score(ex.gt, rows, ex.frames, ex.clip.cuts)  # type: ignore[arg-type]


def leave_one_clip_out(examples: list[ClipExamples],
                       columns: Sequence[int] | None = None) -> list[np.ndarray]:
    """Each clip's confidences from weights fitted on the other clips."""
    out = []
    for i, ex in enumerate(examples):
        rest = [e for j, e in enumerate(examples) if j != i]
        bias, w = fit_logistic(np.vstack([e.x for e in rest]), np.concatenate([e.y for e in rest]),
                               columns=columns)
        out.append(confidence(bias, w, ex.x))
    return out


def sum_scores(scores: list[dict[str, float]]) -> tuple[float, float, int]:
    """Recall, precision and GT rows over several clips' counts."""
    gt = sum(int(s["gt_rows"]) for s in scores)
    tp = sum(int(s["tp"]) for s in scores)
    fp = sum(int(s["fp"]) for s in scores)
    return (tp / gt if gt else float("nan"), tp / (tp + fp) if tp + fp else float("nan"), gt)


def threshold_table(groups: Sequence[tuple[str, Sequence[tuple[ClipExamples, np.ndarray]]]],
                    thresholds: Sequence[float]) -> str:
    """A Markdown table of recall / precision per threshold (rows) and group (columns), each
    group's clips scored with their confidences (clip, one confidence per track report)."""
    lines = ["| min_confidence | " + " | ".join(f"{name} recall / precision" for name, _ in groups) + " |",
             "|---:|" + "---:|" * len(groups)]
    for thr in sorted(set(thresholds)):
        cells = []
        for _, members in groups:
            r, p, _ = sum_scores([score_clip(ex, conf, thr) for ex, conf in members])
            cells.append(f"{r:.3f} / {p:.3f}")
        label = f"{thr:g}" + (" (paper: matched only)" if thr == 0 else "")
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def weights_yaml(bias: float, w: np.ndarray, min_confidence: float) -> str:
    lines = ["perception:", "  confidence:", f"    min_confidence: {min_confidence:g}",
             f"    bias: {bias:.4f}"]
    lines += [f"    w_{name}: {v:.4f}" for name, v in zip(FEATURES, w, strict=True)]
    return "\n".join(lines) + "\n"
