"""The flight-link scenarios against a real PX4 SITL, opt-in: set MIDAIR_SITL_URL, e.g.
``udpin://0.0.0.0:14540`` with PX4's ``make px4_sitl sihsim_quadx`` running. Skipped
otherwise. The test arms, takes off, lets midair evade, checks PX4 went to Offboard and
back to Hold, and lands."""

from __future__ import annotations

import asyncio
import os
import time

import pytest

URL = os.environ.get("MIDAIR_SITL_URL")
pytestmark = pytest.mark.skipif(not URL, reason="MIDAIR_SITL_URL not set (no PX4 SITL)")


@pytest.mark.asyncio
@pytest.mark.timeout(180)
async def test_evasion_against_px4_sitl() -> None:
    from mavsdk.asyncio.plugins.action import ActionAsync

    from app.config import FlightConfig
    from app.decision import EVADE, NONE, Command
    from app.engagement import Decision, Engagement
    from app.flight import control_loop
    from hardware.px4 import Px4Link

    assert URL is not None
    link = Px4Link(URL)
    await link.connect(timeout_s=30.0)
    action = ActionAsync(link._system)
    try:
        await action.arm()
        await action.takeoff()
        t0 = time.monotonic()
        while not (link.snapshot().in_air and (link.snapshot().altitude_m or 0) > 2.5):
            assert time.monotonic() - t0 < 60, "takeoff did not reach 2.5 m"
            await asyncio.sleep(0.2)
        await action.hold()
        await asyncio.sleep(2.0)
        latest: list[Decision | None] = [None]
        stop = asyncio.Event()
        eng = Engagement(FlightConfig(), 3.0)
        task = asyncio.create_task(control_loop(link, eng, lambda: latest[0], stop))
        modes = []
        for k in range(90):  # 3 s of threat, then 3 s of calm
            cmd = Command(EVADE, 0.0, 1.5, 0.0, 1, "sitl") if k < 45 else Command(NONE)
            latest[0] = Decision(cmd, time.monotonic())
            modes.append(link.snapshot().mode)
            await asyncio.sleep(1 / 15)
        stop.set()
        await task
        assert "offboard" in modes
        assert link.snapshot().mode == "hold"
    finally:
        await action.land()
        await link.close()
