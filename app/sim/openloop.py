"""Open loop: a development measure of *when* and *which way* the decision first acts.

Each encounter is flown by its script (the vehicle hovers or flies its leg; nothing it
commands is flown), rendered and run through the same perception and decision as the
flight process, faster than real time, and stopped at the first command. That command is
then scored against the encounter's exact geometry:

- **cleared**: had the vehicle moved from that moment as the response model says
  (``decision.response_*``: dead time, lag, acceleration limit) along the commanded
  direction, would the object have passed at least the two radii + the campaign's margin
  off? The forward motion is kept as scripted (the flight process commands no forward
  speed during an evasion, and a vehicle that slows has more time, so this errs short).
- **towards**: for objects approaching at 20-50°, does the first evasion move towards the
  object's true passage (:func:`app.sim.simulate._direction_vs_truth`, as the campaign)?
- its source (image, depth, fused), the time left it saw against the truth, and the age of
  the commanding object's 2-D track and of its 3-D (depth) track.
- **the passage's doubt**: how far the commanding object's predicted passage (at the
  plausible size nearest the object's) lay from the true one across the line of flight, in
  metres and in its stated standard errors: the escape trusts that doubt.

It is not the closed loop (``midair simulate --campaign``, which flies the vehicle in real
time against the stand-in PX4): it leaves out the feedback of the vehicle's own motion into
the camera, the perception thread's frame dropping and the MAVLink path. It runs a 150
encounter set in a few minutes, so a change to the decision can be screened on several
seeds and worlds before a closed-loop campaign settles it.
"""

from __future__ import annotations

import csv
import math
import time
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import asdict, dataclass
from multiprocessing import get_context
from pathlib import Path

import numpy as np

from app.config import Config
from app.decision.policy import EVADE, NONE, DecisionMaker
from app.decision.response import ResponseModel
from app.perception.near import depth_lens
from app.perception.pipeline import Perception
from app.perception.tracking import TrackReport
from app.sim.fast import _Script, script_ego
from app.sim.results import wilson
from app.sim.simulate import (
    SAFETY_MARGIN_M,
    VEHICLE_RADIUS_M,
    Encounter,
    SimulatedCamera,
    _direction_vs_passage,
    _true_passage,
    on_object,
    world_for,
)


@dataclass
class OpenLoopResult:
    encounter: Encounter
    threat: bool
    set: str = "main"  # main | wide | crossing | free
    in_view_s: float = 0.0
    # first frame a confirmed track lay on the object (the campaign's gate), and one that
    # perception's confidence reported, s before the closest approach
    tracked_before_cpa_s: float | None = None
    reported_before_cpa_s: float | None = None
    # share of the frames 2.0-1.0 s before the closest approach, the object in view, in which
    # a reported track (matched or coasting) lay on it (None: commanded before, or not in view
    # then): a first sighting says little when the object is lost again among clutter
    reported_share_2_1: float | None = None
    commanded: bool = False
    action: str = NONE
    command_before_cpa_s: float | None = None
    source: str = ""  # the commanding object's estimate: image | depth | fused
    tau_s: float | None = None  # the time left it saw, s
    true_tau_s: float | None = None  # the truth's time to the camera plane then, s
    track_age_s: float | None = None  # of its 2-D track (perception), s
    depth_age_s: float | None = None  # of its 3-D track (depth), s; None: image only
    passage_std_m: float | None = None  # its passage's stated std (smallest plausible size), m
    # its predicted passage against the truth's, across the line of flight (at the plausible
    # size nearest the object's): the distance, m, and that in the passage's stated std
    passage_err_m: float | None = None
    passage_err_sigmas: float | None = None
    right_mps: float = 0.0
    down_mps: float = 0.0
    towards_passage: bool | None = None
    passage_along_m: float | None = None  # the true passage along the escape's direction, m
    separation_m: float = math.inf  # the closest approach had it moved as the response model says
    cleared: bool = False
    reason: str = ""
    wall_s: float = 0.0

    def row(self) -> dict[str, object]:
        out = {k: v for k, v in asdict(self).items() if k != "encounter"}
        out.update({f"enc_{k}": v for k, v in asdict(self.encounter).items()})
        return out


