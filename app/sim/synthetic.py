"""A synthetic flight: a moving camera over a textured world with small flying objects.

Used as the embedded default (no camera needed), by the benchmark and by tests that need
frames with exact ground truth. Deterministic for a given seed.

The world is a large texture (sky gradient with soft clouds above a textured treeline
and ground). The camera pans, tilts and rolls slowly over it: frame t is the world seen
through a homography. Objects are dark ellipses with their own image motion, drawn after
the warp, so their motion relative to the background is known exactly.
"""

from __future__ import annotations

import csv
import json
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from app.camera import CameraModel, Intrinsics
from app.perception.frames import Frame, FrameSource
from app.sim.world import draw_object


@dataclass(frozen=True)
class SyntheticObject:
    object_id: int
    start_xy: tuple[float, float]  # image px at frame 1
    velocity: tuple[float, float]  # image px/frame, relative to the image
    size_px: float  # ellipse major axis at frame 1, px
    growth: float = 1.0  # size multiplier per frame (an approaching object grows)
    start_m: float = 30.0  # distance at frame 1, m (for the depth frame)
    closing_mps: float = 0.0  # how fast the distance shrinks, m/s
    brightness: int = 40  # grey level of the object


@dataclass(frozen=True)
class SyntheticObject3D:
    """An object moving in colour-camera XYZ (m; X right, Y down, Z forward), projected
    with the scene's intrinsics: its image size and depth follow its distance exactly."""

    object_id: int
    start_xyz_m: tuple[float, float, float]
    velocity_mps: tuple[float, float, float]
    diameter_m: float = 0.3
    brightness: int = 40
    t0_s: float = 0.0  # it appears at this scene time (at start_xyz_m), s


@dataclass(frozen=True)
class SyntheticScene:
    width: int = 640
    height: int = 480
    fps: float = 30.0
    frames: int = 150
    seed: int = 1
    pan_px_per_frame: float = 2.5  # camera pan: the background moves -2.5 px/frame in x
    noise_std: float = 1.5  # sensor noise, grey levels
    objects: tuple[SyntheticObject, ...] = (
        SyntheticObject(1, (120.0, 150.0), (3.0, 0.8), 18.0),
        SyntheticObject(2, (520.0, 300.0), (-0.5, -1.2), 26.0, growth=1.004,
                        start_m=20.0, closing_mps=3.0),
    )
    objects_3d: tuple[SyntheticObject3D, ...] = ()
    first_frame: int = 0  # 0-based number of the scene's first frame (a scene continued)

    def camera(self) -> CameraModel:
        """Colour intrinsics of a D435i-like lens at this resolution; depth aligned to it."""
        intr = Intrinsics(640, 480, 615.0, 615.0, 319.5, 239.5).scaled_to(self.width, self.height)
        return CameraModel(intr, intr)


def approach_scene(start_xyz_m: tuple[float, float, float], closing_mps: float = 4.0,
                   frames: int = 75, seed: int = 2, diameter_m: float = 0.3,
                   lateral_mps: tuple[float, float] = (0.0, 0.0), fps: float = 30.0) -> SyntheticScene:
    """One object flying at the camera (a ball thrown at the drone), over a still camera."""
    return SyntheticScene(
        fps=fps, frames=frames, seed=seed, pan_px_per_frame=0.5, objects=(),
        objects_3d=(SyntheticObject3D(1, start_xyz_m, (lateral_mps[0], lateral_mps[1], -closing_mps),
                                      diameter_m),),
    )


