"""``midair replay``: run perception over a recorded source and write what it found.

Outputs in the chosen folder:

- ``tracks.csv``: MOT-challenge rows ``frame,id,x,y,w,h,conf,-1,-1,-1`` (frames 1-based,
  confirmed tracks matched in that frame only);
- ``summary.json``: frames, statuses, per-stage median/p95 ms, frames per second;
- ``annotated.mp4`` (unless disabled): mask outline, clusters, tracks with IDs and trails;
  with depth also the safe window, each object's distance and the decision;
- ``decisions.csv`` when the source has depth: ``frame,action,forward_mps,right_mps,
  down_mps,object_id`` for every processed frame.
"""

from __future__ import annotations

import csv
import json
import logging
import sys
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TextIO

import cv2
import numpy as np

from app.camera import camera_from_config
from app.config import Config
from app.decision.policy import Command, DecisionMaker
from app.errors import SourceError
from app.perception.frames import FrameSource
from app.perception.mot import MOT_HEADER, mot_row
from app.perception.pipeline import Perception, PerceptionResult
from app.tools.annotate import annotate

log = logging.getLogger(__name__)

TrackRow = tuple[int, int, float, float, float, float, float]  # frame, id, x, y, w, h px, confidence


@dataclass
class ReplayStats:
    frames: int = 0
    statuses: Counter[str] = field(default_factory=Counter)
    timings: dict[str, list[float]] = field(default_factory=dict)
    track_rows: list[TrackRow] = field(default_factory=list)
    decisions: list[tuple[int, Command]] = field(default_factory=list)
    wall_s: float = 0.0

    def add(self, r: PerceptionResult) -> None:
        self.frames += 1
        self.statuses[r.status] += 1
        for k, v in r.timings_ms.items():
            self.timings.setdefault(k, []).append(v)
        for t in r.tracks:
            if t.reported:
                x, y, w, h = t.box
                self.track_rows.append((r.frame.index, t.track_id, x, y, w, h, t.confidence))

    def summary(self, source: FrameSource) -> dict[str, object]:
        stages = {
            k.removesuffix("_ms"): {
                "median_ms": round(float(np.median(v)), 3),
                "p95_ms": round(float(np.percentile(v, 95)), 3),
            }
            for k, v in self.timings.items()
        }
        return {
            "source": source.name,
            "frames": self.frames,
            "source_fps": round(source.fps, 3),
            "statuses": dict(self.statuses),
            "confirmed_ids": len({row[1] for row in self.track_rows}),
            "track_rows": len(self.track_rows),
            "stages": stages,
            "processing_fps": round(self.frames / self.wall_s, 1) if self.wall_s > 0 else None,
            "decisions": dict(Counter(c.action for _, c in self.decisions)) if self.decisions else None,
        }


def run_replay(
    source: FrameSource,
    cfg: Config,
    out_dir: Path | None = None,
    video: bool = True,
    progress: Callable[[int, int], None] | None = None,
    altitude_m: float | None = None,
) -> ReplayStats:
    """Run perception (and, with depth, the decision) over every frame of ``source``;
    write outputs if ``out_dir`` is given. ``altitude_m`` stands in for the flight side's
    altitude above home (None: unknown, so no downward escape)."""
    decider = None
    if source.has_depth:
        decider = DecisionMaker.for_perception(cfg.decision, source.camera or camera_from_config(cfg.camera),
                                               cfg.perception.detection)
    perception = Perception(cfg.perception, camera=decider.camera if decider is not None else None)
    stats = ReplayStats()
    writer: cv2.VideoWriter | None = None
    video_path = out_dir / "annotated.mp4" if out_dir is not None else None
    if out_dir is not None:
        out_dir.mkdir(parents=True, exist_ok=True)
    total = len(source)
    t_start = time.perf_counter()
    n_in = 0
    try:
        for frame in source:
            n_in += 1
            result = perception.push(frame)
            if progress is not None:
                progress(n_in, total)
            if result is None:
                continue
            stats.add(result)
            command, objects = None, None
            if decider is not None:
                command, objects = decider.step(result.tracks, result.frame.depth,
                                                result.frame.t_s, altitude_m)
                stats.decisions.append((result.frame.index, command))
            if video and video_path is not None:
                img = annotate(result, decision=(command, objects, decider) if decider else None)
                if writer is None:
                    writer = _open_writer(video_path, source.fps, img.shape[1], img.shape[0])
                writer.write(img)
    finally:
        if writer is not None:
            writer.release()
    stats.wall_s = time.perf_counter() - t_start
    if n_in == 0:
        raise SourceError(f"{source.name}: the source yielded no frames")
    if out_dir is not None:
        write_tracks_csv(out_dir / "tracks.csv", stats.track_rows)
        if decider is not None:
            write_decisions_csv(out_dir / "decisions.csv", stats.decisions)
        (out_dir / "summary.json").write_text(json.dumps(stats.summary(source), indent=2) + "\n")
    return stats


def _open_writer(path: Path, fps: float, width: int, height: int) -> cv2.VideoWriter:
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter.fourcc(*"mp4v"), fps, (width, height))
    if not writer.isOpened():
        raise SourceError(f"{path}: cannot open a video writer (mp4v)")
    return writer


def write_tracks_csv(path: Path, rows: list[TrackRow]) -> None:
    tmp = path.with_suffix(".csv.tmp")
    with tmp.open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(MOT_HEADER)
        for frame, tid, x, y, bw, bh, conf in rows:
            w.writerow(mot_row(frame, tid, x, y, bw, bh, conf))
    tmp.replace(path)


def write_decisions_csv(path: Path, rows: list[tuple[int, Command]]) -> None:
    tmp = path.with_suffix(".csv.tmp")
    with tmp.open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["frame", "action", "forward_mps", "right_mps", "down_mps", "object_id"])
        for frame, c in rows:
            w.writerow([frame, c.action, f"{c.forward_mps:.3f}", f"{c.right_mps:.3f}",
                        f"{c.down_mps:.3f}", "" if c.object_id is None else c.object_id])
    tmp.replace(path)


class ProgressBar:
    """tqdm's bar over the frames of a replay (with its rate and ETA); on a terminal only."""

    def __init__(self, label: str, stream: TextIO | None = None) -> None:
        from tqdm import tqdm

        # sys.stderr when called, not when imported: a default bound at import keeps a stream
        # that may since have been replaced and closed (a test's capture did)
        self.bar = tqdm(desc=label, unit="frame", file=stream or sys.stderr, disable=None, dynamic_ncols=True,
                        mininterval=0.2)

    def __call__(self, done: int, total: int) -> None:
        if total > 0 and self.bar.total != total:
            self.bar.total = total
        self.bar.update(done - self.bar.n)

    def close(self) -> None:
        self.bar.close()
