"""Closed-loop encounters: the real flight process against a rendered world and the stand-in PX4.

One encounter = the vehicle flying (hovering, or a Mission leg at ``own_speed_mps``) and one
object on a straight line that, left alone, passes ``miss_m`` from the vehicle ``t_cpa_s``
after the start. The camera (:class:`SimulatedCamera`) renders colour and depth from the
vehicle's *true* pose in the stand-in PX4 at the frame rate, in real time; everything else is
the production path: capture, perception thread, decision, offboard coroutine, MAVSDK over
UDP, the vehicle's dynamics. Nothing in the decision path knows it is a simulation.

Each encounter is a pure function of ``(config, Encounter)`` (the encounter carries its own
seed), so a campaign can be run by any pool of workers.
"""

from __future__ import annotations

import asyncio
import json
import math
import time
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any, TypeGuard

import numpy as np

from app.camera import Intrinsics
from app.config import Config
from app.decision.ego import camera_rotation
from app.perception.frames import Frame, FrameSource
from app.sim.world import Monochrome, Renderer, Sphere, Tilted, d435i_color, d435i_infrared, load_world

VEHICLE_RADIUS_M = 0.25  # a 250-size quadrotor with props: ~0.5 m across
SAFETY_MARGIN_M = 0.2  # separation beyond the two radii that counts as a clean miss


@dataclass(frozen=True)
class Encounter:
    """One scripted encounter (m, m/s, deg, s). The object's straight path would pass
    ``miss_m`` from where the vehicle would be at ``t_cpa_s`` had nobody reacted."""

    seed: int = 1
    kind: str = "ball"  # ball, bird or drone (for the report)
    object_speed_mps: float = 6.0
    approach_deg: float = 0.0  # 0: head-on; +: coming from the right of the nose
    climb_deg: float = 0.0  # +: the object climbs on its way
    miss_m: float = 0.0  # 0: collision course (constant bearing)
    miss_dir_deg: float = 45.0  # where the miss lies around the line of sight (0 right, 90 down)
    size_m: float = 0.3  # ball 0.2-0.3, bird 0.3-0.6, small drone 0.3-0.5
    grey: int = 40  # object brightness (sky ~175-215, ground ~100)
    own_speed_mps: float = 0.0  # the vehicle's forward speed (Mission leg), 0: hovering
    altitude_m: float = 6.0
    t_cpa_s: float = 4.0
    after_s: float = 1.5  # keep flying this long after closest approach
    fps: float = 30.0
    with_object: bool = True
    world: str = ""  # "package.module:factory" of another world (app.sim.world.load_world); "": built-in
    xy_vel_p_acc: float = 1.8  # the stand-in vehicle's MPC_XY_VEL_P_ACC (PX4's default 1.8)
    # the stand-in's hover drifts as PX4 SITL's does, times this (app.sim.px4.Wander); 0: still
    wander: float = 0.0
    # the camera is fixed to the body and banks and pitches with the vehicle's acceleration
    # (app.sim.world.Tilted); False: held level, as by a gimbal
    tilt: bool = False

    @property
    def threat(self) -> bool:
        """Left alone, would it pass inside the two radii plus the margin?"""
        return self.with_object and self.miss_m < self.size_m / 2 + VEHICLE_RADIUS_M + SAFETY_MARGIN_M

    def object_path(self) -> tuple[np.ndarray, np.ndarray]:
        """Start position (NED, m) and velocity (m/s) of the object."""
        a, c = math.radians(self.approach_deg), math.radians(self.climb_deg)
        vel = self.object_speed_mps * np.array([-math.cos(a) * math.cos(c), -math.sin(a) * math.cos(c),
                                                -math.sin(c)])
        cpa_vehicle = np.array([self.own_speed_mps * self.t_cpa_s, 0.0, -self.altitude_m])
        rel = vel - np.array([self.own_speed_mps, 0.0, 0.0])  # seen from the vehicle
        los = rel / (np.linalg.norm(rel) + 1e-9)
        # a unit vector across the line of sight: "right" and "down" as the vehicle sees it
        right = np.cross([0.0, 0.0, 1.0], los)
        norm = float(np.linalg.norm(right))
        right = right / norm if norm > 1e-6 else np.array([0.0, 1.0, 0.0])
        down = np.cross(los, right)
        d = math.radians(self.miss_dir_deg)
        offset = self.miss_m * (math.cos(d) * right + math.sin(d) * down)
        start = cpa_vehicle + offset - vel * self.t_cpa_s
        return start, vel

    def relative_path(self, t: np.ndarray) -> np.ndarray:
        """The object relative to the vehicle flying its script (hovering, or north at its
        own speed), had nobody moved, at ``t`` s from the start: (len(t), 3) NED m."""
        start, vel = self.object_path()
        vehicle = np.stack([self.own_speed_mps * t, np.zeros_like(t), np.full_like(t, -self.altitude_m)], 1)
        return start + vel * t[:, None] - vehicle

    def in_view_s(self, intr: Intrinsics) -> float:
        """How long, before the closest approach, the object's centre lies inside the lens's
        image on the course it would fly had nobody moved (the vehicle hovering or flying its
        leg, camera level, facing north). A forward camera cannot avoid what it never sees:
        a collision course from 40° off the nose stays outside a 55° lens to the end."""
        if not self.with_object:
            return 0.0
        dt = 1.0 / self.fps
        t = np.arange(0.0, self.t_cpa_s, dt)
        rel = self.relative_path(t)  # NED; camera: X = east, Y = down, Z = north
        z = rel[:, 0]
        ok = z > 0.3
        u = intr.fx * rel[:, 1] / np.where(ok, z, 1.0) + intr.ppx
        v = intr.fy * rel[:, 2] / np.where(ok, z, 1.0) + intr.ppy
        seen = ok & (u >= 0) & (u < intr.width) & (v >= 0) & (v < intr.height)
        return round(float(seen.sum()) * dt, 3)


