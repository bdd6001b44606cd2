"""Campaigns of closed-loop encounters: sampling, a process pool, the report and its plots.

Each encounter is a pure function of (configuration, :class:`app.sim.simulate.Encounter`), and
every encounter carries its own seed, so the sample is reproducible from the campaign seed
and the runs can go to any pool: a local process pool here (each encounter runs in real
time, so the pool's size is bounded by the cores that keep perception on time), or a
distributed engine's map for campaigns that outgrow one machine.
"""

from __future__ import annotations

import csv
import json
import math
import os
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace
from multiprocessing import get_context
from pathlib import Path
from typing import Any

import numpy as np

from app.config import Config
from app.sim.fast import run_one
from app.sim.results import ResultLog, poisson_upper, wilson
from app.sim.simulate import Encounter, EncounterResult, lens_for

SPEED_BINS = (2.0, 4.0, 6.0, 8.0, 10.0, 14.0)  # m/s
ANGLE_BINS = (0.0, 10.0, 20.0, 30.0, 40.0, 50.0)  # |approach|, deg (sampled to 50; the lens sees +-27.5)
# A threat counts as "in view" when its centre is inside the image, on its nominal course, for
# at least this long before the closest approach: perception's ~0.3 s to confirm plus the
# vehicle's ~1 s to move its clearance (the response model, DecisionConfig.response_*).
IN_VIEW_S = 1.5
KINDS = {  # size m, brightness range (sky ~175-215): ball, bird, small drone
    "ball": (0.25, (20, 60)),
    "bird": (0.4, (50, 120)),
    "drone": (0.35, (20, 50)),
}


def sample_encounters(n: int, seed: int) -> list[Encounter]:
    """``n`` randomised encounters, reproducible from ``seed``."""
    rng = np.random.default_rng(seed)
    out = []
    for i in range(n):
        kind = str(rng.choice(list(KINDS)))
        size, (g0, g1) = KINDS[kind]
        out.append(Encounter(
            seed=int(seed * 100_003 + i), kind=kind,
            object_speed_mps=round(float(rng.uniform(2.0, 14.0)), 2),
            approach_deg=round(float(rng.uniform(-50.0, 50.0)), 1),  # crossing objects too
            climb_deg=round(float(rng.uniform(-15.0, 15.0)), 1),
            miss_m=round(float(rng.choice([0.0, rng.uniform(0.0, 0.6)])), 2),
            miss_dir_deg=round(float(rng.uniform(0.0, 360.0)), 0),
            size_m=round(size * float(rng.uniform(0.8, 1.25)), 2),
            grey=int(rng.integers(g0, g1 + 1)),
            own_speed_mps=float(rng.choice([0.0, 0.0, 1.0, 2.0, 3.0, 4.0])),
        ))
    return out


WIDE_MISS_M = (2.0, 4.0)  # wide passes: outside the 1.5 m window plus its 0.3 m release margin


def wide_passes(n: int, seed: int) -> list[Encounter]:
    """``n`` encounters like :func:`sample_encounters` whose object would miss by 2-4 m:
    nothing to avoid, so every evasion is an unnecessary one (the cost of an eager trigger,
    which the success rate of threats cannot show)."""
    rng = np.random.default_rng(seed + 1)
    return [replace(e, seed=e.seed + 70_000, miss_m=round(float(rng.uniform(*WIDE_MISS_M)), 2))
            for e in sample_encounters(n, seed + 1)]


CROSSING_DEG = (20.0, 50.0)  # |approach| of the crossing set, deg
CROSSING_MISS_M = (0.15, 0.55)  # its misses: inside the clearance, but with a side to pass on


def crossing_set(n: int, seed: int) -> list[Encounter]:
    """``n`` encounters like :func:`sample_encounters` that cross the view (approach 20-50°
    either side) and would pass 0.15-0.55 m off: threats with a side to their passage, so the
    first evasion's direction can be judged against it (a collision course has none)."""
    rng = np.random.default_rng(seed + 2)
    out = []
    for e in sample_encounters(n, seed + 2):
        angle = float(rng.uniform(*CROSSING_DEG)) * float(rng.choice([-1.0, 1.0]))
        out.append(replace(e, seed=e.seed + 80_000, approach_deg=round(angle, 1),
                           miss_m=round(float(rng.uniform(*CROSSING_MISS_M)), 2)))
    return out


