"""The open-loop screen (app.sim.openloop): its geometry against the encounter's script, and
one encounter flown through perception and decision to its first command."""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from app.config import Config
from app.decision.response import ResponseModel
from app.sim.openloop import fly_open_loop, separation_after, write_open_loop
from app.sim.simulate import Encounter

RESPONSE = ResponseModel(0.15, 0.79, 4.0, 3.0)


@pytest.mark.parametrize("approach, climb, own, miss", [(0.0, 0.0, 0.0, 0.0), (35.0, 10.0, 3.0, 0.4),
                                                        (-45.0, -12.0, 4.0, 2.5)])
def test_with_no_command_the_object_passes_at_the_scripted_miss(approach: float, climb: float, own: float,
                                                                 miss: float) -> None:
    enc = Encounter(approach_deg=approach, climb_deg=climb, own_speed_mps=own, miss_m=miss,
                    miss_dir_deg=120.0)
    assert separation_after(enc, None, 0.0, 0.0, RESPONSE) == pytest.approx(miss, abs=0.01)


def test_a_command_away_from_the_passage_adds_what_the_response_model_moves_and_towards_it_takes_it() -> None:
    """A head-on object passing 0.4 m to the right (hovering): commanded 1.0 s before the
    closest approach, a move left adds the response model's displacement in that second (the
    nearest comes a little earlier), a move up adds it at right angles, and a move right
    crosses the object's path on the way."""
    enc = Encounter(object_speed_mps=6.0, miss_m=0.4, miss_dir_deg=180.0)
    start, vel = enc.object_path()
    assert (start + vel * enc.t_cpa_s)[1] == pytest.approx(0.4)  # east of the vehicle: its right
    moved = RESPONSE.displacement_m(1.0)
    assert 0.5 < moved < 2.0
    left = separation_after(enc, enc.t_cpa_s - 1.0, -3.0, 0.0, RESPONSE)
    right = separation_after(enc, enc.t_cpa_s - 1.0, 3.0, 0.0, RESPONSE)
    # the nearest is a little before the closest approach, while the vehicle is still moving
    early = RESPONSE.displacement_m(0.85)
    assert 0.4 + early <= left <= 0.4 + moved
    assert right < left - 0.5  # towards the passage: it crossed the object's path on the way
    up = separation_after(enc, enc.t_cpa_s - 1.0, 0.0, -3.0, RESPONSE)
    assert math.hypot(0.4, early) <= up <= math.hypot(0.4, moved)


def test_a_head_on_ball_is_commanded_in_time_and_cleared_open_loop(tmp_path: Path) -> None:
    """The README's first encounter flown by its script through perception and decision: the
    first command comes early enough to clear it, and the summary says so."""
    enc = Encounter(seed=3, object_speed_mps=6.0, approach_deg=10.0)
    res = fly_open_loop(Config(), enc)
    assert res.commanded and res.action == "evade"
    assert res.command_before_cpa_s is not None and res.command_before_cpa_s > 0.8
    assert res.tracked_before_cpa_s is not None and res.tracked_before_cpa_s > res.command_before_cpa_s
    assert res.source in ("image", "fused") and res.tau_s is not None
    assert res.cleared and res.separation_m > enc.size_m / 2 + 0.45
    # its predicted passage against the truth's (head-on: through the vehicle), within its doubt
    assert res.passage_err_m is not None and res.passage_err_m < 0.3
    assert res.passage_std_m is not None and res.passage_err_sigmas is not None
    assert res.passage_err_sigmas == pytest.approx(res.passage_err_m / res.passage_std_m, abs=0.02)
    text = write_open_loop(tmp_path, [res])
    assert "threats cleared (main + crossing): 1/1" in text
    off = int(res.passage_err_sigmas > 2.0)
    assert f"more than 2 stated std: 0 of 0 image, 0 of 0 depth, {off} of 1 fused" in text
    assert (tmp_path / "openloop.csv").read_text().count("\n") == 2


def test_how_steadily_the_object_was_reported_before_a_late_command_is_measured() -> None:
    """With the paper's fixed distances the first command comes under a second before the
    closest approach, so the share of the frames 2-1 s before it in which a reported track lay
    on the ball is measured: with every matched track reported (``min_confidence: 0``) the
    ball is held in most of them; the confidence suppresses it in some (it sits on the
    horizon, ground texture in its ring). A command earlier than 1 s before leaves it unset.
    Through the colour lens, where it was measured: the infrared imager's coarser pixels track
    the same ball 1.8 s before the closest approach, not 3.0 s, and report it only 0.77 s
    before (the next test)."""
    from dataclasses import replace

    from app.config import CaptureConfig

    cfg = replace(Config(), capture=replace(CaptureConfig(), stream="color"))
    late = replace(cfg, decision=replace(cfg.decision, trigger="distance"))
    every = replace(late, perception=replace(late.perception, confidence=replace(
        late.perception.confidence, min_confidence=0.0)))
    enc = Encounter(seed=3, object_speed_mps=6.0, approach_deg=10.0)
    res, all_matched = fly_open_loop(late, enc), fly_open_loop(every, enc)
    for r in (res, all_matched):
        assert r.commanded and r.command_before_cpa_s is not None and r.command_before_cpa_s < 1.0
    assert all_matched.reported_share_2_1 is not None and all_matched.reported_share_2_1 >= 0.7
    assert res.reported_share_2_1 is not None and 0 < res.reported_share_2_1 < all_matched.reported_share_2_1
    early = fly_open_loop(cfg, enc)  # the response trigger: commanded before 1 s
    assert early.command_before_cpa_s is not None and early.command_before_cpa_s > 1.0
    assert early.reported_share_2_1 is None


def test_the_readme_ball_through_the_infrared_imager_is_evaded_over_a_second_ahead() -> None:
    """The default stream's wider, coarser lens: the README's ball (6 m/s, 10° off the nose)
    is tracked later than through the colour lens, and its confidence stays under
    min_confidence until after the 2-1 s window, but the fused estimate (the image's looming
    with a range that confirms it) commands the evasion more than a second before the
    closest approach, and it clears."""
    cfg = Config()
    assert cfg.capture.stream == "infrared"
    r = fly_open_loop(cfg, Encounter(seed=3, object_speed_mps=6.0, approach_deg=10.0))
    assert r.tracked_before_cpa_s is not None and r.tracked_before_cpa_s > 1.5
    assert r.commanded and r.command_before_cpa_s is not None and r.command_before_cpa_s > 1.0
    assert r.source == "fused" and r.cleared


def test_the_open_loop_without_sets_or_with_resume_is_refused_by_name(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from app.cli import main

    assert main(["simulate", "--open-loop", "--out", str(tmp_path / "ol")]) == 2
    assert "--open-loop: give the sets to fly" in capsys.readouterr().err
    assert main(["simulate", "--open-loop", "--campaign", "2", "--resume", str(tmp_path)]) == 2
    assert "neither resumes nor runs on Ray" in capsys.readouterr().err
    assert not (tmp_path / "ol").exists()  # nothing written
