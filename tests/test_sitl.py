"""The flight-link scenarios against a real PX4 SITL (SIH quadrotor), opt-in: ``pytest -m sitl``
with ``MIDAIR_SITL_URL=udpin://0.0.0.0:14540`` and a fresh PX4 SITL running (docs/sitl.md).
Skipped otherwise; the same scenarios run against the stand-in (app/sim/px4.py) in
tests/test_flight_link.py.

Three parties, as in flight:

- midair: :class:`hardware.px4.Px4Link` ticked by :func:`app.flight.loop.control_loop` with the
  real :class:`app.flight.engagement.Engagement`, fed from a latest-decision slot. Its link goes
  through :class:`tests.sitl_proxy.MavlinkProxy`, which binds PX4's offboard port, counts
  what midair asks of PX4 on the wire and can cut the link both ways.
- the pilot: a second MAVSDK connection on PX4's ground-station link (14550): it arms and
  takes off, uploads and starts missions, switches modes, and observes the vehicle
  (velocity, position, yaw, mode, mission item, status texts) independently of midair's link.
- PX4 itself: flight modes reported in its 1 Hz heartbeat (seen 0.4-0.9 s late), Offboard
  accepted only after about a second of setpoints, offboard-loss fallback ~1 s after the
  last one. Every wait for a mode is a deadline that fits those reports, never a fixed
  short window.

Each test starts from hover in Hold at >= 2.5 m whatever the previous one left (the
``hover`` fixture: lands-in-progress, ground, any mode in the air).
"""

from __future__ import annotations

import asyncio
import math
import os
import re
import time
from collections.abc import AsyncIterator, Callable
from dataclasses import dataclass, field
from typing import Any

import pytest
import pytest_asyncio

from app.config import FlightConfig
from app.decision.policy import EVADE, NONE, Command
from app.flight.engagement import ENGAGED, MONITOR, Decision, Engagement, status_text
from app.flight.loop import control_loop

URL = os.environ.get("MIDAIR_SITL_URL")  # midair's link: PX4's offboard/API port
GCS_URL = os.environ.get("MIDAIR_SITL_GCS_URL", "udpin://0.0.0.0:14550")  # the pilot's link
_PORT = re.fullmatch(r"udpin://[^:/]*:(\d+)", URL or "")

pytestmark = [
    pytest.mark.sitl,
    pytest.mark.skipif(not URL, reason="MIDAIR_SITL_URL not set: needs a running PX4 SITL "
                       "(e.g. udpin://0.0.0.0:14540; see docs/sitl.md)"),
    pytest.mark.skipif(bool(URL) and _PORT is None,
                       reason=f"MIDAIR_SITL_URL={URL!r}: the SITL tests relay midair's link "
                       "through a UDP proxy and need udpin://HOST:PORT"),
]

HOVER_ALT_M = 7.0  # take-off altitude; every test starts at or above MIN_ALT_M
MIN_ALT_M = 2.5
MODE_REPORT_S = 2.5  # a mode change shows in telemetry within this (1 Hz heartbeat + margin)
MAX_SPEED = 3.0  # decision.max_speed_mps
ZERO = (0.0, 0.0, 0.0)


async def until(pred: Callable[[], bool], timeout: float, what: str,
                every: float = 0.02) -> float:
    """Wait until ``pred()``; the monotonic time it held. AssertionError after ``timeout`` s."""
    t0 = time.monotonic()
    while not pred():
        if time.monotonic() - t0 > timeout:
            raise AssertionError(f"{what}: not within {timeout:g} s")
        await asyncio.sleep(every)
    return time.monotonic()


# ---------------------------------------------------------------------- the pilot's link


@dataclass
class Sample:
    t: float
    pos_ned: tuple[float, float, float]  # m, PX4's local origin
    vel_ned: tuple[float, float, float]  # m/s
    yaw_rad: float