def _world(scene: SyntheticScene, rng: np.random.Generator) -> np.ndarray:
    """Grey world texture, about 2x the frame, horizon 60 % down."""
    h, w = scene.height * 2, scene.width * 3
    y = np.linspace(0, 1, h)[:, None]
    sky: np.ndarray = 200 - 40 * y + np.zeros((h, w))
    clouds = cv2.GaussianBlur(rng.normal(0, 1, (h // 8, w // 8)), (0, 0), 3)
    clouds = cv2.resize(clouds, (w, h), interpolation=cv2.INTER_CUBIC)
    sky += 25 * clouds / (np.abs(clouds).max() + 1e-9)
    horizon = int(h * 0.6)
    ground_noise = rng.normal(0, 1, (h - horizon, w))
    ground = 90 + 30 * cv2.GaussianBlur(ground_noise, (0, 0), 1.2) / 0.3
    # a ragged treeline
    tops = horizon - (20 + 15 * np.abs(np.sin(np.arange(w) / 17.0)) + rng.integers(0, 10, w))
    img = sky
    img[horizon:] = ground
    cols = np.arange(w)
    for x in cols[::1]:
        t = int(tops[x])
        img[t:horizon, x] = 70 + rng.normal(0, 12, horizon - t)
    # the lens's blur: real frames carry no detail finer than about a pixel
    return cv2.GaussianBlur(np.clip(img, 0, 255).astype(np.uint8), (0, 0), 1.0)


def ball_scene(fps: float = 30.0) -> SyntheticScene:
    """The desk demo: a 0.3 m ball thrown from 12.8 m at the upper left at 4 m/s, over a
    still camera; 3.67 s (110 frames at 30 fps), dodged about 3 s in."""
    return approach_scene((-0.4, -0.3, 12.8), closing_mps=4.0, frames=int(round(3.67 * fps)),
                          fps=fps)


class SyntheticSource(FrameSource):
    """A scene rendered frame by frame as the camera (no files): colour, depth, calibration."""

    def __init__(self, scene: SyntheticScene, name: str = "synthetic") -> None:
        self.scene = scene
        self.name = name
        self.fps = scene.fps
        self.has_depth = True
        self.camera = scene.camera()

    def __len__(self) -> int:
        return self.scene.frames

    def __iter__(self) -> Iterator[Frame]:
        for frame, _truth in render(self.scene):
            yield frame


class ThrowsSource(FrameSource):
    """Balls thrown at a hovering vehicle now and then, rendered live, until stopped (or
    for ``seconds``): a desk run of ``midair fly`` long enough to watch shadow mode or the
    service. Each throw starts 9-14 m out within the view and closes at 3-6 m/s, aimed to
    pass within 0.5 m; 2-6 s of quiet sky lie between throws. Deterministic for ``seed``.
    """

    CHUNK_FRAMES = 9000  # rendered as scenes of this many frames, continued seamlessly

    def __init__(self, seconds: float | None = None, fps: float = 30.0, seed: int = 0,
                 name: str = "synthetic throws") -> None:
        if seconds is not None and not seconds > 0:
            raise ValueError(f"seconds = {seconds}: must be > 0")
        self.seconds = seconds
        self.fps = fps
        self.seed = seed
        self.name = name
        self.has_depth = True
        self.camera = SyntheticScene(fps=fps).camera()
        self.throws: list[SyntheticObject3D] = []  # every throw so far (its truth)

    def __len__(self) -> int:
        return 0 if self.seconds is None else int(self.seconds * self.fps)

    def _throws_until(self, rng: np.random.Generator, t_end_s: float) -> None:
        t = self.throws[-1].t0_s + self._flight_s(self.throws[-1]) if self.throws else 1.5
        while t < t_end_s:
            z = float(rng.uniform(9.0, 14.0))
            closing = float(rng.uniform(3.0, 6.0))
            x, y = float(rng.uniform(-0.25, 0.25)) * z, float(rng.uniform(-0.18, 0.18)) * z
            miss = rng.uniform(-0.5, 0.5, 2)  # where it crosses the camera plane, m
            fly_s = z / closing
            vel = ((miss[0] - x) / fly_s, (miss[1] - y) / fly_s, -closing)
            ob = SyntheticObject3D(len(self.throws) + 1, (x, y, z), vel, 0.3, t0_s=t)
            self.throws.append(ob)
            t += self._flight_s(ob) + float(rng.uniform(2.0, 6.0))

    @staticmethod
    def _flight_s(ob: SyntheticObject3D) -> float:
        return ob.start_xyz_m[2] / -ob.velocity_mps[2]

    def __iter__(self) -> Iterator[Frame]:
        rng = np.random.default_rng(self.seed)
        total = None if self.seconds is None else int(self.seconds * self.fps)
        first = 0
        while total is None or first < total:
            n = self.CHUNK_FRAMES if total is None else min(self.CHUNK_FRAMES, total - first)
            t_end = (first + n) / self.fps
            self._throws_until(rng, t_end)
            live = tuple(o for o in self.throws
                         if o.t0_s < t_end and o.t0_s + self._flight_s(o) > first / self.fps)
            scene = SyntheticScene(fps=self.fps, frames=n, seed=2, pan_px_per_frame=0.0,
                                   objects=(), objects_3d=live, first_frame=first)
            for frame, _truth in render(scene):
                yield frame
            first += n


def camera_homography(scene: SyntheticScene, k: int) -> np.ndarray:
    """World px -> image px of frame k (0-based): a slow pan, tilt wobble and roll."""
    tx = 0.5 * scene.width + scene.pan_px_per_frame * k
    ty = 0.55 * scene.height + 12 * np.sin(k / 25.0)
    roll = 0.01 * np.sin(k / 40.0)
    zoom = 1.0 + 0.02 * np.sin(k / 60.0)
    c, s = np.cos(roll) * zoom, np.sin(roll) * zoom
    # image = R * (world - (tx, ty))
    return np.array([[c, -s, -(c * tx - s * ty)], [s, c, -(s * tx + c * ty)], [0, 0, 1]])


def render(scene: SyntheticScene) -> Iterator[tuple[Frame, list[tuple[int, float, float, float, float]]]]:
    """Frames (colour BGR + depth mm) and their ground-truth boxes ``(id, x, y, w, h)``."""
    rng = np.random.default_rng(scene.seed)
    world = _world(scene, rng)
    size = (scene.width, scene.height)
    for k in range(scene.first_frame, scene.first_frame + scene.frames):
        grey = cv2.warpPerspective(world, camera_homography(scene, k), size, flags=cv2.INTER_LINEAR,
                                   borderMode=cv2.BORDER_REFLECT)
        depth = np.zeros((scene.height, scene.width), np.uint16)  # sky and far ground: no data
        truth = []
        for ob in scene.objects:
            x = ob.start_xy[0] + ob.velocity[0] * k
            y = ob.start_xy[1] + ob.velocity[1] * k
            d = ob.size_px * ob.growth**k
            a, b = d / 2, d / 3.2
            if not (-d < x < scene.width + d and -d < y < scene.height + d):
                continue
            mask = np.zeros_like(grey)
            cv2.ellipse(mask, ((x, y), (2 * a, 2 * b), 15.0), 255, -1, cv2.LINE_AA)
            alpha = mask.astype(np.float32) / 255.0
            grey = (grey * (1 - alpha) + ob.brightness * alpha).astype(np.uint8)
            dist_m = max(0.3, ob.start_m - ob.closing_mps * k / scene.fps)
            depth[mask > 127] = int(dist_m * 1000)
            x0, y0, x1, y1 = max(0, x - a), max(0, y - a), min(scene.width, x + a), min(scene.height, y + a)
            if x1 > x0 and y1 > y0:
                truth.append((ob.object_id, x0, y0, x1 - x0, y1 - y0))
        cam = scene.camera().color
        for ob3 in scene.objects_3d:
            t = k / scene.fps - ob3.t0_s
            if t < 0:
                continue  # not thrown yet
            x3, y3, z3 = (p + v * t for p, v in zip(ob3.start_xyz_m, ob3.velocity_mps, strict=True))
            if z3 < 0.25:
                continue  # at or past the camera
            (u, v), = cam.project(np.array([[x3, y3, z3]]))
            d = cam.fx * ob3.diameter_m / z3
            if not (-d < u < scene.width + d and -d < v < scene.height + d):
                continue
            mask = np.zeros_like(grey)
            draw_object(mask, "disc", float(u), float(v), d / 2, 0.0)  # supersampled: no whole-px steps
            alpha = mask.astype(np.float32) / 255.0
            grey = (grey * (1 - alpha) + ob3.brightness * alpha).astype(np.uint8)
            depth[mask > 127] = int(z3 * 1000)
            x0, y0 = max(0.0, u - d / 2), max(0.0, v - d / 2)
            x1, y1 = min(float(scene.width), u + d / 2), min(float(scene.height), v + d / 2)
            if x1 > x0 and y1 > y0:
                truth.append((ob3.object_id, x0, y0, x1 - x0, y1 - y0))
        noisy = grey.astype(np.float32) + rng.normal(0, scene.noise_std, grey.shape)
        colour = cv2.cvtColor(np.clip(noisy, 0, 255).astype(np.uint8), cv2.COLOR_GRAY2BGR)
        # a tint so the colour frame is not grey: sky bluish
        colour[:, :, 0] = np.minimum(colour[:, :, 0].astype(np.int16) + 25, 255).astype(np.uint8)
        yield Frame(k + 1, k / scene.fps, colour, depth), truth


def write_recording(scene: SyntheticScene, folder: Path) -> Path:
    """Write the scene as a recording folder (``color.mp4``, ``depth/``, ``frames.csv``)
    plus its ground truth ``gt.csv``. Returns the folder."""
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "depth").mkdir(exist_ok=True)
    (folder / "intrinsics.json").write_text(json.dumps(scene.camera().to_json(), indent=2) + "\n")
    writer = cv2.VideoWriter(str(folder / "color.mp4"), cv2.VideoWriter.fourcc(*"mp4v"),
                             scene.fps, (scene.width, scene.height))
    if not writer.isOpened():
        raise RuntimeError(f"cannot write {folder / 'color.mp4'}")
    try:
        with (folder / "frames.csv").open("w", newline="") as ft, \
                (folder / "gt.csv").open("w", newline="") as fg:
            wt, wg = csv.writer(ft), csv.writer(fg)
            wt.writerow(["frame", "t_s"])
            wg.writerow(["frame", "id", "x", "y", "w", "h"])
            for frame, truth in render(scene):
                writer.write(frame.color)
                if frame.depth is not None:
                    cv2.imwrite(str(folder / "depth" / f"{frame.index:06d}.png"), frame.depth)
                wt.writerow([frame.index, f"{frame.t_s:.6f}"])
                for oid, x, y, w, h in truth:
                    wg.writerow([frame.index, oid, f"{x:.2f}", f"{y:.2f}", f"{w:.2f}", f"{h:.2f}"])
    finally:
        writer.release()
    return folder
