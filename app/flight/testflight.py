"""``test-flight`` mode: the paper's experiment (§5-C) as a state machine.

Take off to ``test_altitude_m``, fly forward at ``forward_speed_mps`` in Offboard until an
evasion is needed, evade, then hold; land when asked. Pure logic like
:mod:`app.flight.engagement`, with the same safety rules: setpoints stream before Offboard is
requested, every setpoint comes from a fresh decision (else zero, then Hold), any mode
change by the pilot ends midair's part at once, the forward leg is bounded by
``test_max_cruise_s``, speeds are clamped to ``max_speed_mps``.

Phases::

    ground ─start─▶ takeoff ─at altitude─▶ warmup ─1.2 s of zero─▶ cruise ─threat─▶ evade
                                                                      │ max time     │ clear
                                                                      ▼              ▼
                                                                     hold ◀──────────┘
    any phase ─land requested─▶ landing        any phase ─pilot changes mode─▶ pilot
"""

from __future__ import annotations

import math

from app.config import FlightConfig
from app.decision.policy import NONE, Command
from app.flight.engagement import ZERO, Decision, Output, VehicleState, clamp_velocity, status_text

WARMUP_S = 1.2  # PX4 accepts Offboard after a second of setpoints (PX4 user guide)
RETRY_S = 0.25


class TestFlight:
    """Parameters: ``cfg`` (flight section: test_altitude_m, forward_speed_mps,
    test_max_cruise_s, max_decision_age_ms, stale_release_s, release_after_s,
    offboard_confirm_s) and ``max_speed_mps``."""

    __test__ = False  # not a pytest class

    def __init__(self, cfg: FlightConfig, max_speed_mps: float) -> None:
        self.cfg = cfg
        self.max_speed_mps = max_speed_mps
        self.phase = "ground"
        self._since = 0.0
        self._last_request = -math.inf
        self._stale_since: float | None = None
        self._calm_since: float | None = None
        self._start = False
        self._land = False

    @property
    def in_control(self) -> bool:
        return self.phase in ("warmup", "cruise", "evade")

    def shutdown(self) -> Output:
        """Zero, and out of Offboard to Hold if the test had it."""
        was = self.phase in ("cruise", "evade")
        self._to("hold", self._since)
        return Output(self.phase, setpoint=ZERO, leave_to="hold" if was else None,
                      status="midair: stopping, leaving to Hold" if was else None)

    def request_start(self) -> None:
        self._start = True

    def request_land(self) -> None:
        self._land = True

    def _to(self, phase: str, t: float) -> None:
        self.phase, self._since = phase, t

    def tick(self, v: VehicleState, d: Decision | None) -> Output:
        c = self.cfg
        if self._land and self.phase not in ("landing", "pilot"):
            self._to("landing", v.t_s)
            return Output(self.phase, action="land", status="midair: test flight: landing")
        if not v.connected or self.phase in ("landing", "pilot", "hold"):
            return Output(self.phase)
        offboard_phases = ("cruise", "evade")
        if self.phase in offboard_phases and v.mode != "offboard":
            self._to("pilot", v.t_s)
            # Zero replaces the setpoint MAVSDK keeps re-sending; outside Offboard it commands
            # nothing, and a later switch back to Offboard finds "hold", not "fly forward".
            return Output(self.phase, setpoint=ZERO,
                          status=f"midair: pilot switched to {v.mode}: test ends")

        if self.phase == "ground":
            if self._start and v.mode != "offboard":
                self._to("takeoff", v.t_s)
                return Output(self.phase, action="arm_takeoff", takeoff_altitude_m=c.test_altitude_m,
                              status=f"midair: test flight: take-off to {c.test_altitude_m:g} m")
            return Output(self.phase)
        if self.phase == "takeoff":
            alt = v.altitude_m if v.altitude_m is not None else -math.inf
            if v.armed and v.in_air and alt >= c.test_altitude_m - 0.5 and v.mode in ("hold", "position"):
                self._to("warmup", v.t_s)
            return Output(self.phase)
        if self.phase == "warmup":
            if v.mode == "offboard":
                self._to("cruise", v.t_s)
            elif v.t_s - self._since > WARMUP_S + c.offboard_confirm_s:
                self._to("hold", v.t_s)
                return Output(self.phase, setpoint=ZERO, status="midair: offboard refused: test ends")
            elif v.t_s - self._since >= WARMUP_S and v.t_s - self._last_request >= RETRY_S:
                self._last_request = v.t_s
                return Output(self.phase, setpoint=ZERO, start_offboard=True,
                              status="midair: test flight: offboard, forward")
            if self.phase == "warmup":
                return Output(self.phase, setpoint=ZERO)

        cmd = d.command if d is not None and v.t_s - d.t_s <= c.max_decision_age_ms / 1000 else None
        if cmd is None:  # dead-man
            self._stale_since = self._stale_since if self._stale_since is not None else v.t_s
            if v.t_s - self._stale_since > c.stale_release_s:
                return self._hold(v, "midair: perception stale, leaving to Hold")
            return Output(self.phase, setpoint=ZERO)
        self._stale_since = None
        if cmd.action != NONE:
            status = None
            if self.phase == "cruise":
                self._to("evade", v.t_s)
                status = status_text(cmd)
            self._calm_since = None
            return Output(self.phase, setpoint=self._clamp(cmd), status=status)
        if self.phase == "evade":
            self._calm_since = self._calm_since if self._calm_since is not None else v.t_s
            if v.t_s - self._calm_since > c.release_after_s:
                return self._hold(v, "midair: test flight: evaded, holding")
            return Output(self.phase, setpoint=ZERO)
        if v.t_s - self._since > c.test_max_cruise_s:
            return self._hold(v, "midair: test flight: end of the forward leg, holding")
        return Output(self.phase, setpoint=self._clamp(Command("cruise", c.forward_speed_mps)))

    def _hold(self, v: VehicleState, text: str) -> Output:
        self._to("hold", v.t_s)
        return Output(self.phase, setpoint=ZERO, leave_to="hold", status=text)

    def _clamp(self, cmd: Command) -> tuple[float, float, float]:
        return clamp_velocity(cmd, self.max_speed_mps)
