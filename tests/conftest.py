"""Shared fixtures: the real clips in ../shared/data (skipped cleanly when absent)."""

from __future__ import annotations

import os
from pathlib import Path

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
