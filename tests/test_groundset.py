"""Synthetic flights over textured ground with truth (app.sim.groundset): reproducible, labels
on the objects' pixels, objects in front of the ground as well as the sky, read by
``midair evaluate`` as one group."""

from __future__ import annotations

import csv
from pathlib import Path

import cv2
import numpy as np
import pytest

from app.cli import main
from app.sim.groundset import plan_flights, write_dataset
from app.tools.evaluate import find_clips


def test_the_plan_is_reproducible_and_keeps_every_object_above_the_ground() -> None:
    a, b = plan_flights(8, 5), plan_flights(8, 5)
    assert a == b and a != plan_flights(8, 6)
    for f in a:
        assert 5.0 <= f.altitude_m <= 40.0 and 0.0 <= f.speed_mps <= 4.0
        assert 2 <= len(f.objects) <= 3 and f.objects[0].approaching
        for o in f.objects:
            for t in (0.0, f.seconds):
                assert o.start_m[2] + o.velocity_mps[2] * t < -1.0  # NED: above the ground


def test_labels_lie_on_the_objects_pixels_in_front_of_ground_and_sky(tmp_path: Path) -> None:
    flights = write_dataset(tmp_path, 2, 3, seconds=4.0)
    (clip_a, clip_b) = find_clips(tmp_path)
    assert {clip_a.group, clip_b.group} == {"groundflights"}
    horizon = (480 - 1) / 2.0  # level camera: the horizon is the principal row
    below = above = 0
    checked = 0
    for clip, flight in zip((clip_a, clip_b), flights, strict=True):
        with clip.gt.open(newline="") as fh:
            rows = [[float(v) for v in r] for r in list(csv.reader(fh))[1:]]
        assert rows, clip.name
        by_frame: dict[int, list[list[float]]] = {}
        for r in rows:
            by_frame.setdefault(int(r[0]), []).append(r)
        cap = cv2.VideoCapture(str(clip.video))
        for k in range(1, int(flight.seconds * 30) + 1):
            ok, frame = cap.read()
            assert ok
            grey = cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY)
            for _f, oid, x, y, w, h in by_frame.get(k, []):
                assert 0 <= x and 0 <= y and x + w <= 848.01 and y + h <= 480.01
                u, v = x + w / 2, y + h / 2
                below += v > horizon + h
                above += v < horizon - h
                uncut = x > 0 and y > 0 and x + w < 848 and y + h < 480
                if w >= 12 and h >= 12 and uncut:  # its body at its centre
                    obj = flight.objects[int(oid) - 1]
                    centre = grey[int(v) - 1:int(v) + 2, int(u) - 1:int(u) + 2].astype(int)
                    closest = int(np.abs(centre - obj.grey).min())
                    assert closest < 30, (clip.name, k, oid, centre.tolist(), obj.grey)
                    checked += 1
        cap.release()
    assert checked > 10 and below > 0 and above > 0


def test_demo_writes_and_scores_ground_flights_and_refuses_a_bad_count(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["demo", "--ground-flights", "0", "--out", str(tmp_path / "none")]) == 2
    assert "--ground-flights 0: must be at least 1" in capsys.readouterr().err
    assert not (tmp_path / "none").exists()
    for command in ("demo", "simulate"):  # numpy's own error was a traceback
        with pytest.raises(SystemExit) as exit_info:
            main([command, "--seed", "-1", "--out", str(tmp_path / "none")])
        assert exit_info.value.code == 2
        assert "argument --seed: -1: must be 0 or more" in capsys.readouterr().err
    assert not (tmp_path / "none").exists()
    out = tmp_path / "ground"
    assert main(["demo", "--ground-flights", "1", "--seed", "4", "--workers", "1", "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "| groundflights | 1 |" in text
    assert (out / "evaluation.md").exists() and (out / "clips.csv").exists()
    with (out / "objects.csv").open(newline="") as fh:
        objects = list(csv.DictReader(fh))
    coming = sum(o["approaching"] == "1" for o in objects)
    assert coming >= 1 and "objects coming at the vehicle: " in text and f"of {coming} ever reported" in text


def test_how_steadily_objects_coming_at_the_vehicle_are_reported_needs_the_objects_index(
        tmp_path: Path) -> None:
    from app.config import Config
    from app.errors import UsageError
    from app.tools.evaluate import ApproachShare, approach_shares

    with pytest.raises(UsageError, match="no objects.csv"):
        approach_shares(tmp_path, Config())
    assert ApproachShare("c", 1, 10, 4, 7, 5).share == pytest.approx(5 / 7)
    assert ApproachShare("c", 1, 10, None, 0, 0).share is None


def test_with_depth_each_flight_is_a_recording_through_the_infrared_imager_with_its_depth(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """``--depth``: recording folders that the replay reads with depth registered to the
    image (so the depth path runs), one depth frame per frame, and the labels' objects nearer
    in depth than what lies beside them; asked for without ground flights, refused by name."""
    from app.perception.near import registered
    from app.runtime.sources import open_source

    assert main(["demo", "--depth", "--out", str(tmp_path / "none")]) == 2
    assert "--depth: only with --ground-flights" in capsys.readouterr().err
    write_dataset(tmp_path, 1, 4, seconds=2.0, depth=True)  # (seed 4: an object low, in front of the ground)
    (clip,) = find_clips(tmp_path)
    assert clip.video.is_dir() and clip.name == clip.video.name
    source = open_source(clip.video)
    assert source.has_depth and source.camera is not None
    assert registered(source.camera, (480, 848)) and source.camera.color.fx < 450  # 87° across
    gt: dict[int, list[list[float]]] = {}
    with clip.gt.open(newline="") as fh:
        for row in csv.DictReader(fh):
            gt.setdefault(int(row["frame"]), []).append([float(row[k]) for k in ("x", "y", "w", "h")])
    frames = checked = nearer = 0
    for f in source:
        frames += 1
        assert f.depth is not None and f.depth.shape == (480, 848) and f.depth.dtype == np.uint16
        for x, y, w, h in gt.get(f.index, []):
            u, v = int(x + w / 2), int(y + h / 2)
            ring = f.depth[v, max(0, u - int(w) - 20):max(0, u - int(w))]
            if f.depth[v, u] and ring.any():
                checked += 1
                nearer += int(f.depth[v, u] < np.median(ring[ring > 0]))
    assert frames == 60 and checked > 10 and nearer >= 0.8 * checked
