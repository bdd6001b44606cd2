"""The offboard coroutine: ticks the engagement logic against a flight link at a fixed rate.

The link is anything with ``snapshot() -> VehicleState`` and ``async apply(Output)``
(:class:`hardware.px4.Px4Link` for PX4 through MAVSDK). Decisions come from a callable
returning the newest :class:`app.flight.engagement.Decision` (a latest-value slot: never a queue).
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from app.flight.engagement import Decision, Output, VehicleState


class FlightLink(Protocol):
    def snapshot(self) -> VehicleState: ...

    async def apply(self, out: Output) -> None: ...


class Controller(Protocol):
    """:class:`app.flight.engagement.Engagement` (guard, shadow) or
    :class:`app.flight.testflight.TestFlight`."""

    @property
    def in_control(self) -> bool: ...

    def tick(self, v: VehicleState, d: Decision | None) -> Output: ...

    def shutdown(self) -> Output: ...


@dataclass
class LoopStats:
    ticks: int = 0
    setpoints: int = 0
    # from the decision's t_s (in the flight process: its frame's capture time) to sent
    decision_to_wire_ms: list[float] = field(default_factory=list)
    period_ms: list[float] = field(default_factory=list)

    def summary(self) -> dict[str, float]:
        lat = np.asarray(self.decision_to_wire_ms) if self.decision_to_wire_ms else np.zeros(1)
        per = np.asarray(self.period_ms) if self.period_ms else np.zeros(1)
        return {
            "ticks": self.ticks, "setpoints": self.setpoints,
            "rate_hz": round(1000.0 / float(np.median(per)), 1) if per.any() else 0.0,
            "decision_to_wire_median_ms": round(float(np.median(lat)), 2),
            "decision_to_wire_p99_ms": round(float(np.percentile(lat, 99)), 2),
        }


async def control_loop(
    link: FlightLink,
    engagement: Controller,
    latest: Callable[[], Decision | None],
    stop: asyncio.Event,
    rate_hz: float = 20.0,
    stats: LoopStats | None = None,
    wake: asyncio.Event | None = None,
    on_tick: Callable[[VehicleState, Decision | None, Output, float], None] | None = None,
) -> None:
    """Tick at ``rate_hz`` and at once whenever ``wake`` is set (a new decision), until
    ``stop`` is set; then, if in control, zero velocity and leave to Hold.
    ``on_tick(state, decision, output, t_sent)`` sees every tick after it was carried out
    (the flight record and latency accounting hang off it; it must not block).

    Cancellation and errors end the same way (``finally``): the vehicle is never left
    flying our last command.
    """
    period = 1.0 / rate_hz
    stats = stats if stats is not None else LoopStats()
    last = time.monotonic()
    try:
        while not stop.is_set():
            t0 = time.monotonic()
            d = latest()
            v = link.snapshot()
            out = engagement.tick(v, d)
            await link.apply(out)
            sent = time.monotonic()
            if on_tick is not None:
                on_tick(v, d, out, sent)
            stats.ticks += 1
            stats.period_ms.append((t0 - last) * 1000.0)
            last = t0
            if out.setpoint is not None:
                stats.setpoints += 1
                if d is not None and out.setpoint != (0.0, 0.0, 0.0):
                    stats.decision_to_wire_ms.append((sent - d.t_s) * 1000.0)
            await _sleep_until(max(0.0, period - (time.monotonic() - t0)), stop, wake)
    finally:
        if engagement.in_control:
            out = engagement.shutdown()
            await asyncio.shield(link.apply(out))
            if on_tick is not None:
                on_tick(link.snapshot(), None, out, time.monotonic())


async def _sleep_until(timeout: float, stop: asyncio.Event, wake: asyncio.Event | None) -> None:
    """Return after ``timeout`` s, or as soon as ``stop`` or ``wake`` is set (``wake`` is
    cleared on the way out)."""
    waiters = [asyncio.ensure_future(stop.wait())]
    if wake is not None:
        waiters.append(asyncio.ensure_future(wake.wait()))
    try:
        await asyncio.wait(waiters, timeout=timeout, return_when=asyncio.FIRST_COMPLETED)
    finally:
        for w in waiters:
            w.cancel()
        if wake is not None:
            wake.clear()

