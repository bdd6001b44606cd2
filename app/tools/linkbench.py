"""Benchmarks against the PX4-faithful vehicle over UDP.

``midair bench --link``: the offboard path alone. Feeds decisions at a perception-like rate,
each with a distinct velocity, and measures on the vehicle's side when each first arrives:
setpoint rate on the wire and the time from a decision to its setpoint on the wire.

``midair bench --fly``: the whole flight process (:func:`app.runtime.process.fly`, with the flight
record on as in flight) on a generated recording at the camera's frame rate: frames kept
up with, per-frame latency capture → perceived → decided → setpoint sent.
"""

from __future__ import annotations

import asyncio
import subprocess
import sys
import time
from typing import Any

import numpy as np

from app.config import Config
from app.decision.policy import EVADE, Command
from app.errors import UsageError
from app.flight.engagement import Decision, Engagement
from app.flight.loop import LoopStats, control_loop


async def _connect_flying(link: Any, timeout_s: float = 10.0) -> None:
    await link.connect(timeout_s=timeout_s)
    await link.wait_flying(timeout_s)


async def _run(cfg: Config, seconds: float, decision_hz: float, rate_hz: float) -> dict[str, object]:
    try:
        from app.sim.px4 import SimPx4, free_udp_port
        from hardware.px4 import Px4Link
    except ImportError as exc:
        raise UsageError(f"bench --link needs the dev extra (pymavlink, mavsdk): {exc}") from None
    port = free_udp_port()
    sim = SimPx4(port, rate_hz=250.0).start()  # polls at 4 ms: arrival times within 4 ms
    link = Px4Link(f"udpin://0.0.0.0:{port}")
    try:
        await _connect_flying(link)
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


def run_fly_bench(cfg: Config, fps: float = 60.0, seconds: float = 10.0) -> dict[str, object]:
    """The flight process on a generated ``seconds``-long recording at ``fps`` (balls thrown
    at the vehicle one after another), against the simulated PX4, flight record on."""
    import dataclasses
    import tempfile
    from pathlib import Path

    from app.runtime.process import fly
    from app.runtime.record import FlightRecord
    from app.runtime.sources import open_source
    from app.sim.synthetic import approach_scene, write_recording

    if fps <= 0 or seconds < 2:
        raise UsageError("bench --fly needs --fps > 0 and --seconds >= 2")
    try:
        from app.sim.px4 import free_udp_port  # the vehicle itself runs as its own process
        from hardware.px4 import Px4Link
    except ImportError as exc:
        raise UsageError(f"bench --fly needs the dev extra (pymavlink, mavsdk): {exc}") from None

    async def go(folder: Path) -> dict[str, object]:
        source = open_source(folder)
        record = FlightRecord(dataclasses.replace(cfg.record, dir=str(folder / "records")), cfg,
                              source.camera).start()
        port = free_udp_port()
        # the vehicle in its own process, as PX4 is: it does not share our interpreter's lock
        sim = subprocess.Popen([sys.executable, "-m", "app.sim.px4", "--port", str(port)],
                               stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        link = Px4Link(f"udpin://0.0.0.0:{port}")
        try:
            await _connect_flying(link)
            stats = await fly(cfg, source, link, install_signals=False, record=record)
        finally:
            await link.close()
            sim.terminate()
            sim.wait(timeout=10)
        summary = stats.summary()
        record.close(summary)
        summary["record"] = json.loads((record.folder / "summary.json").read_text())["record"]
        return summary

    import json

    with tempfile.TemporaryDirectory(prefix="midair-bench-") as tmp:
        folder = Path(tmp) / "rec"
        frames = int(round(seconds * fps))
        # a ball from 2 s out: 8 m at 4 m/s, so there is something to track and dodge at the end
        scene = approach_scene((-0.4, -0.3, 4.0 * min(seconds, 3.0)), closing_mps=4.0,
                               frames=frames, fps=fps)
        scene = dataclasses.replace(scene, objects_3d=tuple(
            dataclasses.replace(o, start_xyz_m=(o.start_xyz_m[0], o.start_xyz_m[1],
                                                o.start_xyz_m[2] + 4.0 * max(0.0, seconds - 3.0)))
            for o in scene.objects_3d))
        write_recording(scene, folder)
        result = asyncio.run(go(folder))
    result["bench"] = {"fps": fps, "seconds": seconds, "frames": frames}
    return result
