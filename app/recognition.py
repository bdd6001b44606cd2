"""Stage 2 — recognition: blobs of the motion mask clustered into objects (paper Alg. 2, §4-A).

A DBSCAN variant that weighs blobs by area. Blobs closer than ``dist_px`` (gap between
their boxes) are neighbours; a connected group of neighbours is a cluster if its summed
area reaches ``area_px``. So a blob that big is a cluster by itself, smaller blobs count
only together with their neighbours, and scattered specks are noise. A cluster's position
is the area-weighted mean of its blobs' centroids; its box encloses its blobs.

Coordinates are image pixels of the frame the mask belongs to.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import connected_components

from app.config import RecognitionConfig


@dataclass(frozen=True)
class Blobs:
    """Connected regions of a binary mask, one row each."""

    ids: np.ndarray  # (N,) label of each blob in ``labels``
    areas: np.ndarray  # (N,) px²
    centroids: np.ndarray  # (N, 2) x, y px
    boxes: np.ndarray  # (N, 4) x, y, w, h px
    labels: np.ndarray  # (H, W) int32 label image; 0 = background

    def __len__(self) -> int:
        return len(self.areas)


@dataclass(frozen=True)
class Cluster:
    """One recognised object candidate in one frame."""

    x: float  # area-weighted centroid, px
    y: float
    box: tuple[int, int, int, int]  # x, y, w, h px enclosing the member blobs
    area: int  # summed blob area, px²
    blob_labels: tuple[int, ...]  # labels in ``Blobs.labels`` of the member blobs


def find_blobs(mask: np.ndarray, min_blob_px: int = 1, max_blobs: int | None = None) -> Blobs:
    """Connected components (8-connected) of a binary mask, minus those under ``min_blob_px``;
    when more than ``max_blobs`` remain, the largest ones."""
    _n, labels, stats, cents = cv2.connectedComponentsWithStats(mask, connectivity=8)
    areas = stats[1:, cv2.CC_STAT_AREA]
    keep = np.flatnonzero(areas >= min_blob_px)
    if max_blobs is not None and len(keep) > max_blobs:
        keep = np.sort(keep[np.argsort(areas[keep])[::-1][:max_blobs]])
    return Blobs(
        ids=keep + 1,
        areas=areas[keep].astype(np.int64),
        centroids=cents[1:][keep],
        boxes=stats[1:, :4][keep],
        labels=labels,
    )


def box_gaps(boxes: np.ndarray) -> np.ndarray:
    """Pairwise gap between axis-aligned boxes (0 when they touch or overlap), px. (N, N)."""
    x0, y0 = boxes[:, 0].astype(float), boxes[:, 1].astype(float)
    x1, y1 = x0 + boxes[:, 2], y0 + boxes[:, 3]
    dx = np.maximum(0.0, np.maximum(x0[:, None] - x1[None, :], x0[None, :] - x1[:, None]))
    dy = np.maximum(0.0, np.maximum(y0[:, None] - y1[None, :], y0[None, :] - y1[:, None]))
    return np.hypot(dx, dy)


class Recognizer:
    """Area-weighted DBSCAN over mask blobs.

    Parameters
    ----------
    cfg
        ``min_blob_px`` (px², specks ignored), ``area_px`` (px², a cluster's summed area
        must reach it), ``dist_px`` (px, neighbour gap), ``max_blobs``, ``max_cluster_frac``.
    """

    def __init__(self, cfg: RecognitionConfig) -> None:
        self.cfg = cfg

    def __call__(self, mask: np.ndarray) -> tuple[list[Cluster], Blobs]:
        blobs = find_blobs(mask, self.cfg.min_blob_px, self.cfg.max_blobs)
        return self.cluster(blobs, mask.shape[0] * mask.shape[1]), blobs

    def cluster(self, blobs: Blobs, frame_area: int) -> list[Cluster]:
        n = len(blobs)
        if n == 0:
            return []
        adj = box_gaps(blobs.boxes) < self.cfg.dist_px
        n_groups, group = connected_components(csr_matrix(adj), directed=False)
        out: list[Cluster] = []
        max_area = self.cfg.max_cluster_frac * frame_area
        for g in range(n_groups):
            idx = np.flatnonzero(group == g)
            a = blobs.areas[idx]
            total = int(a.sum())
            if total < self.cfg.area_px or total > max_area:
                continue
            cx, cy = (blobs.centroids[idx] * a[:, None]).sum(axis=0) / total
            b = blobs.boxes[idx]
            x0, y0 = int(b[:, 0].min()), int(b[:, 1].min())
            x1, y1 = int((b[:, 0] + b[:, 2]).max()), int((b[:, 1] + b[:, 3]).max())
            out.append(Cluster(float(cx), float(cy), (x0, y0, x1 - x0, y1 - y0), total,
                               tuple(int(i) for i in blobs.ids[idx])))
        return out
