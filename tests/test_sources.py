from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from app.errors import SourceError
from app.runtime.sources import open_source


def _run(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "app.cli", *args], capture_output=True,
                          text=True, timeout=120)


def test_missing_path(tmp_path: Path) -> None:
    with pytest.raises(SourceError, match="no such file or folder"):
        open_source(tmp_path / "nothing.mp4")


def test_unreadable_and_empty_video(tmp_path: Path) -> None:
    junk = tmp_path / "junk.mp4"
    junk.write_bytes(b"this is not a video" * 100)
    with pytest.raises(SourceError, match="junk.mp4"):
        open_source(junk)
    empty = tmp_path / "empty.mp4"
    empty.write_bytes(b"")
    with pytest.raises(SourceError, match="empty.mp4"):
        open_source(empty)


def test_folder_with_a_non_image_file(tmp_path: Path) -> None:
    cv2.imwrite(str(tmp_path / "000001.png"), np.zeros((10, 10), np.uint8))
    (tmp_path / "notes.txt").write_text("hello")
    with pytest.raises(SourceError, match="notes.txt is not an image"):
        open_source(tmp_path)


def test_grey_and_colour_images_both_become_bgr(tmp_path: Path) -> None:
    cv2.imwrite(str(tmp_path / "a.png"), np.full((20, 30), 90, np.uint8))
    cv2.imwrite(str(tmp_path / "b.png"), np.full((20, 30, 3), 90, np.uint8))
    cv2.imwrite(str(tmp_path / "c.png"), np.full((20, 30), 90 * 256, np.uint16))
    frames = list(open_source(tmp_path, fps=10))
    assert [f.color.shape for f in frames] == [(20, 30, 3)] * 3
    assert all(int(f.color[0, 0, 0]) == 90 for f in frames)
    assert [f.t_s for f in frames] == [0.0, 0.1, 0.2]


def test_images_of_different_sizes(tmp_path: Path) -> None:
    cv2.imwrite(str(tmp_path / "a.png"), np.zeros((20, 30), np.uint8))
    cv2.imwrite(str(tmp_path / "b.png"), np.zeros((21, 30), np.uint8))
    with pytest.raises(SourceError, match="b.png: size 30x21 differs"):
        list(open_source(tmp_path))


def test_recording_folder_with_depth_and_times(tmp_path: Path) -> None:
    (tmp_path / "color").mkdir()
    (tmp_path / "depth").mkdir()
    for i in (1, 2):
        cv2.imwrite(str(tmp_path / "color" / f"{i:06d}.png"), np.zeros((10, 12, 3), np.uint8))
        cv2.imwrite(str(tmp_path / "depth" / f"{i:06d}.png"), np.full((10, 12), 1500 * i, np.uint16))
    (tmp_path / "frames.csv").write_text("frame,t_s\n1,10.0\n2,10.02\n")
    src = open_source(tmp_path)
    frames = list(src)
    assert src.has_depth and abs(src.fps - 50) < 1e-6
    assert [f.t_s for f in frames] == [10.0, 10.02]
    assert frames[1].depth is not None and int(frames[1].depth[0, 0]) == 3000


def test_bad_frames_csv(tmp_path: Path) -> None:
    (tmp_path / "color").mkdir()
    cv2.imwrite(str(tmp_path / "color" / "1.png"), np.zeros((10, 12, 3), np.uint8))
    (tmp_path / "frames.csv").write_text("frame,time\n1,0\n")
    with pytest.raises(SourceError, match="frames.csv: header must be frame,t_s"):
        open_source(tmp_path)


def test_cli_user_errors_exit_3_without_traceback(tmp_path: Path) -> None:
    junk = tmp_path / "junk.mp4"
    junk.write_bytes(b"\x00" * 1000)
    proc = _run("replay", str(junk), "--out", str(tmp_path / "o"))
    assert proc.returncode == 3
    assert "junk.mp4" in proc.stderr and "Traceback" not in proc.stderr

    small = tmp_path / "small"
    small.mkdir()
    for i in range(3):
        cv2.imwrite(str(small / f"{i}.png"), np.zeros((100, 150), np.uint8))
    proc = _run("replay", str(small), "--out", str(tmp_path / "o2"))
    assert proc.returncode == 3
    assert "frame 150x100 is too small for the detection windows" in proc.stderr
    assert "Traceback" not in proc.stderr
