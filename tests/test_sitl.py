"""The flight-link scenarios against a real PX4 SITL, opt-in: set MIDAIR_SITL_URL, e.g.
``udpin://0.0.0.0:14540`` with PX4's ``make px4_sitl sihsim_quadx`` running. Skipped
otherwise (no PX4 SITL on the development machine or CI; the same scenarios run against
app/sim/px4.py in test_flight_link.py).

Each test arms and takes off if needed, runs one scenario, and ends in Hold; the last one
lands. What cannot be done to a SITL from here (cutting its radio link) stays with the
stand-in vehicle."""

from __future__ import annotations

import asyncio
import os
import time
from collections.abc import AsyncIterator

import pytest
import pytest_asyncio

URL = os.environ.get("MIDAIR_SITL_URL")
pytestmark = pytest.mark.skipif(not URL, reason="MIDAIR_SITL_URL not set (no PX4 SITL)")

if URL:
    from mavsdk.asyncio.plugins.action import ActionAsync

    from app.config import FlightConfig
    from app.decision.policy import EVADE, NONE, Command
    from app.flight.engagement import Decision, Engagement
    from app.flight.loop import control_loop
    from hardware.px4 import Px4Link


@pytest_asyncio.fixture
async def airborne() -> AsyncIterator[tuple[Px4Link, ActionAsync]]:
    assert URL is not None
    link = Px4Link(URL)
    await link.connect(timeout_s=30.0)
    action = ActionAsync(link._system)
    v = link.snapshot()
    if not v.in_air:
        await action.arm()
        await action.takeoff()
    t0 = time.monotonic()
    while not (link.snapshot().in_air and (link.snapshot().altitude_m or 0) > 2.5):
        assert time.monotonic() - t0 < 60, "takeoff did not reach 2.5 m"
        await asyncio.sleep(0.2)
    await action.hold()
    await asyncio.sleep(2.0)
    try:
        yield link, action
    finally:
        await link.close()


async def _run(link: Px4Link, commands: list[Command], hz: float = 15.0,
               cfg: FlightConfig | None = None, hook=None):
    latest: list[Decision | None] = [None]
    stop = asyncio.Event()
    eng = Engagement(cfg or FlightConfig(), 3.0)
    task = asyncio.create_task(control_loop(link, eng, lambda: latest[0], stop))
    await asyncio.sleep(1.5)  # the zero stream warms PX4's offboard path
    modes, vels = [], []
    for k, cmd in enumerate(commands):
        if cmd is not None:
            latest[0] = Decision(cmd, time.monotonic())
        if hook is not None:
            await hook(k)
        v = link.snapshot()
        modes.append(v.mode)
        vels.append(v.velocity_ned_mps)
        await asyncio.sleep(1 / hz)
    stop.set()
    await task
    return modes, vels


@pytest.mark.asyncio
@pytest.mark.timeout(180)
@pytest.mark.parametrize(("right", "down"), [(1.5, 0.0), (-1.5, 0.0), (0.0, -1.0)])
async def test_sitl_evasion_then_back_to_hold(airborne, right: float, down: float) -> None:
    link, _ = airborne
    cmds = [Command(EVADE, 0.0, right, down, 1, "sitl")] * 30 + [Command(NONE)] * 45
    modes, vels = await _run(link, cmds)
    assert "offboard" in modes
    assert link.snapshot().mode == "hold"


@pytest.mark.asyncio
@pytest.mark.timeout(180)
async def test_sitl_pilot_mode_change_wins(airborne) -> None:
    link, action = airborne

    async def pilot(k: int) -> None:
        if k == 25:
            await action.hold()  # another mode than Offboard, not asked for by midair

    cmds = [Command(EVADE, 0.0, 1.5, 0.0, 1, "sitl")] * 75
    modes, _ = await _run(link, cmds, hook=pilot)
    assert "offboard" in modes[:25]
    assert all(m != "offboard" for m in modes[35:])  # never taken back during the cooldown


@pytest.mark.asyncio
@pytest.mark.timeout(180)
async def test_sitl_stalled_perception_leaves_to_hold(airborne) -> None:
    link, action = airborne
    cmds = [Command(EVADE, 0.0, 1.5, 0.0, 1, "sitl")] * 15 + [None] * 45  # decisions stop
    modes, _ = await _run(link, cmds, cfg=FlightConfig(stale_release_s=1.0))  # type: ignore[arg-type]
    assert "offboard" in modes
    assert modes[-1] == "hold"
    await action.land()
