"""MAVSDK against the PX4-faithful MAVLink vehicle over UDP on loopback: the real adapter,
the real engagement logic, real MAVLink on the wire."""

from __future__ import annotations

import asyncio
import socket
import time
from collections.abc import AsyncIterator

import pytest
import pytest_asyncio

pytest.importorskip("mavsdk")
pytest.importorskip("pymavlink")

from app.config import FlightConfig  # noqa: E402
from app.decision import EVADE, NONE, Command  # noqa: E402
from app.engagement import Decision, Engagement  # noqa: E402
from app.flight import LoopStats, control_loop  # noqa: E402
from hardware.px4 import FlightLinkError, Px4Link  # noqa: E402
from hardware.sim_px4 import SimPx4, SimState  # noqa: E402


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class Slot:
    """Latest-value decision slot, as perception fills it."""

    def __init__(self) -> None:
        self.value: Decision | None = None

    def set(self, cmd: Command) -> None:
        self.value = Decision(cmd, time.monotonic())

    def get(self) -> Decision | None:
        return self.value


async def wait_for(pred, timeout: float = 5.0) -> None:  # type: ignore[no-untyped-def]
    t0 = time.monotonic()
    while not pred():
        if time.monotonic() - t0 > timeout:
            raise AssertionError("condition not reached in time")
        await asyncio.sleep(0.02)


@pytest_asyncio.fixture
async def rig() -> AsyncIterator[tuple[SimPx4, Px4Link]]:
    port = free_udp_port()
    sim = SimPx4(port, state=SimState(mode="position")).start()
    link = Px4Link(f"udpin://0.0.0.0:{port}")
    await link.connect(timeout_s=10.0)
    def known() -> bool:  # the telemetry the take-over conditions read has arrived
        v = link.snapshot()
        return v.connected and v.armed and v.in_air and v.mode == "position" and v.altitude_m is not None

    await wait_for(known)
    try:
        yield sim, link
    finally:
        await link.close()
        sim.stop()


async def run_loop(link: Px4Link, slot: Slot, cfg: FlightConfig | None = None):  # type: ignore[no-untyped-def]
    eng = Engagement(cfg or FlightConfig(), max_speed_mps=3.0)
    stop = asyncio.Event()
    stats = LoopStats()
    task = asyncio.create_task(control_loop(link, eng, slot.get, stop, rate_hz=20.0, stats=stats))
    return eng, stop, task, stats


@pytest.mark.asyncio
@pytest.mark.timeout(60)
async def test_unreachable_autopilot_is_a_clear_error() -> None:
    link = Px4Link(f"udpin://0.0.0.0:{free_udp_port()}")
    with pytest.raises(FlightLinkError, match="no autopilot answered .* within 1 s"):
        await link.connect(timeout_s=1.0)


@pytest.mark.asyncio
@pytest.mark.timeout(60)
@pytest.mark.parametrize(("right", "down"), [(2.0, 2.0), (-2.0, 2.0), (2.0, -2.0), (-2.0, -2.0)])
async def test_evasion_reaches_the_vehicle_in_each_direction_then_hands_back(
        rig: tuple[SimPx4, Px4Link], right: float, down: float) -> None:
    sim, link = rig
    slot = Slot()
    eng, stop, task, stats = await run_loop(link, slot)

    async def feed(cmd: Command, seconds: float) -> None:
        t_end = time.monotonic() + seconds
        while time.monotonic() < t_end:
            slot.set(cmd)
            await asyncio.sleep(0.033)  # a 30 fps perception

    await feed(Command(EVADE, 0.0, right, down, 1, "test"), 1.5)
    assert sim.mode == "offboard"
    got = [r.velocity_body for r in sim.received if r.velocity_body is not None]
    assert any(v[1] == pytest.approx(right) and v[2] == pytest.approx(down) for v in got)
    fwd, r_now, d_now = sim.velocity_body()
    assert r_now * right > 0 and d_now * down > 0  # the vehicle is moving that way
    await feed(Command(NONE), 1.5)
    await wait_for(lambda: sim.mode == "hold")  # started in Position: back to Hold
    stop.set()
    await task
    summary = stats.summary()
    assert summary["setpoints"] > 20


@pytest.mark.asyncio
@pytest.mark.timeout(60)
async def test_pilot_mode_switch_wins(rig: tuple[SimPx4, Px4Link]) -> None:
    sim, link = rig
    slot = Slot()
    eng, stop, task, _ = await run_loop(link, slot)
    for _ in range(30):
        slot.set(Command(EVADE, 0.0, 2.0, -2.0, 1, "test"))
        await asyncio.sleep(0.033)
    assert sim.mode == "offboard", (sim.acks, sim.mode_log, eng.state)
    sim.pilot_set_mode("position")
    for _ in range(60):  # the threat persists for 2 s
        slot.set(Command(EVADE, 0.0, 2.0, -2.0, 1, "test"))
        await asyncio.sleep(0.033)
    assert sim.mode == "position"  # never taken back
    assert [m for _, m, why in sim.mode_log if why == "command"].count("offboard") == 1
    stop.set()
    await task