@dataclass
class GcsView:
    mode: str | None = None  # None until the first heartbeat
    modes: list[tuple[float, str]] = field(default_factory=list)  # each change
    landed: str | None = None  # LandedState name; None until EXTENDED_SYS_STATE arrived
    armed: bool | None = None
    rel_alt_m: float = math.nan
    lat_lon: tuple[float, float] | None = None
    abs_alt_m: float = math.nan
    yaw_rad: float = math.nan
    samples: list[Sample] = field(default_factory=list)
    mission_item: int | None = None
    mission_items: list[tuple[float, int]] = field(default_factory=list)  # each change
    texts: list[tuple[float, str]] = field(default_factory=list)


class GroundStation:
    """MAVSDK as a ground station on PX4's GCS link: the pilot, and an observer that does
    not depend on midair's link."""

    def __init__(self, url: str) -> None:
        self.url = url
        self.v = GcsView()
        self._tasks: list[asyncio.Task[None]] = []

    async def connect(self, timeout_s: float = 20.0) -> None:
        from mavsdk import ComponentType, Configuration
        from mavsdk.asyncio import Mavsdk
        from mavsdk.asyncio.plugins.action import ActionAsync
        from mavsdk.asyncio.plugins.mission import MissionAsync
        from mavsdk.asyncio.plugins.telemetry import TelemetryAsync

        from hardware.px4 import _route_core_log

        _route_core_log()  # the C++ core's lines into logging, not stdout
        self._mavsdk = Mavsdk(Configuration.create_with_component_type(ComponentType.GROUND_STATION))
        await self._mavsdk.add_any_connection(self.url)
        system = await self._mavsdk.first_autopilot(timeout_s)
        assert system is not None, f"no autopilot on the ground-station link {self.url}"
        self._system = system
        self.telemetry = TelemetryAsync(system)
        self.action = ActionAsync(system)
        self.mission = MissionAsync(system)
        tel = self.telemetry
        for sub, on in ((tel.subscribe_flight_mode, self._on_mode),
                        (tel.subscribe_landed_state, self._on_landed),
                        (tel.subscribe_armed, self._on_armed),
                        (tel.subscribe_position, self._on_position),
                        (tel.subscribe_attitude_euler, self._on_attitude),
                        (tel.subscribe_position_velocity_ned, self._on_pv),
                        (tel.subscribe_status_text, self._on_text),
                        (self.mission.subscribe_mission_progress, self._on_progress)):
            self._tasks.append(asyncio.create_task(self._watch(sub, on)))

    async def close(self) -> None:
        for t in self._tasks:
            t.cancel()
        await asyncio.gather(*self._tasks, return_exceptions=True)
        mavsdk = self.__dict__.pop("_mavsdk", None)
        if mavsdk is not None:
            for name in ("telemetry", "action", "mission"):
                plugin = self.__dict__.pop(name, None)
                if plugin is not None:
                    plugin.destroy()
            self.__dict__.pop("_system", None)
            await asyncio.get_running_loop().run_in_executor(None, mavsdk.destroy)

    async def _watch(self, subscribe: Callable[[], Any], on: Callable[[Any], None]) -> None:
        async for value in subscribe():
            on(value)

    def _on_mode(self, m: Any) -> None:
        from hardware.px4 import _MODES

        mode = _MODES.get(getattr(m, "name", str(m)), str(getattr(m, "name", m)).lower())
        if mode != self.v.mode:
            self.v.modes.append((time.monotonic(), mode))
        self.v.mode = mode

    def _on_landed(self, s: Any) -> None:
        self.v.landed = getattr(s, "name", str(s))

    def _on_armed(self, a: Any) -> None:
        self.v.armed = bool(a)

    def _on_position(self, p: Any) -> None:
        self.v.rel_alt_m = float(p.relative_altitude_m)
        self.v.abs_alt_m = float(p.absolute_altitude_m)
        self.v.lat_lon = (float(p.latitude_deg), float(p.longitude_deg))

    def _on_attitude(self, e: Any) -> None:
        self.v.yaw_rad = math.radians(float(e.yaw_deg))

    def _on_pv(self, pv: Any) -> None:
        p, w = pv.position, pv.velocity
        self.v.samples.append(Sample(time.monotonic(), (p.north_m, p.east_m, p.down_m),
                                     (w.north_m_s, w.east_m_s, w.down_m_s), self.v.yaw_rad))

    def _on_text(self, s: Any) -> None:
        self.v.texts.append((time.monotonic(), str(s.text).strip()))

    def _on_progress(self, p: Any) -> None:
        if p.current != self.v.mission_item:
            self.v.mission_items.append((time.monotonic(), int(p.current)))
        self.v.mission_item = int(p.current)

    # ------------------------------------------------------------------ observations

    @property
    def in_air(self) -> bool | None:
        """None while unknown (no EXTENDED_SYS_STATE yet, or PX4 says UNKNOWN)."""
        s = self.v.landed
        return None if s in (None, "UNKNOWN") else s != "ON_GROUND"

    def speed(self) -> float:
        return math.dist(self.v.samples[-1].vel_ned, ZERO) if self.v.samples else math.inf

    def modes_since(self, t: float) -> list[str]:
        return [m for tm, m in self.v.modes if tm >= t]

    def texts_since(self, t: float) -> list[str]:
        return [s for ts, s in self.v.texts if ts >= t]

    def window(self, t0: float, t1: float) -> list[Sample]:
        return [s for s in self.v.samples if t0 <= s.t <= t1]

    async def mode_is(self, mode: str, timeout: float = MODE_REPORT_S) -> float:
        return await until(lambda: self.v.mode == mode, timeout,
                           f"the ground station did not see {mode} (mode {self.v.mode})")

    async def start_mission(self, timeout: float = 15.0) -> None:
        """Start the uploaded mission and wait until a heartbeat reports Mission. PX4 refuses
        it for a moment after an upload ("Switching to Mission is currently not available"
        until its feasibility check has run): retried."""
        from mavsdk.asyncio.plugins.mission import MissionError

        t0 = time.monotonic()
        while True:
            try:
                await self.mission.start_mission()
                await self.mode_is("mission", MODE_REPORT_S)
                return
            except (MissionError, AssertionError):
                if time.monotonic() - t0 > timeout:
                    raise
                await asyncio.sleep(0.5)

    async def hold(self, timeout: float = 10.0) -> None:
        """Switch to Hold (retrying a refusal) and wait until a heartbeat reports it."""
        from mavsdk.asyncio.plugins.action import ActionError

        t0 = time.monotonic()
        while True:
            try:
                await self.action.hold()
                await self.mode_is("hold", MODE_REPORT_S)
                return
            except (ActionError, AssertionError):
                if time.monotonic() - t0 > timeout:
                    raise
                await asyncio.sleep(0.5)


