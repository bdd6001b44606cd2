"""The flight record: what one ``midair fly`` run saw, decided and did, on disk.

Each run gets a folder ``<record.dir>/<UTC start>_<pid>/`` holding

- ``meta.json``: start time (UTC and monotonic, so every ``t`` below maps to wall time),
  version, configuration, camera calibration;
- ``events.jsonl``, ``telemetry.jsonl``, ``decisions.jsonl``, ``tracks.jsonl``,
  ``latency.jsonl``: one JSON object per line, each with ``t`` = seconds since the run
  started on the monotonic clock;
- a *recording folder* (``color/000001.png``, ``depth/000001.png``, ``frames.csv``,
  ``intrinsics.json``) of the frames perception processed, in order, which
  ``midair replay`` reads back; and ``tracks.csv``, the confirmed tracks in the same MOT form
  as replay writes (so a replay of the record can be compared line by line);
- ``summary.json`` at the end (frame counts, latency percentiles, why the run ended).

Writing happens in one background thread: the event loop and the perception thread only
enqueue. Files are flushed and fsync'ed every ``flush_s``, so a crash or power cut loses at
most that much. Size is bounded: all runs together stay under ``max_total_mb`` (the oldest
runs are deleted first; when this run alone would exceed it, or the disk's free space falls
below ``min_free_mb``, frames stop being saved — the text logs go on), and when the writer
falls behind by ``queue_frames`` frames, frames are skipped and counted, never the flight.
"""

from __future__ import annotations

import csv
import dataclasses
import json
import logging
import math
import os
import queue
import shutil
import threading
import time
from datetime import UTC, datetime
from pathlib import Path
from typing import IO, Any

import cv2
import numpy as np

from app import __version__
from app.camera import CameraModel
from app.config import Config, RecordConfig, to_yaml
from app.perception.frames import Frame
from app.perception.mot import MOT_HEADER, mot_row

log = logging.getLogger(__name__)

MB = 1024 * 1024
WRITER_NICE = 10  # the writer thread's niceness (Linux: per thread), relative to the rest
_STREAMS = ("events", "telemetry", "decisions", "latency", "tracks")


def folder_size(path: Path) -> int:
    total = 0
    for root, _dirs, files in os.walk(path):
        for name in files:
            try:
                total += (Path(root) / name).stat().st_size
            except OSError:
                pass
    return total


def _runs(parent: Path, exclude: Path | None = None) -> list[Path]:
    """Run folders, oldest first (their names start with the UTC start time)."""
    if not parent.is_dir():
        return []
    return sorted(p for p in parent.iterdir()
                  if p.is_dir() and (p / "meta.json").exists() and p != exclude)


