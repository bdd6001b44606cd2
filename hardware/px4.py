"""PX4 through MAVSDK (``mavsdk`` >= 4, the native binding, asyncio API in ``mavsdk.asyncio``).

The only module that imports ``mavsdk``. It keeps the newest telemetry (draining every
stream it subscribes to, so nothing queues up) and carries out the engagement logic's
:class:`app.flight.engagement.Output`: velocity setpoints in the body frame, offboard start and
stop, resuming a mission, status texts for the ground station.

Facts this relies on (mavsdk 4.1 against PX4 SITL): ``udpin://0.0.0.0:PORT`` (not
``udpin://:PORT``); ``first_autopilot()`` returns None on timeout; plugins are built as
``OffboardAsync(system)``; the C++ core logs to stdout unless its log is subscribed to;
``offboard.stop()`` leaves to Hold; MAVSDK re-sends the last setpoint at 20 Hz by itself.
"""

from __future__ import annotations

import asyncio
import logging
import math
import time
from collections import deque
from collections.abc import Awaitable, Callable
from dataclasses import dataclass

from app.flight.engagement import MONITOR, STATUS_TEXT_MAX, Output, VehicleState

log = logging.getLogger(__name__)

# A ground station shows every status text it gets (QGroundControl lists them all): midair
# sends at most one a second. Texts that come faster wait their turn, the newest few kept
# (every text goes to the log at once).
STATUS_TEXT_PERIOD_S = 1.0
STATUS_TEXT_BACKLOG = 3

# MAVSDK FlightMode names → the mode names of app.config.FLIGHT_MODES
_MODES = {
    "POSCTL": "position", "HOLD": "hold", "MISSION": "mission", "OFFBOARD": "offboard",
    "ALTCTL": "altitude", "MANUAL": "manual", "STABILIZED": "manual", "ACRO": "manual",
    "RATTITUDE": "manual", "RETURN_TO_LAUNCH": "return", "LAND": "land", "TAKEOFF": "takeoff",
}


class FlightLinkError(Exception):
    """The autopilot cannot be reached or refused what it must do."""


class PortInUseError(FlightLinkError):
    """The connection's local port is taken by another program (another midair,
    QGroundControl, mavlink-router): MAVSDK could not bind it."""


@dataclass
class _Telemetry:
    armed: bool = False
    in_air: bool = False
    mode: str = "other"
    altitude_m: float | None = None
    connected: bool = False
    last_rx: float = -math.inf  # monotonic time of the newest position message
    mode_t: float = -math.inf  # monotonic time of the newest flight-mode report (each heartbeat)
    velocity_ned: tuple[float, float, float] | None = None  # m/s
    lat_lon: tuple[float, float] | None = None  # deg
    local_ned: tuple[float, float, float] | None = None  # m from PX4's local origin
    offboard_ack: float = -math.inf  # monotonic time offboard.start() last succeeded
    yaw_rad: float | None = None
    attitude: tuple[float, float, float] | None = None  # roll, pitch, yaw, rad
    velocity_t: float = -math.inf  # monotonic time of the newest velocity
    attitude_t: float = -math.inf  # monotonic time of the newest attitude


def _route_core_log() -> None:
    """Send the C++ core's log lines into Python logging instead of stdout."""
    from mavsdk import log_subscribe

    core = logging.getLogger("mavsdk.core")

    def handler(level: object, message: str, file: str | None, line: int) -> bool:
        name = getattr(level, "name", "INFO").upper()
        core.log(logging.DEBUG if name == "DEBUG" else logging.WARNING if name in ("WARN", "WARNING")
                 else logging.ERROR if name == "ERR" or name == "ERROR" else logging.INFO, message)
        return True

    log_subscribe(handler)