@dataclass
class Truth:
    """What the simulated camera knew at one frame (shared monotonic clock)."""

    frame: int
    t_s: float
    vehicle_m: tuple[float, float, float]
    object_m: tuple[float, float, float] | None
    pixel: tuple[float, float, float, float] | None  # u, v, radius px, z m (when in view)


def _tilts(world: Renderer) -> TypeGuard[Tilted | Monochrome]:
    """The world turns its camera to the vehicle's attitude (render takes ``rotation``)."""
    return isinstance(world, Tilted) or (isinstance(world, Monochrome) and world.tilts)


class SimulatedCamera(FrameSource):
    """Renders the world from the stand-in vehicle's true pose, frame by frame in real time.

    A live source: frames are stamped on the monotonic clock when rendered, and the runtime
    neither paces nor re-stamps them.
    """

    live = True
    carried = True  # rendered from the vehicle's own pose (held level: see _encounter)

    def __init__(self, enc: Encounter, pose: Any, world: Renderer, paced: bool = True,
                 attitude: Callable[[], tuple[float, float, float]] | None = None) -> None:
        if _tilts(world) and attitude is None:
            raise ValueError("SimulatedCamera: a tilting camera needs the vehicle's attitude")
        self.enc = enc
        self.attitude = attitude  # () -> (roll, pitch, yaw) rad, for a tilting camera
        # paced: one frame per period on the monotonic clock (the closed loop); else as fast as
        # it renders, stamped as if paced (faster-than-real-time flights, app.sim.fast)
        self.paced = paced
        # () -> (pos_ned, vel_ned, yaw) when paced; (seconds since the first frame) -> the same
        self.pose = pose
        self.world = world
        self.fps = enc.fps
        self.name = f"simulated encounter {enc.seed}"
        self.has_depth = True
        self.lens = self.world.camera()  # never None here (FrameSource.camera may be)
        self.camera = self.lens
        self.truth: list[Truth] = []
        self.t_start: float | None = None
        self._start, self._vel = enc.object_path()
        self._origin = np.zeros(3)

    def __len__(self) -> int:
        return int(round((self.enc.t_cpa_s + self.enc.after_s) * self.fps))

    def object_at(self, t: float) -> np.ndarray:
        """The object at ``t`` s after the first frame; its path is laid relative to where the
        vehicle was at that frame (it may have been flying for a while)."""
        return self._origin + self._start + self._vel * t

    def __iter__(self) -> Iterator[Frame]:
        period = 1.0 / self.fps
        t0 = time.monotonic()
        self.t_start = t0
        self._origin = np.asarray(self.pose()[0], float) - np.array([0.0, 0.0, -self.enc.altitude_m])
        for k in range(len(self)):
            if self.paced:
                delay = t0 + k * period - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
                now = time.monotonic()
            else:
                now = t0 + k * period
            pos, _vel, yaw = self.pose() if self.paced else self.pose(now - t0)
            obj = self.object_at(now - t0) if self.enc.with_object else None
            spheres = ([Sphere(1, (float(obj[0]), float(obj[1]), float(obj[2])), self.enc.size_m,
                               self.enc.grey, self.enc.kind)] if obj is not None else [])
            vehicle = (float(pos[0]), float(pos[1]), float(pos[2]))
            if _tilts(self.world) and self.attitude is not None:
                roll, pitch, _ = self.attitude()
                turn = camera_rotation((0.0, 0.0, yaw), (roll, pitch, yaw))
                colour, depth, seen = self.world.render(vehicle, yaw, spheres, rotation=turn)
            else:
                colour, depth, seen = self.world.render(vehicle, yaw, spheres)
            where = None if obj is None else (float(obj[0]), float(obj[1]), float(obj[2]))
            self.truth.append(Truth(k + 1, now, vehicle, where, seen.get(1)))
            yield Frame(k + 1, now, colour, depth)