# ---------------------------------------------------------------------- midair


@dataclass(frozen=True)
class Tick:
    t: float
    state: str
    connected: bool
    mode: str
    setpoint: tuple[float, float, float] | None
    leave_to: str | None
    status: str | None


class Midair:
    """midair's flight process: the engagement logic ticked at 20 Hz on its own link, fed
    by a 30 fps "perception" that publishes the newest decision (or stalls)."""

    def __init__(self, link: Any, cfg: FlightConfig | None = None) -> None:
        self.link = link
        self.eng = Engagement(cfg or FlightConfig(), max_speed_mps=MAX_SPEED)
        self.decision: Decision | None = None
        self.ticks: list[Tick] = []
        self._stop = asyncio.Event()
        self._task: asyncio.Task[None] | None = None

    async def start(self) -> None:
        def on_tick(v: Any, d: Any, out: Any, sent: float) -> None:
            self.ticks.append(Tick(sent, out.state, v.connected, v.mode, out.setpoint,
                                   out.leave_to, out.status))

        self._task = asyncio.create_task(control_loop(self.link, self.eng, lambda: self.decision,
                                                      self._stop, rate_hz=20.0, on_tick=on_tick))
        # midair streams zero all along while flying: PX4 accepts Offboard only after ~1 s of it
        await until(lambda: sum(t.setpoint == ZERO for t in self.ticks) >= 30, 5.0,
                    "midair streams no zero setpoints while flying")

    async def feed(self, cmd: Command, seconds: float = math.inf,
                   until_: Callable[[], bool] | None = None, what: str = "") -> float:
        """Publish ``cmd`` afresh every 33 ms for ``seconds``, or until ``until_()`` (then
        ``seconds`` is its deadline). Returns when it stopped."""
        t0 = time.monotonic()
        while True:
            now = time.monotonic()
            if until_ is not None and until_():
                return now
            if now - t0 >= seconds:
                if until_ is not None:
                    raise AssertionError(f"{what or 'condition'}: not within {seconds:g} s "
                                         f"(midair {self.eng.state}, link mode {self.link.snapshot().mode})")
                return now
            self.decision = Decision(cmd, now)
            await asyncio.sleep(0.033)

    async def close(self) -> None:
        self._stop.set()
        if self._task is not None:
            await self._task

    def first(self, pred: Callable[[Tick], bool], after: float) -> Tick | None:
        return next((t for t in self.ticks if t.t >= after and pred(t)), None)

    def statuses(self) -> list[str]:
        return [t.status for t in self.ticks if t.status]


