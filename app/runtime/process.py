"""The flight process: capture → perception (worker thread) → offboard, in one asyncio loop.

Hand-offs are latest-value slots (a stale frame is worth nothing): capture overwrites the
newest frame, perception takes whatever is newest when it is free, and publishes the newest
decision, which wakes the offboard coroutine at once.

Shutdown (the recording ended, SIGINT/SIGTERM, or an error in any coroutine) stops control
first — zero velocity, leave Offboard to Hold — then perception, then the camera, each step
bounded in time. Latency is accounted per frame: capture → stages 1–3 done → decision →
first setpoint sent that carried it.
"""

from __future__ import annotations

import asyncio
import logging
import math
import queue
import signal
import threading
import time
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from typing import Generic, TypeVar

import numpy as np

from app.camera import camera_from_config
from app.config import Config
from app.decision.ego import EgoMotion, derotation
from app.decision.policy import DecisionMaker, passage_fields
from app.flight.engagement import Decision, Engagement, Output, VehicleState
from app.flight.loop import Controller, FlightLink, LoopStats, control_loop
from app.flight.testflight import TestFlight
from app.perception.frames import Frame, FrameSource
from app.perception.near import depth_lens
from app.perception.pipeline import Perception
from app.runtime.notify import Notifier
from app.runtime.record import FlightRecord

log = logging.getLogger(__name__)
T = TypeVar("T")

CONTROL_STOP_S = 2.0  # bound on leaving Offboard at shutdown
PERCEPTION_STOP_S = 2.0  # bound on the frame in the worker thread
CAMERA_STOP_S = 3.0  # bound on the camera's last wait and close
# the vehicle's velocity and attitude older than this are not used by the decision (PX4 streams
# both at 10-50 Hz; the stand-in vehicle at 20 Hz), s
EGO_MAX_AGE_S = 0.3
STALL_FACTOR = 5.0  # no frame for this many frame intervals is logged as a camera stall


class LatestSlot(Generic[T]):
    """One newest value and an event that says a newer one arrived (never a queue).
    ``taken`` is set when the consumer has taken the newest value."""

    def __init__(self) -> None:
        self.value: T | None = None
        self.version = 0
        self.event = asyncio.Event()
        self.taken = asyncio.Event()
        self.taken.set()

    def put(self, value: T) -> None:
        self.value = value
        self.version += 1
        self.taken.clear()
        self.event.set()

    def get(self) -> T | None:
        return self.value

    def take(self) -> T | None:
        """The newest value, marked as taken."""
        self.taken.set()
        return self.value


def _pct(values: list[float], q: float) -> float:
    return round(float(np.percentile(values, q)), 2) if values else math.nan


@dataclass
class RunStats:
    frames_in: int = 0
    frames_processed: int = 0
    frames_dropped: int = 0  # overwritten in the slot before perception took them
    camera_stalls: int = 0
    perception_ms: list[float] = field(default_factory=list)  # stages 1-4 work per frame
    capture_to_perceived_ms: list[float] = field(default_factory=list)
    capture_to_decision_ms: list[float] = field(default_factory=list)
    capture_to_setpoint_ms: list[float] = field(default_factory=list)
    # per frame: capture -> setpoint minus (one frame interval + that frame's perception time)
    setpoint_excess_ms: list[float] = field(default_factory=list)
    frame_interval_ms: float = math.nan
    ended_by: str = ""
    loop: LoopStats = field(default_factory=LoopStats)

    def summary(self) -> dict[str, object]:
        out: dict[str, object] = {
            "frames_in": self.frames_in, "frames_processed": self.frames_processed,
            "frames_dropped": self.frames_dropped, "camera_stalls": self.camera_stalls,
            "ended_by": self.ended_by,
            "frame_interval_ms": round(self.frame_interval_ms, 2),
            "perception_median_ms": _pct(self.perception_ms, 50),
            "perception_p99_ms": _pct(self.perception_ms, 99),
        }
        for name in ("capture_to_perceived", "capture_to_decision", "capture_to_setpoint"):
            values = getattr(self, f"{name}_ms")
            out[f"{name}_median_ms"] = _pct(values, 50)
            out[f"{name}_p99_ms"] = _pct(values, 99)
        # the runtime issue's target: capture -> setpoint p99 <= one frame interval + perception
        # time + 5 ms; per frame, what is left after the interval and its own perception time
        out["setpoint_excess_median_ms"] = _pct(self.setpoint_excess_ms, 50)
        out["setpoint_excess_p99_ms"] = _pct(self.setpoint_excess_ms, 99)
        out["offboard"] = self.loop.summary()
        return out