@pytest.mark.asyncio
@pytest.mark.timeout(60)
async def test_stalled_perception_stops_then_holds(rig: tuple[SimPx4, Px4Link]) -> None:
    sim, link = rig
    slot = Slot()
    eng, stop, task, _ = await run_loop(link, slot, FlightConfig(stale_release_s=1.0))
    for _ in range(20):
        slot.set(Command(EVADE, 0.0, 2.0, 0.0, 1, "test"))
        await asyncio.sleep(0.033)
    assert sim.mode == "offboard"
    t_stall = time.monotonic()  # perception hangs: the slot keeps its last decision
    await wait_for(lambda: sim.mode == "hold", timeout=4.0)
    held_after = time.monotonic() - t_stall
    zeros = [r for r in sim.received if r.t > t_stall + 0.3 and r.velocity_body == (0.0, 0.0, 0.0)]
    assert zeros, "no zero setpoint after the decision went stale"
    assert 1.0 <= held_after <= 2.5
    stop.set()
    await task


@pytest.mark.asyncio
@pytest.mark.timeout(60)
async def test_offboard_loss_failsafe_of_the_vehicle(rig: tuple[SimPx4, Px4Link]) -> None:
    """The vehicle itself: without setpoints PX4 refuses Offboard, and leaves it 1 s after
    they stop (our stand-in must do this, or the dead-man tests prove nothing)."""
    sim, link = rig
    from mavsdk.asyncio.plugins.offboard import OffboardError

    with pytest.raises(OffboardError):
        await link._offboard.start()  # no setpoint yet
    assert sim.mode == "position"


@pytest.mark.asyncio
@pytest.mark.timeout(60)
async def test_release_resumes_the_mission() -> None:
    port = free_udp_port()
    sim = SimPx4(port, state=SimState(mode="mission")).start()
    link = Px4Link(f"udpin://0.0.0.0:{port}")
    try:
        await link.connect(timeout_s=10.0)
        await wait_for(lambda: link.snapshot().mode == "mission" and link.snapshot().in_air
                       and link.snapshot().armed)
        slot = Slot()
        eng, stop, task, _ = await run_loop(link, slot)
        for _ in range(30):
            slot.set(Command(EVADE, 0.0, -2.0, 0.0, 1, "test"))
            await asyncio.sleep(0.033)
        assert sim.mode == "offboard"
        for _ in range(40):
            slot.set(Command(NONE))
            await asyncio.sleep(0.033)
        await wait_for(lambda: sim.mode == "mission")
        stop.set()
        await task
    finally:
        await link.close()
        sim.stop()


@pytest.mark.asyncio
@pytest.mark.timeout(60)
async def test_link_loss_then_reconnect_never_resumes_a_stale_command(
        rig: tuple[SimPx4, Px4Link]) -> None:
    """The link drops mid-evasion: the vehicle's own offboard-loss failsafe fires after
    COM_OF_LOSS_T, and when the link returns midair does not take it back (the pilot or
    failsafe has it), and the setpoint MAVSDK re-sends is zero, not the old evasion."""
    sim, link = rig
    slot = Slot()
    eng, stop, task, _ = await run_loop(link, slot)
    for _ in range(30):
        slot.set(Command(EVADE, 0.0, 2.0, 0.0, 1, "test"))
        await asyncio.sleep(0.033)
    assert sim.mode == "offboard"
    sim.set_link(False)
    t_cut = time.monotonic()
    await wait_for(lambda: sim.mode == "hold", timeout=3.0)
    failsafe_after = time.monotonic() - t_cut
    assert 0.9 <= failsafe_after <= 1.6  # COM_OF_LOSS_T = 1 s
    for _ in range(15):  # perception keeps asking for the evasion during the outage
        slot.set(Command(EVADE, 0.0, 2.0, 0.0, 1, "test"))
        await asyncio.sleep(0.033)
    sim.set_link(True)
    t_back = time.monotonic()
    for _ in range(60):
        slot.set(Command(EVADE, 0.0, 2.0, 0.0, 1, "test"))
        await asyncio.sleep(0.033)
    assert sim.mode == "hold", (sim.mode_log, sim.acks[-6:])  # not re-taken
    after = [r.velocity_body for r in sim.received if r.t > t_back + 0.2]
    assert after and all(v == (0.0, 0.0, 0.0) for v in after)
    stop.set()
    await task