def separation_after(enc: Encounter, t_cmd: float | None, right: float, down: float,
                     response: ResponseModel) -> float:
    """The closest approach (m) when the vehicle, from ``t_cmd`` s after the start (None:
    never), moves along (right, down) as ``response`` says; forward as scripted."""
    t = np.arange(0.0, enc.t_cpa_s + enc.after_s, 0.005)
    rel = enc.relative_path(t)
    speed = math.hypot(right, down)
    if t_cmd is not None and speed > 0:
        scale = speed / response.speed_mps
        s = np.array([response.displacement_m(v - t_cmd) * scale for v in t])
        # body right = east, down = down (the script flies north at yaw 0)
        rel[:, 1] -= s * right / speed
        rel[:, 2] -= s * down / speed
    return float(np.min(np.linalg.norm(rel, axis=1)))


def fly_open_loop(cfg: Config, enc: Encounter, set_name: str = "main") -> OpenLoopResult:
    """One encounter by its script, stopped at the first command, scored from the truth."""
    import cv2

    cv2.setNumThreads(1)
    wall0 = time.monotonic()
    camera = SimulatedCamera(enc, _Script(enc.altitude_m, enc.own_speed_mps), world=world_for(cfg, enc),
                             paced=False)
    perception = Perception(cfg.perception, camera=depth_lens(camera.lens, cfg.capture.stream))
    decider = DecisionMaker.for_perception(cfg.decision, camera.lens, cfg.perception.detection)
    ego = script_ego(enc)  # the autopilot's velocity: the script's, flown exactly
    res = OpenLoopResult(enc, enc.threat, set_name, in_view_s=enc.in_view_s(camera.lens.color))
    first_2d: dict[int, float] = {}
    first_3d: dict[int, float] = {}
    window = [0, 0]  # frames 2.0-1.0 s before the closest approach with the object in view, reported
    t0 = 0.0
    t_cmd_s: float | None = None  # when the first command came, s after the first frame
    for frame in camera:
        t0 = camera.t_start or 0.0  # set as the first frame is drawn; frames are stamped from it
        result = perception.push(frame)
        if result is None:
            continue
        t_s = result.frame.t_s
        for tr in result.tracks:
            first_2d.setdefault(tr.track_id, t_s)
        before_cpa_s = enc.t_cpa_s - (t_s - t0)
        on = _mark_tracked(res, camera, result.frame.index, result.tracks, before_cpa_s)
        if on is not None and 1.0 <= before_cpa_s <= 2.0:
            window[0] += 1
            window[1] += on
        command, objects = decider.step(result.tracks, result.frame.depth, t_s, enc.altitude_m, ego=ego)
        for o in objects:
            if o.source != "image":
                first_3d.setdefault(o.track_id, t_s)
        if command.action == NONE:
            continue
        t_cmd = t_s - t0
        res.commanded, res.action, res.reason = True, command.action, command.reason
        res.command_before_cpa_s = round(enc.t_cpa_s - t_cmd, 3)
        res.right_mps, res.down_mps = round(command.right_mps, 3), round(command.down_mps, 3)
        obj = next((o for o in objects if o.track_id == command.object_id), None)
        passages = []
        if obj is not None:
            res.source = obj.source
            res.tau_s = None if obj.tau_s is None else round(obj.tau_s, 3)
            tid = obj.track_id
            res.track_age_s = round(t_s - first_2d.get(tid, t_s), 3)
            res.depth_age_s = round(t_s - first_3d[tid], 3) if tid in first_3d else None
            passages = obj.passages(cfg.decision.object_diameter_min_m, cfg.decision.object_diameter_max_m)
            res.passage_std_m = round(min(s for _, _, s in passages), 3) if passages else None
        t_cmd_s = t_cmd
        truth = _true_passage(camera, result.frame.index) if enc.with_object else None
        if truth is not None:
            _passage_error(res, passages, truth[0], enc.size_m)
        if enc.with_object:
            rel = enc.relative_path(np.array([t_cmd]))[0]
            closing = enc.own_speed_mps - enc.object_path()[1][0]  # north: the camera's Z
            res.true_tau_s = round(rel[0] / closing, 3) if closing > 0 else None
            if 20.0 <= abs(enc.approach_deg) <= 50.0 and command.action == EVADE:
                res.towards_passage, _, res.passage_along_m = _direction_vs_passage(
                    truth, [0.0, command.right_mps, command.down_mps])
        break
    if window[0] and (t_cmd_s is None or enc.t_cpa_s - t_cmd_s <= 1.0):
        res.reported_share_2_1 = round(window[1] / window[0], 3)
    if enc.with_object:
        res.separation_m = round(separation_after(enc, t_cmd_s, res.right_mps, res.down_mps,
                                                  decider.response), 3)
        res.cleared = res.separation_m >= enc.size_m / 2 + VEHICLE_RADIUS_M + SAFETY_MARGIN_M
    res.wall_s = round(time.monotonic() - wall0, 2)
    return res