# ---------------------------------------------------------------------------- coroutines


class _Reader:
    """One daemon thread that runs blocking camera calls in order. A daemon, unlike an
    executor's worker, so a camera stuck in its SDK can never keep the process from exiting."""

    def __init__(self, loop: asyncio.AbstractEventLoop) -> None:
        self._loop = loop
        self._calls: queue.Queue[tuple[Callable[[], object], asyncio.Future[object]] | None] = queue.Queue()
        threading.Thread(target=self._run, name="capture", daemon=True).start()

    def call(self, fn: Callable[[], object]) -> asyncio.Future[object]:
        fut: asyncio.Future[object] = self._loop.create_future()
        self._calls.put((fn, fut))
        return fut

    def close(self) -> None:
        self._calls.put(None)

    def _run(self) -> None:
        while (item := self._calls.get()) is not None:
            fn, fut = item
            try:
                result, error = fn(), None
            except BaseException as exc:  # handed to the coroutine, which raises it
                result, error = None, exc
            try:
                self._loop.call_soon_threadsafe(_settle, fut, result, error)
            except RuntimeError:  # the loop is closed: nobody waits any more
                return


def _settle(fut: asyncio.Future[object], result: object, error: BaseException | None) -> None:
    if fut.cancelled():
        return
    if error is not None:
        fut.set_exception(error)
    else:
        fut.set_result(result)


async def capture(source: FrameSource, frames: LatestSlot[Frame], stop: asyncio.Event,
                  stats: RunStats, realtime: bool = True, record: FlightRecord | None = None) -> None:
    """Put the source's frames into the slot. A live camera stamps its own frames and its
    newest frame replaces one perception has not yet taken. A recording is played at its
    frame rate, every frame perceived (the next is put only once perception has taken the
    last: playback falls behind rather than drop frames) and with its own frame times, so
    that it gives the same tracks and decisions on every playback; the time it arrived
    (``Frame.t_arrived_s``) serves latency accounting and the decisions' age.

    The blocking read runs in a thread; the source is closed (in that thread) on the way out.
    """
    period = 1.0 / source.fps if source.fps > 0 else 0.0
    stall_s = max(0.25, STALL_FACTOR * period)
    t0 = time.monotonic()
    reader = _Reader(asyncio.get_running_loop())
    iterator: Iterator[Frame] = iter(source)
    k = 0
    last = time.monotonic()
    stalled = False
    try:
        while not stop.is_set():
            pending = reader.call(lambda: next(iterator, None))
            while True:  # notice a stall while the read is still blocked
                done, _ = await asyncio.wait([pending], timeout=stall_s)
                if done or stop.is_set():
                    break
                if not stalled:
                    stalled = True
                    stats.camera_stalls += 1
                    log.warning("camera: no frame for %.2f s", time.monotonic() - last)
                    if record:
                        record.event("camera_stall", since_s=record.t(last))
            if not done:
                break  # stopping while the camera is silent
            frame = pending.result()
            assert frame is None or isinstance(frame, Frame)
            if frame is None:
                log.info("camera: end of the recording")
                stats.ended_by = stats.ended_by or "end of recording"
                break
            now = time.monotonic()
            if stalled:
                stalled = False
                log.warning("camera: frames again after %.2f s", now - last)
                if record:
                    record.event("camera_resumed", gap_s=round(now - last, 3))
            last = now
            if not source.live:
                await _wait_either(frames.taken, stop)
                if stop.is_set():
                    break
                if realtime:
                    delay = t0 + k * period - time.monotonic()
                    if delay > 0:
                        await asyncio.sleep(delay)
                    elif delay < -period:  # late (after a stall): play on from now, no burst
                        t0, k = time.monotonic(), 0
                frame = replace(frame, t_arrived_s=time.monotonic())
            stats.frames_in += 1
            frames.put(frame)
            k += 1
    finally:
        close = getattr(iterator, "close", None)
        closed = reader.call(close or source.close)
        reader.close()
        done, _ = await asyncio.wait([closed], timeout=CAMERA_STOP_S)
        if not done:
            log.error("camera: did not close within %g s (left to its thread)", CAMERA_STOP_S)


