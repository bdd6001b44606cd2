"""``midair evaluate``: replay clips against their ground truth and score them.

Matching rule (stated in every report): a track matches a ground-truth object in the
same frame when their *centres* lie within a gate of ``max(gate_px, gate_scale × the
larger side of the ground-truth box)``. Centre distance is fair for this detector: its
boxes come from mask blobs (dilated, merged patches), looser than hand-drawn labels.
Matching within a frame is a minimum-distance assignment (py-motmetrics). Scene cuts
split a clip into segments scored separately, so an ID change at a cut is not a switch.

Metrics: recall and precision over frames × objects, MOTA and IDF1 (py-motmetrics).
"""

from __future__ import annotations

import csv
import logging
import math
import os
from collections.abc import Iterable
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass
from multiprocessing import get_context
from pathlib import Path

import numpy as np

from app.config import Config
from app.errors import SourceError, UsageError, UserError
from app.runtime.sources import open_source
from app.tools.replay import TrackRow, run_replay

log = logging.getLogger(__name__)

GATE_PX = 20.0  # smallest gate, px
GATE_SCALE = 1.0  # gate as a multiple of the GT box's larger side

Row = TrackRow


@dataclass(frozen=True)
class Clip:
    name: str
    video: Path
    gt: Path
    group: str  # what the clip is reported with, e.g. "halmstad/bird"
    cuts: tuple[int, ...] = ()  # 1-based first frames of new shots
    static_camera: bool = False


@dataclass
class ClipScore:
    clip: str
    group: str
    frames: int
    gt_rows: int
    hyp_rows: int
    tp: int
    fn: int
    fp: int
    id_switches: int
    recall: float
    precision: float
    mota: float
    idf1: float
    static_gt_rows: int  # GT rows of objects that do not move in the image (invisible to motion)
    median_ms: float


def read_boxes(path: Path) -> dict[int, list[tuple[int, float, float, float, float]]]:
    """``frame,id,x,y,w,h`` CSV (header line, frames 1-based) → rows per frame."""
    out: dict[int, list[tuple[int, float, float, float, float]]] = {}
    try:
        with path.open(newline="") as fh:
            reader = csv.reader(fh)
            header = next(reader, None)
            if header is None or [h.strip() for h in header[:6]] != ["frame", "id", "x", "y", "w", "h"]:
                raise SourceError(f"{path}: header must start with frame,id,x,y,w,h")
            for n, row in enumerate(reader, start=2):
                try:
                    f, i = int(row[0]), int(float(row[1]))
                    x, y, w, h = (float(v) for v in row[2:6])
                except (ValueError, IndexError):
                    raise SourceError(f"{path}: line {n} is not frame,id,x,y,w,h numbers") from None
                out.setdefault(f, []).append((i, x, y, w, h))
    except OSError as exc:
        raise SourceError(f"{path}: cannot be read: {exc.strerror}") from None
    return out


def static_rows(gt: dict[int, list[tuple[int, float, float, float, float]]], window: int = 5,
                px_per_frame: float = 0.3) -> int:
    """GT rows whose object's centre moves less than ``px_per_frame`` (averaged over
    ±``window`` frames): with a static camera a motion detector cannot see them."""
    centres: dict[int, dict[int, tuple[float, float]]] = {}
    for f, rows in gt.items():
        for i, x, y, w, h in rows:
            centres.setdefault(i, {})[f] = (x + w / 2, y + h / 2)
    n = 0
    for track in centres.values():
        for f in track:
            a, b = track.get(f - window), track.get(f + window)
            if a is None or b is None:
                continue
            if np.hypot(b[0] - a[0], b[1] - a[1]) / (2 * window) < px_per_frame:
                n += 1
    return n