class FlightRecord:
    """One run's record. ``start()`` once, then any thread may call the ``log`` methods;
    ``close()`` at the end."""

    def __init__(self, cfg: RecordConfig, config: Config | None = None,
                 camera: CameraModel | None = None) -> None:
        self.cfg = cfg
        self.parent = Path(cfg.dir)
        stamp = datetime.now(UTC).strftime("%Y-%m-%dT%H-%M-%SZ")
        self.folder = self.parent / f"{stamp}_{os.getpid()}"
        self.t0 = time.monotonic()
        self._config = config
        self._camera = camera
        self._queue: queue.Queue[tuple[str, Any] | None] = queue.Queue()
        self._pending_frames = 0
        self._lock = threading.Lock()
        self._thread: threading.Thread | None = None
        self._numbered = 0  # frames given a number in the record
        self._last_saved = 0  # the newest frame number on disk
        self.frames_skipped = 0  # the writer was behind
        self.frames_refused = 0  # size limit or disk space
        self._saving = cfg.frames != "none"
        self._written = 0  # bytes of this run (frames; text is small and counted at flush)
        self._others = 0  # bytes of the other runs still on disk
        self.error: str | None = None

    # ------------------------------------------------------------------ life cycle

    def start(self) -> FlightRecord:
        self.parent.mkdir(parents=True, exist_ok=True)
        self._others = self._prune(0)
        self.folder.mkdir()
        if self.cfg.frames != "none":
            (self.folder / "color").mkdir()
            if self.cfg.frames == "color+depth":
                (self.folder / "depth").mkdir()
        meta = {
            "version": __version__, "pid": os.getpid(),
            "start_utc": datetime.now(UTC).isoformat(timespec="milliseconds"),
            "start_monotonic_s": self.t0,
            "note": "every 't' in the .jsonl files is seconds since start_monotonic_s",
        }
        (self.folder / "meta.json").write_text(json.dumps(meta, indent=2) + "\n")
        if self._config is not None:
            (self.folder / "config.yaml").write_text(to_yaml(self._config))
        if self._camera is not None:
            self.set_camera(self._camera)
        self._thread = threading.Thread(target=self._writer, name="record", daemon=True)
        self._thread.start()
        log.info("flight record: %s", self.folder)
        return self

    def set_camera(self, camera: CameraModel) -> None:
        (self.folder / "intrinsics.json").write_text(json.dumps(camera.to_json(), indent=2) + "\n")

    def close(self, summary: dict[str, object] | None = None) -> None:
        if self._thread is None:
            return
        self._queue.put(None)
        self._thread.join(timeout=30.0)
        self._thread = None
        out = dict(summary or {})
        out["record"] = {"frames_saved": self.frames_saved, "frames_skipped": self.frames_skipped,
                         "frames_refused": self.frames_refused,
                         "size_mb": round(folder_size(self.folder) / MB, 2)}
        if self.error:
            out["record"]["error"] = self.error  # type: ignore[index]
        (self.folder / "summary.json").write_text(json.dumps(out, indent=2, default=str) + "\n")

    @property
    def frames_saved(self) -> int:
        return self._numbered - self.frames_refused - self._pending_frames

    def t(self, monotonic_s: float | None = None) -> float:
        return round((time.monotonic() if monotonic_s is None else monotonic_s) - self.t0, 6)

    # ------------------------------------------------------------------ what gets logged

    def event(self, kind: str, **fields: object) -> None:
        self._line("events", {"t": self.t(), "event": kind, **fields})

    def telemetry(self, fields: dict[str, object]) -> None:
        self._line("telemetry", {"t": self.t(), **fields})

    def decision(self, fields: dict[str, object]) -> None:
        self._line("decisions", {"t": self.t(), **fields})

    def latency(self, fields: dict[str, object]) -> None:
        self._line("latency", {"t": self.t(), **fields})

    def frame(self, frame: Frame) -> int | None:
        """Queue a processed frame for saving; returns its number in the record (1-based),
        or None when it is not saved."""
        if not self._saving:
            return None
        with self._lock:
            if self._pending_frames >= self.cfg.queue_frames:
                self.frames_skipped += 1
                return None
            self._pending_frames += 1
            self._numbered += 1
            number = self._numbered
        # frames.csv keeps perception's clock, so that the record replays to the tracks flown:
        # the record's clock for a live camera, the recording's own for one played as camera
        t_frame = frame.t_s if not math.isnan(frame.t_arrived_s) else self.t(frame.t_s)
        self._queue.put(("frame", (number, t_frame, frame)))
        return number

    def tracks(self, frame: int, t_capture: float, record_frame: int | None,
               boxes: list[tuple[int, float, float, float, float, float, bool]]) -> None:
        """Confirmed tracks of a processed frame, matched or reported: (id, x, y, w, h,
        confidence, reported) with (x, y) the top-left corner, px. All to ``tracks.jsonl``;
        for a saved frame the reported ones also to ``tracks.csv`` under its number."""
        self._line("tracks", {"t": self.t(), "frame": frame, "t_capture": self.t(t_capture),
                              "tracks": [[tid, round(x, 1), round(y, 1), round(w, 1), round(h, 1),
                                          round(c, 3), r] for tid, x, y, w, h, c, r in boxes]})
        if record_frame is not None and self._thread is not None:
            self._queue.put(("mot", (record_frame, boxes)))

    def _line(self, stream: str, obj: dict[str, object]) -> None:
        if self._thread is not None:
            self._queue.put((stream, obj))

    # ------------------------------------------------------------------ the writer thread

    def _writer(self) -> None:
        try:  # the disk can wait, the flight cannot: this thread yields the CPU to the others
            os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), WRITER_NICE)
        except (AttributeError, OSError) as exc:
            log.debug("record writer priority unchanged: %s", exc)
        files: dict[str, IO[str]] = {s: (self.folder / f"{s}.jsonl").open("a") for s in _STREAMS}
        frames_csv = mot_csv = None
        if self.cfg.frames != "none":
            frames_csv = (self.folder / "frames.csv").open("a", newline="")
            csv.writer(frames_csv).writerow(["frame", "t_s"])
            mot_csv = (self.folder / "tracks.csv").open("a", newline="")
            csv.writer(mot_csv).writerow(MOT_HEADER)
        extra = [f for f in (frames_csv, mot_csv) if f is not None]
        last_flush = time.monotonic()
        try:
            while True:
                timeout = max(0.0, last_flush + self.cfg.flush_s - time.monotonic())
                try:
                    item = self._queue.get(timeout=timeout)
                except queue.Empty:
                    item = ("flush", None)
                if item is None:
                    # What this thread queued itself after close() queued the end (the event
                    # that frames are no longer saved, when the last frames hit the limit) is
                    # written too: it came after the end only because this thread was behind.
                    while True:
                        try:
                            rest = self._queue.get_nowait()
                        except queue.Empty:
                            break
                        if rest is not None:
                            self._handle(*rest, files, frames_csv, mot_csv)
                    break
                self._handle(*item, files, frames_csv, mot_csv)
                if time.monotonic() - last_flush >= self.cfg.flush_s:
                    self._flush([*files.values(), *extra])
                    last_flush = time.monotonic()
        except Exception as exc:  # a full or failing disk must not take the flight down
            self.error = f"{type(exc).__name__}: {exc}"
            log.error("flight record stopped: %s", self.error)
            self._saving = False
            while self._queue.get() is not None:  # keep the queue from growing; exit on close
                pass
        finally:
            self._flush([*files.values(), *extra])
            for fh in [*files.values(), *extra]:
                fh.close()

    def _handle(self, kind: str, payload: Any, files: dict[str, IO[str]], frames_csv: IO[str] | None,
                mot_csv: IO[str] | None) -> None:
        """Write one queued item (in the writer thread)."""
        if kind == "frame":
            self._save_frame(payload, frames_csv)
        elif kind == "mot" and mot_csv is not None:
            number, boxes = payload
            if number <= self._last_saved:  # its frame is on disk (in queue order)
                rows = csv.writer(mot_csv)
                for tid, x, y, w, h, c, reported in boxes:
                    if reported:
                        rows.writerow(mot_row(number, tid, x, y, w, h, c))
        elif kind in files:
            files[kind].write(json.dumps(payload, default=_jsonable) + "\n")

    def _save_frame(self, payload: tuple[int, float, Frame], frames_csv: IO[str] | None) -> None:
        number, t, frame = payload
        try:
            if not self._saving:
                self.frames_refused += 1
                return
            params = [cv2.IMWRITE_PNG_COMPRESSION, self.cfg.png_compression]
            ok, color = cv2.imencode(".png", frame.color, params)
            if not ok:
                raise OSError(f"PNG encoding of frame {number} failed")
            depth = None
            if self.cfg.frames == "color+depth" and frame.depth is not None:
                ok, depth = cv2.imencode(".png", frame.depth, params)
                if not ok:
                    raise OSError(f"PNG encoding of depth frame {number} failed")
            size = len(color) + (len(depth) if depth is not None else 0)
            if not self._room(size):
                self.frames_refused += 1
                return
            name = f"{number:06d}.png"
            (self.folder / "color" / name).write_bytes(color.tobytes())
            if depth is not None:
                (self.folder / "depth" / name).write_bytes(depth.tobytes())
            self._written += size
            if frames_csv is not None:
                frames_csv.write(f"{number},{t:.6f}\n")
            self._last_saved = number
        finally:
            with self._lock:
                self._pending_frames -= 1

    def _room(self, size: int) -> bool:
        """May ``size`` more bytes be written? Deletes older runs to make room."""
        limit = self.cfg.max_total_mb * MB
        text = 64 * 1024  # headroom for the text logs still to come
        if self._others + self._written + size + text > limit:
            self._others = self._prune(self._written + size + text)
        if self._others + self._written + size + text > limit:
            self._stop_saving(f"the record limit of {self.cfg.max_total_mb:g} MB is reached")
            return False
        if self._numbered % 30 == 1 or self._written == 0:  # a statvfs now and then
            free = shutil.disk_usage(self.parent).free
            if free - size < self.cfg.min_free_mb * MB:
                self._stop_saving(f"the disk has only {free / MB:.0f} MB free")
                return False
        return True

    def _stop_saving(self, why: str) -> None:
        self._saving = False
        log.warning("flight record: frames no longer saved: %s", why)
        self.event("record_frames_stopped", why=why)

    def _prune(self, own_bytes: int) -> int:
        """Delete the oldest other runs until they and ``own_bytes`` fit; return their size."""
        runs = _runs(self.parent, exclude=self.folder)
        sizes = [folder_size(r) for r in runs]
        limit = self.cfg.max_total_mb * MB
        while runs and sum(sizes) + own_bytes > limit:
            oldest = runs.pop(0)
            sizes.pop(0)
            log.info("flight record: deleting the oldest run %s to stay under %g MB",
                     oldest.name, self.cfg.max_total_mb)
            shutil.rmtree(oldest, ignore_errors=True)
        return sum(sizes)

    @staticmethod
    def _flush(files: list[IO[str]]) -> None:
        for fh in files:
            fh.flush()
            os.fsync(fh.fileno())


def _jsonable(obj: object) -> object:
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return dataclasses.asdict(obj)
    if isinstance(obj, np.ndarray | np.generic):
        return obj.tolist()
    return str(obj)
