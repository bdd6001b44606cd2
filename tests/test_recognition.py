from __future__ import annotations

import cv2
import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from app.config import RecognitionConfig
from app.perception.recognition import (
    SMALL_BLOB_COUNT,
    Recognizer,
    _components,
    _neighbour_groups,
    box_gaps,
    find_blobs,
)


def _mask(*rects: tuple[int, int, int, int], shape: tuple[int, int] = (240, 320)) -> np.ndarray:
    m = np.zeros(shape, np.uint8)
    for x, y, w, h in rects:
        m[y:y + h, x:x + w] = 255
    return m


def test_blob_areas_and_centroids_are_exact_for_rectangles() -> None:
    blobs = find_blobs(_mask((10, 20, 8, 5), (100, 100, 3, 3)))
    order = np.argsort(blobs.areas)
    assert blobs.areas[order].tolist() == [9.0, 40.0]
    assert np.allclose(blobs.centroids[order][1], (13.5, 22.0), atol=0.6)
    assert blobs.boxes[order][1].tolist() == [10, 20, 8, 5]


def test_one_large_blob_is_a_cluster_by_itself() -> None:
    rec = Recognizer(RecognitionConfig(area_px=40, dist_px=10))
    clusters, _ = rec(_mask((50, 60, 10, 10)))
    assert len(clusters) == 1
    c = clusters[0]
    assert c.area == 100
    assert abs(c.x - 54.5) < 0.6 and abs(c.y - 64.5) < 0.6
    assert c.box == (50, 60, 10, 10)


def test_small_neighbouring_patches_join_with_area_weighted_centre() -> None:
    # three 4x4 patches (16 px each) and one 6x6 (36 px), gaps of 3 px: together 84 >= 40
    rects = [(100, 100, 4, 4), (107, 100, 4, 4), (100, 107, 4, 4), (107, 107, 6, 6)]
    rec = Recognizer(RecognitionConfig(area_px=40, dist_px=5))
    clusters, blobs = rec(_mask(*rects))
    assert len(blobs) == 4
    assert len(clusters) == 1
    c = clusters[0]
    assert c.area == 16 * 3 + 36
    expect_x = (101.5 * 16 + 108.5 * 16 + 101.5 * 16 + 109.5 * 36) / 84
    expect_y = (101.5 * 16 + 101.5 * 16 + 108.5 * 16 + 109.5 * 36) / 84
    assert abs(c.x - expect_x) < 0.6 and abs(c.y - expect_y) < 0.6
    assert c.box == (100, 100, 13, 13)
    pix, origin = c.pixel_mask()
    assert origin == (100, 100) and int((pix > 0).sum()) == 84


def test_scattered_small_noise_is_not_an_object() -> None:
    rng = np.random.default_rng(3)
    rects = [(int(x), int(y), 3, 3) for x, y in zip(rng.integers(0, 300, 25) // 40 * 40,
                                                      rng.integers(0, 220, 25) // 40 * 40, strict=True)]
    rec = Recognizer(RecognitionConfig(area_px=40, dist_px=10))
    clusters, blobs = rec(_mask(*rects))
    assert len(blobs) > 5
    assert clusters == []


def test_far_apart_patches_stay_separate_and_small_ones_drop() -> None:
    rec = Recognizer(RecognitionConfig(area_px=40, dist_px=10))
    clusters, _ = rec(_mask((10, 10, 8, 8), (200, 150, 8, 8), (100, 100, 4, 4)))
    assert sorted(c.box for c in clusters) == [(10, 10, 8, 8), (200, 150, 8, 8)]


def test_a_cluster_covering_the_frame_is_rejected() -> None:
    rec = Recognizer(RecognitionConfig(max_cluster_frac=0.25))
    clusters, _ = rec(_mask((0, 0, 300, 200)))
    assert clusters == []


def test_box_gaps() -> None:
    g = box_gaps(np.array([[0, 0, 10, 10], [13, 0, 5, 5], [13, 14, 2, 2]]))
    assert g[0, 1] == 3 and g[1, 0] == 3
    assert np.isclose(g[0, 2], np.hypot(3, 4))
    assert g[0, 0] == 0


def test_many_blobs_are_capped_to_the_largest() -> None:
    m = np.zeros((240, 320), np.uint8)
    for i in range(50):
        cv2.circle(m, (10 + (i % 10) * 30, 10 + (i // 10) * 40), 1 + i % 4, 255, -1)
    blobs = find_blobs(m, max_blobs=10)
    assert len(blobs) == 10
    assert blobs.areas.min() >= np.sort(find_blobs(m).areas)[-10]


def test_min_fill_rejects_a_patchwork_but_keeps_a_compact_object() -> None:
    # foliage-like: 12 specks of 3x3 scattered over a 60x60 area, each within 10 px of another
    specks = [(200 + 12 * (i % 5), 100 + 12 * (i // 5), 3, 3) for i in range(12)]
    mask = _mask(*specks, (40, 40, 10, 10))
    loose = Recognizer(RecognitionConfig(area_px=40, dist_px=10, min_fill=0.0))(mask)[0]
    strict = Recognizer(RecognitionConfig(area_px=40, dist_px=10, min_fill=0.25))(mask)[0]
    assert sorted(c.box for c in loose) == [(40, 40, 10, 10), (200, 100, 51, 27)]
    assert [c.box for c in strict] == [(40, 40, 10, 10)]


_box = st.tuples(st.integers(0, 300), st.integers(0, 200), st.integers(1, 40), st.integers(1, 40))


@settings(max_examples=300, deadline=None)
@given(st.lists(_box, min_size=2, max_size=SMALL_BLOB_COUNT), st.sampled_from([0.5, 5.0, 20.0, 20.5, 60.0]))
def test_pairwise_grouping_of_few_blobs_matches_the_matrix_one(
        boxes: list[tuple[int, int, int, int]], dist: float) -> None:
    # Few blobs are grouped pair by pair in plain Python, many by the gap matrix: the same groups
    # in the same order (the clusters' order, and so the tracker's, depends on it), touching and
    # overlapping boxes and gaps exactly at the distance included.
    n_groups, label = _components(box_gaps(np.array(boxes, np.int64)) < dist)
    by_matrix = [np.flatnonzero(label == g).tolist() for g in range(n_groups)]
    assert _neighbour_groups([list(b) for b in boxes], dist) == by_matrix


def test_pairwise_grouping_joins_a_chain_whose_ends_are_far_apart() -> None:
    # 0 and 2 are 26 px apart but both within 8 px of 1; 3 stands alone; 4 touches 0.
    boxes = [[0, 0, 10, 10], [18, 0, 10, 10], [36, 0, 10, 10], [200, 200, 5, 5], [10, 10, 3, 3]]
    assert _neighbour_groups(boxes, 10.0) == [[0, 1, 2, 4], [3]]
