"""Synthetic flights over textured ground, with truth: a dataset for ``midair evaluate``
(issue 19, item 5).

The real clips here look up at sky from the ground; a drone's forward camera flying low sees
objects in front of fields and trees as well, from a camera that moves through the scene.
Each flight is drawn by the closed loop's renderer (``app.sim.world``; by default the
``shaped`` world: birds and quadrotors drawn as such, clouds that drift, trees, ground whose
parallax follows the vehicle's motion) from a vehicle flying a straight, level leg at 5-40 m
altitude, 0-4 m/s, turning slowly or not at all, with two or three objects on straight courses:
some coming at the vehicle, some crossing, above and below the horizon. Every object whose
image circle is at least ``MIN_LABEL_RADIUS_PX`` is labelled, its box the circle's square
(``frame,id,x,y,w,h``, the format of ``../shared/data``); the flights are written as MP4 (as
the Halmstad clips) beside a ``clips.csv`` index, so ``midair evaluate DIR`` scores them as one
group, ``groundflights``. Nothing here was used to fit anything.

With ``depth``, each flight is written instead as a recording folder (``color.mp4``, the
stereo depth as ``depth/000001.png …`` in millimetres, ``intrinsics.json``) through the
D435i's left infrared imager, whose depth is registered to it (the default stream): the
same evaluation then runs perception with depth (``app.perception.near``).

What it leaves out: no colour (the renderer draws grey), no attitude (the camera stays level:
no roll or pitch, yaw only), no motion blur, rolling shutter or depth holes.
"""

from __future__ import annotations

import csv
import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from app.camera import Intrinsics
from app.errors import UsageError
from app.sim.world import Monochrome, Renderer, Sphere, d435i_color, d435i_infrared, load_world

# objects drawn smaller are not labelled (4 px across; the README's 2-4 px birds go unseen)
MIN_LABEL_RADIUS_PX = 2.0
FPS = 30.0
KINDS = {  # diameter range m, brightness range (sky ~175-215, ground ~70-130)
    "ball": ((0.2, 0.3), (20, 60)),
    "bird": ((0.3, 0.6), (40, 140)),
    "drone": ((0.3, 0.6), (20, 60)),
}


@dataclass(frozen=True)
class FlightObject:
    kind: str
    diameter_m: float
    grey: int
    start_m: tuple[float, float, float]  # NED at t = 0
    velocity_mps: tuple[float, float, float]  # NED
    approaching: bool  # aimed at the vehicle's path (passes within a few metres)


@dataclass(frozen=True)
class GroundFlight:
    name: str
    seed: int
    altitude_m: float
    speed_mps: float  # along the heading
    yaw_rate_dps: float
    seconds: float
    objects: tuple[FlightObject, ...]

    def vehicle_at(self, t: float) -> tuple[tuple[float, float, float], float]:
        return flight_vehicle(self.altitude_m, self.speed_mps, self.yaw_rate_dps, t)


def plan_flights(n: int, seed: int, seconds: float = 10.0) -> list[GroundFlight]:
    """``n`` flights, reproducible from ``seed``."""
    if n < 1:
        raise UsageError(f"--ground-flights {n}: must be at least 1")
    rng = np.random.default_rng(seed)
    flights = []
    for i in range(n):
        altitude = round(float(rng.uniform(5.0, 40.0)), 1)
        speed = round(float(rng.choice([0.0, 1.0, 2.0, 3.0, 4.0])), 1)
        yaw_rate = round(float(rng.choice([0.0, 0.0, rng.uniform(-8.0, 8.0)])), 2)
        objects = []
        for k in range(int(rng.integers(2, 4))):
            kind = str(rng.choice(list(KINDS)))
            (d0, d1), (g0, g1) = KINDS[kind]
            diameter = round(float(rng.uniform(d0, d1)), 2)
            grey = int(rng.integers(g0, g1 + 1))
            approaching = k == 0 or bool(rng.random() < 0.3)
            for _try in range(100):  # a course that stays above the ground throughout
                start, vel = _course(rng, altitude, speed, yaw_rate, seconds, approaching)
                if max(start[2], start[2] + vel[2] * seconds) < -1.0:
                    break
            objects.append(FlightObject(kind, diameter, grey, tuple(float(v) for v in start),  # type: ignore[arg-type]
                                        tuple(float(v) for v in vel), approaching))  # type: ignore[arg-type]
        flights.append(GroundFlight(f"ground_{seed}_{i:02d}", int(seed * 1000 + i), altitude, speed,
                                    yaw_rate, seconds, tuple(objects)))
    return flights


def _course(rng: np.random.Generator, altitude: float, speed: float, yaw_rate: float,
            seconds: float, approaching: bool) -> tuple[np.ndarray, np.ndarray]:
    """An object's start (NED, m) and velocity (m/s): at the flight's middle it is 8-40 m
    ahead within the lens, from 4 m above the vehicle to most of the way down to the ground
    (below the horizon: in front of the ground); coming at the vehicle (towards where it will
    be at the end, missing by up to 2 m) or crossing the view at 60-120 degrees."""
    object_speed = float(rng.uniform(2.0, 12.0))
    t_mid = seconds / 2
    (vx, vy, vz), yaw = flight_vehicle(altitude, speed, yaw_rate, t_mid)
    ahead = float(rng.uniform(8.0, 40.0))
    bearing = yaw + math.radians(float(rng.uniform(-25.0, 25.0)))
    below = float(rng.uniform(-4.0, 0.8 * altitude))  # m below the vehicle (negative: above)
    mid = np.array([vx + ahead * math.cos(bearing), vy + ahead * math.sin(bearing), vz + below])
    if approaching:
        (ex, ey, ez), _ = flight_vehicle(altitude, speed, yaw_rate, seconds)
        direction = np.array([ex, ey, ez]) + rng.uniform(-2.0, 2.0, 3) - mid
    else:
        heading = bearing + math.radians(float(rng.choice([-1.0, 1.0]) * rng.uniform(60.0, 120.0)))
        direction = np.array([math.cos(heading), math.sin(heading), float(rng.uniform(-0.2, 0.2))])
    vel = direction / max(1e-6, float(np.linalg.norm(direction))) * object_speed
    return mid - vel * t_mid, vel