def score(
    gt: dict[int, list[tuple[int, float, float, float, float]]],
    hyp: Iterable[Row],
    frames: int,
    cuts: tuple[int, ...] = (),
    gate_px: float = GATE_PX,
    gate_scale: float = GATE_SCALE,
) -> dict[str, float]:
    """Recall, precision, MOTA, IDF1 and counts of ``hyp`` against ``gt``."""
    import motmetrics as mm

    hyp_by_frame: dict[int, list[Row]] = {}
    for row in hyp:
        hyp_by_frame.setdefault(row[0], []).append(row)
    bounds = [1, *sorted(c for c in cuts if 1 < c <= frames), frames + 1]
    accs = []
    for start, stop in zip(bounds[:-1], bounds[1:], strict=True):
        acc = mm.MOTAccumulator(auto_id=True)
        for f in range(start, stop):
            g = gt.get(f, [])
            h = hyp_by_frame.get(f, [])
            d = np.full((len(g), len(h)), np.nan)
            for a, (_, gx, gy, gw, gh) in enumerate(g):
                gate = max(gate_px, gate_scale * max(gw, gh))
                for b, (_, _, hx, hy, hw, hh, _) in enumerate(h):
                    dist = np.hypot(gx + gw / 2 - hx - hw / 2, gy + gh / 2 - hy - hh / 2)
                    if dist <= gate:
                        d[a, b] = dist
            acc.update([r[0] for r in g], [r[1] for r in h], d)
        accs.append(acc)
    mh = mm.metrics.create()
    names = ["num_objects", "num_predictions", "num_misses", "num_false_positives",
             "num_switches", "mota", "idf1"]
    df = mh.compute_many(accs, metrics=names, names=[str(i) for i in range(len(accs))],
                         generate_overall=True)
    o = df.loc["OVERALL"]
    n_gt, n_hyp = int(o["num_objects"]), int(o["num_predictions"])
    fn, fp = int(o["num_misses"]), int(o["num_false_positives"])
    tp = n_gt - fn
    return {
        "gt_rows": n_gt, "hyp_rows": n_hyp, "tp": tp, "fn": fn, "fp": fp,
        "id_switches": int(o["num_switches"]),
        "recall": tp / n_gt if n_gt else float("nan"),
        "precision": tp / (tp + fp) if tp + fp else float("nan"),
        "mota": float(o["mota"]) if n_gt else float("nan"),
        "idf1": float(o["idf1"]) if n_gt else float("nan"),
    }


def evaluate_clip(clip: Clip, cfg: Config) -> ClipScore:
    import cv2

    cv2.setNumThreads(1)
    gt = read_boxes(clip.gt)
    source = open_source(clip.video)
    stats = run_replay(source, cfg, out_dir=None, video=False)
    s = score(gt, stats.track_rows, len(source), clip.cuts)
    total = stats.timings.get("total_ms", [float("nan")])
    return ClipScore(
        clip=clip.name, group=clip.group, frames=len(source),
        static_gt_rows=static_rows(gt) if clip.static_camera else 0,
        median_ms=float(np.median(total)), **s,  # type: ignore[arg-type]
    )


def find_clips(path: Path, gt: Path | None = None) -> list[Clip]:
    """One clip (a video or image folder with ``gt``), or every clip under a data folder
    (``clips.csv`` index if present; else ``*.mp4`` beside ``*.gt.csv`` and ``*/img`` beside
    ``*/gt.csv``)."""
    if not path.exists():
        raise SourceError(f"{path}: no such file or folder")
    if gt is not None:
        return [Clip(path.stem if path.is_file() else path.name, path, gt, "clip")]
    index = path / "clips.csv"
    if index.is_file():
        return _clips_from_index(path, index)
    if path.is_file():
        guess = path.with_suffix(".gt.csv")
        if not guess.exists():
            raise UserError(f"{path}: no ground truth found ({guess.name}); pass --gt FILE")
        return [Clip(path.stem, path, guess, "clip")]
    clips = [Clip(v.stem, v, v.with_suffix(".gt.csv"), path.name)
             for v in sorted(path.rglob("*.mp4")) if v.with_suffix(".gt.csv").exists()]
    clips += [Clip(d.parent.name, d, d.parent / "gt.csv", path.name)
              for d in sorted(path.rglob("img")) if (d.parent / "gt.csv").exists()]
    if not clips:
        raise UserError(f"{path}: no clip with ground truth found")
    return clips


