"""A campaign of encounters flown against PX4 SITL, each on a fresh PX4, and the same
encounters against the stand-in vehicle: does avoidance hold with PX4's own controllers?

    .venv/bin/python tests/sitl_campaign.py ~/px4/build/px4_sitl_lean --campaign 30 --seed 41 \\
        --out out/sitl-campaign [--crossing 10] [--from leg] [--resume]

For every encounter: ``../shared/px4-sitl/start.sh`` starts PX4 (SIH quadrotor, fresh
parameters), the pilot's link (the ``sitl`` tests' ground station, 14550) takes off to a
hover in Hold, and :func:`app.sim.simulate.run_encounter` flies the encounter with the camera
rendered from PX4's telemetry and midair on PX4's offboard port (14540), as
``midair simulate --connection`` does; then PX4 is stopped. The encounters are the
campaign's (``sample_encounters`` / ``crossing_set`` of the seed) at the ground station's
take-off altitude, flown from a hover (``--from hover``), or (``--from leg``) at each
encounter's own speed: the ground station flies a Mission leg north at that speed (0: a
hover), and the encounter starts once PX4 flies it steadily. Results go to
``OUT/sitl`` and ``OUT/standin`` (``encounters.csv``, ``report.md``) as each finishes, and the
two are compared pair by pair (``midair simulate compare``). A development tool: it needs a
PX4 build (docs/sitl.md), which CI does not have.
"""

from __future__ import annotations

import argparse
import asyncio
import math
import os
import signal
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))  # the sitl tests' ground station

from test_sitl import HOVER_ALT_M, GroundStation, bring_to_hover, until  # noqa: E402

from app.config import Config  # noqa: E402
from app.errors import UsageError  # noqa: E402
from app.sim.campaign import crossing_set, sample_encounters, write_report  # noqa: E402
from app.sim.results import ResultLog, compare  # noqa: E402
from app.sim.simulate import Encounter, EncounterResult, run_encounter  # noqa: E402

START = Path(__file__).resolve().parents[2] / "shared" / "px4-sitl" / "start.sh"
OFFBOARD_URL = "udpin://0.0.0.0:14540"
GCS_URL = "udpin://0.0.0.0:14550"


def start_px4(build: Path, log: Path, start: Path = START) -> int:
    """A fresh PX4 SITL, ready for take-off; its PID (start.sh's own checks and errors)."""
    out = subprocess.run([str(start), str(build), str(log)], capture_output=True, text=True, timeout=180)
    if out.returncode != 0:
        raise RuntimeError(f"start.sh failed ({out.returncode}): {out.stderr.strip()}")
    return int(out.stdout.strip().splitlines()[-1])


def stop_px4(pid: int) -> None:
    """PX4 and its process group (start.sh runs it under setsid), waited for."""
    for sig in (signal.SIGTERM, signal.SIGKILL):
        try:
            os.killpg(pid, sig)
        except ProcessLookupError:
            return
        for _ in range(50):
            try:
                os.kill(pid, 0)
            except ProcessLookupError:
                return
            time.sleep(0.1)


LEG_M = 400.0  # the Mission leg's length: a minute and more at 4 m/s, far past any encounter
STEADY_MPS = 0.25  # the leg is flown steadily once every velocity of the last second is
STEADY_S = 1.0  # within this of the leg's, and the heading within STEADY_YAW_DEG of north
STEADY_YAW_DEG = 5.0


async def hover(cruise_mps: float = 0.0) -> None:
    """Take off to a hover in Hold; with ``cruise_mps`` > 0, then fly a Mission leg north at
    that speed (to a waypoint LEG_M north at the take-off altitude) and return once PX4 flies
    it steadily, as the stand-in's Mission does from the start. (SIH's hover wanders, as a
    real one does in wind on GPS: ±0.5 m and up to 0.7 m/s over a minute measured here, so an
    encounter laid as a collision course from where the vehicle is at its first frame may
    pass off by as much.)"""
    gcs = GroundStation(GCS_URL)
    try:
        await gcs.connect()
        await bring_to_hover(gcs)
        if cruise_mps > 0:
            await fly_north(gcs, cruise_mps)
    finally:
        await gcs.close()