# ---------------------------------------------------------------------- fixtures


@pytest.fixture(scope="session")
def proxy() -> Any:
    """The UDP relay in PX4's offboard port's place, for the whole session."""
    assert _PORT is not None
    from tests.sitl_proxy import MavlinkProxy

    p = MavlinkProxy(int(_PORT.group(1))).start()
    yield p
    p.stop()


@pytest_asyncio.fixture
async def gcs() -> AsyncIterator[GroundStation]:
    g = GroundStation(GCS_URL)
    try:
        await g.connect()
        yield g
    finally:
        await g.close()


@pytest_asyncio.fixture
async def hover(gcs: GroundStation) -> GroundStation:
    """From whatever state: hovering in Hold at >= MIN_ALT_M, nearly still."""
    await bring_to_hover(gcs)
    return gcs


async def bring_to_hover(gcs: GroundStation) -> None:
    from mavsdk.asyncio.plugins.action import ActionError

    v = gcs.v
    # The first telemetry comes before the landed state is known: wait for it (and the
    # heartbeat's armed flag and mode) rather than read "not in air" from a default.
    await until(lambda: gcs.in_air is not None and v.armed is not None and v.mode is not None
                and bool(v.samples) and math.isfinite(v.rel_alt_m), 15.0,
                "the vehicle's landed state, armed flag, mode and position")
    if v.landed == "LANDING" or v.mode == "land":
        await until(lambda: v.landed == "ON_GROUND", 90.0, "a landing in progress did not finish")
    if v.landed == "TAKING_OFF" or v.mode == "takeoff":
        await until(lambda: v.landed == "IN_AIR" and v.mode != "takeoff", 60.0, "take-off did not end")
    if v.landed == "ON_GROUND":
        await gcs.action.set_takeoff_altitude(HOVER_ALT_M)
        t0 = time.monotonic()
        while True:  # arming is refused for a while after a landing or at boot: retry
            try:
                await gcs.action.arm()
                await gcs.action.takeoff()
                break
            except ActionError:
                if time.monotonic() - t0 > 40.0:
                    raise
                await asyncio.sleep(1.0)
        await until(lambda: v.landed == "IN_AIR" and v.rel_alt_m > HOVER_ALT_M - 0.7, 60.0,
                    f"take-off to {HOVER_ALT_M:g} m")
    elif v.rel_alt_m < HOVER_ALT_M - 1.5:  # in the air, but low (a descent, an RTL)
        # Climb by a one-item mission over where it is (this PX4 refuses MAVSDK 4.1's
        # goto_location: "frame invalid for command 192").
        from mavsdk.asyncio.plugins.mission import MissionItem, MissionPlan

        await gcs.hold()
        lat, lon = v.lat_lon or (math.nan, math.nan)
        await gcs.mission.upload_mission(MissionPlan([MissionItem(lat, lon, HOVER_ALT_M, 2.0, False)]))
        await gcs.start_mission()
        await until(lambda: v.rel_alt_m > HOVER_ALT_M - 0.7, 30.0, f"climb to {HOVER_ALT_M:g} m")
    await gcs.hold()
    await until(lambda: gcs.speed() < 0.3, 20.0, "the vehicle did not settle in Hold")
    assert v.armed and gcs.in_air and v.rel_alt_m >= MIN_ALT_M, v