def _passage_error(res: OpenLoopResult, passages: list[tuple[float, tuple[float, float, float], float]],
                   true_ned: np.ndarray, size_m: float) -> None:
    """Set ``res.passage_err_m`` / ``_sigmas``: the predicted passage (camera X right, Y down)
    at the plausible size nearest ``size_m`` against the truth's (NED: east, down; the script
    flies north at yaw 0)."""
    if not passages:
        return
    _, m, std = min(passages, key=lambda p: abs(p[0] - size_m))
    err = math.hypot(m[0] - float(true_ned[1]), m[1] - float(true_ned[2]))
    res.passage_err_m = round(err, 3)
    res.passage_err_sigmas = round(err / std, 2) if std > 0 else None


def _mark_tracked(res: OpenLoopResult, camera: SimulatedCamera, index: int, tracks: list[TrackReport],
                  before_cpa_s: float) -> bool | None:
    """Note when a track's cluster first lay on the object, and when a reported one's did (the
    campaign's :func:`app.sim.simulate.on_object`); return whether a reported track, matched
    or coasting, lies on it in this frame (None: the object is not in view)."""
    truth = camera.truth[index - 1] if 0 < index <= len(camera.truth) else None
    if truth is None or truth.pixel is None:
        return None
    for tr in tracks:
        if tr.cluster is not None and on_object(tr.cluster.box, truth.pixel):
            if res.tracked_before_cpa_s is None:
                res.tracked_before_cpa_s = round(before_cpa_s, 3)
            if tr.reported and res.reported_before_cpa_s is None:
                res.reported_before_cpa_s = round(before_cpa_s, 3)
    return any(tr.reported and on_object(tr.box, truth.pixel) for tr in tracks)


def run_open_loop(cfg: Config, sets: Sequence[tuple[str, Sequence[Encounter]]], workers: int,
                  progress: Callable[[OpenLoopResult], None] | None = None) -> list[OpenLoopResult]:
    """Every encounter of every (name, encounters) set, on ``workers`` processes; in order."""
    jobs = [(name, e) for name, group in sets for e in group]
    if workers <= 1:
        out = []
        for name, e in jobs:
            out.append(fly_open_loop(cfg, e, name))
            if progress:
                progress(out[-1])
        return out
    done: dict[int, OpenLoopResult] = {}
    with ProcessPoolExecutor(workers, mp_context=get_context("spawn")) as pool:
        futures = {pool.submit(fly_open_loop, cfg, e, name): i for i, (name, e) in enumerate(jobs)}
        for fut in as_completed(futures):
            done[futures[fut]] = r = fut.result()
            if progress:
                progress(r)
    return [done[i] for i in range(len(jobs))]


def _frac(k: int, n: int) -> str:
    if not n:
        return "–"
    lo, hi = wilson(k, n)
    return f"{k}/{n} ({lo:.0%}–{hi:.0%})"