def object_free(minutes: float, seed: int, run_s: float = 30.0) -> list[Encounter]:
    """Flights with no object at all over varied worlds and speeds (false evasions)."""
    rng = np.random.default_rng(seed)
    n = max(1, int(math.ceil(minutes * 60.0 / run_s)))
    return [Encounter(seed=int(seed * 100_003 + 50_000 + i), with_object=False, t_cpa_s=run_s,
                      after_s=0.0, own_speed_mps=float(rng.choice([0.0, 1.0, 2.0, 3.0])),
                      altitude_m=round(float(rng.uniform(3.0, 15.0)), 1)) for i in range(n)]


def run_campaign(cfg: Config, encounters: Sequence[Encounter], workers: int,
                 progress: Callable[[EncounterResult], None] | None = None,
                 log: ResultLog | None = None, fast_object_free: bool = False,
                 backend: str = "pool", ray_address: str | None = None) -> list[EncounterResult]:
    """Run every encounter on ``workers`` processes (threats in real time; object-free
    flights faster than real time with ``fast_object_free``, see :mod:`app.sim.fast`);
    results in input order. Each result goes to ``log`` (``encounters.csv``) the moment it
    is done, and encounters ``log`` already holds are not run again (``--resume``).
    ``backend`` "ray" hands the encounters to a Ray cluster instead (:mod:`app.sim.cluster`)."""
    done = dict(log.done) if log is not None else {}
    todo = [e for e in encounters if e.seed not in done]

    def finished(r: EncounterResult) -> None:
        done[r.encounter.seed] = r
        if log is not None:
            log.append(r)
        if progress:
            progress(r)

    if backend == "ray":
        from app.sim.cluster import run_on_ray

        run_on_ray(cfg, todo, finished, fast_object_free, ray_address)
    elif workers <= 1:
        for enc in todo:
            finished(run_one(cfg, enc, fast_object_free))
    else:
        from concurrent.futures import as_completed

        with ProcessPoolExecutor(workers, mp_context=get_context("spawn")) as pool:
            futures = [pool.submit(run_one, cfg, enc, fast_object_free) for enc in todo]
            for fut in as_completed(futures):
                finished(fut.result())
    return [done[e.seed] for e in encounters if e.seed in done]


