"""Frame sources for replay: a video file, a folder of images, or a recording folder.

A *recording folder* holds ``color.mp4`` or ``color/`` (images sorted by name), and
optionally ``depth/000001.png …`` (uint16 depth units, 0 = no data), ``frames.csv``
(``frame,t_s``: 1-based frame number and capture time in seconds) and ``intrinsics.json``
(the colour and depth calibration, see :class:`app.camera.CameraModel`).

Every source yields :class:`app.perception.pipeline.Frame` with 8-bit BGR colour, whatever the
file held (grey, BGRA or 16-bit images are converted), and raises
:class:`app.errors.SourceError` with the file's name when something cannot be read.
"""

from __future__ import annotations

import csv
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np

from app.camera import CameraModel
from app.config import CaptureConfig
from app.errors import SourceError
from app.perception.frames import Frame, FrameSource, to_bgr8

IMAGE_EXTS = {".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".pgm", ".ppm", ".webp"}
DEFAULT_FPS = 30.0  # assumed for image folders without frames.csv


class VideoSource(FrameSource):
    def __init__(self, path: Path, fps: float | None = None, times: list[float] | None = None) -> None:
        self.path = path
        self.name = path.stem
        cap = cv2.VideoCapture(str(path))
        try:
            if not cap.isOpened():
                raise SourceError(f"{path}: cannot be opened as a video")
            ok, _ = cap.read()
            if not ok:
                raise SourceError(f"{path}: no frame could be decoded (empty or unreadable video)")
            self.fps = fps or cap.get(cv2.CAP_PROP_FPS) or DEFAULT_FPS
            self._count = int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
        finally:
            cap.release()
        self._times = times  # capture times from frames.csv, if any

    def __len__(self) -> int:
        return self._count

    def __iter__(self) -> Iterator[Frame]:
        cap = cv2.VideoCapture(str(self.path))
        try:
            i = 0
            while True:
                ok, img = cap.read()
                if not ok:
                    break
                i += 1
                t = self._times[i - 1] if self._times and i <= len(self._times) else (i - 1) / self.fps
                yield Frame(i, t, to_bgr8(img, f"{self.path} frame {i}"))
        finally:
            cap.release()


class ImageFolderSource(FrameSource):
    def __init__(self, folder: Path, fps: float | None = None,
                 times: list[float] | None = None) -> None:
        self.folder = folder
        self.name = folder.name if folder.name not in ("img", "color") else folder.parent.name
        files = sorted(p for p in folder.iterdir() if not p.name.startswith("."))
        for p in files:
            if p.is_dir() or p.suffix.lower() not in IMAGE_EXTS:
                raise SourceError(f"{folder}: {p.name} is not an image (expected only image files)")
        if not files:
            raise SourceError(f"{folder}: the folder holds no images")
        self.files = files
        self.fps = fps or DEFAULT_FPS
        self._times = times  # capture times from frames.csv, if any

    def __len__(self) -> int:
        return len(self.files)

    def __iter__(self) -> Iterator[Frame]:
        shape = None
        for i, p in enumerate(self.files, start=1):
            img = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
            if img is None:
                raise SourceError(f"{p}: cannot be decoded as an image")
            img = to_bgr8(img, str(p))
            if shape is None:
                shape = img.shape
            elif img.shape != shape:
                raise SourceError(
                    f"{p}: size {img.shape[1]}x{img.shape[0]} differs from the first image's "
                    f"{shape[1]}x{shape[0]}"
                )
            t = self._times[i - 1] if self._times and i <= len(self._times) else (i - 1) / self.fps
            yield Frame(i, t, img)


class RecordingSource(FrameSource):
    """``color.mp4`` or ``color/`` + optional ``depth/`` + optional ``frames.csv``."""

    def __init__(self, folder: Path) -> None:
        self.folder = folder
        self.name = folder.name
        times = read_frames_csv(folder / "frames.csv") if (folder / "frames.csv").exists() else None
        fps = None
        if times and len(times) > 1 and times[-1] > times[0]:
            fps = (len(times) - 1) / (times[-1] - times[0])
        color: FrameSource
        if (folder / "color.mp4").is_file():
            color = VideoSource(folder / "color.mp4", fps, times)
        elif (folder / "color").is_dir():
            color = ImageFolderSource(folder / "color", fps, times)
        else:
            raise SourceError(f"{folder}: a recording folder needs color.mp4 or color/")
        self.color = color
        self.fps = color.fps
        self.depth_dir = folder / "depth"
        self.has_depth = self.depth_dir.is_dir()
        if (folder / "intrinsics.json").is_file():
            self.camera = CameraModel.load(folder / "intrinsics.json")

    def __len__(self) -> int:
        return len(self.color)

    def __iter__(self) -> Iterator[Frame]:
        for f in self.color:
            depth = self._depth(f.index) if self.has_depth else None
            yield Frame(f.index, f.t_s, f.color, depth)

    def _depth(self, index: int) -> np.ndarray | None:
        p = self.depth_dir / f"{index:06d}.png"
        if not p.exists():
            return None  # no depth for this frame: "no data", never "close"
        d = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
        if d is None or d.dtype != np.uint16 or d.ndim != 2:
            raise SourceError(f"{p}: depth must be a single-channel 16-bit PNG in millimetres")
        return d


def read_frames_csv(path: Path) -> list[float]:
    """``frame,t_s`` rows → capture times in frame order."""
    times: list[float] = []
    try:
        with path.open(newline="") as fh:
            rows = csv.DictReader(fh)
            if rows.fieldnames is None or not {"frame", "t_s"} <= set(rows.fieldnames):
                raise SourceError(f"{path}: header must be frame,t_s")
            for n, row in enumerate(rows, start=1):
                try:
                    frame, t = int(row["frame"]), float(row["t_s"])
                except (TypeError, ValueError):
                    raise SourceError(f"{path}: line {n + 1} is not frame,t_s numbers") from None
                if frame != n:
                    raise SourceError(f"{path}: line {n + 1} has frame {frame}, expected {n}")
                times.append(t)
    except OSError as exc:
        raise SourceError(f"{path}: cannot be read: {exc.strerror}") from None
    return times


def open_source(path: str | Path, fps: float | None = None,
                capture: CaptureConfig | None = None) -> FrameSource:
    """A video file, an image folder, a recording folder or a RealSense recording
    (``.db3``/``.bag``, needs pyrealsense2), chosen by what ``path`` is."""
    p = Path(path)
    if not p.exists():
        raise SourceError(f"{p}: no such file or folder")
    if p.is_file() and p.suffix.lower() in (".db3", ".bag"):
        from hardware.realsense import RealSenseSource

        return RealSenseSource(capture or CaptureConfig(), p)
    if p.is_dir():
        if (p / "color.mp4").exists() or (p / "color").is_dir():
            return RecordingSource(p)
        return ImageFolderSource(p, fps)
    return VideoSource(p, fps)
