"""A world of another team's making for the ``--world`` tests: plain sky and a flat floor,
objects drawn as squares (not spheres), depth only for the objects."""

from __future__ import annotations

import numpy as np

from app.camera import CameraModel, Intrinsics
from app.sim.world import Sphere, Vec3


class PlainWorld:
    def __init__(self, seed: int) -> None:
        self.seed = seed
        self.intr = Intrinsics(320, 240, 300.0, 300.0, 159.5, 119.5)
        self.frames = 0

    def camera(self) -> CameraModel:
        return CameraModel(self.intr, self.intr)

    def render(self, position_m: Vec3, yaw_rad: float, spheres: list[Sphere]
               ) -> tuple[np.ndarray, np.ndarray, dict[int, tuple[float, float, float, float]]]:
        self.frames += 1
        h, w = self.intr.height, self.intr.width
        grey = np.full((h, w), 190, np.uint8)
        grey[h // 2:] = 110
        depth = np.zeros((h, w), np.uint16)
        seen = {}
        for s in spheres:
            rel = np.subtract(s.position_m, position_m)  # yaw 0 only: north is forward
            z = float(rel[0])
            if z < 0.2:
                continue
            u = self.intr.fx * rel[1] / z + self.intr.ppx
            v = self.intr.fy * rel[2] / z + self.intr.ppy
            r = self.intr.fx * s.diameter_m / 2 / z
            x0, x1 = int(max(0, u - r)), int(min(w, u + r + 1))
            y0, y1 = int(max(0, v - r)), int(min(h, v + r + 1))
            if x1 > x0 and y1 > y0:
                grey[y0:y1, x0:x1] = s.grey
                depth[y0:y1, x0:x1] = int(z * 1000)
                seen[s.object_id] = (float(u), float(v), float(r), z)
        noise = np.random.default_rng(self.seed + self.frames).normal(0, 1.5, grey.shape)
        colour = np.clip(grey + noise, 0, 255).astype(np.uint8)
        return np.repeat(colour[:, :, None], 3, axis=2), depth, seen


def factory(seed: int, lens: object) -> PlainWorld:
    return PlainWorld(seed)  # its own lens, whatever the configuration streams


def not_a_world(seed: int, lens: object) -> object:
    return object()