# ---------------------------------------------------------------------------- one encounter


@dataclass
class EncounterResult:
    encounter: Encounter
    threat: bool
    in_view_s: float = 0.0  # nominal time in the lens's view before the closest approach, s
    detected: bool = False
    detect_range_m: float | None = None  # object distance when first tracked
    detect_before_cpa_s: float | None = None  # how long before the closest approach
    evaded: bool = False  # any evasion or stop command
    evade_range_m: float | None = None
    evade_before_cpa_s: float | None = None
    min_separation_m: float = math.inf
    t_min_separation_s: float | None = None  # since the start
    success: bool = False  # min separation >= radii + margin
    # the first evasion's direction judged from the truth, for objects approaching at
    # 20-50 deg (crossing the view): towards the true passage point (relative to the vehicle,
    # in its right/down plane), and along the object's lateral motion (into its path)
    towards_passage: bool | None = None
    into_path: bool | None = None
    # how far the true passage lies along that evasion's direction, m: over
    # TOWARDS_TOLERANCE_M it is towards; a few centimetres either way is the estimate's noise
    # on a passage close to the line of flight, half a metre is a wrong side
    passage_along_m: float | None = None
    false_evasions: int = 0  # commands with no object in the world
    frames: int = 0
    frames_dropped: int = 0
    capture_to_setpoint_p99_ms: float | None = None
    wall_s: float = 0.0
    record: str | None = None
    # object-free flights run faster than real time (app.sim.fast): what the fast run
    # counted, and its wall time (None: flown in real time only)
    fast_commands: int | None = None
    fast_wall_s: float | None = None

    def row(self) -> dict[str, object]:
        out = {k: v for k, v in asdict(self).items() if k != "encounter"}
        out.update({f"enc_{k}": v for k, v in asdict(self.encounter).items()})
        return out


def run_encounter(cfg: Config, enc: Encounter, out_dir: Path | None = None,
                  save_frames: bool = False, connection: str | None = None,
                  pose_from_telemetry: bool = False) -> EncounterResult:
    """Fly one encounter in real time; return what happened.

    Against the stand-in PX4 (started here) by default, the camera rendering from its true
    pose; with ``connection`` (a PX4 SITL already flying), the pose comes from MAVLink
    telemetry (local position and attitude), as it does with ``pose_from_telemetry``.
    """
    return asyncio.run(_encounter(cfg, enc, out_dir, save_frames, connection, pose_from_telemetry))


