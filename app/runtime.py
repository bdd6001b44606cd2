"""The flight process: capture → perception (worker thread) → offboard, in one asyncio loop.

Hand-offs are latest-value slots (a stale frame is worth nothing): capture overwrites the
newest frame, perception takes whatever is newest when it is free, and publishes the newest
decision, which wakes the offboard coroutine at once.

This first version plays a recording (``--camera PATH``) at its own frame rate; the D435i
adapter comes with the runtime issue's capture work.
"""

from __future__ import annotations

import asyncio
import logging
import signal
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from typing import Generic, TypeVar

import numpy as np

from app.camera import camera_from_config
from app.config import Config
from app.decision import DecisionMaker
from app.engagement import Decision, Engagement
from app.flight import Controller, FlightLink, LoopStats, control_loop
from app.perception import Frame, Perception
from app.sources import FrameSource
from app.testflight import TestFlight

log = logging.getLogger(__name__)
T = TypeVar("T")


class LatestSlot(Generic[T]):
    """One newest value and an event that says a newer one arrived (never a queue)."""

    def __init__(self) -> None:
        self.value: T | None = None
        self.version = 0
        self.event = asyncio.Event()

    def put(self, value: T) -> None:
        self.value = value
        self.version += 1
        self.event.set()

    def get(self) -> T | None:
        return self.value


@dataclass
class RunStats:
    frames_in: int = 0
    frames_processed: int = 0
    frames_dropped: int = 0  # overwritten in the slot before perception took them
    capture_to_decision_ms: list[float] = field(default_factory=list)
    loop: LoopStats = field(default_factory=LoopStats)

    def summary(self) -> dict[str, object]:
        lat = np.asarray(self.capture_to_decision_ms) if self.capture_to_decision_ms else np.zeros(1)
        return {
            "frames_in": self.frames_in, "frames_processed": self.frames_processed,
            "frames_dropped": self.frames_dropped,
            "capture_to_decision_median_ms": round(float(np.median(lat)), 2),
            "capture_to_decision_p99_ms": round(float(np.percentile(lat, 99)), 2),
            "offboard": self.loop.summary(),
        }


async def capture(source: FrameSource, frames: LatestSlot[Frame], stop: asyncio.Event,
                  stats: RunStats, realtime: bool = True) -> None:
    """Play ``source`` into the frame slot at its frame rate, stamping monotonic capture times."""
    period = 1.0 / source.fps if source.fps > 0 else 0.0
    t0 = time.monotonic()
    loop = asyncio.get_running_loop()
    iterator = iter(source)
    k = 0
    while not stop.is_set():
        frame = await loop.run_in_executor(None, next, iterator, None)  # decoding is I/O-ish
        if frame is None:
            log.info("camera: end of the recording")
            break
        if realtime:
            delay = t0 + k * period - time.monotonic()
            if delay > 0:
                await asyncio.sleep(delay)
        stats.frames_in += 1
        frames.put(replace(frame, t_s=time.monotonic()))
        k += 1


async def perceive(frames: LatestSlot[Frame], decisions: LatestSlot[Decision], wake: asyncio.Event,
                   stop: asyncio.Event, cfg: Config, decider: DecisionMaker, link: FlightLink,
                   stats: RunStats) -> None:
    """Stages 1–4 in a dedicated worker thread; publish each new decision."""
    perception = Perception(cfg.perception)
    pool = ThreadPoolExecutor(1, thread_name_prefix="perception")
    loop = asyncio.get_running_loop()
    seen = 0
    try:
        while not stop.is_set():
            await frames.event.wait()
            frames.event.clear()
            frame = frames.get()
            if frame is None or frames.version == seen:
                continue  # woken without a new frame (shutdown)
            stats.frames_dropped += max(0, frames.version - seen - 1)
            seen = frames.version
            altitude = link.snapshot().altitude_m

            def work(f: Frame = frame, alt: float | None = altitude) -> Decision | None:
                result = perception.push(f)
                if result is None:
                    return None
                command, _objects = decider.step(result.tracks, result.frame.depth,
                                                 result.frame.t_s, alt)
                return Decision(command, result.frame.t_s)

            decision = await loop.run_in_executor(pool, work)
            stats.frames_processed += 1
            if decision is not None:
                # The decision is for the frame before this one (detection's one-frame latency):
                # its timestamp is that frame's capture time, so the dead-man ages it honestly.
                stats.capture_to_decision_ms.append((time.monotonic() - decision.t_s) * 1000.0)
                decisions.put(decision)
                wake.set()
    finally:
        pool.shutdown(wait=True, cancel_futures=True)


async def fly(cfg: Config, source: FrameSource, link: FlightLink, *, install_signals: bool = True,
              realtime: bool = True) -> RunStats:
    """Run the three coroutines until the recording ends or SIGINT/SIGTERM; then stop
    control first (zero velocity, leave Offboard), then perception, then the camera."""
    frames: LatestSlot[Frame] = LatestSlot()
    decisions: LatestSlot[Decision] = LatestSlot()
    stop, wake = asyncio.Event(), asyncio.Event()
    stats = RunStats()
    decider = DecisionMaker(cfg.decision, source.camera or camera_from_config(cfg.camera))
    controller: Controller
    if cfg.flight.mode == "test-flight":
        tf = TestFlight(cfg.flight, cfg.decision.max_speed_mps)
        tf.request_start()
        controller = tf
    else:
        controller = Engagement(cfg.flight, cfg.decision.max_speed_mps)
    loop = asyncio.get_running_loop()
    if install_signals:
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.add_signal_handler(sig, stop.set)
    try:
        async with asyncio.TaskGroup() as tg:
            control = tg.create_task(control_loop(link, controller, decisions.get, stop,
                                                  stats=stats.loop, wake=wake))
            cam = tg.create_task(capture(source, frames, stop, stats, realtime))
            per = tg.create_task(perceive(frames, decisions, wake, stop, cfg, decider, link, stats))
            await cam  # the recording ended (or stop was set)
            if not stop.is_set():
                await asyncio.sleep(0.5)  # the last decisions act before control stops
            stop.set()
            frames.event.set()  # release perception's wait
            await control
            per.cancel()
    finally:
        if install_signals:
            for sig in (signal.SIGINT, signal.SIGTERM):
                loop.remove_signal_handler(sig)
    return stats