def write_open_loop(out: Path, results: list[OpenLoopResult], in_view_s: float = 1.5) -> str:
    """``openloop.csv`` and a short summary (returned, and written as ``openloop.md``)."""
    out.mkdir(parents=True, exist_ok=True)
    rows = [r.row() for r in results]
    if rows:
        with (out / "openloop.csv").open("w", newline="") as fh:
            w = csv.DictWriter(fh, fieldnames=list(rows[0]))
            w.writeheader()
            w.writerows(rows)
    threats = [r for r in results if r.threat and r.set in ("main", "crossing")]
    seen = [r for r in threats if r.in_view_s >= in_view_s]
    wide = [r for r in results if r.set == "wide"]
    free = [r for r in results if not r.encounter.with_object]

    def towards(group: list[OpenLoopResult]) -> str:
        judged = [r for r in group if r.towards_passage is not None]
        return f"{sum(bool(r.towards_passage) for r in judged)} of {len(judged)}"

    def doubt(source: str) -> str:
        judged = [r for r in results if r.source == source and r.passage_err_sigmas is not None]
        off = sum((r.passage_err_sigmas or 0.0) > 2.0 for r in judged)
        return f"{off} of {len(judged)}"

    def median(vals: list[float | None]) -> str:
        v = [x for x in vals if x is not None]
        return f"{float(np.median(v)):.2f}" if v else "–"

    slow = [r for r in seen if r.encounter.object_speed_mps <= 8.0]
    mid = [r for r in seen if 8.0 < r.encounter.object_speed_mps <= 12.0]
    lines = [
        "Open loop (each encounter by its script, stopped at the first command, scored from the truth "
        "with the response model; not the closed loop):",
        f"- threats cleared (main + crossing): {_frac(sum(r.cleared for r in threats), len(threats))}; "
        f"in view ≥ {in_view_s:g} s: {_frac(sum(r.cleared for r in seen), len(seen))}",
        f"- in view, ≤ 8 m/s: {_frac(sum(r.cleared for r in slow), len(slow))}; 8–12 m/s: "
        f"{_frac(sum(r.cleared for r in mid), len(mid))}",
        f"- first command before the closest approach, threats in view, median: "
        f"{median([r.command_before_cpa_s for r in seen])} s (≤ 8 m/s: "
        f"{median([r.command_before_cpa_s for r in slow])} s)",
        f"- first evasions towards the true passage (20–50°): main "
        f"{towards([r for r in results if r.set == 'main'])}, crossing set "
        f"{towards([r for r in results if r.set == 'crossing'])}",
        f"- wide passes commanded: {sum(r.commanded for r in wide)} of {len(wide)}",
        f"- first commands' passages off the truth by more than 2 stated std: {doubt('image')} image, "
        f"{doubt('depth')} depth, {doubt('fused')} fused",
    ]
    lost = [r for r in seen if not r.cleared]

    def late(v: float | None) -> bool:
        return v is None or v < 1.0

    lines.append(f"- in-view threats not cleared: {len(lost)}; of them first tracked < 1.0 s before the "
                 f"closest approach (or never) {sum(late(r.tracked_before_cpa_s) for r in lost)}, first "
                 f"reported < 1.0 s (or never) {sum(late(r.reported_before_cpa_s) for r in lost)}, "
                 f"reported in under half the frames 2-1 s before it "
                 f"{sum(r.reported_share_2_1 is not None and r.reported_share_2_1 < 0.5 for r in lost)}, "
                 f"never commanded {sum(not r.commanded for r in lost)}, first evasion towards the passage "
                 f"{sum(bool(r.towards_passage) for r in lost)}")
    if free:
        minutes = sum(r.encounter.t_cpa_s for r in free) / 60.0
        lines.append(f"- object-free: {sum(r.commanded for r in free)} of {len(free)} flights commanded "
                     f"({minutes:g} min; unconfirmed, the first command only)")
    text = "\n".join(lines) + "\n"
    (out / "openloop.md").write_text(text)
    return text