@pytest_asyncio.fixture
async def midair_link(proxy: Any, hover: GroundStation) -> AsyncIterator[Any]:
    """midair's Px4Link through the proxy, with the take-over conditions' telemetry in."""
    from hardware.px4 import Px4Link

    link = Px4Link(proxy.client_url)
    try:
        await link.connect(timeout_s=20.0)
        t0 = time.monotonic()
        await until(lambda: (s := link.snapshot()).connected and s.armed and s.in_air
                    and s.mode == "hold" and s.mode_t_s > t0 and s.altitude_m is not None,
                    10.0, "midair's link: armed, in air, Hold reported, altitude")
        yield link
    finally:
        await link.close()


@pytest_asyncio.fixture
async def midair(midair_link: Any) -> AsyncIterator[Midair]:
    m = Midair(midair_link)
    await m.start()
    try:
        yield m
    finally:
        await m.close()


async def take_over(m: Midair, gcs: GroundStation, proxy: Any, cmd: Command) -> float:
    """Feed ``cmd`` until midair is engaged and PX4 reports Offboard; the time of midair's
    (first) offboard request on the wire."""
    t0 = time.monotonic()
    await m.feed(cmd, 5.0, lambda: m.eng.state == ENGAGED and gcs.v.mode == "offboard",
                 "midair engaged and the vehicle in Offboard")
    asked = [r for r in proxy.requests_since(t0) if r.mode == "offboard"]
    assert asked, "engaged without an offboard request on the wire"
    return asked[0].t


def body(s: Sample) -> tuple[float, float, float]:
    """A sample's velocity in the body frame PX4 applies velocity setpoints in (yaw only)."""
    n, e, d = s.vel_ned
    c, si = math.cos(s.yaw_rad), math.sin(s.yaw_rad)
    return (c * n + si * e, -si * n + c * e, d)


def along(vec: tuple[float, float, float], cmd: tuple[float, float, float]) -> float:
    k = math.dist(cmd, ZERO)
    return sum(a * b for a, b in zip(vec, cmd, strict=True)) / k


# ---------------------------------------------------------------------- scenarios


@pytest.mark.asyncio
@pytest.mark.timeout(180)
@pytest.mark.parametrize(("right", "down"), [(2.0, 0.0), (-2.0, 0.0), (1.5, -1.5), (-1.5, 1.0)],
                         ids=["right", "left", "up-right", "down-left"])