async def _encounter(cfg: Config, enc: Encounter, out_dir: Path | None, save_frames: bool,
                     connection: str | None, pose_from_telemetry: bool) -> EncounterResult:
    import tempfile

    from app.runtime.process import fly
    from app.runtime.record import FlightRecord
    from app.sim.px4 import SimPx4, SimState, free_udp_port
    from hardware.px4 import PortInUseError, Px4Link

    wall0 = time.monotonic()
    # The simulated camera renders from the vehicle's position and yaw only: it is held
    # level, as a gimbal would hold it, whatever attitude the autopilot reports (PX4 SITL's
    # roll and pitch are real), and the decision must be told so; with ``enc.tilt`` it is
    # fixed to the body and turned by the vehicle's attitude.
    cfg = replace(cfg, decision=replace(cfg.decision, camera_mount="body" if enc.tilt else "gimbal"))
    sim = None
    link = None
    # the stand-in's port is picked free, released, then bound by MAVSDK: in between another
    # worker's socket can take it (seen once in CI with two workers), so a taken port is
    # retried with a new one; any other failure is not
    for attempt in range(_BIND_ATTEMPTS):
        if connection is None or sim is not None:
            state = SimState(mode="mission" if enc.own_speed_mps > 0 else "position",
                             cruise_mps=enc.own_speed_mps, tilts=enc.tilt)
            state.pos_ned = [0.0, 0.0, -enc.altitude_m]
            port = free_udp_port()
            sim = SimPx4(port, state=state, xy_vel_p_acc=enc.xy_vel_p_acc, wander=enc.wander,
                         wander_seed=enc.seed).start()
            connection = f"udpin://0.0.0.0:{port}"
        assert connection is not None
        link = Px4Link(connection, with_pose=sim is None or pose_from_telemetry)
        try:
            await link.connect(timeout_s=cfg.flight.connect_timeout_s)
            break
        except PortInUseError:
            if sim is None or attempt == _BIND_ATTEMPTS - 1:
                raise
            sim.stop()
        except BaseException:
            if sim is not None:
                sim.stop()
            raise
    assert link is not None
    try:
        source = sim if sim is not None and not pose_from_telemetry else link  # pose and attitude
        camera = SimulatedCamera(enc, source.pose, world=world_for(cfg, enc),
                                 attitude=source.attitude if enc.tilt else None)
        tmp = None
        if out_dir is None:
            tmp = tempfile.TemporaryDirectory(prefix="midair-sim-")
            out_dir = Path(tmp.name)
        rec_cfg = replace(cfg.record, dir=str(out_dir / "records"),
                          frames="color+depth" if save_frames else "none")
        record = FlightRecord(rec_cfg, cfg, camera.camera).start()
        await link.wait_flying()
        stats = await fly(cfg, camera, link, install_signals=False, record=record)
    finally:
        await link.close()
        if sim is not None:
            sim.stop()
    summary = stats.summary()
    record.close(summary)
    result = analyse(enc, camera, record.folder, summary)
    result.wall_s = round(time.monotonic() - wall0, 2)
    result.record = None if tmp else str(record.folder)
    if tmp is None:
        write_truth(out_dir / "truth.csv", camera)
    if tmp is not None:
        tmp.cleanup()
    return result


_BIND_ATTEMPTS = 5  # new ports tried for the stand-in when the picked one is taken


def world_for(cfg: Config, enc: Encounter) -> Renderer:
    """The encounter's world, the built-in one drawn through the lens the configuration
    streams: the D435i's colour camera at ``capture.color_width`` x ``color_height``, or with
    ``capture.stream: infrared`` its left infrared imager at ``depth_width`` x
    ``depth_height``, whose frames are grey."""
    lens = lens_for(cfg)
    world: Renderer = Tilted(enc.world, enc.seed, lens) if enc.tilt else load_world(enc.world, enc.seed, lens)
    return Monochrome(world) if cfg.capture.stream == "infrared" else world


