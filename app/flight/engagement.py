"""When midair takes control of the vehicle, what it streams, and how it gives control back.

Pure logic: one :meth:`Engagement.tick` per control period with the newest vehicle state
and the newest decision; it returns what the flight adapter must do. No MAVSDK here.

States::

    monitor ──threat & may take over──▶ requesting ──vehicle reports Offboard──▶ engaged
       ▲                                    │ refused / timed out                  │
       │◀───────────────────────────────────┘                                      │
       │◀── released (no threat for release_after_s: back to Mission, else Hold) ──┤
       │◀── stale decisions for stale_release_s: Hold ─────────────────────────────┤
       └◀── cooldown ◀── pilot changed the mode / link came back in another mode ──┘

Safety rules held here:

- Take over only when armed, in air, at or above ``min_takeover_altitude_m``, connected,
  in one of ``takeover_modes`` and not in a pilot cooldown. Shadow mode never commands.
- Setpoints stream before offboard is requested: while armed and in air in guard mode,
  zero velocity is streamed all the time (PX4 accepts Offboard only after a second of
  setpoints; outside Offboard it ignores them).
- Dead-man: every setpoint comes from a decision younger than ``max_decision_age_ms``;
  otherwise zero velocity; stale for ``stale_release_s``: leave offboard to Hold. (MAVSDK
  re-sends the last setpoint by itself, so PX4's own offboard-loss failsafe does not
  protect against this process hanging.)
- Pilot wins: once engaged, any mode other than Offboard means the pilot (or a failsafe)
  took over: stop commanding at once, never re-take control during ``pilot_cooldown_s``.
- Link loss: the setpoint is cleared to zero at once. After the link returns, nothing but
  zero is sent until the vehicle has reported its mode anew (the mode in hand predates the
  outage) and a decision made after the reconnection arrives; if the vehicle is no longer
  in Offboard (PX4's offboard-loss failsafe, or the pilot) we do not take it back. An outage
  longer than ``offboard_loss_s`` (PX4's COM_OF_LOSS_T) gives control up in any case: PX4's
  failsafe has acted, and PX4 re-enters Offboard *by itself* once setpoints arrive again
  (MAVSDK re-sends the cleared one), which must not read as ours (PX4 SITL, seen).
- Offboard that is not ours: once midair has given control up, a vehicle reported in
  Offboard more than ``UNOWNED_GRACE_S`` later sits on midair's zero stream; it is handed
  to Hold (when in doubt, hold position).
- Every velocity is clamped to ``max_speed_mps``.

Velocities are body frame (forward, right, down), m/s; times are monotonic seconds.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from app.config import FlightConfig
from app.decision.ego import EgoMotion, camera_velocity, mounted
from app.decision.policy import NONE, STOP, Command, describe_direction

MONITOR, REQUESTING, ENGAGED = "monitor", "requesting", "engaged"
ZERO = (0.0, 0.0, 0.0)
OFFBOARD_RETRY_S = 0.25  # while requesting, ask PX4 again this often, s
# after midair gives control up, an Offboard report this much later is not a stale one (PX4
# reports its mode in the 1 Hz heartbeat, seen 0.4-0.9 s late), s
UNOWNED_GRACE_S = 1.5


@dataclass(frozen=True)
class VehicleState:
    """The autopilot as last reported (newest values only)."""

    t_s: float  # monotonic time of this snapshot, s
    connected: bool  # heartbeats arriving
    armed: bool
    in_air: bool
    mode: str  # one of app.config.FLIGHT_MODES
    altitude_m: float | None  # above home, m; None or NaN while unknown
    mode_t_s: float = -math.inf  # when the mode was last reported (PX4: every heartbeat), s
    velocity_ned_mps: tuple[float, float, float] | None = None  # local NED, m/s
    lat_lon_deg: tuple[float, float] | None = None  # WGS84 position, deg
    # when the autopilot last acknowledged a switch to Offboard (MAVSDK's offboard.start()
    # returned without error); PX4 reports the mode itself only once a second, s
    offboard_ack_t_s: float = -math.inf
    attitude_rad: tuple[float, float, float] | None = None  # roll, pitch, yaw (ZYX Euler), rad
    # monotonic time of the older of the newest velocity and the newest attitude, s
    motion_t_s: float = -math.inf

    def ego(self, max_age_s: float, mount: str = "body") -> EgoMotion | None:
        """The camera's velocity in its own axes (camera on the body's forward axis, or held
        level by a gimbal: ``mount``), when the velocity and the attitude are both known and
        younger than ``max_age_s``."""
        attitude = self.camera_attitude(max_age_s, mount)
        if self.velocity_ned_mps is None or attitude is None:
            return None
        return EgoMotion(camera_velocity(self.velocity_ned_mps, *attitude))

    def camera_attitude(self, max_age_s: float, mount: str = "body") -> tuple[float, float, float] | None:
        """The camera's attitude (roll, pitch, yaw rad) from the vehicle's, when known and
        younger than ``max_age_s``."""
        if self.attitude_rad is None or self.t_s - self.motion_t_s > max_age_s:
            return None
        return mounted(self.attitude_rad, mount)


@dataclass(frozen=True)
class Decision:
    command: Command
    t_s: float  # monotonic capture time of the frame it is about (its age is judged by it), s
    frame: int = 0  # that frame's number in its source (latency accounting)
    t_perceived_s: float = math.nan  # monotonic time stages 1-3 finished, s
    t_decided_s: float = math.nan  # monotonic time stage 4 finished, s
    t_started_s: float = math.nan  # monotonic time perception began (on the next frame), s


@dataclass(frozen=True)
class Output:
    """What the flight adapter does this tick."""

    state: str
    setpoint: tuple[float, float, float] | None = None  # stream this (FRD m/s); None: hands off
    start_offboard: bool = False  # switch to Offboard (after the setpoint is set)
    leave_to: str | None = None  # leave Offboard to this mode ("mission" or "hold")
    status: str | None = None  # a status text for the ground station and the log
    action: str | None = None  # test flight only: "arm_takeoff" or "land"
    takeoff_altitude_m: float | None = None  # with arm_takeoff, m above home


class Engagement:
    """The take-over / release state machine.

    Parameters
    ----------
    cfg
        Flight settings (s, ms, m; see :class:`app.config.FlightConfig`).
    max_speed_mps
        Bound on every setpoint's speed, m/s (``decision.max_speed_mps``).
    """

    def __init__(self, cfg: FlightConfig, max_speed_mps: float) -> None:
        self.cfg = cfg
        self.max_speed_mps = max_speed_mps
        self.state = MONITOR
        self._since = 0.0  # when the current state (or threat-free spell) began
        self._calm_since: float | None = None
        self._stale_since: float | None = None
        self._return_to = "hold"
        self._cooldown_until = -math.inf
        self._link_was_lost = False
        self._fresh_after = -math.inf  # only decisions made after this may command
        self._awaiting_mode_since: float | None = None  # link back while in control
        self._said: str | None = None  # the last "would ..." text's gist (said once)
        self._last_request = -math.inf
        self._requested_at = -math.inf  # when the current take-over began
        self._engaged_at = -math.inf
        self._had_link = False  # a link that never was cannot be "lost"
        self._lost_at = -math.inf  # when the current outage began
        self._left_at = -math.inf  # when midair last gave control up (left, or handed off)

    @property
    def in_control(self) -> bool:
        return self.state != MONITOR

    def shutdown(self) -> Output:
        """What to send when the process stops: zero, and out of Offboard if we were in it."""
        was = self.in_control
        self.state = MONITOR
        return Output(MONITOR, setpoint=ZERO, leave_to="hold" if was else None,
                      status="midair: stopping, leaving to Hold" if was else None)

    # ------------------------------------------------------------------ main

    def tick(self, v: VehicleState, d: Decision | None) -> Output:
        c = self.cfg
        if not v.connected:
            return self._link_lost(v)
        self._had_link = True
        if self._link_was_lost:
            self._link_was_lost = False
            self._fresh_after = v.t_s
            self._stale_since = None
            if self.state != MONITOR and v.t_s - self._lost_at > c.offboard_loss_s:
                # PX4's offboard-loss failsafe has acted: control is not ours any more, even
                # if PX4 goes back to Offboard on the (zero) setpoint MAVSDK re-sends.
                self._awaiting_mode_since = None
                return self._pilot_took_over(v, "midair: link was lost, hands off")
            if self.state != MONITOR:
                # The mode in hand predates the outage: wait for the vehicle to report it anew.
                self._awaiting_mode_since = v.t_s
        if self._awaiting_mode_since is not None:
            since = self._awaiting_mode_since
            if v.mode_t_s > since:
                self._awaiting_mode_since = None
                if v.mode != "offboard":
                    return self._pilot_took_over(v, f"midair: link back in {v.mode}, hands off")
            elif v.t_s - since > c.max_mode_age_s:
                self._awaiting_mode_since = None
                self._cooldown_until = v.t_s + c.pilot_cooldown_s
                return self._leave(v, "hold", "midair: link back, mode unknown: leaving to Hold")
            else:
                return Output(self.state, setpoint=ZERO)

        cmd = d.command if d is not None and self._usable(d, v.t_s) else None
        if self.state == MONITOR:
            if (v.mode == "offboard" and v.mode_t_s > self._requested_at > -math.inf
                    and self.cfg.mode == "guard"):
                # Our request was accepted after we had given up on it: the vehicle sits in
                # Offboard on our zero stream. Hand it back instead of leaving it there.
                self._requested_at = -math.inf
                return self._leave(v, self._return_to, "midair: offboard came late: handing back")
            if (v.mode == "offboard" and self.cfg.mode == "guard" and v.armed and v.in_air
                    and v.mode_t_s > self._left_at + UNOWNED_GRACE_S > -math.inf):
                return self._leave(v, "hold", "midair: Offboard not ours, to Hold")
            return self._monitor(v, cmd)

        # requesting or engaged: we hold (or are asking for) control. PX4 reports its mode
        # once a second, so only a report newer than our switch says the pilot changed it.
        if self.state == ENGAGED and v.mode != "offboard" and v.mode_t_s > self._engaged_at:
            return self._pilot_took_over(v, f"midair: pilot took {v.mode}, hands off")
        if not v.armed or not v.in_air:
            self.state = MONITOR
            return Output(MONITOR, status="midair: vehicle landed or disarmed, hands off")
        retry = False
        if self.state == REQUESTING:
            if v.offboard_ack_t_s >= self._requested_at or (v.mode == "offboard"
                                                            and v.mode_t_s >= self._requested_at):
                self.state = ENGAGED  # acknowledged, or already reported
                self._engaged_at = v.t_s
                # The request is answered: an Offboard report from now on is our own
                # engagement (or, after we leave, a stale report), not a late acceptance.
                self._requested_at = -math.inf
            elif v.t_s - self._since > c.offboard_confirm_s:
                self.state = MONITOR
                self._cooldown_until = v.t_s + c.offboard_confirm_s  # back off, then try again
                return Output(MONITOR, setpoint=ZERO,
                              status=f"midair: offboard refused (still {v.mode})")
            elif v.t_s - self._last_request >= OFFBOARD_RETRY_S:
                retry = True  # PX4 may have refused an early request; ask again
                self._last_request = v.t_s

        # dead-man: stale decisions stream zero, and for too long, leave to Hold
        if cmd is None:
            if self._stale_since is None:
                self._stale_since = v.t_s
            if v.t_s - self._stale_since > c.stale_release_s:
                return self._leave(v, "hold", "midair: perception stale, leaving to Hold")
            return Output(self.state, setpoint=ZERO)
        self._stale_since = None

        if cmd.action == NONE:
            if self._calm_since is None:
                self._calm_since = v.t_s
            if v.t_s - self._calm_since > c.release_after_s and self.state == ENGAGED:
                return self._leave(v, self._return_to, f"midair: clear, back to {self._return_to}")
            return Output(self.state, setpoint=ZERO)
        self._calm_since = None
        return Output(self.state, setpoint=self._velocity(cmd), start_offboard=retry)

    # ------------------------------------------------------------------ states

    def _monitor(self, v: VehicleState, cmd: Command | None) -> Output:
        # Keep the offboard path warm: PX4 enters Offboard only after setpoints have streamed
        # for over a second (PX4 user guide, "Offboard Mode"), which a mid-air encounter does
        # not leave. Zero velocity is ignored outside Offboard and means "hold" inside it.
        warm = ZERO if self.cfg.mode == "guard" and v.armed and v.in_air else None
        if cmd is None or cmd.action == NONE:
            self._said = None
            return Output(MONITOR, setpoint=warm)
        why_not = self._may_not_take_over(v)
        if why_not:
            # said once per (command, reason), not every tick: a ground station shows them all
            gist = f"{cmd.action}|{cmd.object_id}|{why_not[0]}"
            said, self._said = self._said, gist
            text = f"midair: {_verb(cmd)} held: {why_not[1]}"
            return Output(MONITOR, setpoint=warm, status=text if said != gist else None)
        if self.cfg.mode == "shadow":
            gist = f"{cmd.action}|{cmd.object_id}|shadow"
            said, self._said = self._said, gist
            return Output(MONITOR, status=status_text(cmd, shadow=True) if said != gist else None)
        self._said = None
        self.state = REQUESTING
        self._since = v.t_s
        self._last_request = v.t_s
        self._requested_at = v.t_s
        self._calm_since = None
        self._stale_since = None
        self._return_to = "mission" if v.mode == "mission" else "hold"
        return Output(REQUESTING, setpoint=self._velocity(cmd), start_offboard=True,
                      status=status_text(cmd))

    def _may_not_take_over(self, v: VehicleState) -> tuple[str, str] | None:
        """Why midair may not take over now: (a key that stays the same while the reason
        does, a short text for the ground station), or None."""
        c = self.cfg
        if v.t_s < self._cooldown_until:
            return "cooldown", f"pilot cooldown {self._cooldown_until - v.t_s:.0f} s"
        if not v.armed:
            return "disarmed", "disarmed"
        if not v.in_air:
            return "ground", "on the ground"
        if v.altitude_m is None or not math.isfinite(v.altitude_m):
            return "altitude", "altitude unknown"
        if v.altitude_m < c.min_takeover_altitude_m:
            return "low", f"below {c.min_takeover_altitude_m:g} m"
        if v.mode not in c.takeover_modes:
            return f"mode {v.mode}", f"mode {v.mode} not allowed"
        if v.t_s - v.mode_t_s > c.max_mode_age_s:
            return "mode age", "no recent mode report"
        return None

    def _pilot_took_over(self, v: VehicleState, text: str) -> Output:
        self.state = MONITOR
        self._requested_at = -math.inf
        self._left_at = v.t_s
        self._cooldown_until = v.t_s + self.cfg.pilot_cooldown_s
        return Output(MONITOR, status=text)

    def _leave(self, v: VehicleState, to: str, text: str) -> Output:
        # Leaving answers any open request: without this, the Offboard the vehicle still
        # reports until its next heartbeat (PX4: 1 Hz) read as a late acceptance, and the
        # next tick left a second time (a second offboard stop, a second mission start).
        self.state = MONITOR
        self._requested_at = -math.inf
        self._left_at = v.t_s
        return Output(MONITOR, setpoint=ZERO, leave_to=to, status=text)

    def _link_lost(self, v: VehicleState) -> Output:
        first = not self._link_was_lost and self._had_link
        if first:
            self._lost_at = v.t_s
        self._link_was_lost = self._link_was_lost or self._had_link
        if self.state == MONITOR:
            return Output(MONITOR, status="midair: link lost" if first else None)
        # Replace the setpoint MAVSDK keeps re-sending, so a returning link carries zero.
        return Output(self.state, setpoint=ZERO,
                      status="midair: link lost, setpoint cleared" if first else None)

    # ------------------------------------------------------------------ helpers

    def _usable(self, d: Decision, now: float) -> bool:
        fresh = now - d.t_s <= self.cfg.max_decision_age_ms / 1000.0
        return fresh and d.t_s >= self._fresh_after

    def _velocity(self, cmd: Command) -> tuple[float, float, float]:
        return clamp_velocity(cmd, self.max_speed_mps)


STATUS_TEXT_MAX = 50  # characters one MAVLink STATUSTEXT carries (common.xml)


def _verb(cmd: Command) -> str:
    return "stop" if cmd.action == STOP else "evade"


def status_text(cmd: Command, shadow: bool = False) -> str:
    """A status text for the pilot's ground station: what, which object, which way, in
    that order and within one STATUSTEXT (:data:`STATUS_TEXT_MAX` characters)."""
    obj = f"object {cmd.object_id}" if cmd.object_id is not None else "an object"
    if shadow:
        head = "midair shadow: would " + ("stop" if cmd.action == STOP else "evade")
    else:
        head = "midair: emergency stop," if cmd.action == STOP else "midair: evading"
    text = f"{head} {obj}"
    if cmd.action != STOP:
        text += f" {describe_direction((cmd.right_mps, cmd.down_mps))}"
    return text


def clamp_velocity(cmd: Command, max_speed_mps: float) -> tuple[float, float, float]:
    """The command's body velocity (forward, right, down m/s), scaled down to at most
    ``max_speed_mps``; zero for anything not finite."""
    vel = (cmd.forward_mps, cmd.right_mps, cmd.down_mps)
    if not all(math.isfinite(x) for x in vel):
        return ZERO
    speed = math.sqrt(sum(x * x for x in vel))
    if speed > max_speed_mps:
        k = max_speed_mps / speed
        vel = (vel[0] * k, vel[1] * k, vel[2] * k)
    return vel