async def test_sitl_evasion_moves_the_vehicle_that_way_then_hands_back_to_hold(
        proxy: Any, hover: GroundStation, midair: Midair, right: float, down: float) -> None:
    gcs = hover
    cmd = Command(EVADE, 0.0, right, down, 1, "sitl")
    want = (0.0, right, down)
    t_req = await take_over(midair, gcs, proxy, cmd)
    yaw0 = gcs.v.samples[-1].yaw_rad
    p0 = gcs.v.samples[-1].pos_ned
    t_clear = await midair.feed(cmd, 2.5)
    p1 = gcs.v.samples[-1].pos_ned

    # the command went out as commanded, in the body frame ...
    sent = [s for s in proxy.setpoints_since(t_req) if s.t < t_clear and s.velocity != ZERO]
    assert sent and all(s.velocity == pytest.approx(want, abs=1e-3) for s in sent), sent[-3:]
    assert {s.frame for s in sent} == {8}  # MAV_FRAME_BODY_NED
    # ... and the vehicle really moved that way (its own telemetry, rotated by its yaw)
    speeds = [along(body(s), want) for s in gcs.window(t_req, t_clear + 0.2)]
    assert max(speeds) >= 0.5 * math.dist(want, ZERO), f"peak {max(speeds):.2f} m/s along {want}"
    dn, de, dd = (b - a for a, b in zip(p0, p1, strict=True))
    c, s = math.cos(yaw0), math.sin(yaw0)
    moved = (c * dn + s * de, -s * dn + c * de, dd)
    gone = along(moved, want)
    off = math.dist(moved, tuple(gone * x / math.dist(want, ZERO) for x in want))
    assert gone >= 1.0 and off < 0.6 * gone, f"moved {moved} (FRD m) for {want}"

    # no threat: back to Hold (it began in Hold), one offboard stop on the wire
    await midair.feed(Command(NONE), 0.5 + MODE_REPORT_S + 0.5, lambda: gcs.v.mode == "hold",
                      "back in Hold after the threat cleared")
    await midair.feed(Command(NONE), 2.5)  # past PX4's next heartbeat (still "offboard" once)
    assert proxy.modes_requested_since(t_clear) == ["hold"]
    assert midair.eng.state == MONITOR and gcs.v.mode == "hold"
    assert not any("late" in s for s in midair.statuses()), midair.statuses()
    # the pilot was told, through PX4, on the ground-station link
    assert status_text(cmd) in gcs.texts_since(t_req - 0.5), gcs.texts_since(t_req - 0.5)


@pytest.mark.asyncio
@pytest.mark.timeout(180)
async def test_sitl_pilot_mode_change_wins_and_midair_stays_out_during_the_cooldown(
        proxy: Any, hover: GroundStation, midair: Midair) -> None:
    gcs = hover
    cmd = Command(EVADE, 0.0, 1.5, 0.0, 1, "sitl")
    await take_over(midair, gcs, proxy, cmd)
    await midair.feed(cmd, 1.0)
    t_pilot = time.monotonic()
    await gcs.action.hold()  # the pilot flips the mode switch (ground-station link)
    t_acked = time.monotonic()

    # midair sees it in PX4's next heartbeat and stops commanding
    t_seen = await midair.feed(cmd, MODE_REPORT_S, lambda: midair.eng.state == MONITOR,
                               "midair did not notice the pilot's Hold")
    assert t_seen - t_acked < MODE_REPORT_S
    assert any(s.startswith("midair: pilot took hold") for s in midair.statuses()), midair.statuses()
    # the threat persists for 8 s of the 10 s cooldown: midair never takes it back
    t_end = await midair.feed(cmd, 8.0)
    assert proxy.requests_since(t_pilot) == [], proxy.requests_since(t_pilot)
    assert all(s.velocity == ZERO for s in proxy.setpoints_since(t_seen + 0.1))
    beats = proxy.heartbeat_modes_since(t_pilot)
    first_hold = next(i for i, (_, m) in enumerate(beats) if m == "hold")
    assert first_hold <= 1, beats[:4]  # the first or second heartbeat after the switch
    assert all(m == "hold" for _, m in beats[first_hold:]), beats
    assert all(t.state == MONITOR for t in midair.ticks if t_seen <= t.t <= t_end)
    assert "offboard" not in gcs.modes_since(t_pilot) and gcs.v.mode == "hold", gcs.v.modes


MISSION_LEGS_M = [(18.0, 0.0), (18.0, 18.0), (0.0, 18.0), (0.0, 0.0), (18.0, 0.0), (18.0, 18.0)]


