"""The evaluation's matching rule on hand-made rows, and the evaluate and bench commands."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from app.sim.synthetic import SyntheticObject, SyntheticScene, write_recording
from app.tools.evaluate import read_boxes, score

Rows = dict[int, list[tuple[int, float, float, float, float]]]


def _hyp(frame: int, tid: int, cx: float, cy: float, side: float = 10.0) -> tuple:
    return (frame, tid, cx - side / 2, cy - side / 2, side, side, 1.0)


def test_score_counts_a_hand_made_case() -> None:
    # One labelled object, a 10 px box centred at (105, 105), in frames 1-6.
    gt: Rows = {f: [(1, 100.0, 100.0, 10.0, 10.0)] for f in range(1, 7)}
    hyp = [
        # frame 1: nothing (a miss)
        _hyp(2, 7, 105, 105),
        _hyp(3, 7, 105 + 19, 105),  # 19 px off: inside the 20 px gate (box side 10 < 20)
        _hyp(4, 7, 105 + 21, 105),  # 21 px off: outside, so a miss and a false object
        _hyp(5, 8, 105, 105),  # the object under another id: a switch
        _hyp(6, 8, 105, 105),
        _hyp(6, 9, 300, 300),  # far from anything: a false object
    ]
    s = score(gt, hyp, 6)
    assert (s["gt_rows"], s["hyp_rows"]) == (6, 6)
    assert (s["tp"], s["fn"], s["fp"]) == (4, 2, 2)
    assert s["id_switches"] == 1
    assert s["recall"] == pytest.approx(4 / 6) and s["precision"] == pytest.approx(4 / 6)
    assert s["mota"] == pytest.approx(1 - (2 + 2 + 1) / 6)
    # a scene cut at frame 5 starts a new segment: the new id there is not a switch
    assert score(gt, hyp, 6, cuts=(5,))["id_switches"] == 0
    # the gate grows with the labelled box: 21 px off a 30 px box is a match
    big: Rows = {4: [(1, 111.0, 90.0, 30.0, 30.0)]}
    assert score(big, [_hyp(4, 7, 126 + 21, 105)], 4)["tp"] == 1


def test_read_boxes_names_a_bad_file(tmp_path: Path) -> None:
    from app.errors import SourceError

    bad = tmp_path / "gt.csv"
    bad.write_text("frame,x,y\n1,2,3\n")
    with pytest.raises(SourceError, match="header must start with frame,id,x,y,w,h"):
        read_boxes(bad)


def test_evaluate_command_on_one_clip_writes_the_tables(tmp_path: Path) -> None:
    scene = SyntheticScene(frames=40, seed=5, objects=(SyntheticObject(1, (120.0, 100.0), (3.0, 0.5), 20.0),))
    rec = write_recording(scene, tmp_path / "clip")
    out = tmp_path / "eval"
    proc = subprocess.run([sys.executable, "-m", "app.cli", "evaluate", str(rec), "--gt", str(rec / "gt.csv"),
                           "--out", str(out)], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert "recall" in proc.stdout and "matching" in (out / "evaluation.md").read_text().lower()
    rows = (out / "evaluation.csv").read_text().splitlines()
    header, first = rows[0].split(","), rows[1].split(",")
    row = dict(zip(header, first, strict=True))
    assert row["clip"] == "clip" and int(row["gt_rows"]) == 40
    # the object is seen from its 5th frame (1 warm-up + 4 to confirm) to the second last
    assert float(row["recall"]) >= 30 / 40 and float(row["precision"]) > 0.95
    # a folder without any ground truth is a user error, not a traceback
    empty = tmp_path / "nothing"
    empty.mkdir()
    bad = subprocess.run([sys.executable, "-m", "app.cli", "evaluate", str(empty)],
                         capture_output=True, text=True, timeout=60)
    assert bad.returncode == 3 and "no clip with ground truth found" in bad.stderr  # unusable input
    assert "Traceback" not in bad.stderr


def test_bench_command_reports_both_variants_as_json() -> None:
    proc = subprocess.run([sys.executable, "-m", "app.cli", "bench", "--frames", "30", "--repeats", "2",
                           "--warmup", "0", "--json"], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    r = json.loads(proc.stdout.strip().splitlines()[-1])
    assert r["frame_size"] == "640x480" and r["opencv_threads"] == 1
    assert r["frames_timed"] == 2 * 28  # per repeat: no result for the first frame, the second warms up
    for variant in ("windows", "full_frame"):
        stages = r[variant]
        assert set(stages) == {"detection", "recognition", "tracking", "total"}
        assert all(0 < s["median_ms"] <= s["p95_ms"] for s in stages.values())
    assert r["median_ms_per_frame"] == r["windows"]["total"]["median_ms"]
    assert r["baseline_median_ms_per_frame"] == r["full_frame"]["total"]["median_ms"]
    ratio = r["baseline_median_ms_per_frame"] / r["median_ms_per_frame"]
    assert r["speedup_vs_full_frame"] == round(ratio, 2)
    assert len(r["repeat_medians_ms"]) == 2
    # the depth path, timed apart on the clip's depth (it runs only where depth is registered)
    assert 0 < r["depth_path"]["median_ms"] <= r["depth_path"]["p95_ms"]
    # the variants take turns every 30 frames; the spread of the ratio within the turns
    assert r["turn_frames"] == 30
    p10, p50, p90 = r["turn_speedup_p10_p50_p90"]
    assert 0 < p10 <= p50 <= p90
    bad = subprocess.run([sys.executable, "-m", "app.cli", "bench", "--repeats", "0"],
                         capture_output=True, text=True, timeout=60)
    assert bad.returncode == 2 and "--repeats 0: must be at least 1" in bad.stderr
    nan = subprocess.run([sys.executable, "-m", "app.cli", "bench", "--warmup", "nan"],
                         capture_output=True, text=True, timeout=60)
    assert nan.returncode == 2 and "--warmup nan: must be between 0 and 600 s" in nan.stderr