@dataclass
class _Worked:
    decision: Decision | None
    # id, x, y, w, h px, confidence, reported
    boxes: list[tuple[int, float, float, float, float, float, bool]]
    frame: int  # source frame number the result is for
    objects: list[dict[str, object]]


async def perceive(frames: LatestSlot[Frame], decisions: LatestSlot[Decision], wake: asyncio.Event,
                   stop: asyncio.Event, cfg: Config, decider: DecisionMaker, link: FlightLink,
                   stats: RunStats, record: FlightRecord | None = None,
                   notifier: Notifier | None = None, carried: bool = False) -> None:
    """Stages 1–4 in a dedicated worker thread; publish each new decision; kick the watchdog.
    ``carried``: the frames come from the vehicle's own camera, so the vehicle's velocity and
    attitude are the camera's (:attr:`FrameSource.carried`)."""
    perception = Perception(cfg.perception, camera=depth_lens(decider.camera, cfg.capture.stream))
    pool = ThreadPoolExecutor(1, thread_name_prefix="perception")
    loop = asyncio.get_running_loop()
    seen = 0
    record_number: dict[int, int | None] = {}  # source frame -> frame number in the record
    lens_k = decider.camera.color.matrix()
    last_attitude: list[tuple[float, float, float] | None] = [None]  # at the last frame decided on
    # per frame not yet decided on: the camera's velocity and attitude when it arrived
    motion: dict[int, tuple[EgoMotion | None, tuple[float, float, float] | None]] = {}
    last_command = ""
    try:
        while not stop.is_set():
            await frames.event.wait()
            frames.event.clear()
            frame = frames.take()
            if frame is None or frames.version == seen or stop.is_set():
                continue  # woken without a new frame (shutdown)
            stats.frames_dropped += max(0, frames.version - seen - 1)
            seen = frames.version
            if record is not None:
                record_number[frame.index] = record.frame(frame)
            vehicle = link.snapshot()
            altitude = vehicle.altitude_m
            # the camera's velocity and attitude as this frame arrives, kept for when
            # perception decides on it (one frame later: it decides on the frame before the
            # newest), so that the turn taken out is the one between the frames themselves
            # (only for the vehicle's own camera: a recording played as the camera moved as
            # its own vehicle did, and the static-structure test would misplace its objects)
            mount = cfg.decision.camera_mount
            motion[frame.index] = (vehicle.ego(EGO_MAX_AGE_S, mount) if carried else None,
                                   vehicle.camera_attitude(EGO_MAX_AGE_S, mount) if carried else None)

            def work(f: Frame = frame, alt: float | None = altitude) -> _Worked | None:
                t_start = time.monotonic()
                result = perception.push(f)
                if result is None:
                    return None
                t_perceived = time.monotonic()
                ego, attitude = motion.get(result.frame.index, (None, None))
                for old in [i for i in motion if i < result.frame.index]:
                    del motion[old]
                # the camera's rotation since the last frame decided on, taken out of the
                # image history (none when either attitude is unknown or stale)
                before = last_attitude[0]
                last_attitude[0] = attitude
                turn = None if before is None or attitude is None else derotation(before, attitude, lens_k)
                command, objects = decider.step(result.tracks, result.frame.depth, result.frame.t_s, alt,
                                                derotation=turn, ego=ego)
                t_decided = time.monotonic()
                stats.perception_ms.append((t_decided - t_start) * 1000.0)
                boxes = [(t.track_id, *t.box, t.confidence, t.reported) for t in result.tracks
                         if t.matched or t.reported]
                objs: list[dict[str, object]] = [] if record is None else [  # for the record only
                    {"id": o.track_id, "xyz_m": [round(c, 3) for c in o.xyz_m],
                     "closing_mps": round(o.closing_mps, 2),
                     "ttc_s": None if o.ttc_s is None else round(o.ttc_s, 3),
                     **passage_fields(o)} for o in objects]
                d = Decision(command, result.frame.t_monotonic_s, result.frame.index, t_perceived,
                             t_decided, t_start)
                return _Worked(d, boxes, result.frame.index, objs)

            worked = await loop.run_in_executor(pool, work)
            stats.frames_processed += 1
            if notifier is not None:
                notifier.kick()
            if worked is None or worked.decision is None:
                continue
            d = worked.decision
            stats.capture_to_perceived_ms.append((d.t_perceived_s - d.t_s) * 1000.0)
            stats.capture_to_decision_ms.append((d.t_decided_s - d.t_s) * 1000.0)
            decisions.put(d)
            wake.set()
            if record is not None:
                record.tracks(worked.frame, d.t_s, record_number.pop(worked.frame, None), worked.boxes)
                for old in [k for k in record_number if k < worked.frame]:
                    del record_number[old]
                c = d.command
                record.decision({"frame": d.frame, "t_capture": record.t(d.t_s), "action": c.action,
                                 "velocity_frd_mps": [c.forward_mps, c.right_mps, c.down_mps],
                                 "object_id": c.object_id, "reason": c.reason,
                                 "objects": worked.objects})
                if c.action != last_command:
                    record.event("command", action=c.action, object_id=c.object_id, reason=c.reason)
            last_command = d.command.action
    finally:
        # the frame in the worker finishes (bounded by the caller); queued work is dropped
        pool.shutdown(wait=False, cancel_futures=True)