def default_workers() -> int:
    return max(1, (os.cpu_count() or 2) // 2)


# ---------------------------------------------------------------------------- the report


def _wrong_by(rows: list[EncounterResult]) -> str:
    """How far along the escape each passage moved towards lay (m), for the report: a few
    centimetres is a passage at the line of flight, decided on noise; a metre, a wrong side."""
    along = sorted(r.passage_along_m for r in rows if r.towards_passage and r.passage_along_m is not None)
    return f" (the passage {', '.join(f'{a:.2f}' for a in along)} m along the escape)" if along else ""


def _rate(rows: list[EncounterResult]) -> str:
    if not rows:
        return "–"
    ok = sum(r.success for r in rows)
    lo, hi = wilson(ok, len(rows))
    return f"{ok / len(rows):.0%} ({ok}/{len(rows)}; {lo:.0%}–{hi:.0%})"


def _median(values: Sequence[float | None]) -> str:
    vals = [v for v in values if v is not None]
    return f"{float(np.median(vals)):.2f}" if vals else "–"


def _bins(rows: list[EncounterResult], key: Callable[[EncounterResult], float],
          edges: Sequence[float]) -> list[tuple[str, list[EncounterResult]]]:
    out = []
    for lo, hi in zip(edges, edges[1:], strict=False):
        out.append((f"{lo:g}–{hi:g}", [r for r in rows if lo <= key(r) < hi]))
    return out


def envelope(rows: list[EncounterResult], threshold: float = 0.9) -> float | None:
    """The object speed above which success falls below ``threshold`` (lowest failing bin's
    lower edge), among threats; None when every bin holds."""
    threats = [r for r in rows if r.threat]
    for label, group in _bins(threats, lambda r: r.encounter.object_speed_mps, SPEED_BINS):
        if group and sum(r.success for r in group) / len(group) < threshold:
            return float(label.split("–")[0])
    return None


def _wander(rows: list[EncounterResult]) -> str:
    k = rows[0].encounter.wander if rows else 0.0
    return f", its hover drifting as PX4 SITL's × {k:g}" if k else ""


def _lens(cfg: Config) -> str:
    """What the campaign's perception saw: the stream, its size and width across."""
    lens = lens_for(cfg)
    across = 2.0 * math.degrees(math.atan2(lens.width / 2.0, lens.fx))
    name = "infrared" if cfg.capture.stream == "infrared" else "colour"
    return f"{name} {lens.width}x{lens.height} ({across:.0f}° across)"


def write_report(out: Path, rows: list[EncounterResult], free: list[EncounterResult],
                 cfg: Config, wall_s: float, title: str = "Campaign",
                 wide: Sequence[EncounterResult] = (), crossing: Sequence[EncounterResult] = ()) -> Path:
    """``report.md``, ``encounters.csv`` and PNG plots in ``out``; returns the report's path.
    ``rows``: the campaign's encounters (every rate of the table); ``wide``, ``crossing`` and
    ``free``: the wide passes, the crossing set and the object-free flights, reported apart."""
    crossing_set_rows = list(crossing)
    out.mkdir(parents=True, exist_ok=True)
    tmp = out / "encounters.csv.tmp"  # in campaign order; replaces the log streamed as they ran
    with tmp.open("w", newline="") as fh:
        all_rows = [r.row() for r in [*rows, *wide, *crossing, *free]]
        if all_rows:
            w = csv.DictWriter(fh, fieldnames=list(all_rows[0]))
            w.writeheader()
            w.writerows(all_rows)
    tmp.replace(out / "encounters.csv")
    threats = [r for r in rows if r.threat]
    course = [r for r in threats if r.encounter.miss_m < 0.15]
    # what every set was flown with (a campaign of object-free flights alone has no main rows)
    flown = next((r.encounter for r in [*rows, *wide, *crossing, *free]), Encounter())
    lines = [f"# {title}", "",
             f"{len(rows)} encounters ({len(threats)} threats: would pass within the two radii + "
             f"{0.2:g} m if nobody moved), trigger `{cfg.decision.trigger}`, camera "
             f"{_lens(cfg)} at {flown.fps:g} fps, stand-in vehicle's "
             f"MPC_XY_VEL_P_ACC {flown.xy_vel_p_acc:g}"
             f"{_wander(rows)}, wall time {wall_s:.0f} s.", "",
             "| set | success | detected | detection range median, m | detected before CPA median, s "
             "| evasion before CPA median, s | min separation median, m |",
             "|---|---|---|---|---|---|---|"]
    table_at = len(lines) - 2

    def line(name: str, group: list[EncounterResult]) -> str:
        det = sum(r.detected for r in group)
        return (f"| {name} | {_rate(group)} | {det}/{len(group)} | "
                f"{_median([r.detect_range_m for r in group])} | "
                f"{_median([r.detect_before_cpa_s for r in group])} | "
                f"{_median([r.evade_before_cpa_s for r in group])} | "
                f"{_median([r.min_separation_m for r in group])} |")

    lines.append(line("all threats", threats))
    lines.append(line("collision course (constant bearing, miss < 0.15 m)", course))
    lines.append(line("near misses", [r for r in threats if r.encounter.miss_m >= 0.15]))
    seen = [r for r in threats if r.in_view_s >= IN_VIEW_S]
    lines.append(line(f"in the lens's view ≥ {IN_VIEW_S:g} s before CPA", seen))
    lines.append(line(f"in view < {IN_VIEW_S:g} s (outside the lens until late)",
                      [r for r in threats if r.in_view_s < IN_VIEW_S]))
    for label, group in _bins(seen, lambda r: r.encounter.object_speed_mps, SPEED_BINS):
        lines.append(line(f"in view, object {label} m/s", group))
    for label, group in _bins(threats, lambda r: r.encounter.object_speed_mps, SPEED_BINS):
        lines.append(line(f"object {label} m/s", group))
    for label, group in _bins(threats, lambda r: abs(r.encounter.approach_deg), ANGLE_BINS):
        lines.append(line(f"approach |{label}|°", group))
    for kind, (size, _) in KINDS.items():
        lines.append(line(f"{kind} (~{size} m)", [r for r in threats if r.encounter.kind == kind]))
    env = envelope(rows)
    if env is None:
        text = "every speed bin tested holds"
    elif env <= SPEED_BINS[0]:
        text = ("not reached: below 90 % already in the slowest bin tested "
                f"({SPEED_BINS[0]:g}–{SPEED_BINS[1]:g} m/s)")
    else:
        text = f"holds below {env:g} m/s"
    lines += ["", f"Envelope (success ≥ 90 %): {text}", ""]
    if not threats:  # an object-free (or wide-pass) run: no table of empty rows
        del lines[table_at:]
    crossing = [r for r in rows if r.towards_passage is not None]
    if crossing:
        towards = sum(bool(r.towards_passage) for r in crossing)
        into = sum(bool(r.into_path) for r in crossing)
        lines += [f"Direction (from the truth, first evasion of encounters approaching at 20–50°): "
                  f"{towards} of {len(crossing)} moved towards the object's true passage"
                  f"{_wrong_by(crossing)}; "
                  f"{into} of {len(crossing)} moved along its lateral motion (into its path, not behind it).",
                  ""]
    if crossing_set_rows:
        judged = [r for r in crossing_set_rows if r.towards_passage is not None]
        lo, hi = CROSSING_MISS_M
        lines += [f"Crossing set ({len(crossing_set_rows)} encounters at 20–50°, each passing "
                  f"{lo:g}–{hi:g} m off if nobody moved): {sum(bool(r.towards_passage) for r in judged)} of "
                  f"{len(judged)} first evasions moved towards the object's true passage{_wrong_by(judged)}; "
                  f"{sum(bool(r.into_path) for r in judged)} along its lateral motion; avoided "
                  f"{_rate(crossing_set_rows)}.", ""]
    if wide:
        lo, hi = WIDE_MISS_M
        lines += [f"Wide passes (would miss by {lo:g}–{hi:g} m, outside the window: nothing to do): "
                  f"{sum(r.evaded for r in wide)} of {len(wide)} evaded unnecessarily; min separation "
                  f"median {_median([r.min_separation_m for r in wide])} m.", ""]
    if free:
        minutes = sum(r.encounter.t_cpa_s for r in free) / 60.0
        n_false = sum(r.false_evasions for r in free)
        hours = minutes / 60.0
        per_hour = n_false / hours if hours else math.nan
        fast = [r for r in free if r.fast_wall_s]
        how = ""
        if fast:
            from app.sim.fast import speed_factor

            refl = sum(1 for r in fast if r.fast_commands)
            how = (f" Flown faster than real time ({speed_factor(fast):.1f}x per core) through the same "
                   f"perception and decision, without MAVLink; {refl} flights in which that run would "
                   f"have commanded something were flown again in real time through the full loop, "
                   f"and those counts are the ones given ({sum(r.fast_commands or 0 for r in fast)} "
                   f"commands in the fast runs).")
        lines += [f"Object-free flight: {minutes:.1f} simulated minutes ({hours:.2f} h), {n_false} false "
                  f"evasions ({per_hour:.2f} per hour; 95 % upper bound "
                  f"{poisson_upper(n_false, hours):.2f} per hour, exact Poisson).{how}", ""]
    lat = [r.capture_to_setpoint_p99_ms for r in rows if r.capture_to_setpoint_p99_ms]
    drops = sum(r.frames_dropped for r in rows)
    if lat:
        lines += [f"Latency (capture → setpoint p99 per encounter): median {_median(lat)} ms; "
                  f"frames dropped in all: {drops}.", ""]
    plots = _plots(out, threats)
    lines += [f"![{p.stem}]({p.name})" for p in plots]
    (out / "report.md").write_text("\n".join(lines) + "\n")
    (out / "summary.json").write_text(json.dumps({
        "encounters": len(rows), "threats": len(threats),
        "success_rate": sum(r.success for r in threats) / len(threats) if threats else None,
        "in_view_threats": len(seen), "in_view_success_rate":
            sum(r.success for r in seen) / len(seen) if seen else None,
        "envelope_mps": env, "wall_s": wall_s,
        "wide_passes": len(wide), "unnecessary_evasions": sum(r.evaded for r in wide),
        "false_evasions": sum(r.false_evasions for r in free),
        "object_free_minutes": sum(r.encounter.t_cpa_s for r in free) / 60.0,
        "false_evasions_per_hour_upper95": poisson_upper(
            sum(r.false_evasions for r in free), sum(r.encounter.t_cpa_s for r in free) / 3600.0)
        if free else None}, indent=2) + "\n")
    return out / "report.md"


def _plots(out: Path, threats: list[EncounterResult]) -> list[Path]:
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:  # the report stands without its pictures
        return []
    if not threats:
        return []
    paths = []
    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    for ax, key, edges, xlabel in (
        (axes[0], lambda r: r.encounter.object_speed_mps, SPEED_BINS, "object speed, m/s"),
        (axes[1], lambda r: abs(r.encounter.approach_deg), ANGLE_BINS, "approach angle |deg| (0 = head-on)"),
    ):
        groups = _bins(threats, key, edges)
        rates = [sum(r.success for r in g) / len(g) if g else 0.0 for _, g in groups]
        ax.bar([lab for lab, _ in groups], rates, color="tab:green")
        for i, (_, g) in enumerate(groups):
            ax.text(i, 0.02, f"n={len(g)}", ha="center", fontsize=8)
        ax.axhline(0.9, color="k", ls="--", lw=0.8)
        ax.set_ylim(0, 1)
        ax.set_xlabel(xlabel)
        ax.set_ylabel("success rate")
    fig.suptitle("Avoided collisions (threat encounters)")
    paths.append(_save(plt, fig, out / "success.png"))

    fig, ax = plt.subplots(figsize=(6, 4))
    speed = [r.encounter.object_speed_mps for r in threats]
    margin = [r.evade_before_cpa_s if r.evade_before_cpa_s is not None else -0.1 for r in threats]
    colours = ["tab:green" if r.success else "tab:red" for r in threats]
    ax.scatter(speed, margin, c=colours, s=18)
    ax.set_xlabel("object speed, m/s")
    ax.set_ylabel("evasion started before closest approach, s")
    ax.set_title("Time margin (green: avoided, red: not; below 0: never evaded)")
    paths.append(_save(plt, fig, out / "margin.png"))

    # the envelope map: success per (object speed, approach angle) cell, with its counts
    grid = np.full((len(ANGLE_BINS) - 1, len(SPEED_BINS) - 1), np.nan)
    fig, ax = plt.subplots(figsize=(7, 4.5))
    for i, (_, by_angle) in enumerate(_bins(threats, lambda r: abs(r.encounter.approach_deg), ANGLE_BINS)):
        for j, (_, cell) in enumerate(_bins(by_angle, lambda r: r.encounter.object_speed_mps, SPEED_BINS)):
            if cell:
                k = sum(r.success for r in cell)
                grid[i, j] = k / len(cell)
                ax.text(j, i, f"{k}/{len(cell)}", ha="center", va="center", fontsize=9)
    im = ax.imshow(grid, cmap="RdYlGn", vmin=0.0, vmax=1.0, origin="lower", aspect="auto")
    ax.set_xticks(range(len(SPEED_BINS) - 1),
                  [f"{a:g}–{b:g}" for a, b in zip(SPEED_BINS, SPEED_BINS[1:], strict=False)])
    ax.set_yticks(range(len(ANGLE_BINS) - 1),
                  [f"{a:g}–{b:g}" for a, b in zip(ANGLE_BINS, ANGLE_BINS[1:], strict=False)])
    ax.set_xlabel("object speed, m/s")
    ax.set_ylabel("approach |deg| (0 = head-on)")
    ax.set_title("Envelope: threats avoided per cell (avoided/flown)")
    fig.colorbar(im, ax=ax, label="success rate")
    paths.append(_save(plt, fig, out / "envelope.png"))
    return paths


def _save(plt: Any, fig: Any, path: Path) -> Path:
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def with_trigger(cfg: Config, trigger: str) -> Config:
    return replace(cfg, decision=replace(cfg.decision, trigger=trigger))