def lens_for(cfg: Config) -> Intrinsics:
    """The D435i lens perception sees through with this configuration's ``capture``."""
    cap = cfg.capture
    if cap.stream == "infrared":
        return d435i_infrared(cap.depth_width, cap.depth_height)
    return d435i_color(cap.color_width, cap.color_height)


def _jsonl(path: Path) -> list[dict[str, Any]]:
    if not path.exists():
        return []
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


def analyse(enc: Encounter, camera: SimulatedCamera, folder: Path,
            summary: dict[str, object]) -> EncounterResult:
    """Score one run from the camera's truth and the flight record (one monotonic clock)."""
    res = EncounterResult(enc, enc.threat, in_view_s=enc.in_view_s(camera.lens.color),
                          frames=len(camera.truth),
                          frames_dropped=int(summary.get("frames_dropped", 0)),  # type: ignore[call-overload]
                          capture_to_setpoint_p99_ms=summary.get("capture_to_setpoint_p99_ms"))  # type: ignore[arg-type]
    truth = {t.frame: t for t in camera.truth}
    t0 = camera.t_start or 0.0
    meta = json.loads((folder / "meta.json").read_text())
    rec_t0 = float(meta["start_monotonic_s"])
    decisions = _jsonl(folder / "decisions.jsonl")
    commands = [d for d in decisions if d["action"] != "none"]
    if not enc.with_object:
        res.false_evasions = _episodes([int(d["frame"]) for d in commands])
        res.success = res.false_evasions == 0
        return res
    # the closest approach, from consecutive samples (linear in between)
    rows = [(t.t_s, np.subtract(t.object_m, t.vehicle_m)) for t in camera.truth if t.object_m is not None]
    best, t_best = math.inf, None
    for (ta, ra), (tb, rb) in zip(rows, rows[1:], strict=False):
        d = rb - ra
        s = float(np.clip(-ra @ d / (d @ d + 1e-12), 0.0, 1.0))
        dist = float(np.linalg.norm(ra + s * d))
        if dist < best:
            best, t_best = dist, ta + s * (tb - ta)
    res.min_separation_m = round(best, 3)
    res.t_min_separation_s = None if t_best is None else round(t_best - t0, 3)
    res.success = best >= enc.size_m / 2 + VEHICLE_RADIUS_M + SAFETY_MARGIN_M
    t_cpa = t0 + enc.t_cpa_s

    def distance(frame: int) -> float | None:
        tr = truth.get(frame)
        if tr is None or tr.object_m is None:
            return None
        return float(np.linalg.norm(np.subtract(tr.object_m, tr.vehicle_m)))

    for line in _jsonl(folder / "tracks.jsonl"):
        tr = truth.get(int(line["frame"]))
        if tr is None or tr.pixel is None:
            continue
        if any(on_object((x, y, w, h), tr.pixel)
               for _id, x, y, w, h, *_confidence_reported in line["tracks"]):
            res.detected = True
            d = distance(tr.frame)
            res.detect_range_m = None if d is None else round(d, 2)
            res.detect_before_cpa_s = round(t_cpa - tr.t_s, 3)
            break
    if commands:
        first = commands[0]
        if 20.0 <= abs(enc.approach_deg) <= 50.0 and first["action"] == "evade":
            res.towards_passage, res.into_path, res.passage_along_m = _direction_vs_truth(
                camera, int(first["frame"]), first["velocity_frd_mps"])
        res.evaded = True
        d = distance(int(first["frame"]))
        res.evade_range_m = None if d is None else round(d, 2)
        res.evade_before_cpa_s = round(t_cpa - (rec_t0 + float(first["t_capture"])), 3)
    return res


def on_object(box: tuple[float, float, float, float], pixel: tuple[float, float, float, float]) -> bool:
    """Does a track's box (x, y, w, h px) lie on the object the truth draws at ``pixel`` (u, v,
    radius px, z m)? Its centre within two radii, and never less than 20 px (the mask's ghosts
    and merges move a small object's box by that much)."""
    x, y, w, h = box
    u, v, r, _z = pixel
    return math.hypot(x + w / 2 - u, y + h / 2 - v) <= max(20.0, 2.0 * r)


