"""Configuration: ``config.yaml`` loaded into frozen dataclasses and validated at start.

Every tunable of every stage lives here, with its unit in the key name or its doc.
The dataclass defaults *are* the shipped configuration: ``config.yaml`` at the
repository root spells them out, and a test keeps the two identical.

Validation happens once, at load time, and stops the program with a message that
names the key, the value and the rule, e.g.::

    perception.recognition.area_px = -3: must be > 0
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar, get_type_hints

import yaml

from app.errors import ConfigError

T = TypeVar("T")


def param(
    default: Any,
    doc: str,
    *,
    gt: float | None = None,
    ge: float | None = None,
    lt: float | None = None,
    le: float | None = None,
    choices: tuple[Any, ...] | None = None,
    odd: bool = False,
) -> Any:
    """A configuration field with its documentation and validation rules."""
    meta = {"doc": doc, "gt": gt, "ge": ge, "lt": lt, "le": le, "choices": choices, "odd": odd}
    return field(default=default, metadata=meta)


# --------------------------------------------------------------------------- perception


@dataclass(frozen=True)
class DetectionConfig:
    """Stage 1 — camera-motion compensation and frame differencing (paper Alg. 1, §3-F)."""

    window_px: int = param(70, "side of each square border window for LK flow, px (paper: 70)", ge=16)
    window_count: int = param(
        6,
        "border windows: 4 = corners, 6 = + top/bottom middles (paper), 8 = + left/right middles",
        choices=(4, 6, 8),
    )
    min_points_per_window: int = param(
        8, "n of Alg. 1: re-seed a window when fewer tracked points remain", ge=1
    )
    max_points_per_window: int = param(15, "points seeded per window at most", ge=1)
    feature_quality: float = param(
        0.01, "goodFeaturesToTrack quality level, relative to the window's best", gt=0, lt=1
    )
    feature_min_distance_px: float = param(5.0, "min spacing of seeded points, px", gt=0)
    lk_window_px: int = param(21, "Lucas-Kanade search window side, px", ge=5, odd=True)
    lk_pyramid_levels: int = param(
        2,
        "Lucas-Kanade pyramid levels above the base (each larger than the LK window in a "
        "window_px + lk_search_px crop: checked at start)",
        ge=0, le=6,
    )
    lk_search_px: int = param(
        48, "how far beyond its window a point may move between frames, px", ge=8
    )
    lk_max_iterations: int = param(10, "Lucas-Kanade iterations per level", ge=1)
    lk_predict: bool = param(
        True,
        "start each window's LK at its points moved by the window's last median flow (fast pans)",
    )
    lk_min_eigen: float = param(
        1e-4, "drop LK points whose gradient matrix is weaker (featureless sky)", gt=0
    )
    min_texture: float = param(
        1e-4,
        "a window whose strongest corner (min eigenvalue) is weaker is featureless sky: not seeded",
        gt=0,
    )
    ransac_reproj_px: float = param(2.0, "RANSAC inlier reprojection error, px", gt=0)
    min_inliers: int = param(
        10, "fewer RANSAC inliers than this: the frame is skipped (tracker coasts)", ge=4
    )
    combine: str = param(
        "mean",
        "how the two compensated differences are merged: mean (paper) or min (no ghosts)",
        choices=("mean", "min"),
    )
    median_ksize: int = param(3, "median filter aperture, px", ge=1, le=255, odd=True)
    dilate_ksize: int = param(5, "dilation kernel side, px (1 = none)", ge=1, odd=True)
    threshold: int = param(16, "binarisation threshold on the filtered difference, grey levels", ge=1, le=254)
    near_sigmas: float = param(
        5.0,
        "depth path (only where depth is in the image's own pixels: the infrared imager, or a "
        "recording so registered): also mark pixels whose inverse depth exceeds that of the valid depth "
        "beside them on their row by this many of near_noise_per_m, so that an object as bright "
        "as the ground behind it is seen by its range (0 = off)",
        ge=0, le=100.0,
    )
    near_noise_per_m: float = param(
        0.0036,
        "the depth camera's error in inverse depth, 1/m (a stereo pair's is constant: Intel's "
        "D400 RMS error 0.0036 z^2 m is 0.0036 /m in 1/z)",
        gt=0, le=1.0,
    )
    near_min_size_m: float = param(
        0.15, "the depth path's smallest object: a marked patch holding under a quarter of a disc "
        "this wide at its distance is dropped (a clump of the stereo matcher's wrong matches), m "
        "(0 = none dropped; at most decision.object_diameter_min_m)", ge=0, le=5.0,
    )
    near_window_px: int = param(80, "the depth path's row window: the background of a pixel is the "
                                "valid depth within this many px on its row, px", ge=8, le=1000)
    chroma_gain: float = param(
        0.0,
        "also difference the colour's chroma (YCrCb's Cr and Cb, half resolution), weighted by "
        "this against the grey difference, so that an object as bright as its background but of "
        "another colour is seen (0 = grey only)",
        ge=0, le=8.0,
    )
    max_mask_frac: float = param(
        0.15,
        "a mask covering more of the frame than this means a bad warp: the frame is skipped (0-1)",
        gt=0, le=1,
    )
    border_px: int = param(
        4, "ignore this band along the frame edges, px", ge=0
    )
    object_margin_px: int = param(
        10, "grow tracked objects' boxes by this before masking border windows, px", ge=0
    )
    scene_cut_correlation: float = param(
        0.5,
        "grey histogram correlation of consecutive frames below this is a scene cut (-1 to 1)",
        ge=-1,
        le=1,
    )
    slow_baseline_s: float = param(
        0.2,
        "also difference each frame against the registered frames this long and twice this long "
        "before it (half resolution), so that an object on a collision course, which only grows, "
        "is seen while it grows by less than a pixel a frame, s (0 = off)",
        ge=0, le=1.0,
    )
    slow_registration_px: float = param(
        0.5,
        "the slow difference tolerates this much misregistration of the background over its "
        "baseline: a difference smaller than the image gradient times this is not motion, px",
        ge=0,
    )
    # What the slow difference marks of an object is the rim it grew by: a disc of 60 px
    # radius growing 0.5 px a frame (τ 2 s at 30 fps; faster, the fast difference sees it)
    # leaves a ring of ~1 100 px² in 0.2 s, 0.3 % of an 848 x 480 frame.
    slow_max_frac: float = param(
        0.005,
        "the slow difference is left out of a frame where it alone marks more than this "
        "fraction of it: it marks the rims that growing objects add, a few tenths of a per "
        "cent, so more is the long baseline's registration failing (parallax, a turn, a close "
        "object the camera follows; Halmstad target group 0.794 / 0.781 with no limit)",
        gt=0, le=1,
    )
    slow_parallax_tile_px: int = param(
        32,
        "where the slow difference marks too much (slow_max_frac), register it again tile by "
        "tile: the background's residual shift in each tile of this side (Lucas-Kanade at its "
        "centre, smoothed over its neighbours) is taken out, which cancels the parallax of "
        "ground the camera flies over (near the horizon it moves by a few pixels in 0.2 s); "
        "tiles still marked over slow_parallax_tile_frac are left out, px (0 = off)",
        ge=0,
    )
    slow_parallax_tile_frac: float = param(
        0.1,
        "a tile of the parallax-registered slow difference marked over this fraction is left "
        "out: the shift did not explain its background (near ground, trees) (0-1)",
        gt=0, le=1,
    )


@dataclass(frozen=True)
class RecognitionConfig:
    """Stage 2 — area-weighted DBSCAN over the blobs of the motion mask (paper Alg. 2, §4-A)."""

    min_blob_px: int = param(3, "blobs smaller than this are ignored outright, px²", ge=1)
    area_px: int = param(
        40, "a cluster must reach this summed blob area; a blob this big stands alone, px²", gt=0
    )
    dist_px: float = param(
        20.0, "blobs whose boxes are closer than this join one cluster (distThresh), px", gt=0
    )
    max_blobs: int = param(
        400, "keep only the largest blobs when a noisy mask has more than this", ge=1
    )
    min_fill: float = param(
        0.0,
        "a cluster whose blobs fill less of its box than this is a patchwork (foliage, "
        "parallax edges), not an object (0-1; 0 = off)",
        ge=0, lt=1,
    )
    max_cluster_frac: float = param(
        0.25, "a cluster covering more of the frame than this is not an object (0-1)", gt=0, le=1
    )


@dataclass(frozen=True)
class TrackingConfig:
    """Stage 3 — association, candidate/confirmed/lost life cycle, Kalman filter (Alg. 3, §4-B/C)."""

    dist_px: float = param(
        50.0, "a cluster farther than this from a track's prediction is not it (distThresh), px", gt=0
    )
    noise_frames: int = param(
        3, "a candidate seen in more than this many frames becomes confirmed (noiseThresh)", ge=0
    )
    candidate_max_misses: int = param(
        2, "a candidate missed this many frames in a row is dropped as noise", ge=1
    )
    lost_s: float = param(1.0, "a confirmed track unmatched this long is deleted, s", gt=0)
    measurement_std_px: float = param(3.0, "Kalman measurement noise (std), px", gt=0)
    process_accel_std_px: float = param(
        2.0, "Kalman process noise: white acceleration (std), px/frame²", gt=0
    )
    predict_with_homography: bool = param(
        False, "move track predictions through the frame's homography before association"
    )


@dataclass(frozen=True)
class ConfidenceConfig:
    """Track confidence — object or moving clutter (beyond the paper; app/perception/confidence.py).
    Weights: `midair fit-confidence ../shared/data --min-confidence 0.35` (all 32 Halmstad
    clips, 28 829 track reports, with the detection/tracking defaults of then; the first nine
    features: contrast and core, measured leave-one-dataset-out, are not weighted)."""

    min_confidence: float = param(
        0.35, "a confirmed track is reported as an object in the frames its confidence reaches "
        "this, coasting or not (0-1; 0 = every matched track, as the paper)", ge=0, lt=1,
    )
    ring_px: int = param(10, "width of the band around a cluster whose texture is measured, px", ge=1)
    history_frames: int = param(
        30, "ring texture, elongation, fill and contrast are medians, and core a share, over this many "
        "of the track's latest matched frames", ge=1
    )
    straightness_frames: int = param(
        10, "straightness is measured over this many of the latest trail points, frames", ge=3
    )
    match_frames: int = param(10, "match fraction over this many of the latest frames", ge=1)
    edge_frames: int = param(
        5, "the bottom-edge feature reaches 1 after this many matched frames in a row at the bottom edge",
        ge=1,
    )
    bias: float = param(-0.5664, "logistic regression intercept")
    w_matched: float = param(0.9415, "weight of: matched in this frame (0/1)")
    w_log_hits: float = param(0.7052, "weight of: log(1 + frames matched)")
    w_ring_gradient: float = param(
        -1.1965, "weight of: log(1 + median 75th-percentile gradient in the ring, grey levels/px)"
    )
    w_ring_std: float = param(-0.5174, "weight of: log(1 + median grey std in the ring, grey levels)")
    w_straightness: float = param(0.6517, "weight of: net displacement / path length (0-1)")
    w_match_fraction: float = param(3.6073, "weight of: fraction of recent frames matched (0-1)")
    w_elongation: float = param(-2.1498, "weight of: median log(long / short side) of the cluster box")
    w_fill: float = param(-0.9872, "weight of: median blob area / box area of the cluster (0-1)")
    w_bottom_edge: float = param(
        -7.5980, "weight of: matched frames in a row with the ring across the bottom edge / edge_frames "
        "(0-1)",
    )
    w_contrast: float = param(
        0.0, "weight of: median |mean grey inside the cluster - mean of its ring| / (ring's grey std + 1)"
    )
    w_core: float = param(
        0.0, "weight of: fraction of recent matched frames with a photometric core (0-1)"
    )
    coast_match: float = param(
        0.5, "a track coasting on its prediction (no cluster matched in this frame) is reported only "
        "where its last matched look is still found near the prediction: the grey patch's normalised "
        "cross-correlation reaches this (0 = coasting tracks reported on their confidence alone). On the "
        "Halmstad target group 485 of the coasting rows reported were false and 301 true; with it 117 "
        "and 252 (docs/measurements.md)", ge=0, le=1,
    )
    coast_search_px: int = param(
        8, "how far from the coasting track's predicted centre its last look is searched for, px", ge=0
    )


@dataclass(frozen=True)
class PerceptionConfig:
    """Perception: stages 1-3 of the paper, and a confidence per track."""

    detection: DetectionConfig = field(default_factory=DetectionConfig)
    recognition: RecognitionConfig = field(default_factory=RecognitionConfig)
    tracking: TrackingConfig = field(default_factory=TrackingConfig)
    confidence: ConfidenceConfig = field(default_factory=ConfidenceConfig)


# --------------------------------------------------------------------------- camera


@dataclass(frozen=True)
class StreamIntrinsics:
    """Pinhole intrinsics of one stream, px."""

    width: int = param(640, "image width, px", ge=1)
    height: int = param(480, "image height, px", ge=1)
    fx: float = param(615.0, "focal length along x, px", gt=0)
    fy: float = param(615.0, "focal length along y, px", gt=0)
    ppx: float = param(320.0, "principal point x, px")
    ppy: float = param(240.0, "principal point y, px")


def _depth_default() -> StreamIntrinsics:
    return StreamIntrinsics(fx=385.0, fy=385.0)


@dataclass(frozen=True)
class CameraConfig:
    """Calibration used when neither the camera nor the recording provides one. Defaults:
    typical D435i factory calibrations at 640x480 (colour fx ~ 615 px, depth fx ~ 385 px, as
    printed by `rs-enumerate-devices -c` in RealSense users' reports); use your own."""

    color: StreamIntrinsics = field(default_factory=StreamIntrinsics)
    depth: StreamIntrinsics = field(default_factory=_depth_default)
    depth_to_color_x_m: float = param(
        0.015, "colour camera's offset from the depth camera along X, m (D435i: ~15 mm)"
    )
    depth_to_color_y_m: float = param(0.0, "offset along Y, m")
    depth_to_color_z_m: float = param(0.0, "offset along Z, m")
    depth_scale_m: float = param(0.001, "metres per depth unit", gt=0)


# --------------------------------------------------------------------------- capture


@dataclass(frozen=True)
class CaptureConfig:
    """The camera of ``midair fly``: the D435i through pyrealsense2, and how it recovers."""

    camera: str = param(
        "realsense",
        "realsense: the D435i (live); or a path: a recording folder, a video, or a RealSense "
        "recording (.db3/.bag) played as the camera at its frame rate",
    )
    serial: str = param("", "serial number of the D435i to open; empty: the first one found")
    # infrared since 2026-12-06: paired closed-loop campaigns (seed 41, 230 threats) avoided
    # 177 -> 194 and 184 -> 195 against colour, open loop 186 -> 197 of 266 over three worlds
    # (docs/measurements.md, "A wider lens")
    stream: str = param(
        "infrared",
        "the image perception sees: color (the RGB camera, 69 x 42 degrees, rolling shutter) or "
        "infrared (the left imager of the depth pair: 87 x 58 degrees, global shutter, grey, "
        "registered to depth by construction; streamed at depth_width x depth_height and "
        "depth_fps, with the IR projector off so its dots do not sit still in a moving image)",
        choices=("color", "infrared"),
    )
    # 848: the sensor's full width. Paired campaign (100 encounters, seed 11, docs/measurements.md):
    # threats avoided 47 % at 640x480 -> 62 % at 848x480 (McNemar p = 0.014); perception
    # 2.0-2.6 -> 2.5 ms per frame (midair bench --width)
    color_width: int = param(848, "colour stream width, px: 848 (x480) sees the D435i's full 69 degrees "
                             "across, 640 (x480) a 55-degree crop (fewer pixels, less of the sky)", gt=0)
    color_height: int = param(480, "colour stream height, px", gt=0)
    color_fps: int = param(60, "colour frame rate (D435i: 6, 15, 30 or 60 at 640x480 and 848x480), frames/s",
                           choices=(6, 15, 30, 60))
    depth_width: int = param(848, "depth stream width (848x480 is the D435i's best depth "
                             "resolution), px", gt=0)
    depth_height: int = param(480, "depth stream height, px", gt=0)
    depth_fps: int = param(60, "depth frame rate, frames/s", choices=(6, 15, 30, 60, 90))
    # high_accuracy: Intel's preset with the higher confidence threshold and lower fill
    # (librealsense wiki, "D400 Series Visual Presets"). A wrong match is a range that can
    # start an evasion (126 false evasions in 10 simulated minutes of clumped mismatches before
    # the depth guards, docs/measurements.md); a missing one leaves the object to the image.
    # Not measured on a camera here: compare in field tests.
    depth_preset: str = param(
        "high_accuracy",
        "the D435i's depth preset, set when the live camera starts: high_accuracy (fewer wrong "
        "matches, less fill), default, medium_density, high_density (more fill, more wrong "
        "matches) or keep (whatever the camera holds)",
        choices=("high_accuracy", "default", "medium_density", "high_density", "keep"),
    )
    enable_imu: bool = param(False, "also stream the IMU (accel + gyro); off: less USB and CPU load")
    frame_timeout_ms: float = param(
        500.0, "no frame for this long is a stall: restart the pipeline, ms", gt=0
    )
    restarts_before_reset: int = param(
        2, "pipeline restarts that failed before the device gets a USB hardware reset", ge=0
    )
    backoff_initial_s: float = param(0.5, "first wait between recovery attempts, s", gt=0)
    backoff_max_s: float = param(4.0, "longest wait between recovery attempts (doubling), s", gt=0)
    give_up_s: float = param(
        10.0, "no frame for this long: exit with an error (systemd restarts the service; its "
        "watchdog, 15 s, must stay longer), s", gt=0
    )


# --------------------------------------------------------------------------- flight record


@dataclass(frozen=True)
class RecordConfig:
    """The flight record: a folder per run under ``dir``, bounded in total size."""

    enabled: bool = param(True, "write a flight record for every `midair fly` run")
    dir: str = param("records", "folder that holds one sub-folder per run (relative to the "
                     "working directory; the systemd service runs in /var/lib/midair)")
    frames: str = param(
        "none",
        "also save every processed frame (lossless PNG) as a recording folder that `midair "
        "replay` reads: color+depth, color or none. Costs ~8 ms of CPU and ~150 KB per frame "
        "(measured, docs/measurements.md); for desk and test flights, not on a Pi at 60 fps",
        choices=("color+depth", "color", "none"),
    )
    png_compression: int = param(1, "PNG compression of saved frames (0 fastest .. 9 smallest)",
                                 ge=0, le=9)
    max_total_mb: float = param(
        4000.0, "all runs together stay below this; the oldest runs are deleted first, MB", gt=0
    )
    min_free_mb: float = param(
        500.0, "stop saving frames when the disk has less free space than this, MB", ge=0
    )
    queue_frames: int = param(
        120, "frames waiting for the writer; when it falls behind, frames are skipped "
        "(counted), never the flight", gt=0,
    )
    flush_s: float = param(1.0, "written to disk at least this often (a crash loses at most "
                           "this much), s", gt=0)


# --------------------------------------------------------------------------- decision


@dataclass(frozen=True)
class DecisionConfig:
    """Stage 4 — threat assessment and the evasive command (paper Alg. 4, §4-D, eq. 4.3)."""

    min_range_m: float = param(0.2, "depth below this is no data (D435i min-Z), m", gt=0)
    max_range_m: float = param(
        16.0, "depth beyond this is not used; nearer, its error is modelled as growing with z² "
        "(depth_rms_per_m2; the paper stops at the D435i's ~10 m), m", gt=0
    )
    depth_percentile: float = param(
        25.0, "percentile of the blob's depth pixels taken as its distance", ge=0, le=100
    )
    min_depth_pixels: int = param(6, "fewer trusted depth pixels on the blob: no distance", ge=1)
    min_depth_cover: float = param(
        0.25, "a near surface holding fewer depth pixels than this share of a disc "
        "object_diameter_min_m across at its distance gives no distance: no object is that small "
        "there, but a clump of the stereo matcher's wrong matches is (real objects held >= 0.96 "
        "of it in the open loop, seed 11, `stereo` world; clumps 0.01-0.2); 0 = off", ge=0, le=1,
    )
    min_track_confidence: float = param(
        0.0, "tracks below this perception confidence are not measured in depth (0-1; 0 = "
        "every confirmed track: depth itself tells a closing object from clutter)", ge=0, lt=1,
    )
    emergency_m: float = param(0.6, "closer than this: emergency stop (emergencyThresh), m", gt=0)
    safe_window_m: float = param(
        1.5, "lateral radius of the safe window, R_safe (paper §5-C: 1.5 m), m", gt=0
    )
    avoid_m: float | None = param(
        1.0,
        "evade a hostile object closer than this (avoidThresh; paper §5-C: 1 m), m; "
        "null: derive from eq. 4.3 with object_speed_mps",
        gt=0,
    )
    object_speed_mps: float = param(
        2.0, "expected object speed v_obj for eq. 4.3 (used when avoid_m is null), m/s", gt=0
    )
    # 6 since 2026-12-07: on PX4 SITL (SIH, defaults) a body-right command from hover moved
    # 0.98-1.07 m in the first second at 3 m/s, 1.42-1.50 at 4.5 and 1.68-1.92 at 6
    # (PX4's velocity loop accelerates in proportion to the speed asked: docs/sitl.md)
    evade_speed_mps: float = param(
        6.0, "evasion speed flown (paper §5-C: 3 m/s max manoeuvre speed; PX4 moves further in "
        "the first second the faster it is asked to go), m/s", gt=0
    )
    max_speed_mps: float = param(6.0, "no command exceeds this speed (v_max), m/s", gt=0)
    release_margin_m: float = param(
        0.3, "an evasion ends once the object is this far outside the window, m", ge=0
    )
    min_altitude_m: float = param(
        2.0, "below this (or with altitude unknown) never command a downward component, m", ge=0
    )
    trigger: str = param(
        "response",
        "response: evade when the predicted time to the closest approach falls to what the "
        "vehicle needs to move clear (response_*) plus trigger_margin_s, from the image's "
        "looming before depth and fused with depth after; ttc: evade when the depth track's "
        "time-to-collision is under ttc_avoid_s; distance: the paper's fixed thresholds only",
        choices=("distance", "ttc", "response"),
    )
    vehicle_radius_m: float = param(
        0.25, "the vehicle's radius with its propellers (a 450 mm quad: 0.25), m", gt=0
    )
    clearance_margin_m: float = param(
        0.2, "response trigger: pass the object with this much air between the two, m", ge=0
    )
    trigger_margin_s: float = param(
        0.3, "response trigger: start this much earlier than the vehicle's need, s", ge=0
    )
    own_wander_mps: float = param(
        0.13, "response trigger: the vehicle's own unplanned motion (a hover's wander in wind "
        "and GPS noise): where it will be at the passage is uncertain by this times the time "
        "left, added to the passage's uncertainty when judging whether it must move (PX4 SITL "
        "SIH hovering: 0.05 / 0.10 / 0.13 / 0.17 m at 0.5 / 0.8 / 1.0 / 1.2 s, docs/sitl.md), "
        "m/s; 0 = a vehicle that holds still", ge=0,
    )
    object_diameter_min_m: float = param(
        0.15, "smallest plausible object (a small bird, a ball), m: turns the image's miss in "
        "object sizes into metres until depth gives the range", gt=0,
    )
    object_diameter_max_m: float = param(
        1.0, "largest plausible object (a large drone, a big bird), m", gt=0
    )
    image_confirm_s: float = param(
        0.06, "response trigger: an object seen in the image only (no range) must be urgent in "
        "consecutive frames, each consistent with the last, the first this long before the "
        "latest (a quarter frame spared for jitter; at least 3 frames) before it triggers: 3 "
        "frames at 30 fps, 5 at 60, so that a faster camera does not ask less evidence time, s",
        gt=0,
    )
    passage_sigmas: float = param(
        1.0, "the predicted passage is judged this many standard errors towards the vehicle "
        "(worst case over the estimate's uncertainty)", ge=0,
    )
    image_max_passage_std_m: float = param(
        1.0, "response trigger: an object seen in the image only whose passage's standard error "
        "(at the smallest plausible size) exceeds this does not trigger yet: the image cannot say "
        "where it passes, and the worst case over so wide an error is always a hit; m, 0 = off "
        "(1.0: about the widest clearance, 0.25 + 1.0 / 2 + 0.2 m)",
        ge=0,
    )
    looming_window_s: float = param(
        1.0, "image estimate: the course in object sizes (1/angular size and bearing/angular size, "
        "both linear in time on a straight approach) is fitted over this window, s (open-loop "
        "campaign, seed 11: 1.0 s avoided 55 of 98 threats, 0.4 s 51)", gt=0
    )
    looming_min_samples: int = param(6, "image estimate: fewest matched frames in the window", ge=3)
    camera_mount: str = param(
        "body", "how the colour camera is carried: body (fixed to the airframe, looking along "
        "its forward axis: it rolls and pitches with it) or gimbal (held level, turning with "
        "the yaw only); the vehicle's attitude turns its velocity into the camera's axes and "
        "takes the camera's rotation out of the image history", choices=("body", "gimbal"))
    unreported_looming_sigmas: float = param(
        0.0, "response trigger: an object seen in the image only that perception's confidence "
        "does not report may still trigger when its size grows by at least this many standard "
        "errors of the fit's expansion (0: never; static structure is still cleared by the "
        "static-structure test)", ge=0)
    ego_rate_noise_rad_s: float = param(
        0.02, "static-structure test (app.decision.ego): the camera's rotation rate not taken "
        "out of the image (attitude jitter), added to a bearing rate's error, rad/s", ge=0)
    looming_max_chi2: float = param(
        9.0, "image estimate: no time to contact when the size's samples stray further than this "
        "from a constant-velocity approach (reduced chi-square at 1 px of noise; real objects in "
        "campaigns 0.3-3.6, clutter that evaded 7-820)", gt=0)
    looming_min_size_px: float = param(
        6.0, "image estimate: no time to contact from blobs smaller than this (after the mask's "
        "dilation): a few pixels are mostly the mask's margin, and one more pixel reads as a "
        "collapse of the time left, px", ge=1)
    max_descent_mps: float = param(
        1.5, "an evasion descends no faster than this: what PX4 flies in Offboard (MPC_Z_VEL_MAX_DN, "
        "default 1.5), m/s", gt=0,
    )
    max_climb_mps: float = param(
        3.0, "an evasion climbs no faster than this (PX4 MPC_Z_VEL_MAX_UP, default 3), m/s", gt=0
    )
    response_speed_mps: float = param(
        3.0, "vehicle response: the evasion speed the response trigger and the choice of escape "
        "count on (the paper's 3 m/s); evasions are flown at evade_speed_mps in the same "
        "direction, and what that buys over this plan is margin, m/s", gt=0,
    )
    response_dead_time_s: float = param(
        0.15, "vehicle response: time before a command starts to move the vehicle (PX4 SITL "
        "SIH: 0.13-0.23 s, docs/sitl.md), s", ge=0,
    )
    response_lag_s: float = param(
        0.79, "vehicle response: first-order time constant of the velocity (PX4 SITL SIH: 2 m/s "
        "commanded reached 1 m/s after ~0.7 s, docs/sitl.md), s", gt=0,
    )
    response_accel_mps2: float = param(
        4.0, "vehicle response: acceleration limit (the stand-in's; PX4's Offboard velocity control "
        "has none of its own, its tilt limit binds: a 3 m/s command moved 0.93-1.07 m in 1 s on "
        "SITL, this model 0.99; 6 m/s 1.68-1.92 m, this model 1.45: short of PX4 at speed, "
        "docs/sitl.md), m/s²",
        gt=0,
    )
    ttc_avoid_s: float = param(
        1.5, "with trigger ttc: evade when time-to-collision < this (campaigns: 1.5 s beat 1.0 s), s",
        gt=0,
    )
    max_depth_age_s: float = param(
        0.2, "a distance older than this never triggers (stale depth is not 'close'), s", gt=0
    )
    kalman_measurement_std_m: float = param(0.15, "3-D track: position measurement noise (std), m", gt=0)
    depth_rms_per_m2: float = param(
        0.0036,
        "3-D track: distance noise grows as this x distance² when that exceeds the above "
        "(D435i: 0.08 subpixel / (447 px x 0.05 m), Intel's D400 tuning guide), 1/m",
        ge=0,
    )
    kalman_accel_std_mps2: float = param(6.0, "3-D track: white acceleration noise (std), m/s²", gt=0)
    kalman_initial_speed_std_mps: float = param(
        5.0,
        "3-D track: velocity uncertainty when an object is first measured (std, per axis; "
        "an approaching object closes at 2-14 m/s: at 1.5 a young track's closing speed read "
        "15-60 % short and its time left long, so evasions started late; open loop, seeds 11 "
        "and 23 and the shaped world: 5.0 cleared 17 more of 386 threats and none fewer, but "
        "evaded 13 of 60 wide passes against 8), m/s",
        gt=0,
    )
    max_hold_s: float = param(
        1.5, "an evasion or stop whose object is no longer measured ends after this, s", gt=0
    )


# --------------------------------------------------------------------------- flight

FLIGHT_MODES = ("position", "hold", "mission", "altitude", "manual", "offboard", "return",
                "land", "takeoff", "other")


@dataclass(frozen=True)
class FlightConfig:
    """Engagement with the autopilot: when midair may take control and how it gives it back."""

    connection: str = param(
        "serial:///dev/serial0:921600",
        "MAVSDK connection URL: the Pi's UART to TELEM2; udpin://0.0.0.0:14540 for PX4 SITL",
    )
    connect_timeout_s: float = param(
        10.0, "give up (exit, systemd retries) when no autopilot answers within this, s", gt=0
    )
    mode: str = param(
        "guard",
        "guard: monitor and intervene; shadow: never command, only log what it would do; "
        "test-flight: the paper's experiment (take off, fly forward, evade, hold)",
        choices=("guard", "shadow", "test-flight"),
    )
    test_altitude_m: float = param(5.0, "test-flight: take-off altitude above home, m", gt=0)
    forward_speed_mps: float = param(
        2.0, "test-flight: forward speed of the leg (paper §5-C: 2 m/s), m/s", gt=0
    )
    test_max_cruise_s: float = param(
        10.0, "test-flight: the forward leg ends (Hold) after this even without a threat, s", gt=0
    )
    takeover_modes: tuple[str, ...] = param(
        ("position", "hold", "mission"),
        "flight modes in which midair may switch the vehicle to offboard",
        choices=FLIGHT_MODES,
    )
    min_takeover_altitude_m: float = param(
        2.0, "never take control below this altitude above home, m", ge=0
    )
    max_decision_age_ms: float = param(
        150.0, "a setpoint comes from a decision younger than this, or is zero velocity, ms", gt=0
    )
    stale_release_s: float = param(
        1.0, "decisions stale this long while in control: leave offboard to Hold, s", gt=0
    )
    release_after_s: float = param(
        0.5, "no threat for this long while in control: hand control back, s", gt=0
    )
    offboard_confirm_s: float = param(
        1.0, "the vehicle must report Offboard this soon after we ask, or we give up, s", gt=0
    )
    max_mode_age_s: float = param(
        2.0, "a flight mode reported longer ago than this is unknown (PX4 reports it at 1 Hz), s",
        gt=0,
    )
    pilot_cooldown_s: float = param(
        10.0, "after the pilot takes control back, do not take over again for this long, s", ge=0
    )
    offboard_loss_s: float = param(
        1.0, "PX4's COM_OF_LOSS_T: a link outage longer than this while in control means PX4's "
        "offboard-loss failsafe has acted, and midair gives control up for the cooldown, s", gt=0,
    )


@dataclass(frozen=True)
class Config:
    """midair configuration."""

    perception: PerceptionConfig = field(default_factory=PerceptionConfig)
    camera: CameraConfig = field(default_factory=CameraConfig)
    decision: DecisionConfig = field(default_factory=DecisionConfig)
    flight: FlightConfig = field(default_factory=FlightConfig)
    capture: CaptureConfig = field(default_factory=CaptureConfig)
    record: RecordConfig = field(default_factory=RecordConfig)


# --------------------------------------------------------------------------- loading


def load_config(path: str | Path | None = None) -> Config:
    """Load and validate a YAML configuration; ``None`` gives the built-in defaults.

    Keys left out of the file keep their defaults. Raises :class:`ConfigError` naming
    the offending key for an unknown key, a wrong type or an out-of-range value.
    """
    if path is None:
        return Config()
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ConfigError(f"config file {p} does not exist") from None
    except OSError as exc:
        raise ConfigError(f"config file {p} cannot be read: {exc.strerror}") from None
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark else ""
        raise ConfigError(f"config file {p} is not valid YAML{where}") from None
    if data is None:
        data = {}
    return config_from_mapping(data, source=str(p))


def config_from_mapping(data: Any, source: str = "config") -> Config:
    """Build a validated :class:`Config` from plain data (as parsed from YAML)."""
    if not isinstance(data, Mapping):
        raise ConfigError(f"{source}: the top level must be a mapping of sections")
    cfg = _build(Config, data, prefix="")
    check_consistency(cfg)
    return cfg


# Keys a config file of an earlier version may hold, and what took their place.
RENAMED = {
    "decision.image_confirm_frames": "use decision.image_confirm_s, the same evidence in seconds "
                                     "(3 frames at 30 fps: 0.06), which holds at any frame rate",
}


def _build(cls: type[T], data: Mapping[str, Any], prefix: str) -> T:
    hints = get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
    for key in data:
        if key not in fields:
            if f"{prefix}{key}" in RENAMED:
                raise ConfigError(f"{prefix}{key}: no longer a setting: {RENAMED[f'{prefix}{key}']}")
            known = ", ".join(sorted(fields))
            raise ConfigError(f"{prefix}{key}: unknown key (known here: {known})")
    kwargs: dict[str, Any] = {}
    for name, f in fields.items():
        if name not in data:
            continue
        key = f"{prefix}{name}"
        value = data[name]
        typ = hints[name]
        if dataclasses.is_dataclass(typ):
            if not isinstance(value, Mapping):
                raise ConfigError(f"{key} = {value!r}: must be a section (a mapping)")
            kwargs[name] = _build(typ, value, prefix=f"{key}.")  # type: ignore[arg-type]
        else:
            kwargs[name] = _check(key, value, typ, f.metadata)
    return cls(**kwargs)


def _check(key: str, value: Any, typ: Any, meta: Mapping[str, Any]) -> Any:
    shown = f"{key} = {value!r}"
    args = getattr(typ, "__args__", ())
    if type(None) in args:  # "X | None": null is allowed, anything else must be an X
        if value is None:
            return None
        typ = next(a for a in args if a is not type(None))
    if getattr(typ, "__origin__", None) is tuple:  # tuple[str, ...]: a YAML list of strings
        if not isinstance(value, list) or not all(isinstance(v, str) for v in value):
            raise ConfigError(f"{shown}: must be a list of strings")
        choices = meta.get("choices")
        for v in value:
            if choices is not None and v not in choices:
                raise ConfigError(f"{shown}: {v!r} is not one of {', '.join(choices)}")
        return tuple(value)
    if typ is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{shown}: must be true or false")
        return value
    if typ is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{shown}: must be a whole number")
    elif typ is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{shown}: must be a number")
        value = float(value)
        if not math.isfinite(value):
            raise ConfigError(f"{shown}: must be finite")
    elif typ is str:
        if not isinstance(value, str):
            raise ConfigError(f"{shown}: must be a string")
    rules = (("gt", ">", lambda v, b: v > b), ("ge", ">=", lambda v, b: v >= b),
             ("lt", "<", lambda v, b: v < b), ("le", "<=", lambda v, b: v <= b))
    for name, sym, ok in rules:
        bound = meta.get(name)
        if bound is not None and not ok(value, bound):
            raise ConfigError(f"{shown}: must be {sym} {bound:g}")
    choices = meta.get("choices")
    if choices is not None and value not in choices:
        raise ConfigError(f"{shown}: must be one of {', '.join(map(str, choices))}")
    if meta.get("odd") and value % 2 != 1:
        raise ConfigError(f"{shown}: must be odd")
    return value


def pyramid_levels_held(image_px: int, lk_window_px: int) -> int:
    """How many pyramid levels above the base OpenCV's LK builds for an image whose smaller
    side is ``image_px``: it halves the side (rounding up) and stops before a level that is
    not larger than the LK window (cv2.buildOpticalFlowPyramid; checked in the tests)."""
    levels, side = 0, image_px
    while True:
        side = (side + 1) // 2
        if side <= lk_window_px:
            return levels
        levels += 1


def check_consistency(cfg: Config) -> None:
    """Rules that tie several keys together."""
    d = cfg.perception.detection
    if d.min_points_per_window > d.max_points_per_window:
        raise ConfigError(
            f"perception.detection.min_points_per_window = {d.min_points_per_window}: "
            f"must be <= max_points_per_window ({d.max_points_per_window})"
        )
    crop = d.window_px + d.lk_search_px  # a corner window's crop: grown inwards only
    held = pyramid_levels_held(crop, d.lk_window_px)
    if d.lk_pyramid_levels > held:
        # OpenCV would silently build fewer levels than asked for (before this check 3 were
        # configured and 2 ran, unnoticed), and with them track smaller camera motions.
        need = d.lk_search_px
        while pyramid_levels_held(d.window_px + need, d.lk_window_px) < d.lk_pyramid_levels:
            need += 1
        raise ConfigError(
            f"perception.detection.lk_pyramid_levels = {d.lk_pyramid_levels}: a {crop} px crop "
            f"(window_px + lk_search_px) holds at most {held} levels larger than the "
            f"{d.lk_window_px} px LK window; lower it, or raise lk_search_px to {need}"
        )
    dc = cfg.decision
    if dc.min_range_m >= dc.max_range_m:
        raise ConfigError(f"decision.min_range_m = {dc.min_range_m:g}: must be < max_range_m "
                          f"({dc.max_range_m:g})")
    if dc.object_diameter_min_m > dc.object_diameter_max_m:
        raise ConfigError(f"decision.object_diameter_min_m = {dc.object_diameter_min_m:g}: must be "
                          f"<= object_diameter_max_m ({dc.object_diameter_max_m:g})")
    if d.near_min_size_m > dc.object_diameter_min_m:
        raise ConfigError(f"perception.detection.near_min_size_m = {d.near_min_size_m:g}: must be <= "
                          f"decision.object_diameter_min_m ({dc.object_diameter_min_m:g}): the depth "
                          "path would drop objects the decision takes as plausible")
    if dc.response_speed_mps > dc.evade_speed_mps:
        raise ConfigError(f"decision.response_speed_mps = {dc.response_speed_mps:g}: must be <= "
                          f"evade_speed_mps ({dc.evade_speed_mps:g}): the trigger would count on a "
                          "speed the evasion is not flown at")
    if dc.evade_speed_mps > dc.max_speed_mps:
        raise ConfigError(f"decision.evade_speed_mps = {dc.evade_speed_mps:g}: must be <= "
                          f"max_speed_mps ({dc.max_speed_mps:g})")
    if d.near_sigmas > 0 and dc.depth_rms_per_m2 > 0 and abs(d.near_noise_per_m - dc.depth_rms_per_m2) > 1e-9:
        # one stereo error, in two units (sigma_z = c z^2 is sigma_1/z = c): told apart, the
        # depth path and the 3-D track would disagree about the same camera
        raise ConfigError(f"perception.detection.near_noise_per_m = {d.near_noise_per_m:g}: must equal "
                          f"decision.depth_rms_per_m2 ({dc.depth_rms_per_m2:g}), the same stereo error")
    cap = cfg.capture
    if cap.stream == "infrared" and d.chroma_gain > 0:
        raise ConfigError(f"perception.detection.chroma_gain = {d.chroma_gain:g}: the infrared "
                          "imager (capture.stream: infrared) is monochrome; set it to 0")
    if cap.backoff_initial_s > cap.backoff_max_s:
        raise ConfigError(f"capture.backoff_initial_s = {cap.backoff_initial_s:g}: must be <= "
                          f"backoff_max_s ({cap.backoff_max_s:g})")
    if cap.give_up_s * 1000.0 <= cap.frame_timeout_ms:
        raise ConfigError(f"capture.give_up_s = {cap.give_up_s:g}: must be longer than "
                          f"frame_timeout_ms ({cap.frame_timeout_ms:g} ms)")
    avoid = avoid_distance_m(dc)
    if dc.emergency_m >= avoid:
        raise ConfigError(f"decision.emergency_m = {dc.emergency_m:g}: must be < the avoidance "
                          f"distance ({avoid:g} m)")


def avoid_distance_m(dc: DecisionConfig) -> float:
    """avoidThresh: given, or from eq. 4.3, avoidThresh / v_obj = R_safe / v_max."""
    if dc.avoid_m is not None:
        return dc.avoid_m
    return dc.safe_window_m * dc.object_speed_mps / dc.max_speed_mps


def explain(cfg: Config) -> str:
    """Why the decision thresholds have their values (``midair config --explain``)."""
    dc = cfg.decision
    avoid = avoid_distance_m(dc)
    lines = ["Decision thresholds (paper Alg. 4, eq. 4.3: avoidThresh / v_obj = R_safe / v_max)"]
    lines.append(f"  R_safe (decision.safe_window_m)    = {dc.safe_window_m:g} m")
    lines.append(f"  v_max  (decision.max_speed_mps)    = {dc.max_speed_mps:g} m/s")
    if dc.avoid_m is None:
        lines.append(f"  v_obj  (decision.object_speed_mps) = {dc.object_speed_mps:g} m/s")
        lines.append(f"  avoidThresh = R_safe * v_obj / v_max = {dc.safe_window_m:g} * "
                     f"{dc.object_speed_mps:g} / {dc.max_speed_mps:g} = {avoid:.3g} m (derived)")
    else:
        v_obj = avoid * dc.max_speed_mps / dc.safe_window_m
        lines.append(f"  avoidThresh (decision.avoid_m)     = {avoid:g} m (given)")
        lines.append(f"  -> by eq. 4.3 it suits objects up to v_obj = avoidThresh * v_max / R_safe "
                     f"= {v_obj:.3g} m/s")
    lines.append(f"  emergency stop below {dc.emergency_m:g} m; depth trusted in "
                 f"[{dc.min_range_m:g}, {dc.max_range_m:g}] m")
    lines.append(f"  trigger: {dc.trigger}" + (f" (also evade when time-to-collision < "
                                                f"{dc.ttc_avoid_s:g} s)" if dc.trigger == "ttc" else ""))
    return "\n".join(lines)


def describe(cfg: Any = None, prefix: str = "") -> list[tuple[str, Any, str]]:
    """Flatten a config into ``(key, value, doc)`` rows, for ``midair config``."""
    cfg = Config() if cfg is None else cfg
    rows: list[tuple[str, Any, str]] = []
    for f in dataclasses.fields(cfg):
        value = getattr(cfg, f.name)
        if dataclasses.is_dataclass(value):
            rows.extend(describe(value, prefix=f"{prefix}{f.name}."))
        else:
            rows.append((f"{prefix}{f.name}", value, f.metadata.get("doc", "")))
    return rows


def to_yaml(cfg: Any = None) -> str:
    """The configuration as commented YAML that :func:`load_config` reads back."""
    cfg = Config() if cfg is None else cfg
    lines: list[str] = []

    def emit(obj: Any, indent: int) -> None:
        for f in dataclasses.fields(obj):
            value = getattr(obj, f.name)
            pad = "  " * indent
            if dataclasses.is_dataclass(value):
                doc = (type(value).__doc__ or "").strip().splitlines()
                if doc:
                    lines.append(f"{pad}# {doc[0]}")
                lines.append(f"{pad}{f.name}:")
                emit(value, indent + 1)
            else:
                text = yaml.safe_dump(value, default_flow_style=True).strip()
                text = text.removesuffix("...").strip()
                lines.append(f"{pad}{f.name}: {text}  # {f.metadata.get('doc', '')}")

    emit(cfg, 0)
    return "\n".join(lines) + "\n"