def _clips_from_index(root: Path, index: Path) -> list[Clip]:
    clips = []
    with index.open(newline="") as fh:
        for row in csv.DictReader(fh):
            if not row.get("gt"):
                continue
            dataset = row["dataset"]
            video = root / row["path"]
            group = f"{dataset}/{row['objects']}" if dataset == "halmstad" else dataset
            cuts = tuple(int(c) for c in (row.get("cuts") or "").split())
            static = dataset == "halmstad" and float(row.get("cam_moving_frac") or 1) < 0.15
            # a video, a recording folder (its own name), or a Halmstad clip's img/ folder
            name = video.stem if video.is_file() else video.name if (video / "color.mp4").is_file() \
                else video.parent.name
            clips.append(Clip(name, video, root / row["gt"], group, cuts, static))
    return clips


def evaluate_all(clips: list[Clip], cfg: Config, workers: int | None = None) -> list[ClipScore]:
    workers = workers or os.cpu_count() or 1
    if workers == 1 or len(clips) == 1:
        return [evaluate_clip(c, cfg) for c in clips]
    # spawned, not forked: a fork after OpenCV's threads have run in this process can inherit
    # a held lock (`midair demo --ground-flights` renders before it scores)
    with ProcessPoolExecutor(max_workers=workers, mp_context=get_context("spawn")) as pool:
        return list(pool.map(evaluate_clip, clips, [cfg] * len(clips)))


# Groups summed in the report. The first is the one the quality target is set on.
TOTALS = (
    ("halmstad airplane+helicopter+bird", ("halmstad/airplane", "halmstad/helicopter", "halmstad/bird")),
    ("halmstad drone (static camera)", ("halmstad/drone",)),
    ("davis2016 (parallax)", ("davis2016",)),
)


def totals(scores: list[ClipScore]) -> list[dict[str, object]]:
    groups = {s.group for s in scores}
    named: list[tuple[str, tuple[str, ...]]] = [(n, g) for n, g in TOTALS if groups & set(g)]
    named += [(g, (g,)) for g in sorted(groups) if not any(g in gs for _, gs in TOTALS)]
    named.append(("all", tuple(sorted(groups))))
    out = []
    for name, members in named:
        ss = [s for s in scores if s.group in members]
        if not ss:
            continue
        gt = sum(s.gt_rows for s in ss)
        tp = sum(s.tp for s in ss)
        fp = sum(s.fp for s in ss)
        sw = sum(s.id_switches for s in ss)
        out.append({
            "group": name, "clips": len(ss), "gt_rows": gt, "tp": tp, "fp": fp,
            "id_switches": sw,
            "recall": tp / gt if gt else float("nan"),
            "precision": tp / (tp + fp) if tp + fp else float("nan"),
            # MOTA over the group: 1 - (FN + FP + IDSW) / GT
            "mota": 1 - ((gt - tp) + fp + sw) / gt if gt else float("nan"),
            "static_gt_rows": sum(s.static_gt_rows for s in ss),
        })
    return out


