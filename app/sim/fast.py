"""Object-free flight faster than real time: hours of flight for the false-evasion rate.

With no object in the world there is nothing to avoid, so, as long as midair commands
nothing, the vehicle only flies its script (a hover, or a Mission leg north at its cruise
speed) and the closed loop has no feedback to keep: the world can be rendered from the
scripted pose and run through the *same* perception (:class:`Perception`) and decision
(:class:`DecisionMaker`) as fast as the CPU allows, stamped with the clock the frames would
have had. What this leaves out, said in the report: MAVLink, the offboard coroutine and
the perception thread's frame dropping (here every frame is perceived; in real time a late
frame is replaced by the next one). So every flight in which the fast run would have issued
a command is flown again in real time through the full closed loop
(:func:`app.sim.simulate.run_encounter`), and that flight's count is the one reported.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

from app.config import Config
from app.decision.ego import EgoMotion, camera_velocity
from app.decision.policy import NONE, DecisionMaker
from app.perception.near import depth_lens
from app.perception.pipeline import Perception
from app.sim.simulate import Encounter, EncounterResult, SimulatedCamera, _episodes, run_encounter, world_for


@dataclass
class _Script:
    """The pose a vehicle flying its script has at ``t`` s (NED m, m/s, rad): from home at
    ``altitude_m``, north at ``speed_mps`` (0: hovering)."""

    altitude_m: float
    speed_mps: float

    def __call__(self, t: float = 0.0
                 ) -> tuple[tuple[float, float, float], tuple[float, float, float], float]:
        return (self.speed_mps * t, 0.0, -self.altitude_m), (self.speed_mps, 0.0, 0.0), 0.0


def script_ego(enc: Encounter) -> EgoMotion:
    """The camera's velocity as the autopilot would report it on ``enc``'s scripted flight
    (north at its own speed, yaw 0, level: the world's camera is level)."""
    return EgoMotion(camera_velocity((enc.own_speed_mps, 0.0, 0.0), 0.0, 0.0, 0.0))


def fly_fast(cfg: Config, enc: Encounter, confirm: bool = True) -> EncounterResult:
    """One object-free flight (``enc.with_object`` False) faster than real time. If it would
    have commanded anything and ``confirm``, the flight is flown again in real time and that
    result is returned (with ``fast_commands`` noting what the fast run saw)."""
    if enc.with_object:
        raise ValueError("fly_fast: only object-free flights can run faster than real time "
                         "(with an object the vehicle's response feeds back into the camera)")
    if enc.wander:
        raise ValueError("fly_fast: the fast run flies the script exactly; a wandering hover "
                         "(Encounter.wander) flies in real time")
    wall0 = time.monotonic()
    # (a tilting camera stays level too: the script never accelerates)
    camera = SimulatedCamera(enc, _Script(enc.altitude_m, enc.own_speed_mps), world=world_for(cfg, enc),
                             paced=False, attitude=(lambda: (0.0, 0.0, 0.0)) if enc.tilt else None)
    perception = Perception(cfg.perception, camera=depth_lens(camera.lens, cfg.capture.stream))
    decider = DecisionMaker.for_perception(cfg.decision, camera.lens, cfg.perception.detection)
    ego = script_ego(enc)  # the autopilot's velocity: the script's, flown exactly
    command_frames: list[int] = []
    frames = 0
    for frame in camera:
        frames += 1
        result = perception.push(frame)
        if result is None:
            continue
        command, _objects = decider.step(result.tracks, result.frame.depth, result.frame.t_s,
                                         enc.altitude_m, ego=ego)
        if command.action != NONE:
            command_frames.append(result.frame.index)
    episodes = _episodes(command_frames)
    wall = time.monotonic() - wall0
    if episodes and confirm:
        res = run_encounter(cfg, enc)
        res.fast_commands = episodes
        res.fast_wall_s = round(wall, 2)
        return res
    return EncounterResult(enc, False, false_evasions=episodes, success=episodes == 0,
                           frames=frames, wall_s=round(wall, 2), fast_commands=episodes,
                           fast_wall_s=round(wall, 2))


def run_one(cfg: Config, enc: Encounter, fast_object_free: bool = False) -> EncounterResult:
    """One encounter of a campaign, in a worker of any pool: object-free faster than real
    time when asked, everything else in real time; OpenCV on one thread (a worker per core)."""
    import cv2

    cv2.setNumThreads(1)
    if fast_object_free and not enc.with_object:
        return fly_fast(cfg, enc)
    return run_encounter(cfg, enc)


def speed_factor(results: list[EncounterResult]) -> float:
    """Simulated seconds flown per wall second, over the fast runs (per worker: each ran on
    one core)."""
    flown = sum(r.encounter.t_cpa_s + r.encounter.after_s for r in results if r.fast_wall_s)
    wall = sum(r.fast_wall_s or 0.0 for r in results)
    return flown / wall if wall > 0 else math.nan