def flight_vehicle(altitude_m: float, speed_mps: float, yaw_rate_dps: float, t: float
                   ) -> tuple[tuple[float, float, float], float]:
    """Vehicle position (NED, m, from home north at t = 0) and heading (rad) at ``t`` s on a
    level leg at a constant turn rate (a straight line when it is 0)."""
    w = math.radians(yaw_rate_dps)
    if abs(w) < 1e-9:
        return (speed_mps * t, 0.0, -altitude_m), 0.0
    yaw = w * t
    r = speed_mps / w
    return (r * math.sin(yaw), r * (1.0 - math.cos(yaw)), -altitude_m), yaw


def write_flight(flight: GroundFlight, folder: Path, lens: Intrinsics,
                 world: str = "app.sim.world:shaped", depth: bool = False) -> tuple[Path, Path, int]:
    """Render ``flight`` to ``folder/<name>.mp4`` (with ``depth``: the recording folder
    ``folder/<name>/``, grey frames through ``lens`` and their depth) and its truth to
    ``<name>.gt.csv``; return the clip's and the truth's paths and the number of labelled rows."""
    import cv2

    renderer: Renderer = load_world(world, flight.seed, lens)
    folder.mkdir(parents=True, exist_ok=True)
    gt = folder / f"{flight.name}.gt.csv"
    clip = video = folder / f"{flight.name}.mp4"
    depth_dir = None
    if depth:
        renderer = Monochrome(renderer)  # the infrared imager sees grey
        clip = folder / flight.name
        depth_dir = clip / "depth"
        depth_dir.mkdir(parents=True, exist_ok=True)
        video = clip / "color.mp4"
        (clip / "intrinsics.json").write_text(json.dumps(renderer.camera().to_json(), indent=1))
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter.fourcc(*"mp4v"), FPS, (lens.width, lens.height))
    if not writer.isOpened():
        raise OSError(f"{video}: OpenCV cannot write MP4 here")
    rows = 0
    try:
        with gt.open("w", newline="") as fh:
            out = csv.writer(fh)
            out.writerow(["frame", "id", "x", "y", "w", "h"])
            for k in range(int(round(flight.seconds * FPS))):
                t = k / FPS
                position, yaw = flight.vehicle_at(t)
                spheres = [Sphere(j + 1, tuple(float(s + v * t) for s, v in zip(o.start_m, o.velocity_mps,  # type: ignore[arg-type]
                                                                                   strict=True)),
                                  o.diameter_m, o.grey, o.kind) for j, o in enumerate(flight.objects)]
                colour, depth_mm, seen = renderer.render(position, yaw, spheres)
                writer.write(colour if colour.ndim == 3 else cv2.cvtColor(colour, cv2.COLOR_GRAY2BGR))
                if depth_dir is not None:
                    cv2.imwrite(str(depth_dir / f"{k + 1:06d}.png"), depth_mm)
                for oid, (u, v, r, z) in sorted(seen.items()):
                    if r < MIN_LABEL_RADIUS_PX or z <= 0:
                        continue
                    x0, y0 = max(0.0, u - r), max(0.0, v - r)
                    x1, y1 = min(float(lens.width), u + r), min(float(lens.height), v + r)
                    if x1 - x0 < 1 or y1 - y0 < 1:
                        continue
                    out.writerow([k + 1, oid, round(x0, 1), round(y0, 1), round(x1 - x0, 1),
                                  round(y1 - y0, 1)])
                    rows += 1
    finally:
        writer.release()
    return clip, gt, rows


def write_dataset(out: Path, n: int, seed: int, width: int = 848, height: int = 480,
                  world: str = "app.sim.world:shaped", seconds: float = 10.0,
                  depth: bool = False) -> list[GroundFlight]:
    """``n`` flights of ``seconds`` into ``out`` with a ``clips.csv`` index (dataset
    ``groundflights``): through the colour lens as MP4, or with ``depth`` through the infrared
    imager as recording folders with depth."""
    lens = d435i_infrared(width, height) if depth else d435i_color(width, height)
    flights = plan_flights(n, seed, seconds)
    index = []
    for f in flights:
        video, gt, rows = write_flight(f, out, lens, world, depth)
        index.append({"path": video.name, "gt": gt.name, "dataset": "groundflights", "width": width,
                      "height": height, "fps": FPS, "frames": int(round(f.seconds * FPS)),
                      "objects": "+".join(sorted({o.kind for o in f.objects})), "labelled_rows": rows,
                      "altitude_m": f.altitude_m, "speed_mps": f.speed_mps,
                      "yaw_rate_dps": f.yaw_rate_dps, "cuts": ""})
    with (out / "clips.csv").open("w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(index[0]))
        w.writeheader()
        w.writerows(index)
    with (out / "objects.csv").open("w", newline="") as fh:
        ow = csv.writer(fh)
        ow.writerow(["clip", "id", "kind", "approaching", "diameter_m", "grey"])
        for f in flights:
            for j, o in enumerate(f.objects):
                ow.writerow([f.name, j + 1, o.kind, int(o.approaching), o.diameter_m, o.grey])
    return flights