async def upload_square(gcs: GroundStation) -> int:
    from mavsdk.asyncio.plugins.mission import MissionItem, MissionPlan

    assert gcs.v.lat_lon is not None
    lat0, lon0 = gcs.v.lat_lon
    items = []
    for n, e in MISSION_LEGS_M:
        lat = lat0 + n / 111_320.0
        lon = lon0 + e / (111_320.0 * math.cos(math.radians(lat0)))
        items.append(MissionItem(lat, lon, HOVER_ALT_M, 4.0, True, acceptance_radius_m=1.5))
    await gcs.mission.upload_mission(MissionPlan(items))
    return len(items)


@pytest.mark.asyncio
@pytest.mark.timeout(240)
async def test_sitl_mission_take_over_then_resume_from_its_current_item_once(
        proxy: Any, hover: GroundStation, midair_link: Any) -> None:
    gcs = hover
    count = await upload_square(gcs)
    await gcs.start_mission()  # the pilot starts it
    await until(lambda: (gcs.v.mission_item or 0) >= 1, 40.0, "mission item 1 reached")
    m = Midair(midair_link)
    await m.start()  # running all along would be the same; starting here keeps counts clean
    try:
        await until(lambda: midair_link.snapshot().mode == "mission", MODE_REPORT_S,
                    "midair's link reports Mission")
        cmd = Command(EVADE, 0.0, -2.0, 0.0, 1, "sitl")
        await take_over(m, gcs, proxy, cmd)
        seq_taken = gcs.v.mission_item
        assert seq_taken is not None and seq_taken >= 1
        t_clear = await m.feed(cmd, 1.5)
        t_back = await m.feed(Command(NONE), 0.5 + MODE_REPORT_S + 1.0,
                              lambda: gcs.v.mode == "mission", "back in Mission after the threat")
        await m.feed(Command(NONE), 2.5)  # past the next heartbeat: the stale Offboard report
        asked = proxy.modes_requested_since(t_clear)
        assert asked == ["hold", "mission"], asked  # one offboard stop, one mission start
        assert all(r.how == "DO_SET_MODE" for r in proxy.requests_since(t_clear))
        resumed = [s for t, s in gcs.v.mission_items if t >= t_clear]
        seq_back = gcs.v.mission_item
        assert seq_back is not None and seq_back >= seq_taken, (seq_taken, gcs.v.mission_items)
        assert 0 not in resumed, gcs.v.mission_items  # not restarted from its first item
        assert m.eng.state == MONITOR and gcs.v.mode == "mission"
        # and it flies on: the next item is reached
        await until(lambda: (gcs.v.mission_item or 0) > seq_back or gcs.v.mode != "mission",
                    40.0, f"the mission did not go on past item {seq_back} of {count}")
        assert gcs.modes_since(t_back) == [] or gcs.modes_since(t_back)[0] != "offboard"
        assert proxy.modes_requested_since(t_clear) == ["hold", "mission"]
    finally:
        await m.close()
        await gcs.hold()