async def fly_north(gcs: GroundStation, cruise_mps: float) -> None:
    from mavsdk.asyncio.plugins.mission import MissionItem, MissionPlan

    assert gcs.v.lat_lon is not None
    lat0, lon0 = gcs.v.lat_lon
    # MAVSDK sends an item's speed as a change of speed after it (PX4 flew a lone item at its
    # MPC_XY_CRUISE, 5 m/s): the first item, where the vehicle hovers, sets the leg's speed
    items = [MissionItem(lat, lon0, HOVER_ALT_M, cruise_mps, True)
             for lat in (lat0, lat0 + LEG_M / 111_320.0)]
    await gcs.mission.upload_mission(MissionPlan(items))
    await gcs.start_mission()

    def steady() -> bool:
        now = time.monotonic()
        last = [s for s in gcs.v.samples if s.t >= now - STEADY_S]
        return (len(last) >= 5 and gcs.v.samples[0].t < now - STEADY_S
                and all(abs(s.vel_ned[0] - cruise_mps) < STEADY_MPS and abs(s.vel_ned[1]) < STEADY_MPS
                        and abs(s.vel_ned[2]) < STEADY_MPS
                        and abs(math.degrees(s.yaw_rad)) < STEADY_YAW_DEG for s in last))

    await until(steady, 40.0, f"a Mission leg flown steadily north at {cruise_mps:g} m/s")


def fly_on_sitl(cfg: Config, enc: Encounter, build: Path, out: Path, start: Path) -> EncounterResult:
    pid = start_px4(build, out / f"px4-{enc.seed}.log", start)
    try:
        asyncio.run(hover(enc.own_speed_mps))
        return run_encounter(cfg, enc, connection=OFFBOARD_URL)
    finally:
        stop_px4(pid)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("build", type=Path, help="PX4 build folder (PX4_TREE/build/px4_sitl_lean)")
    ap.add_argument("--campaign", type=int, default=20, help="encounters of the campaign's sample")
    ap.add_argument("--crossing", type=int, default=0, help="encounters of the crossing set")
    ap.add_argument("--seed", type=int, default=41)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--resume", action="store_true", help="continue the campaign already in --out "
                    "(same arguments), flying only the encounters it lacks")
    ap.add_argument("--from", dest="origin", choices=("hover", "leg"), default="hover",
                    help="every encounter from a hover, or at its own speed on a Mission leg north")
    ap.add_argument("--start", type=Path, default=START, help=f"PX4 SITL's start script (default {START})")
    args = ap.parse_args(argv)
    if not (args.build / "bin" / "px4").exists():
        ap.error(f"{args.build}: no bin/px4 there (build PX4 SITL first: docs/sitl.md)")
    if not args.start.exists():
        ap.error(f"{args.start}: missing (the shared PX4 SITL scripts)")
    cfg = Config()
    # at the ground station's take-off altitude, camera held level; from a hover, or at
    # the encounter's own speed on a Mission leg
    encs = [replace(e, own_speed_mps=e.own_speed_mps if args.origin == "leg" else 0.0,
                    altitude_m=HOVER_ALT_M, tilt=False)
            for e in [*sample_encounters(args.campaign, args.seed), *crossing_set(args.crossing, args.seed)]]
    plan = {"seed": args.seed, "campaign": args.campaign, "crossing": args.crossing, "from": args.origin}
    names = ("sitl", "standin")
    if not args.resume and any((args.out / n / "encounters.csv").exists() for n in names):
        ap.error(f"{args.out} already holds this tool's results: --resume continues them, or choose "
                 "another --out")
    try:
        logs = {name: ResultLog(args.out / name, plan, resume=args.resume) for name in names}
    except UsageError as exc:
        ap.error(str(exc))
    t0 = time.monotonic()
    results: dict[str, list[EncounterResult]] = {"sitl": [], "standin": []}
    for i, enc in enumerate(encs, 1):
        for name, fly in (("sitl", lambda e: fly_on_sitl(cfg, e, args.build, args.out / "sitl", args.start)),
                          ("standin", lambda e: run_encounter(cfg, e))):
            log = logs[name]
            r = log.done.get(enc.seed)
            if r is None:
                r = fly(enc)
                log.append(r)
            results[name].append(r)
            print(f"{i}/{len(encs)} {enc.seed} {name}: {'avoided' if r.success else 'NOT avoided'} "
                  f"(min {r.min_separation_m:.2f} m, evaded {r.evade_before_cpa_s} s before)", flush=True)
    wall = time.monotonic() - t0
    n_main = args.campaign
    for name, rows in results.items():
        logs[name].close()
        whence = "a hover" if args.origin == "hover" else "a Mission leg"
        write_report(args.out / name, rows[:n_main], [], cfg, wall, title=f"Campaign from {whence} ({name})",
                     crossing=rows[n_main:])
    print(compare(results["sitl"], results["standin"]).text("PX4 SITL", "stand-in"))
    return 0


if __name__ == "__main__":
    sys.exit(main())
