from __future__ import annotations

import csv
import json
import subprocess
import sys
from pathlib import Path

import cv2
import pytest

from app.config import Config
from app.runtime.sources import open_source
from app.sim.synthetic import SyntheticObject, SyntheticScene, write_recording
from app.tools.evaluate import Clip, evaluate_clip, read_boxes, score
from app.tools.replay import run_replay

# Two objects against the sky that never come within a gate of each other: every miss is
# the method's own (warm-up, confirmation after noise_frames, the last frame's missing t+1).
SCENE = SyntheticScene(frames=90, seed=3, objects=(
    SyntheticObject(1, (100.0, 120.0), (3.0, 0.5), 18.0),
    SyntheticObject(2, (540.0, 60.0), (1.0, 0.3), 24.0),  # the background moves -2.5 px/frame
))


@pytest.fixture(scope="module")
def recording(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_recording(SCENE, tmp_path_factory.mktemp("rec") / "flight")


def test_replay_cli_writes_tracks_summary_and_video(recording: Path, tmp_path: Path) -> None:
    out = tmp_path / "out"
    proc = subprocess.run([sys.executable, "-m", "app.cli", "replay", str(recording), "--out", str(out)],
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    rows = list(csv.reader((out / "tracks.csv").open()))
    assert rows[0] == ["frame", "id", "x", "y", "w", "h", "conf", "wx", "wy", "wz"]
    assert len(rows) > 60
    assert all(r[7:] == ["-1", "-1", "-1"] and 1 <= int(r[0]) <= 90 for r in rows[1:])
    summary = json.loads((out / "summary.json").read_text())
    assert summary["frames"] == 89  # the last frame never gets its next frame
    assert set(summary["stages"]) == {"detection", "recognition", "tracking", "total"}
    cap = cv2.VideoCapture(str(out / "annotated.mp4"))
    assert int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) == 89
    ok, img = cap.read()
    assert ok and img.shape == (480, 640, 3)


def test_synthetic_objects_are_found_with_stable_ids(recording: Path) -> None:
    stats = run_replay(open_source(recording), Config(), out_dir=None, video=False)
    s = score(read_boxes(recording / "gt.csv"), stats.track_rows, 90)
    # at most 2 x (1 warm-up + 6 to confirm) + 2 last-frame rows of 180 can be missed
    assert s["recall"] >= (180 - 16) / 180 - 0.02
    assert s["precision"] > 0.95
    assert s["id_switches"] == 0


def test_a_real_clip_end_to_end(data_dir: Path) -> None:
    name = "V_DRONE_001"
    clip = Clip(name, data_dir / "halmstad_drone_dataset" / f"{name}.mp4",
                data_dir / "halmstad_drone_dataset" / f"{name}.gt.csv", "halmstad/drone")
    s = evaluate_clip(clip, Config())
    assert s.frames == 301
    assert s.recall > 0.9 and s.precision > 0.9


def test_demo_command_runs_the_embedded_default(tmp_path: Path) -> None:
    proc = subprocess.run([sys.executable, "-m", "app.cli", "demo", "--out", str(tmp_path),
                           "--frames", "40"], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert "against the truth: recall" in proc.stdout
    for name in ("annotated.mp4", "tracks.csv", "summary.json", "recording/color.mp4",
                 "recording/gt.csv", "recording/intrinsics.json", "recording/depth/000040.png"):
        assert (tmp_path / name).is_file(), name
    bad = subprocess.run([sys.executable, "-m", "app.cli", "demo", "--out", str(tmp_path),
                          "--frames", "3"], capture_output=True, text=True, timeout=60)
    assert bad.returncode == 2 and "--frames 3: must be at least 10" in bad.stderr