class _TickLog:
    """The control loop's per-tick hook: setpoint latency, telemetry and events."""

    def __init__(self, stats: RunStats, record: FlightRecord | None, notifier: Notifier | None) -> None:
        self.stats = stats
        self.record = record
        self.notifier = notifier
        self.last_frame = -1
        self.last_state = ""
        self.last_mode = ""
        self.last_telemetry = -math.inf

    def __call__(self, v: VehicleState, d: Decision | None, out: Output, sent: float) -> None:
        if d is not None and d.frame != self.last_frame and out.setpoint is not None:
            self.last_frame = d.frame
            ms = (sent - d.t_s) * 1000.0
            self.stats.capture_to_setpoint_ms.append(ms)
            work_ms = (d.t_decided_s - d.t_started_s) * 1000.0
            self.stats.setpoint_excess_ms.append(ms - self.stats.frame_interval_ms - work_ms)
            if self.record:
                self.record.latency({
                    "frame": d.frame, "capture_to_perceived_ms": round((d.t_perceived_s - d.t_s) * 1e3, 2),
                    "capture_to_decision_ms": round((d.t_decided_s - d.t_s) * 1e3, 2),
                    "capture_to_setpoint_ms": round(ms, 2)})
        rec = self.record
        if out.state != self.last_state or v.mode != self.last_mode:
            if rec:
                rec.event("state", engagement=out.state, mode=v.mode, armed=v.armed, in_air=v.in_air)
            if self.notifier:
                self.notifier.status(f"{out.state}; vehicle {v.mode}")
            self.last_state, self.last_mode = out.state, v.mode
        if rec and out.status:
            rec.event("status", text=out.status)
        if rec and (sent - self.last_telemetry >= 0.1 or out.start_offboard or out.leave_to):
            self.last_telemetry = sent
            rec.telemetry({"connected": v.connected, "armed": v.armed, "in_air": v.in_air,
                           "mode": v.mode, "altitude_m": v.altitude_m,
                           "velocity_ned_mps": v.velocity_ned_mps, "lat_lon_deg": v.lat_lon_deg,
                           "attitude_rad": v.attitude_rad,  # roll, pitch, yaw: what derotates
                           "engagement": out.state, "setpoint_frd_mps": out.setpoint,
                           "start_offboard": out.start_offboard, "leave_to": out.leave_to})


# ---------------------------------------------------------------------------- the process