@pytest.mark.asyncio
@pytest.mark.timeout(180)
async def test_sitl_link_loss_mid_evasion_failsafe_then_midair_does_not_retake(
        proxy: Any, hover: GroundStation, midair: Midair) -> None:
    gcs = hover
    cmd = Command(EVADE, 0.0, 2.0, 0.0, 1, "sitl")
    await take_over(midair, gcs, proxy, cmd)
    await midair.feed(cmd, 1.0)
    t_cut = proxy.cut()
    try:
        last_sp = max(s.t for s in proxy.setpoints_since(t_cut - 1.0))
        # PX4's offboard-loss fallback, ~1 s after the last setpoint it got
        await midair.feed(cmd, 1.0 + MODE_REPORT_S, lambda: gcs.v.mode not in (None, "offboard"),
                          "PX4 did not leave Offboard after the link was cut")
        fallback = gcs.v.mode
        said = [t for t, s in gcs.v.texts if t > t_cut and "failsafe" in s.lower()]
        assert said, gcs.texts_since(t_cut)
        assert 0.7 <= said[0] - last_sp <= 1.8, said[0] - last_sp
        assert not midair.link.snapshot().connected
        lost = midair.first(lambda t: not t.connected, t_cut)
        assert lost is not None and lost.setpoint == ZERO  # MAVSDK's re-sent setpoint cleared
        await midair.feed(cmd, 1.5)  # the threat persists through the outage
    finally:
        t_back = proxy.restore()
    # the link is back, the threat still there: midair must not take the vehicle back
    await midair.feed(cmd, 6.0)
    asked = proxy.modes_requested_since(t_back)
    ticks = [t for t in midair.ticks if t.t >= t_back]
    moving = [s.velocity for s in proxy.setpoints_since(t_back) if s.velocity != ZERO]
    states = sorted({t.state for t in ticks if t.t > t_back + MODE_REPORT_S})
    beats = [(round(t - t_back, 2), m) for t, m in proxy.heartbeat_modes_since(t_back)]
    px4_back = [round(t - t_back, 2) for t, m in gcs.v.modes if t >= t_back and m == "offboard"]
    first_move = next((round(s.t - t_back, 2) for s in proxy.setpoints_since(t_back)
                       if s.velocity != ZERO), None)
    mode_log = [(round(t - t_back, 2), m) for t, m in gcs.v.modes if t >= t_cut - 1.0]
    detail = (f"fallback {fallback!r} {said[0] - last_sp:.2f} s after the last setpoint; after the "
              f"link came back (t=0 s): the ground station saw Offboard again at {px4_back} s, "
              f"PX4's heartbeats to midair (t, mode) {beats[:3]}..., midair asked {asked}, "
              f"midair's states {states}, {len(moving)} non-zero setpoints {moving[:1]} from "
              f"{first_move} s, statuses {midair.statuses()[-3:]}, PX4 said "
              f"{gcs.texts_since(t_back)[:3]}; ground station's mode log (t, mode) {mode_log}, "
              f"final mode {gcs.v.mode!r}")
    print(detail)  # what happened on the wire, also when it passes (pytest -rP)
    assert "offboard" not in asked, detail
    assert set(asked) <= {"hold"}, detail  # at most: an Offboard not its own handed to Hold
    assert not moving, detail
    assert states == [MONITOR], detail
    # and the vehicle is not left in Offboard on midair's zero stream: Hold (midair's hand-off
    # or the pilot's) or whatever PX4's failsafe chose
    assert gcs.v.mode not in (None, "offboard"), detail


@pytest.mark.asyncio
@pytest.mark.timeout(180)
async def test_sitl_stalled_perception_zero_then_hold_after_stale_release(
        proxy: Any, hover: GroundStation, midair_link: Any) -> None:
    gcs = hover
    cfg = FlightConfig(stale_release_s=1.0)
    m = Midair(midair_link, cfg)
    await m.start()
    try:
        cmd = Command(EVADE, 0.0, 2.0, 0.0, 1, "sitl")
        await take_over(m, gcs, proxy, cmd)
        await m.feed(cmd, 1.0)
        t_stall = time.monotonic()  # perception hangs: the slot keeps its last decision
        t_last = m.decision.t_s if m.decision else t_stall
        stale_at = t_last + cfg.max_decision_age_ms / 1000.0
        v_stall = gcs.speed()
        await gcs.mode_is("hold", cfg.stale_release_s + 0.5 + MODE_REPORT_S)
        await asyncio.sleep(2.5)  # past the next heartbeat: one offboard stop, not two
        sent = proxy.setpoints_since(stale_at + 0.1)  # two ticks after the decision aged out
        assert sent and all(s.velocity == ZERO for s in sent), [s.velocity for s in sent[:5]]
        reqs = proxy.requests_since(t_stall)
        assert [r.mode for r in reqs] == ["hold"], reqs
        left_after = reqs[0].t - stale_at
        assert cfg.stale_release_s - 0.05 <= left_after <= cfg.stale_release_s + 0.3, left_after
        assert "midair: perception stale, leaving to Hold" in m.statuses()
        assert gcs.speed() < v_stall  # and it slowed down
    finally:
        await m.close()
