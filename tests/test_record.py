"""The flight record: bounded in size, flushed often, replayable."""

from __future__ import annotations

import json
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from app.config import Config, RecordConfig
from app.perception.frames import Frame
from app.runtime.record import MB, FlightRecord, folder_size
from app.runtime.sources import open_source

RNG = np.random.default_rng(5)


def noisy_frame(k: int) -> Frame:
    # noise does not compress: each colour PNG is ~0.9 MB, each depth PNG ~0.6 MB
    return Frame(k, 100.0 + k / 30.0, RNG.integers(0, 256, (480, 640, 3), dtype=np.uint8),
                 RNG.integers(0, 65535, (480, 640), dtype=np.uint16))


def old_run(parent: Path, name: str, mb: float) -> Path:
    run = parent / name
    run.mkdir(parents=True)
    (run / "meta.json").write_text("{}")
    (run / "blob").write_bytes(b"\0" * int(mb * MB))
    return run


def events(rec: FlightRecord) -> list[dict[str, object]]:
    return [json.loads(line) for line in (rec.folder / "events.jsonl").read_text().splitlines()]


def saving(tmp_path: Path, **kw: object) -> RecordConfig:
    return replace(RecordConfig(), dir=str(tmp_path), frames="color+depth", **kw)  # type: ignore[arg-type]


def test_frames_are_not_saved_by_default() -> None:
    assert RecordConfig().frames == "none"  # ~8 ms of CPU per frame: opt-in (docs/measurements.md)


def test_oldest_runs_go_first_and_frames_stop_at_the_limit(tmp_path: Path) -> None:
    runs = [old_run(tmp_path, f"2026-01-0{i}T00-00-00Z_1", 1.0) for i in range(1, 4)]
    (tmp_path / "notes.txt").write_text("not a run: never deleted")
    cfg = saving(tmp_path, max_total_mb=6.0, min_free_mb=0.0)
    rec = FlightRecord(cfg, Config()).start()
    assert all(r.exists() for r in runs)  # 3 MB fit under 6 MB
    for k in range(1, 9):
        rec.frame(noisy_frame(k))
        time.sleep(0.05)
    rec.close({"ended_by": "test"})
    assert not runs[0].exists() and not runs[1].exists() and not runs[2].exists()
    assert (tmp_path / "notes.txt").exists()
    total = folder_size(tmp_path)
    assert total <= 6.0 * MB + 0.1 * MB
    summary = json.loads((rec.folder / "summary.json").read_text())
    assert summary["record"]["frames_refused"] > 0 and 2 <= summary["record"]["frames_saved"] < 8
    stopped = [e for e in events(rec) if e["event"] == "record_frames_stopped"]
    assert stopped and "6 MB" in str(stopped[0]["why"])
    # what was saved is a consistent recording folder: frame numbers 1..n, images present
    rows = (rec.folder / "frames.csv").read_text().splitlines()
    assert rows[0] == "frame,t_s" and len(rows) - 1 == summary["record"]["frames_saved"]
    assert len(list((rec.folder / "color").iterdir())) == len(rows) - 1


def test_a_crash_loses_at_most_the_flush_interval(tmp_path: Path) -> None:
    cfg = saving(tmp_path, flush_s=0.2)
    rec = FlightRecord(cfg).start()
    rec.event("takeoff", altitude_m=5.0)
    rec.telemetry({"mode": "position"})
    time.sleep(0.5)
    # read from disk while the run goes on (as after a crash)
    assert '"takeoff"' in (rec.folder / "events.jsonl").read_text()
    assert '"position"' in (rec.folder / "telemetry.jsonl").read_text()
    rec.close()


def test_a_slow_disk_skips_frames_never_blocks(tmp_path: Path) -> None:
    cfg = saving(tmp_path, queue_frames=2, png_compression=9)
    rec = FlightRecord(cfg).start()
    t0 = time.monotonic()
    numbers = [rec.frame(noisy_frame(k)) for k in range(1, 31)]
    assert time.monotonic() - t0 < 1.0  # enqueueing 30 frames does not wait for the disk
    rec.close()
    saved = [n for n in numbers if n is not None]
    assert rec.frames_skipped == 30 - len(saved) > 0
    assert saved == list(range(1, len(saved) + 1))  # consecutive, as frames.csv requires
    src = open_source(rec.folder)
    assert len(src) == len(saved) and src.has_depth


def test_low_disk_space_stops_frames_but_not_the_logs(tmp_path: Path) -> None:
    cfg = saving(tmp_path, min_free_mb=1e12)  # no disk is that free
    rec = FlightRecord(cfg).start()
    assert rec.frame(noisy_frame(1)) == 1
    time.sleep(0.2)
    assert rec.frame(noisy_frame(2)) is None
    rec.event("still_logging")
    rec.close()
    kinds = [e["event"] for e in events(rec)]
    assert "record_frames_stopped" in kinds and "still_logging" in kinds
    assert not any((rec.folder / "color").iterdir())


def test_no_frames_when_asked_for_none(tmp_path: Path) -> None:
    rec = FlightRecord(replace(RecordConfig(), dir=str(tmp_path), frames="none")).start()
    assert rec.frame(noisy_frame(1)) is None
    rec.close()
    assert not (rec.folder / "color").exists() and (rec.folder / "summary.json").exists()