def _true_passage(camera: SimulatedCamera, frame: int, window_s: float = 0.3
                  ) -> tuple[np.ndarray, np.ndarray] | None:
    """Where the object will pass the vehicle as the truth had it at ``frame``: its relative
    position (NED, m) at the closest approach on a straight course fitted to the truth's
    relative positions over the ``window_s`` before, and that course's velocity (m/s). A
    two-frame difference holds the cruise controller's jitter (0.5 m/s on a 4 m/s leg moved
    the passage of an object 10 m off by 0.5 m). None: the object is not in the truth then."""
    rows = [t for t in camera.truth if t.object_m is not None and t.frame <= frame]
    if not rows or rows[-1].frame != frame:
        return None
    recent = [t for t in rows if t.t_s >= rows[-1].t_s - window_s]
    if len(recent) < 2 or recent[-1].t_s <= recent[0].t_s:
        return None
    ts = np.array([t.t_s - recent[-1].t_s for t in recent])
    rel = np.array([np.subtract(t.object_m or (0.0, 0.0, 0.0), t.vehicle_m) for t in recent])  # all set
    slope, icpt = np.polyfit(ts, rel, 1)  # per axis: rel(t) = icpt + slope t, t = 0 at the command
    r, v = icpt, slope
    t = max(0.0, float(-r @ v / (v @ v + 1e-12)))
    return r + v * t, v


TOWARDS_TOLERANCE_M = 0.05  # a passage further than this along the escape: towards it


def _direction_vs_truth(camera: SimulatedCamera, frame: int, frd: list[float], window_s: float = 0.3
                        ) -> tuple[bool | None, bool | None, float | None]:
    """Does an evasion (forward, right, down m/s) commanded at ``frame`` move towards where
    the object will pass the vehicle (:func:`_true_passage`), and along the object's lateral
    motion? And how far along the evasion's direction that passage lies (m). Body axes are
    NED here (the vehicle flies north with yaw 0)."""
    return _direction_vs_passage(_true_passage(camera, frame, window_s), frd)


def _direction_vs_passage(truth: tuple[np.ndarray, np.ndarray] | None, frd: list[float]
                          ) -> tuple[bool | None, bool | None, float | None]:
    """:func:`_direction_vs_truth` for a passage already worked out (``truth``:
    :func:`_true_passage`'s answer)."""
    if truth is None:
        return None, None, None
    passage, v = truth
    d = np.array([frd[1], frd[2]], float)
    lateral_passage, lateral_v = passage[1:], v[1:]
    into = bool(d @ lateral_v > 0) if np.linalg.norm(lateral_v) > 0.3 else None
    norm = float(np.linalg.norm(d))
    if norm == 0:
        return None, into, None
    along = float(d @ lateral_passage) / norm
    return along > TOWARDS_TOLERANCE_M, into, round(along, 3)


def _episodes(frames: list[int], gap: int = 15) -> int:
    """Runs of command frames separated by more than ``gap`` frames count once each."""
    count, last = 0, -10**9
    for f in frames:
        if f - last > gap:
            count += 1
        last = f
    return count


def write_truth(path: Path, camera: SimulatedCamera) -> None:
    """The ground truth of every frame: time since the first frame (s), the vehicle's and the
    object's NED positions (m), and the object's image circle and distance when in view."""
    import csv

    t0 = camera.t_start or 0.0
    with path.open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["frame", "t_s", "vehicle_n", "vehicle_e", "vehicle_d", "object_n", "object_e",
                    "object_d", "u_px", "v_px", "radius_px", "z_m"])
        for t in camera.truth:
            obj = t.object_m or (None, None, None)
            pix = t.pixel or (None, None, None, None)
            w.writerow([t.frame, f"{t.t_s - t0:.4f}", *(f"{v:.3f}" for v in t.vehicle_m),
                        *("" if v is None else f"{v:.3f}" for v in obj),
                        *("" if v is None else f"{v:.2f}" for v in pix)])
