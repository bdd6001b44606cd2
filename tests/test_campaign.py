"""Campaign machinery: results streamed to disk and resumed, the statistics, object-free flight
faster than real time, other worlds, and the Ray backend against the local pool."""

from __future__ import annotations

import csv
import json
import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from app.config import load_config
from app.decision.policy import EVADE, Command, DecisionMaker
from app.errors import UsageError
from app.sim.results import ResultLog, compare, poisson_upper, read_results, result_from_row, wilson
from app.sim.simulate import Encounter, EncounterResult
from app.sim.world import World, load_world

pytest.importorskip("mavsdk")
pytest.importorskip("pymavlink")

from app.cli import main  # noqa: E402
from app.sim.campaign import write_report  # noqa: E402


def _result(seed: int, success: bool, threat: bool = True, **kw: object) -> EncounterResult:
    return EncounterResult(Encounter(seed=seed, object_speed_mps=5.5, miss_m=0.1), threat, success=success,
                           detect_range_m=12.5 if success else None, min_separation_m=0.8,
                           towards_passage=None if seed % 2 else False, **kw)  # type: ignore[arg-type]


def test_a_result_survives_its_csv_row_unchanged(tmp_path: Path) -> None:
    r = _result(7, True, fast_commands=0, fast_wall_s=1.25, in_view_s=3.2)
    r.min_separation_m = math.inf
    path = tmp_path / "x.csv"
    with path.open("w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(r.row()))
        w.writeheader()
        w.writerow(r.row())
    with path.open(newline="") as fh:
        back = result_from_row(next(csv.DictReader(fh)))
    assert back == r


def test_a_row_of_an_older_campaign_reads_with_defaults_for_new_columns() -> None:
    row = {k: str(v) for k, v in _result(3, True).row().items()
           if k not in ("in_view_s", "fast_commands", "fast_wall_s", "enc_world")}
    row = {k: ("" if v == "None" else v) for k, v in row.items()}
    back = result_from_row(row)
    assert back.encounter.seed == 3 and back.encounter.world == "" and back.in_view_s == 0.0
    assert back.fast_commands is None and back.success is True


def test_the_log_keeps_what_finished_and_a_resume_skips_it(tmp_path: Path) -> None:
    plan = {"seed": 1, "campaign": 3}
    log = ResultLog(tmp_path, plan, resume=False)
    log.append(_result(1, True))
    log.append(_result(2, False))
    log.close()
    # the run died while writing a third row
    with (tmp_path / "encounters.csv").open("a") as fh:
        fh.write("False,True,3.1")
    again = ResultLog(tmp_path, plan, resume=True)
    assert sorted(again.done) == [1, 2] and again.done[2].success is False
    again.append(_result(3, True))
    again.close()
    assert [r.encounter.seed for r in read_results(tmp_path)] == [1, 2, 3]
    # a resume under other settings is refused, naming what differs
    with pytest.raises(UsageError, match="campaign differ"):
        ResultLog(tmp_path, {"seed": 1, "campaign": 4}, resume=True)
    # a fresh run into a folder that holds results would overwrite them: refused
    with pytest.raises(UsageError, match=r"already holds a campaign's results \(3 encounters"):
        ResultLog(tmp_path, plan, resume=False)
    assert len(read_results(tmp_path)) == 3
    with pytest.raises(UsageError, match="not a campaign folder"):
        ResultLog(tmp_path / "nowhere", plan, resume=True)


def test_a_report_of_object_free_flight_alone_names_the_rate_it_was_flown_at(tmp_path: Path) -> None:
    """No main set to read the frame rate from: the object-free flights say it (a 60 fps run
    of them was reported as 30)."""
    free = [EncounterResult(Encounter(seed=s, with_object=False, fps=60.0), False, false_evasions=0,
                            success=True, frames=1800, wall_s=30.0) for s in (1, 2)]
    report = write_report(tmp_path, [], free, load_config(None), 60.0).read_text()
    assert "at 60 fps" in report and "at 30 fps" not in report


def test_a_report_says_how_far_each_evasion_towards_the_passage_went_wrong(tmp_path: Path) -> None:
    """A passage a few centimetres to one side of the line of flight and one half a metre
    off are both 'towards'; the report gives each one's distance along the escape."""
    crossing = [EncounterResult(Encounter(seed=s, approach_deg=30.0, miss_m=0.3), True, evaded=True,
                                success=True, towards_passage=along > 0.05, passage_along_m=along)
                for s, along in ((1, -0.3), (2, 0.06), (3, 0.52), (4, 0.02))]
    report = write_report(tmp_path, [], [], load_config(None), 60.0, crossing=crossing).read_text()
    line = next(ln for ln in report.splitlines() if ln.startswith("Crossing set"))
    assert "2 of 4 first evasions moved towards" in line
    assert "(the passage 0.06, 0.52 m along the escape)" in line


def test_poisson_upper_bounds_match_the_exact_tables() -> None:
    assert poisson_upper(0, 1.0) == pytest.approx(2.996, abs=1e-3)  # "rule of three"
    assert poisson_upper(0, 15.0) == pytest.approx(0.1997, abs=1e-3)  # 15 h clean: <= 0.2 per hour
    assert poisson_upper(2, 1.0) == pytest.approx(6.296, abs=1e-3)  # Garwood, one-sided 95 %
    assert poisson_upper(3, 0.0) == math.inf
    lo, hi = wilson(8, 10)
    assert lo == pytest.approx(0.490, abs=1e-3) and hi == pytest.approx(0.943, abs=1e-3)


def test_compare_pairs_by_seed_and_tests_only_the_discordant_pairs() -> None:
    a = [_result(s, True) for s in range(20)]
    b = [_result(s, s >= 10) for s in range(20)]  # B lost ten A avoided
    c = compare(a, b)
    assert (c.pairs, c.a_only, c.b_only) == (20, 10, 0)
    assert c.p_value == pytest.approx(2 * 0.5 ** 10) and c.differ
    # two campaigns that differ by one encounter either way: not beyond chance
    d = compare(a[:19] + [_result(19, False)], [_result(0, False)] + a[1:])
    assert (d.a_only, d.b_only) == (1, 1) and d.p_value == 1.0 and not d.differ
    with pytest.raises(UsageError, match="share no threat"):
        compare(a, [_result(99, True)])


def test_compare_on_the_command_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    for name, results in (("a", [_result(s, True) for s in range(12)]),
                          ("b", [_result(s, s < 2) for s in range(12)])):
        log = ResultLog(tmp_path / name, {"seed": 1}, resume=False)
        for r in results:
            log.append(r)
        log.close()
    assert main(["simulate", "compare", str(tmp_path / "a"), str(tmp_path / "b")]) == 0
    out = capsys.readouterr().out
    assert "avoided by A only: 10, by B only: 0" in out and "differ beyond chance" in out
    assert main(["simulate", "compare", str(tmp_path / "a")]) == 2
    # the open loop's scripts never accelerate: a tilting camera is refused, not ignored
    assert main(["simulate", "--open-loop", "--campaign", "1", "--tilt", "--out", str(tmp_path / "t")]) == 2
    assert "--tilt flies the closed loop only" in capsys.readouterr().err
    # a wandering stand-in cannot be flown where the flights follow the script exactly
    for args, why in ((["--wander", "6", "--campaign", "1"], "--wander 6: a multiple"),
                      (["--wander", "1", "--open-loop", "--campaign", "1"], "not with --connection"),
                      (["--wander", "1", "--object-free", "1"], "--realtime-object-free flies them")):
        assert main(["simulate", *args, "--out", str(tmp_path / "w")]) == 2
        assert why in capsys.readouterr().err
    assert not (tmp_path / "w").exists()
    assert main(["simulate", "compare", str(tmp_path / "a"), str(tmp_path / "none")]) == 2


def test_in_view_time_follows_the_lens() -> None:
    intr = World().intrinsics  # 55 degrees across
    head_on = Encounter(approach_deg=0.0, t_cpa_s=4.0)
    assert head_on.in_view_s(intr) == pytest.approx(4.0, abs=0.05)
    # a collision course from 40 degrees keeps a constant bearing of 40: never in a 55-degree lens
    assert Encounter(approach_deg=40.0).in_view_s(intr) == 0.0
    assert Encounter(with_object=False).in_view_s(intr) == 0.0


# ---------------------------------------------------------------------------- fast object-free


def test_object_free_flight_faster_than_real_time_runs_the_production_path() -> None:
    from app.sim.fast import fly_fast, speed_factor

    cfg = load_config(None)
    enc = Encounter(seed=5, with_object=False, t_cpa_s=3.0, after_s=0.0, own_speed_mps=2.0)
    a, b = fly_fast(cfg, enc), fly_fast(cfg, enc)
    assert a.frames == 90 and a.fast_wall_s is not None and a.false_evasions == 0
    assert (a.false_evasions, a.frames) == (b.false_evasions, b.frames)  # no clock in it
    assert speed_factor([a]) > 0
    with pytest.raises(ValueError, match="only object-free"):
        fly_fast(cfg, Encounter(seed=5))
    with pytest.raises(ValueError, match="wandering hover"):
        fly_fast(cfg, replace(enc, wander=1.0))


def test_a_command_in_the_fast_run_is_flown_again_in_real_time(monkeypatch: pytest.MonkeyPatch) -> None:
    """The fast run is a screen: what it flags is counted by the full closed loop."""
    from app.sim import fast

    cfg = load_config(None)
    real_step = DecisionMaker.step
    calls = {"n": 0}

    def eager(self: DecisionMaker, *args: object, **kw: object) -> tuple[Command, list[object]]:
        command, objects = real_step(self, *args, **kw)  # type: ignore[arg-type]
        calls["n"] += 1
        if calls["n"] == 10:  # the fast run "sees" something once
            return Command(EVADE, 0.0, 1.0, 0.0, 1, reason="test"), objects  # type: ignore[return-value]
        return command, objects  # type: ignore[return-value]

    monkeypatch.setattr(fast.DecisionMaker, "step", eager)
    flown: list[Encounter] = []

    def real_time(cfg_: object, enc: Encounter) -> EncounterResult:
        flown.append(enc)
        return EncounterResult(enc, False, false_evasions=0, success=True, frames=60, wall_s=2.0)

    monkeypatch.setattr(fast, "run_encounter", real_time)
    enc = Encounter(seed=6, with_object=False, t_cpa_s=2.0, after_s=0.0)
    res = fast.fly_fast(cfg, enc)
    assert flown == [enc]  # re-flown in real time
    assert res.fast_commands == 1 and res.false_evasions == 0  # the real-time count is the one kept


# ---------------------------------------------------------------------------- other worlds


def test_a_world_from_a_module_renders_the_encounter(tmp_path: Path) -> None:
    from app.sim.fast import fly_fast

    world = load_world("tests._plain_world:factory", 3, World().intrinsics)
    assert world.camera().color.width == 320
    enc = Encounter(seed=3, with_object=False, t_cpa_s=1.0, after_s=0.0, world="tests._plain_world:factory")
    res = fly_fast(load_config(None), enc)
    assert res.frames == 30 and res.false_evasions == 0
    for spec, why in (("nomodule_xyz:factory", "cannot import"), ("tests._plain_world", "expected"),
                      ("tests._plain_world:missing", "no callable"),
                      ("tests._plain_world:not_a_world", "lacks camera")):
        with pytest.raises(UsageError, match=why):
            load_world(spec, 1, World().intrinsics)
    assert main(["simulate", "--object-free", "0.1", "--world", "nomodule_xyz:f", "--out",
                 str(tmp_path)]) == 2


# ---------------------------------------------------------------------------- whole campaigns


@pytest.mark.timeout(300)
def test_an_interrupted_campaign_resumes_without_running_again_what_it_had(tmp_path: Path) -> None:
    args = ["simulate", "--campaign", "1", "--object-free", "1", "--seed", "4", "--workers", "1",
            "--out", str(tmp_path)]
    assert main(args) == 0
    with (tmp_path / "encounters.csv").open(newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == 3  # one threat encounter, two 30 s object-free flights
    # as if it had been stopped after the first two
    with (tmp_path / "encounters.csv").open("w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows[:2])
    assert main([*args, "--resume", str(tmp_path)]) == 0
    with (tmp_path / "encounters.csv").open(newline="") as fh:
        again = list(csv.DictReader(fh))
    assert again[:2] == rows[:2]  # kept as they were (their wall times too): not flown again
    assert again[2]["enc_seed"] == rows[2]["enc_seed"] and again[2]["frames"] == rows[2]["frames"]
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["object_free_minutes"] == 1.0
    assert summary["false_evasions_per_hour_upper95"] == pytest.approx(
        poisson_upper(summary["false_evasions"], 1 / 60))
    # a different command line cannot resume it
    assert main([*args[:-2], "--seed", "5", "--out", str(tmp_path), "--resume", str(tmp_path)]) == 2


@pytest.mark.timeout(300)
def test_ray_and_the_local_pool_fly_the_same_campaign(tmp_path: Path) -> None:
    pytest.importorskip("ray")
    common = ["simulate", "--campaign", "2", "--object-free", "1", "--seed", "8"]
    assert main([*common, "--workers", "1", "--out", str(tmp_path / "pool")]) == 0
    assert main([*common, "--ray", "--out", str(tmp_path / "ray")]) == 0
    pool, ray = read_results(tmp_path / "pool"), read_results(tmp_path / "ray")
    assert [r.encounter for r in pool] == [r.encounter for r in ray]  # the same sample, same order
    # object-free flights faster than real time have no clock in them: identical
    free_p = [r for r in pool if not r.encounter.with_object]
    free_r = [r for r in ray if not r.encounter.with_object]
    assert [(r.frames, r.false_evasions, r.fast_commands) for r in free_p] == \
           [(r.frames, r.false_evasions, r.fast_commands) for r in free_r]
    # real-time encounters: the rates agree within their intervals
    t_p = [r for r in pool if r.threat]
    t_r = [r for r in ray if r.threat]
    assert len(t_p) == len(t_r)
    if t_p:
        kp, kr, n = sum(r.success for r in t_p), sum(r.success for r in t_r), len(t_p)
        lo_p, hi_p = wilson(kp, n)
        lo_r, hi_r = wilson(kr, n)
        # their 95 % intervals overlap (each rate inside the other's interval was too strict
        # for two real-time encounters: 1 of 2 against 2 of 2 failed on one borderline miss)
        assert lo_p <= hi_r and lo_r <= hi_p


def test_ray_missing_or_unreachable_is_a_clear_error(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import builtins

    real_import = builtins.__import__

    def no_ray(name: str, *a: object, **kw: object) -> object:
        if name == "ray":
            raise ImportError("No module named 'ray'")
        return real_import(name, *a, **kw)  # type: ignore[arg-type]

    monkeypatch.setattr(builtins, "__import__", no_ray)
    cfg = load_config(None)
    from app.sim.cluster import run_on_ray

    with pytest.raises(UsageError, match=r"pip install 'midair\[cluster\]'"):
        run_on_ray(cfg, [replace(Encounter(), with_object=False)], lambda r: None, True, None)


def test_the_shaped_world_draws_flapping_birds_and_quadrotors_inside_their_circle() -> None:
    from app.sim.world import Sphere, shaped

    world = shaped(3, World().intrinsics)
    masks = []
    for kind in ("bird", "bird", "bird", "drone"):
        obj = Sphere(1, (4.0, 0.0, -6.5), 0.5, 40, kind)
        colour, _depth, seen = world.render((0.0, 0.0, -6.0), 0.0, [obj])
        u, v, r, _z = seen[1]
        dark = colour[:, :, 0] < 100
        dark[int(v) + 30:] = False  # the ground and the trees below the horizon are not the object
        ys, xs = dark.nonzero()
        assert ys.size and (np.hypot(xs - u, ys - v) <= r + 2).all()  # inside the reported circle
        masks.append(dark)
    assert (masks[0] != masks[1]).sum() > 20  # the wings beat from frame to frame
    assert masks[3].sum() < 0.6 * math.pi * r * r  # a quadrotor's cross, not a filled disc
    # the sky drifts even with the vehicle still
    a, _, _ = world.render((0.0, 0.0, -6.0), 0.0, [])
    b, _, _ = world.render((0.0, 0.0, -6.0), 0.0, [])
    assert np.abs(a[:100].astype(int) - b[:100].astype(int)).mean() > 0.3


def test_the_crossing_set_crosses_the_view_with_a_side_to_pass_on() -> None:
    from app.sim.campaign import crossing_set, sample_encounters

    encs = crossing_set(40, 5)
    assert encs == crossing_set(40, 5)  # reproducible from the seed
    assert all(20.0 <= abs(e.approach_deg) <= 50.0 for e in encs)
    assert {math.copysign(1, e.approach_deg) for e in encs} == {-1.0, 1.0}
    assert all(0.15 <= e.miss_m <= 0.55 and e.threat for e in encs)
    assert not {e.seed for e in encs} & {e.seed for e in sample_encounters(40, 5)}


def test_the_true_passage_is_judged_on_the_course_not_on_one_frame_of_cruise_jitter() -> None:
    """The vehicle cruises north at 4 m/s with +-1 m/s of controller jitter from frame to
    frame; the object crosses from ahead-right, flying south-west, and passes 0.3 m from where
    the vehicle will be, on its right (east, 0.21 m of it sideways). Leaving to the left is
    away from the passage, to the right towards it, whatever the jitter did in the last frame
    (from the last two frames' relative velocity, the passage changes side)."""
    from types import SimpleNamespace

    from app.sim.simulate import Truth, _direction_vs_truth

    rows, n_v = [], 0.0
    for k in range(1, 31):
        t = k / 30.0
        n_v += (4.0 + (1.0 if k % 2 else -1.0)) / 30.0
        # relative to the vehicle's nominal path (4t north): crossing at t = 2 s, 0.3 m east
        obj = (4.0 * t + 8.0 * (2.0 - t), 0.3 / (8.0 / math.hypot(8.0, 8.0)) + 8.0 * (2.0 - t), -6.0)
        rows.append(Truth(k, t, (n_v, 0.0, -6.0), obj, None))
    cam = SimpleNamespace(truth=rows)
    away, _, left_m = _direction_vs_truth(cam, 30, [0.0, -3.0, 0.0])  # type: ignore[arg-type]
    towards, _, right_m = _direction_vs_truth(cam, 30, [0.0, 3.0, 0.0])  # type: ignore[arg-type]
    assert away is False and towards is True
    # and by how much: the passage's sideways 0.21 m, along each escape
    assert left_m is not None and right_m is not None
    assert right_m == pytest.approx(0.21, abs=0.02) and left_m == pytest.approx(-right_m, abs=1e-3)