class Px4Link:
    """MAVSDK connection to one PX4 autopilot.

    Parameters
    ----------
    url
        MAVSDK connection URL: ``udpin://0.0.0.0:14540`` for SITL, ``serial:///dev/serial0:921600``
        on the Pi.
    link_timeout_s
        No position message for this long means the link is down (MAVSDK's own heartbeat
        timeout is slower).
    """

    def __init__(self, url: str, link_timeout_s: float = 0.5, with_pose: bool = False) -> None:
        self.url = url
        self.with_pose = with_pose  # also follow local position and attitude (simulation)
        self.link_timeout_s = link_timeout_s
        self._tel = _Telemetry()
        self._tasks: list[asyncio.Task[None]] = []
        self._engaged_before = False
        self._last_setpoint: tuple[float, float, float] | None = None
        self.setpoint_log: list[tuple[float, tuple[float, float, float]]] = []  # (t sent, FRD)
        self._texts: deque[str] = deque(maxlen=STATUS_TEXT_BACKLOG)  # waiting to be sent
        self._text_sent_t = -math.inf
        self.texts_sent: list[tuple[float, str]] = []  # (monotonic t, text) on the wire

    async def connect(self, timeout_s: float = 10.0) -> None:
        from mavsdk import ComponentType, Configuration
        from mavsdk.asyncio import Mavsdk
        from mavsdk.asyncio.plugins.action import ActionAsync
        from mavsdk.asyncio.plugins.mission import MissionAsync
        from mavsdk.asyncio.plugins.offboard import OffboardAsync
        from mavsdk.asyncio.plugins.server_utility import ServerUtilityAsync
        from mavsdk.asyncio.plugins.telemetry import TelemetryAsync

        _route_core_log()
        self._mavsdk = Mavsdk(Configuration.create_with_component_type(
            ComponentType.COMPANION_COMPUTER))
        try:
            await self._mavsdk.add_any_connection(self.url)
        except Exception as exc:  # the binding raises its own types for a bad URL
            await self.close()
            if "BIND_ERROR" in str(exc):
                raise PortInUseError(f"connection {self.url!r}: its port is in use by another "
                                     f"program (another midair, QGroundControl, a router?): "
                                     f"{exc}") from None
            raise FlightLinkError(f"connection {self.url!r} rejected: {exc}") from None
        system = await self._mavsdk.first_autopilot(timeout_s)
        if system is None:
            await self.close()
            raise FlightLinkError(f"no autopilot answered on {self.url} within {timeout_s:g} s")
        self._system = system
        self._telemetry = TelemetryAsync(system)
        self._offboard = OffboardAsync(system)
        self._action = ActionAsync(system)
        self._mission = MissionAsync(system)
        self._utility = ServerUtilityAsync(system)
        self._tasks = [
            asyncio.create_task(self._watch(self._telemetry.subscribe_armed, self._on_armed)),
            asyncio.create_task(self._watch(self._telemetry.subscribe_in_air, self._on_in_air)),
            asyncio.create_task(self._watch(self._telemetry.subscribe_flight_mode, self._on_mode)),
            asyncio.create_task(self._watch(self._telemetry.subscribe_position, self._on_position)),
            asyncio.create_task(self._watch(self._telemetry.subscribe_velocity_ned, self._on_velocity)),
            # the attitude turns the velocity into the camera's axes (the decision's
            # static-structure test: app.decision.ego)
            asyncio.create_task(self._watch(self._telemetry.subscribe_attitude_euler, self._on_attitude)),
            asyncio.create_task(self._watch(system.is_connected_state, self._on_connected)),
        ]
        if self.with_pose:
            self._tasks += [
                asyncio.create_task(self._watch(self._telemetry.subscribe_position_velocity_ned,
                                                self._on_local)),
            ]
        self._tel.connected = True

    async def wait_flying(self, timeout_s: float = 10.0) -> None:
        """Wait until the vehicle reports armed, in air, with an altitude (and, with
        ``with_pose``, a local position); :class:`FlightLinkError` after ``timeout_s``."""
        t0 = time.monotonic()
        while True:
            v = self.snapshot()
            if v.armed and v.in_air and v.altitude_m and (not self.with_pose or self.has_pose()):
                return
            if time.monotonic() - t0 > timeout_s:
                raise FlightLinkError(f"the vehicle on {self.url} is not flying (armed, in air, with an "
                                      "altitude" + (" and a local position" if self.with_pose else "")
                                      + "): take off first")
            await asyncio.sleep(0.05)

    async def close(self) -> None:
        """Stop the telemetry tasks and destroy the MAVSDK instance now, on this loop: left
        to the garbage collector, its destructor can run at any moment, from any thread,
        after the loop is gone, and the C++ core then aborts the process (seen here)."""
        for t in self._tasks:
            t.cancel()
        await asyncio.gather(*self._tasks, return_exceptions=True)
        self._tasks.clear()
        mavsdk = getattr(self, "_mavsdk", None)
        if mavsdk is not None:
            self._mavsdk = None
            # plugins first (they hold the System), then MAVSDK itself; mavsdk 4 aborts
            # the process when a plugin is still alive at that point
            for name in ("_telemetry", "_offboard", "_action", "_mission", "_utility"):
                plugin = self.__dict__.pop(name, None)
                if plugin is not None:
                    plugin.destroy()
            self.__dict__.pop("_system", None)
            await asyncio.get_running_loop().run_in_executor(None, mavsdk.destroy)

    # ------------------------------------------------------------------ telemetry

    async def _watch(self, subscribe: Callable[[], object], on: Callable[[object], None]) -> None:
        async for value in subscribe():  # type: ignore[attr-defined]
            on(value)

    def _on_armed(self, v: object) -> None:
        self._tel.armed = bool(v)

    def _on_in_air(self, v: object) -> None:
        self._tel.in_air = bool(v)

    def _on_mode(self, v: object) -> None:
        self._tel.mode = _MODES.get(getattr(v, "name", str(v)), "other")
        self._tel.mode_t = time.monotonic()

    def _on_position(self, p: object) -> None:
        alt = getattr(p, "relative_altitude_m", math.nan)
        self._tel.altitude_m = float(alt) if alt is not None and math.isfinite(alt) else None
        self._tel.last_rx = time.monotonic()
        lat, lon = getattr(p, "latitude_deg", math.nan), getattr(p, "longitude_deg", math.nan)
        self._tel.lat_lon = (float(lat), float(lon)) if math.isfinite(lat) and math.isfinite(lon) else None

    def _on_velocity(self, v: object) -> None:
        vel = tuple(float(getattr(v, k, math.nan)) for k in ("north_m_s", "east_m_s", "down_m_s"))
        self._tel.velocity_ned = vel if all(math.isfinite(x) for x in vel) else None  # type: ignore[assignment]
        self._tel.velocity_t = time.monotonic()

    def _on_local(self, pv: object) -> None:
        pos = getattr(pv, "position", None)
        ned = tuple(float(getattr(pos, k, math.nan)) for k in ("north_m", "east_m", "down_m"))
        self._tel.local_ned = ned if all(math.isfinite(x) for x in ned) else None  # type: ignore[assignment]

    def _on_attitude(self, e: object) -> None:
        angles = tuple(float(getattr(e, k, math.nan)) for k in ("roll_deg", "pitch_deg", "yaw_deg"))
        self._tel.yaw_rad = math.radians(angles[2]) if math.isfinite(angles[2]) else None
        self._tel.attitude = (tuple(math.radians(a) for a in angles)  # type: ignore[assignment]
                              if all(math.isfinite(a) for a in angles) else None)
        self._tel.attitude_t = time.monotonic()

    def has_pose(self) -> bool:
        return self._tel.local_ned is not None

    def pose(self) -> tuple[tuple[float, float, float], tuple[float, float, float], float]:
        """The vehicle's pose from telemetry (``with_pose``): local NED position (m), NED
        velocity (m/s), yaw (rad); the same shape as the stand-in vehicle's true pose."""
        t = self._tel
        if t.local_ned is None:
            raise RuntimeError(f"no local position from {self.url} yet")
        return t.local_ned, t.velocity_ned or (0.0, 0.0, 0.0), t.yaw_rad or 0.0

    def attitude(self) -> tuple[float, float, float]:
        """The vehicle's attitude from telemetry: roll, pitch, yaw (rad); level until known."""
        return self._tel.attitude or (0.0, 0.0, self._tel.yaw_rad or 0.0)

    def _on_connected(self, v: object) -> None:
        self._tel.connected = bool(v)

    def snapshot(self) -> VehicleState:
        now = time.monotonic()
        t = self._tel
        connected = t.connected and now - t.last_rx <= self.link_timeout_s
        return VehicleState(now, connected, t.armed, t.in_air, t.mode, t.altitude_m, t.mode_t,
                            t.velocity_ned, t.lat_lon, t.offboard_ack, t.attitude,
                            min(t.velocity_t, t.attitude_t))

    # ------------------------------------------------------------------ commands

    async def apply(self, out: Output) -> None:
        """Carry out one tick's output. Errors of single commands are logged, not raised:
        the engagement logic sees their effect (or its absence) in the telemetry."""
        from mavsdk.asyncio.plugins.offboard import VelocityBodyYawspeed

        setpoint = out.setpoint
        if setpoint is None and self._engaged_before and out.state == MONITOR:
            # Handing control back without leaving offboard ourselves (the pilot did):
            # replace the setpoint MAVSDK keeps re-sending with zero, which does not change
            # the mode and leaves nothing stale for a later switch back to Offboard.
            setpoint = (0.0, 0.0, 0.0)
        if setpoint is not None:
            await self._guard("set_velocity_body", self._offboard.set_velocity_body(
                VelocityBodyYawspeed(setpoint[0], setpoint[1], setpoint[2], 0.0)))
            self.setpoint_log.append((time.monotonic(), setpoint))
        if out.start_offboard:
            if await self._guard("offboard.start", self._offboard.start()):
                self._tel.offboard_ack = time.monotonic()  # PX4 accepted the switch
        if out.leave_to is not None:
            await self._guard("offboard.stop", self._offboard.stop())  # PX4 goes to Hold
            if out.leave_to == "mission":
                await self._guard("mission.start_mission", self._mission.start_mission())
        if out.action == "arm_takeoff":
            if out.takeoff_altitude_m is not None:
                await self._guard("set_takeoff_altitude",
                                  self._action.set_takeoff_altitude(out.takeoff_altitude_m))
            await self._guard("arm", self._action.arm())
            await self._guard("takeoff", self._action.takeoff())
        elif out.action == "land":
            await self._guard("land", self._action.land())
        if out.status:
            log.info("%s", out.status)
            self._texts.append(out.status)
        await self._send_text()
        self._engaged_before = out.state != MONITOR

    async def _send_text(self) -> None:
        """Send the oldest waiting status text if the last went out over a period ago."""
        from mavsdk.asyncio.plugins.server_utility import StatusTextType

        now = time.monotonic()
        if not self._texts or now - self._text_sent_t < STATUS_TEXT_PERIOD_S:
            return
        text = self._texts.popleft()
        if len(text) > STATUS_TEXT_MAX:  # the engagement logic keeps within one message
            log.warning("status text over %d characters, cut: %r", STATUS_TEXT_MAX, text)
            text = text[:STATUS_TEXT_MAX]
        self._text_sent_t = now
        self.texts_sent.append((now, text))
        await self._guard("status text", self._utility.send_status_text(StatusTextType.INFO, text))

    async def _guard(self, what: str, call: Awaitable[object]) -> bool:
        """Await one command; True when it succeeded (acknowledged), False after a logged error."""
        try:
            await call
        except Exception as exc:  # MAVSDK raises per-plugin error types
            log.warning("%s failed: %s", what, exc)
            return False
        return True