def format_tables(scores: list[ClipScore], sums: list[dict[str, object]]) -> str:
    lines = [
        f"Matching: centre distance <= max({GATE_PX:g} px, {GATE_SCALE:g} x larger GT box side); "
        "scene cuts split clips.",
        "",
        "| clip | group | frames | GT rows | recall | precision | MOTA | IDF1 | IDSW | static GT "
        "| ms/frame |",
        "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for s in scores:
        lines.append(
            f"| {s.clip} | {s.group} | {s.frames} | {s.gt_rows} | {s.recall:.3f} | {s.precision:.3f} "
            f"| {s.mota:.3f} | {s.idf1:.3f} | {s.id_switches} | {s.static_gt_rows} | {s.median_ms:.2f} |"
        )
    lines += ["", "| totals | clips | GT rows | recall | precision | MOTA | IDSW | static GT |",
              "|---|---:|---:|---:|---:|---:|---:|---:|"]
    for t in sums:
        lines.append(
            f"| {t['group']} | {t['clips']} | {t['gt_rows']} | {t['recall']:.3f} | "
            f"{t['precision']:.3f} | {t['mota']:.3f} | {t['id_switches']} | {t['static_gt_rows']} |"
        )
    return "\n".join(lines)


def write_reports(out_dir: Path, scores: list[ClipScore], sums: list[dict[str, object]]) -> None:
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "evaluation.md").write_text(format_tables(scores, sums) + "\n")
    with (out_dir / "evaluation.csv").open("w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(asdict(scores[0]).keys()))
        w.writeheader()
        for s in scores:
            w.writerow(asdict(s))


# ---------------------------------------------------------------- ground flights (app.sim.groundset)


@dataclass(frozen=True)
class ApproachShare:
    """How steadily perception reports an object coming at the vehicle once it has reported
    it (issue 19's target: in >= 95 % of its frames once confirmed)."""

    clip: str
    object_id: int
    frames_in_view: int  # labelled frames
    first_reported: int | None  # frame, None: never
    frames_after: int  # labelled frames from the first reported one on
    reported_after: int  # of them, frames with a reported track on it (evaluate's gate)

    @property
    def share(self) -> float | None:
        return self.reported_after / self.frames_after if self.frames_after else None


def _approach_shares(args: tuple[Path, Path, list[int], Config]) -> list[ApproachShare]:
    import cv2

    video, gt_path, ids, cfg = args

    cv2.setNumThreads(1)
    gt = read_boxes(gt_path)
    stats = run_replay(open_source(video), cfg, out_dir=None, video=False)
    hyp: dict[int, list[tuple[float, float]]] = {}
    for f, _tid, x, y, w, h, _c in stats.track_rows:
        hyp.setdefault(f, []).append((x + w / 2, y + h / 2))
    out = []
    for oid in ids:
        frames = sorted(f for f, rows in gt.items() if any(r[0] == oid for r in rows))
        hits = []
        for f in frames:
            _i, x, y, w, h = next(r for r in gt[f] if r[0] == oid)
            gate = max(GATE_PX, GATE_SCALE * max(w, h))
            hits.append(any(math.hypot(u - x - w / 2, v - y - h / 2) <= gate for u, v in hyp.get(f, [])))
        first = next((k for k, hit in enumerate(hits) if hit), None)
        after = hits[first:] if first is not None else []
        out.append(ApproachShare(video.stem, oid, len(frames), frames[first] if first is not None else None,
                                 len(after), sum(after)))
    return out


def approach_shares(folder: Path, cfg: Config, workers: int | None = None) -> list[ApproachShare]:
    """For every object of a ground-flight folder that comes at the vehicle (``objects.csv``):
    in how many of its labelled frames, from the first one perception reported it in, a
    reported track lay on it (the evaluation's matching rule)."""

    index = folder / "objects.csv"
    if not index.is_file():
        raise UsageError(f"{folder}: no objects.csv (not written by `midair demo --ground-flights`)")
    ids: dict[str, list[int]] = {}
    with index.open(newline="") as fh:
        for row in csv.DictReader(fh):
            if row["approaching"] == "1":
                ids.setdefault(row["clip"], []).append(int(row["id"]))
    jobs = [(folder / clip if (folder / clip).is_dir() else folder / f"{clip}.mp4", folder / f"{clip}.gt.csv",
             oids, cfg)
            for clip, oids in sorted(ids.items())]
    workers = workers or os.cpu_count() or 1
    if workers <= 1 or len(jobs) <= 1:
        results = [_approach_shares(j) for j in jobs]
    else:
        # spawned, not forked: a fork after OpenCV's threads have run can inherit a held lock
        # (seen: both workers asleep for good after the flights were rendered in the parent)
        with ProcessPoolExecutor(max_workers=workers, mp_context=get_context("spawn")) as pool:
            results = list(pool.map(_approach_shares, jobs))
    return [s for r in results for s in r]