async def fly(cfg: Config, source: FrameSource, link: FlightLink, *, install_signals: bool = True,
              realtime: bool = True, record: FlightRecord | None = None,
              notifier: Notifier | None = None, seconds: float | None = None) -> RunStats:
    """Run the three coroutines until the recording ends, ``seconds`` have passed,
    SIGINT/SIGTERM, or an error; then
    stop control first (zero velocity, leave Offboard), then perception, then the camera.

    An error in any coroutine is raised after that shutdown (as the TaskGroup's
    ``ExceptionGroup``); ``stats.ended_by`` says why the run ended.
    """
    frames: LatestSlot[Frame] = LatestSlot()
    decisions: LatestSlot[Decision] = LatestSlot()
    stop, wake = asyncio.Event(), asyncio.Event()
    stats = RunStats(frame_interval_ms=1000.0 / source.fps if source.fps > 0 else math.nan)
    decider = DecisionMaker.for_perception(cfg.decision, source.camera or camera_from_config(cfg.camera),
                                           cfg.perception.detection)
    controller: Controller
    if cfg.flight.mode == "test-flight":
        tf = TestFlight(cfg.flight, cfg.decision.max_speed_mps)
        tf.request_start()
        controller = tf
    else:
        controller = Engagement(cfg.flight, cfg.decision.max_speed_mps)
    loop = asyncio.get_running_loop()

    def on_signal(sig: signal.Signals) -> None:
        log.info("%s: stopping (control first)", sig.name)
        stats.ended_by = stats.ended_by or sig.name
        if record:
            record.event("signal", name=sig.name)
        stop.set()

    if install_signals:
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.add_signal_handler(sig, on_signal, sig)
    if notifier:
        notifier.ready(f"flying in {cfg.flight.mode} mode, camera {source.name}")
    if record:
        record.event("start", mode=cfg.flight.mode, camera=source.name, fps=source.fps)
    try:
        async with asyncio.TaskGroup() as tg:
            control = tg.create_task(control_loop(
                link, controller, decisions.get, stop, stats=stats.loop, wake=wake,
                on_tick=_TickLog(stats, record, notifier)), name="offboard")
            per = tg.create_task(perceive(frames, decisions, wake, stop, cfg, decider, link, stats,
                                          record, notifier, carried=getattr(source, "carried", False)),
                                 name="perception")
            cam = tg.create_task(capture(source, frames, stop, stats, realtime, record), name="capture")
            ends = [cam, asyncio.ensure_future(stop.wait())]
            if seconds is not None:
                ends.append(asyncio.ensure_future(asyncio.sleep(seconds)))
            done, _ = await asyncio.wait(ends, return_when=asyncio.FIRST_COMPLETED)
            for w in ends[1:]:
                w.cancel()
            if seconds is not None and ends[2] in done and not stop.is_set():
                stats.ended_by = stats.ended_by or f"{seconds:g} s up"
            if not stop.is_set():
                await _sleep_or_stop(0.5, stop)  # the last decisions act before control stops
            stop.set()
            if notifier:
                notifier.stopping()
            await _bounded(control, CONTROL_STOP_S, "offboard")  # 1. control: zero, Hold
            frames.event.set()  # release perception's wait
            await _bounded(per, PERCEPTION_STOP_S, "perception")  # 2. perception
            await _bounded(cam, CAMERA_STOP_S + 1.0, "camera")  # 3. the camera
    except BaseException as exc:
        stats.ended_by = stats.ended_by or f"error: {_first_error(exc)}"
        if record:
            record.event("error", error=_first_error(exc))
        raise
    finally:
        if install_signals:
            for sig in (signal.SIGINT, signal.SIGTERM):
                loop.remove_signal_handler(sig)
        if record:
            record.event("end", ended_by=stats.ended_by or "stopped")
    return stats


async def _wait_either(event: asyncio.Event, stop: asyncio.Event) -> None:
    """Return when ``event`` or ``stop`` is set."""
    if event.is_set() or stop.is_set():
        return
    waiters = [asyncio.ensure_future(event.wait()), asyncio.ensure_future(stop.wait())]
    try:
        await asyncio.wait(waiters, return_when=asyncio.FIRST_COMPLETED)
    finally:
        for w in waiters:
            w.cancel()


async def _sleep_or_stop(seconds: float, stop: asyncio.Event) -> None:
    try:
        await asyncio.wait_for(stop.wait(), seconds)
    except TimeoutError:
        pass


async def _bounded(task: asyncio.Task[None], seconds: float, what: str) -> None:
    """Wait for a task to finish on its own; cancel it after ``seconds``."""
    done, _ = await asyncio.wait([task], timeout=seconds)
    if not done:
        log.error("%s did not stop within %g s: cancelled", what, seconds)
        task.cancel()
        await asyncio.wait([task], timeout=1.0)


def _first_error(exc: BaseException) -> str:
    while isinstance(exc, BaseExceptionGroup) and exc.exceptions:
        exc = exc.exceptions[0]
    return f"{type(exc).__name__}: {exc}"
