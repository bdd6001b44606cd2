from __future__ import annotations

import numpy as np

from app.config import TrackingConfig
from app.perception.recognition import Cluster
from app.perception.tracking import Tracker

FPS = 30.0


def _c(x: float, y: float) -> Cluster:
    return Cluster(x, y, (int(x) - 5, int(y) - 5, 10, 10), 100, ())


def test_ids_are_stable_and_survive_a_short_miss() -> None:
    tr = Tracker(TrackingConfig(noise_frames=3, lost_s=0.5))
    ids_seen = []
    for k in range(30):
        clusters = [_c(100 + 4 * k, 100), _c(400 - 3 * k, 300)]
        if 12 <= k < 16:  # both missed for 4 frames (0.13 s < lost_s)
            clusters = []
        tracks = tr.step(clusters, k / FPS)
        if k >= 4:
            ids_seen.append(sorted(t.track_id for t in tracks))
    assert all(ids == [1, 2] for ids in ids_seen)
    final = {t.track_id: t for t in tr.step([_c(220, 100), _c(310, 300)], 30 / FPS)}
    assert abs(final[1].vx - 4) < 0.5 and abs(final[2].vx + 3) < 0.5
    assert final[1].matched


def test_coasting_track_follows_its_prediction() -> None:
    tr = Tracker(TrackingConfig(noise_frames=2))
    for k in range(10):
        tr.step([_c(50 + 5 * k, 80)], k / FPS)
    tracks = tr.step([], 10 / FPS)
    assert len(tracks) == 1 and not tracks[0].matched
    assert abs(tracks[0].x - 100) < 2


def test_a_candidate_seen_too_briefly_is_never_confirmed() -> None:
    tr = Tracker(TrackingConfig(noise_frames=3, candidate_max_misses=2))
    for k in range(40):
        # a flicker seen in 3 frames (not more than noise_frames), then gone for good
        clusters = [_c(200, 200)] if k < 3 else []
        assert tr.step(clusters, k / FPS) == []


def test_confirmation_needs_more_than_noise_frames() -> None:
    tr = Tracker(TrackingConfig(noise_frames=3))
    counts = [len(tr.step([_c(10 + k, 10)], k / FPS)) for k in range(6)]
    assert counts == [0, 0, 0, 1, 1, 1]


def test_lost_track_is_deleted_after_lost_s() -> None:
    tr = Tracker(TrackingConfig(noise_frames=1, lost_s=0.31))
    for k in range(5):
        tr.step([_c(100, 100)], k / FPS)
    alive = [len(tr.step([], (5 + k) / FPS)) for k in range(15)]
    # last seen at frame 4 (0.133 s); deleted once more than 0.31 s passed (frame 14)
    assert alive[:9] == [1] * 9 and alive[9:] == [0] * 6


def test_clusters_beyond_the_gate_start_new_tracks() -> None:
    tr = Tracker(TrackingConfig(noise_frames=1, dist_px=20))
    for k in range(3):
        tr.step([_c(100, 100)], k / FPS)
    tracks = tr.step([_c(160, 100)], 3 / FPS)
    assert [t.matched for t in tracks] == [False]


def test_homography_prediction_keeps_identity_under_a_camera_jump() -> None:
    """The camera pans 40 px between frames; the object is still in the world. Without
    the homography the jump exceeds the gate; with it the track continues."""
    for use_h, expect_same in ((True, True), (False, False)):
        tr = Tracker(TrackingConfig(noise_frames=1, dist_px=25, predict_with_homography=use_h))
        for k in range(4):
            tr.step([_c(300, 200)], k / FPS, np.eye(3))
        shift = np.array([[1, 0, -40.0], [0, 1, 0], [0, 0, 1]])
        tracks = tr.step([_c(260, 200)], 4 / FPS, shift)
        assert (len(tracks) == 1 and tracks[0].matched) == expect_same
