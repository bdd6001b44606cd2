"""``midair bench --link``: the offboard path against the PX4-faithful vehicle over UDP.

Feeds decisions at a perception-like rate, each with a distinct velocity, and measures on
the vehicle's side when each first arrives: setpoint rate on the wire and the time from a
decision to its setpoint on the wire (median, p99).
"""

from __future__ import annotations

import asyncio
import socket
import time

import numpy as np

from app.config import Config
from app.decision import EVADE, Command
from app.engagement import Decision, Engagement
from app.errors import UsageError
from app.flight import LoopStats, control_loop


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


async def _run(cfg: Config, seconds: float, decision_hz: float, rate_hz: float) -> dict[str, object]:
    try:
        from hardware.px4 import Px4Link
        from hardware.sim_px4 import SimPx4
    except ImportError as exc:
        raise UsageError(f"bench --link needs the dev extra (pymavlink, mavsdk): {exc}") from None
    port = _free_port()
    sim = SimPx4(port, rate_hz=250.0).start()  # polls at 4 ms: arrival times within 4 ms
    link = Px4Link(f"udpin://0.0.0.0:{port}")
    try:
        await link.connect(timeout_s=10.0)
        t0 = time.monotonic()
        while not (link.snapshot().armed and link.snapshot().in_air):
            if time.monotonic() - t0 > 10:
                raise UsageError("the simulated vehicle did not report armed and in air")
            await asyncio.sleep(0.05)
        eng = Engagement(cfg.flight, cfg.decision.max_speed_mps)
        latest: list[Decision | None] = [None]
        stop = asyncio.Event()
        stats = LoopStats()
        wake = asyncio.Event()  # perception sets it with each new decision
        task = asyncio.create_task(control_loop(link, eng, lambda: latest[0], stop, rate_hz, stats,
                                                wake))
        await asyncio.sleep(1.5)  # running all along: zero setpoints warm PX4's offboard path
        made: dict[float, float] = {}
        k = 0
        t_end = time.monotonic() + seconds
        while time.monotonic() < t_end:
            right = round(1.0 + (k % 200) * 0.005, 3)  # distinct per decision (float32-exact enough)
            d = Decision(Command(EVADE, 0.0, right, 0.0, 1, "bench"), time.monotonic())
            made.setdefault(right, d.t_s)
            latest[0] = d
            wake.set()
            k += 1
            await asyncio.sleep(1.0 / decision_hz)
            if k % 200 == 0:
                made.clear()  # values repeat: measure each cycle afresh
        stop.set()
        await task
        received = [(r.t, r.velocity_body) for r in sim.received if r.velocity_body is not None]
    finally:
        await link.close()
        sim.stop()
    # latency: first arrival of each value after it was decided (last cycle's values only)
    lat = []
    for right, t_made in made.items():
        arrivals = [t for t, v in received if t >= t_made and abs(v[1] - right) < 1e-3]
        if arrivals:
            lat.append((arrivals[0] - t_made) * 1000.0)
    times = np.array([t for t, _ in received])
    span = times[-1] - times[0] if len(times) > 1 else 1.0
    lat_arr = np.asarray(lat) if lat else np.array([np.nan])
    return {
        "seconds": seconds, "decisions_per_s": decision_hz, "control_rate_hz": rate_hz,
        "setpoints_on_wire_per_s": round(len(times) / span, 1),
        "decision_to_wire_median_ms": round(float(np.median(lat_arr)), 2),
        "decision_to_wire_p99_ms": round(float(np.percentile(lat_arr, 99)), 2),
        "decisions_measured": len(lat),
        "loop": stats.summary(),
    }


def run_link_bench(cfg: Config, seconds: float = 10.0, decision_hz: float = 30.0,
                   rate_hz: float = 20.0) -> dict[str, object]:
    return asyncio.run(_run(cfg, seconds, decision_hz, rate_hz))
