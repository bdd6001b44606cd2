"""Shared fixtures: the real clips in ../shared/data (skipped cleanly when absent)."""

from __future__ import annotations

import asyncio
import contextlib
import os
import time
from collections.abc import AsyncIterator, Callable
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
DATA = Path(os.environ.get("MIDAIR_DATA", ROOT.parent / "shared" / "data"))

cv2.setNumThreads(1)


@pytest.fixture
def data_dir() -> Path:
    if not (DATA / "clips.csv").is_file():
        pytest.skip(f"real clips not found at {DATA}")
    return DATA


def textured(h: int = 480, w: int = 640, seed: int = 0) -> np.ndarray:
    """A grey image with texture everywhere (so every border window has corners)."""
    rng = np.random.default_rng(seed)
    noise = rng.normal(0, 1, (h // 2, w // 2))
    img = cv2.resize(cv2.GaussianBlur(noise, (0, 0), 0.8), (w, h), interpolation=cv2.INTER_CUBIC)
    img = 128 + 60 * img / np.abs(img).max()
    return np.clip(img, 0, 255).astype(np.uint8)


def free_udp_port() -> int:
    from app.sim.px4 import free_udp_port as pick

    return pick()


async def wait_for(pred: Callable[[], bool], timeout: float = 5.0) -> None:
    t0 = time.monotonic()
    while not pred():
        if time.monotonic() - t0 > timeout:
            raise AssertionError("condition not reached in time")
        await asyncio.sleep(0.02)


@contextlib.asynccontextmanager
async def vehicle(state: Any = None, ready: Callable[[Any], bool] | None = None) -> AsyncIterator[Any]:
    """The PX4 stand-in on a free port and a connected :class:`hardware.px4.Px4Link`;
    ``ready(snapshot)`` is awaited before the body runs. Yields ``(sim, link)``."""
    from app.sim.px4 import SimPx4
    from hardware.px4 import Px4Link

    port = free_udp_port()
    sim = SimPx4(port, state=state).start()
    link = Px4Link(f"udpin://0.0.0.0:{port}")
    try:
        await link.connect(timeout_s=10.0)
        if ready is not None:
            await wait_for(lambda: ready(link.snapshot()))
        yield sim, link
    finally:
        await link.close()
        sim.stop()

