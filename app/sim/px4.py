"""A MAVLink vehicle that behaves like PX4 in every way midair depends on (pymavlink, UDP).

It stands in for PX4 SITL in the tests and on a desk: MAVSDK talks to it over UDP exactly
as it talks to PX4. What it reproduces (PX4 v1.14+ behaviour):

- HEARTBEAT with PX4 custom modes (main mode << 16 | sub mode << 24) and the armed flag;
  EXTENDED_SYS_STATE with the landed state; position, velocity, attitude, GPS, home and
  SYS_STATUS streams; AUTOPILOT_VERSION on request; COMMAND_ACK for every command.
- Offboard is refused unless setpoints have been streaming for over ``prestream_s`` (1 s:
  "PX4 enables offboard control only after receiving the signal for more than a second",
  PX4 user guide, Offboard Mode), and left (offboard-loss failsafe) ``COM_OF_LOSS_T`` s
  after the last setpoint, to ``loss_mode``.
- Velocity tracking with a dead time, a first-order lag and an acceleration limit per axis,
  calibrated on PX4 SITL's SIH quadrotor (docs/sitl.md): horizontally dead time 0.15 s and
  time constant 0.79 s (2 m/s commanded → 1 m/s at 0.70 s; SITL 0.58–0.74 s; a stop from
  3 m/s in 2.3 s, SITL 1.4–3.0 s), vertically 0.06 s and 0.15 s (PX4's vertical loop is
  quicker: a 3 m/s up-diagonal moves 0.5 m in 0.5 s, SITL 0.50–0.65 m). The horizontal time
  constant follows the velocity loop's gain MPC_XY_VEL_P_ACC (settable as a parameter, PX4's
  default 1.8) as 0.79 s x 1.8 / gain: at 2.5 and 3.0 this model reaches 2 m/s of a 3 m/s
  command at 0.80 / 0.72 s and moves 1.22 / 1.29 m in the first second, SITL 0.78–0.96 /
  0.65–0.71 s and 1.04–1.20 / 1.21–1.36 m (docs/sitl.md, "PX4 parameters for a quicker evasion").
- Body-frame velocity setpoints are yaw-aligned and horizontal, as PX4 applies them; in
  Offboard the vertical speed is capped at MPC_Z_VEL_MAX_UP (3 m/s) / MPC_Z_VEL_MAX_DN
  (1.5 m/s) as PX4's position controller does (mc_pos_control, Offboard constraints).
- A pilot mode switch (:meth:`pilot_set_mode`), a link cut (:meth:`set_link`) and a
  mission whose progress advances while the mode is Mission.
- After its offboard-loss failsafe, going back to Offboard by itself once setpoints stream
  again for ``OF_RESUME_S`` (PX4 does: seen on SITL 0.49-0.52 s after the link returned).
- Optionally (``wander``), a hover that is not still: :class:`Wander` adds to the position
  the drift PX4 SITL's SIH quadrotor shows in Hold (as a real hover does in wind on GPS).

It runs in its own thread at ``rate_hz``; everything it received is kept for tests.
"""

from __future__ import annotations

import math
import os
import threading
import time
from collections import deque
from dataclasses import dataclass, field

os.environ.setdefault("MAVLINK20", "1")
from pymavlink import mavutil  # noqa: E402
from pymavlink.dialects.v20 import common as ml  # noqa: E402

# PX4 custom modes: (main, sub). px4_custom_mode.h
PX4_MODES: dict[str, tuple[int, int]] = {
    "manual": (1, 0), "altitude": (2, 0), "position": (3, 0), "offboard": (6, 0),
    "takeoff": (4, 2), "hold": (4, 3), "mission": (4, 4), "return": (4, 5), "land": (4, 6),
}
_BY_CODE = {v: k for k, v in PX4_MODES.items()}

# Horizontal: fitted to PX4 SITL's SIH quadrotor (2 m/s commanded -> 1 m/s after 0.58-0.74 s).
DEAD_TIME_S = 0.15
TAU_S = 0.79  # at MPC_XY_VEL_P_ACC = XY_VEL_P_ACC_DEFAULT
XY_VEL_P_ACC_DEFAULT = 1.8  # PX4's default
XY_VEL_P_ACC_RANGE = (1.2, 5.0)  # PX4's parameter range
ACCEL_LIMIT_MPS2 = 4.0
# Vertical: PX4's vertical velocity loop is much quicker (MPC_Z_VEL_P_ACC 4 against
# MPC_XY_VEL_P_ACC 1.8): a 3 m/s up-diagonal reached 1 m/s along the command at 0.22-0.25 s,
# 2 m/s at 0.46-0.58 s and moved 0.50-0.65 m in 0.5 s, 1.53-1.97 m in 1.0 s (SITL, docs/sitl.md)
DEAD_TIME_Z_S = 0.06
TAU_Z_S = 0.15
ACCEL_LIMIT_Z_MPS2 = 8.0
# Tilt (SimState.tilts): the attitude follows the tilt the acceleration needs with the attitude
# loop's time constant, 1 / MC_ROLL_P = 1 / 6.5 (PX4's default roll and pitch P gains)
TILT_TAU_S = 1.0 / 6.5
GRAVITY_MPS2 = 9.81
OF_RESUME_S = 0.5  # PX4 leaves its offboard-loss failsafe after setpoints stream this long, s


# The wander of PX4 SITL's SIH hover (docs/sitl.md): ±0.5 m across, ±0.3 m up and down over a
# minute, at up to 0.7 m/s; its position strays from the straight line through its velocity
# by 0.053 / 0.095 / 0.131 / 0.172 m RMS in 0.5 / 0.8 / 1.0 / 1.2 s (camera plane, 4 flights).
# A damped oscillator driven by white noise per axis, fitted to that table (Monte Carlo, 800 s
# per candidate): 0.053 / 0.098 / 0.132 / 0.168 m, up to 0.64 m/s.
WANDER_SIGMA_M = (0.25, 0.25, 0.15)  # stationary std of the offset, north / east / down
WANDER_OMEGA_RAD_S = 0.6
WANDER_ZETA = 0.7
WANDER_RANGE = (0.0, 5.0)  # the multiples of it the stand-in takes


class Wander:
    """An offset from where the vehicle's controllers put it: per axis ``p'' = -2 ζ ω p' -
    ω² p + q w`` (w white), stationary std ``scale`` × WANDER_SIGMA_M; started from its
    stationary distribution. ``step(dt)`` gives the change of the offset and its rate now."""

    def __init__(self, scale: float, seed: int) -> None:
        import numpy as np

        self._rng = np.random.default_rng(seed)
        w, z = WANDER_OMEGA_RAD_S, WANDER_ZETA
        sigma = [scale * s for s in WANDER_SIGMA_M]
        self._q = [s * math.sqrt(4.0 * z * w ** 3) for s in sigma]  # stationary var = q²/(4ζω³)
        self.p = [float(self._rng.normal(0.0, s)) for s in sigma]
        self.v = [float(self._rng.normal(0.0, s * w)) for s in sigma]

    def step(self, dt: float) -> list[float]:
        if dt <= 0:
            return [0.0, 0.0, 0.0]
        w, z = WANDER_OMEGA_RAD_S, WANDER_ZETA
        noise = self._rng.normal(0.0, 1.0 / math.sqrt(dt), 3)
        moved = []
        for i in range(3):
            acc = -2.0 * z * w * self.v[i] - w * w * self.p[i] + self._q[i] * float(noise[i])
            self.v[i] += acc * dt
            moved.append(self.v[i] * dt)
            self.p[i] += moved[i]
        return moved


@dataclass
class Received:
    t: float  # monotonic, s
    velocity_body: tuple[float, float, float] | None  # forward, right, down m/s


@dataclass
class SimState:
    armed: bool = True
    in_air: bool = True
    mode: str = "position"
    pos_ned: list[float] = field(default_factory=lambda: [0.0, 0.0, -10.0])  # m, home at 0
    vel_ned: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])  # m/s
    yaw_rad: float = 0.0
    roll_rad: float = 0.0  # reported (and, with tilts, what the simulated camera is rendered at)
    pitch_rad: float = 0.0
    tilts: bool = False  # bank and pitch with the horizontal acceleration, as a multirotor does
    mission_seq: int = 0
    mission_count: int = 5
    cruise_mps: float = 2.0  # forward speed while in Mission, m/s


def free_udp_port() -> int:
    """A UDP port on the loopback that nothing uses now (for the stand-in's link)."""
    import socket

    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


class SimPx4:
    """Start with :meth:`start`, stop with :meth:`stop`. ``gcs_port`` is where MAVSDK listens
    (``udpin://0.0.0.0:<gcs_port>``)."""

    def __init__(self, gcs_port: int, rate_hz: float = 50.0, of_loss_t_s: float = 1.0,
                 loss_mode: str = "hold", state: SimState | None = None,
                 prestream_s: float = 1.0, xy_vel_p_acc: float = XY_VEL_P_ACC_DEFAULT,
                 wander: float = 0.0, wander_seed: int = 0) -> None:
        lo, hi = XY_VEL_P_ACC_RANGE
        if not lo <= xy_vel_p_acc <= hi:
            raise ValueError(f"MPC_XY_VEL_P_ACC {xy_vel_p_acc:g}: PX4 accepts {lo:g}-{hi:g}")
        self.prestream_s = prestream_s
        # the hover's drift, a multiple of SIH's (0: still); added to the position it moves
        if not WANDER_RANGE[0] <= wander <= WANDER_RANGE[1]:
            raise ValueError(f"wander {wander:g}: a multiple of SIH's hover drift, "
                             f"{WANDER_RANGE[0]:g}-{WANDER_RANGE[1]:g}")
        self._wander = Wander(wander, wander_seed) if wander > 0 else None
        self.gcs_port = gcs_port
        self.rate_hz = rate_hz
        self.of_loss_t_s = of_loss_t_s
        self.loss_mode = loss_mode
        self.state = state or SimState()
        self.received: list[Received] = []
        self.status_texts: list[str] = []
        self.mode_log: list[tuple[float, str, str]] = []  # (t, mode, why)
        self.acks: list[tuple[int, int]] = []  # (command, result)
        # every mode change asked for on the wire, accepted or not: (t, mode); a
        # MAV_CMD_MISSION_START counts as a request for "mission"
        self.mode_requests: list[tuple[float, str]] = []
        # PX4's defaults for what this vehicle models (mc_pos_control): in Offboard the
        # vertical speed is capped by MPC_Z_VEL_MAX_UP / _DN whatever the setpoint asks
        self.params: dict[str, float] = {"MIS_TAKEOFF_ALT": 2.5, "COM_OF_LOSS_T": of_loss_t_s,
                                         "MPC_Z_VEL_MAX_UP": 3.0, "MPC_Z_VEL_MAX_DN": 1.5,
                                         "MPC_XY_VEL_P_ACC": xy_vel_p_acc}
        self._lock = threading.Lock()
        self._link = True
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._last_setpoint_t = -math.inf
        self._stream_since = math.inf  # start of the current unbroken setpoint stream
        self._setpoint_body = (0.0, 0.0, 0.0)
        self._pipeline: deque[tuple[float, tuple[float, float, float]]] = deque()
        self._applied = (0.0, 0.0, 0.0)  # the command the vehicle is acting on now
        self._pipeline_z: deque[tuple[float, float]] = deque()  # the vertical part's own delay
        self._applied_z = 0.0
        self._mission_s = 0.0
        # in PX4's offboard-loss failsafe: PX4 goes back to Offboard by itself once setpoints
        # stream again for about half a second (PX4 SITL: 0.49-0.52 s, docs/sitl.md)
        self._of_failsafe = False
        self._conn = mavutil.mavlink_connection(
            f"udpout:127.0.0.1:{gcs_port}", source_system=1, source_component=1, dialect="common"
        )

    # ------------------------------------------------------------------ control from tests

    def start(self) -> SimPx4:
        self._thread = threading.Thread(target=self._run, name="sim-px4", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        self._conn.close()

    def pilot_set_mode(self, mode: str) -> None:
        """The pilot flips the mode switch."""
        with self._lock:
            self._set_mode(mode, "pilot")

    def set_link(self, up: bool) -> None:
        """Cut or restore the radio link both ways."""
        with self._lock:
            self._link = up

    @property
    def mode(self) -> str:
        with self._lock:
            return self.state.mode

    def pose(self) -> tuple[tuple[float, float, float], tuple[float, float, float], float]:
        """The true state now: position NED (m, home at 0), velocity NED (m/s), yaw (rad)."""
        with self._lock:
            st = self.state
            n, e, d = st.pos_ned
            return (n, e, d), self._velocity(), st.yaw_rad

    def attitude(self) -> tuple[float, float, float]:
        """The true attitude now: roll, pitch, yaw (rad)."""
        with self._lock:
            return self.state.roll_rad, self.state.pitch_rad, self.state.yaw_rad

    def velocity_body(self) -> tuple[float, float, float]:
        """The vehicle's velocity, forward/right/down m/s."""
        with self._lock:
            n, e, d = self._velocity()
            c, s = math.cos(self.state.yaw_rad), math.sin(self.state.yaw_rad)
            return (c * n + s * e, -s * n + c * e, d)

    def _velocity(self) -> tuple[float, float, float]:
        """What the vehicle moves at: its controllers' velocity and the wander's rate."""
        st = self.state
        n, e, d = st.vel_ned
        if self._wander is None or not (st.armed and st.in_air):
            return (n, e, d)
        wn, we, wd = self._wander.v
        return (n + wn, e + we, d + wd)

    # ------------------------------------------------------------------ loop

    def _run(self) -> None:
        period = 1.0 / self.rate_hz
        k = 0
        t_last = time.monotonic()
        while not self._stop.is_set():
            now = time.monotonic()
            with self._lock:
                self._receive(now)
                self._step(now - t_last, now)
                if self._link:
                    self._send(k)
            t_last = now
            k += 1
            time.sleep(max(0.0, period - (time.monotonic() - now)))

    def _receive(self, now: float) -> None:
        while True:
            try:
                m = self._conn.recv_match(blocking=False)
            except (OSError, ConnectionError):
                return
            if m is None:
                return
            if not self._link:
                continue
            kind = m.get_type()
            if kind == "SET_POSITION_TARGET_LOCAL_NED":
                self._on_setpoint(m, now)
            elif kind in ("COMMAND_LONG", "COMMAND_INT"):
                self._on_command(m, now)
            elif kind == "STATUSTEXT":
                self.status_texts.append(m.text)
            elif kind == "SET_MODE":
                self._on_set_mode_code(m.custom_mode, now)
            elif kind == "PARAM_SET":
                self.params[m.param_id] = float(m.param_value)
                self._conn.mav.param_value_send(m.param_id.encode(), m.param_value, m.param_type,
                                                len(self.params), 0)
            elif kind == "PARAM_REQUEST_READ" and m.param_id in self.params:
                self._conn.mav.param_value_send(m.param_id.encode(), self.params[m.param_id],
                                                ml.MAV_PARAM_TYPE_REAL32, len(self.params), 0)

    def _on_setpoint(self, m: ml.MAVLink_set_position_target_local_ned_message, now: float) -> None:
        ignore_vel = m.type_mask & (ml.POSITION_TARGET_TYPEMASK_VX_IGNORE
                                    | ml.POSITION_TARGET_TYPEMASK_VY_IGNORE
                                    | ml.POSITION_TARGET_TYPEMASK_VZ_IGNORE)
        if now - self._last_setpoint_t > self.of_loss_t_s:
            self._stream_since = now  # a new stream begins
        self._last_setpoint_t = now
        if ignore_vel:
            self.received.append(Received(now, None))
            return
        if m.coordinate_frame in (ml.MAV_FRAME_BODY_NED, ml.MAV_FRAME_BODY_FRD,
                                  ml.MAV_FRAME_BODY_OFFSET_NED):
            body = (m.vx, m.vy, m.vz)
        else:  # local NED: express in body (yaw only)
            c, s = math.cos(self.state.yaw_rad), math.sin(self.state.yaw_rad)
            body = (c * m.vx + s * m.vy, -s * m.vx + c * m.vy, m.vz)
        self._setpoint_body = body
        self.received.append(Received(now, body))
        if (self._of_failsafe and self.state.mode == self.loss_mode
                and now - self._stream_since >= OF_RESUME_S):
            self._set_mode("offboard", "failsafe cleared")

    def _on_command(self, m: object, now: float) -> None:
        cmd = int(m.command)  # type: ignore[attr-defined]
        p = [getattr(m, f"param{i}") for i in range(1, 8)]
        result = ml.MAV_RESULT_ACCEPTED
        if cmd == ml.MAV_CMD_DO_SET_MODE:
            result = self._on_set_mode_code((int(p[1]) << 16) | (int(p[2]) << 24), now)
        elif cmd == ml.MAV_CMD_COMPONENT_ARM_DISARM:
            self.state.armed = p[0] >= 0.5
        elif cmd == ml.MAV_CMD_NAV_TAKEOFF:
            if not self.state.armed:
                result = ml.MAV_RESULT_DENIED
            else:
                self.state.in_air = True
                self._set_mode("takeoff", "command")
        elif cmd == ml.MAV_CMD_NAV_LAND:
            self._set_mode("land", "command")
        elif cmd == ml.MAV_CMD_NAV_RETURN_TO_LAUNCH:
            self._set_mode("return", "command")
        elif cmd == ml.MAV_CMD_MISSION_START:
            self.mode_requests.append((now, "mission"))
            self._set_mode("mission", "command")
        elif cmd == ml.MAV_CMD_REQUEST_MESSAGE:
            self._send_requested(int(p[0]))
        elif cmd in (ml.MAV_CMD_SET_MESSAGE_INTERVAL, ml.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES):
            if cmd == ml.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES:
                self._send_requested(ml.MAVLINK_MSG_ID_AUTOPILOT_VERSION)
        else:
            result = ml.MAV_RESULT_UNSUPPORTED
        self.acks.append((cmd, result))
        self._conn.mav.command_ack_send(cmd, result)

    def _on_set_mode_code(self, custom_mode: int, now: float) -> int:
        main, sub = (custom_mode >> 16) & 0xFF, (custom_mode >> 24) & 0xFF
        mode = _BY_CODE.get((main, sub)) or _BY_CODE.get((main, 0))
        if mode is None:
            return ml.MAV_RESULT_UNSUPPORTED
        self.mode_requests.append((now, mode))
        if mode == "offboard" and (now - self._last_setpoint_t > self.of_loss_t_s
                                   or now - self._stream_since < self.prestream_s):
            return ml.MAV_RESULT_DENIED  # PX4: offboard signal not (yet) valid
        self._set_mode(mode, "command")
        return ml.MAV_RESULT_ACCEPTED

    def _set_mode(self, mode: str, why: str) -> None:
        if why != "offboard loss":
            self._of_failsafe = False  # a mode asked for (or the pilot's) ends the failsafe
        if mode != self.state.mode:
            self.state.mode = mode
            self.mode_log.append((time.monotonic(), mode, why))

    # ------------------------------------------------------------------ dynamics

    def _commanded_body(self, now: float) -> tuple[float, float, float]:
        st = self.state
        if st.mode == "offboard":
            if now - self._last_setpoint_t > self.of_loss_t_s:
                self._set_mode(self.loss_mode, "offboard loss")
                self._of_failsafe = True
                return (0.0, 0.0, 0.0)
            f, r, d = self._setpoint_body
            d = max(-self.params["MPC_Z_VEL_MAX_UP"], min(self.params["MPC_Z_VEL_MAX_DN"], d))
            return (f, r, d)
        if st.mode == "mission":
            return (st.cruise_mps, 0.0, 0.0)  # a leg flown straight ahead (MPC_XY_CRUISE)
        if st.mode == "takeoff":
            return (0.0, 0.0, -1.5)
        if st.mode == "land":
            return (0.0, 0.0, 0.7)
        return (0.0, 0.0, 0.0)  # position, hold, return (simplified)

    def _step(self, dt: float, now: float) -> None:
        st = self.state
        if not st.armed or not st.in_air:
            st.vel_ned = [0.0, 0.0, 0.0]
            return
        cmd = self._commanded_body(now)
        self._pipeline.append((now, cmd))
        self._pipeline_z.append((now, cmd[2]))
        while self._pipeline and now - self._pipeline[0][0] >= DEAD_TIME_S:
            self._applied = self._pipeline.popleft()[1]  # commands act after the dead time
        while self._pipeline_z and now - self._pipeline_z[0][0] >= DEAD_TIME_Z_S:
            self._applied_z = self._pipeline_z.popleft()[1]
        target = self._applied
        c, s = math.cos(st.yaw_rad), math.sin(st.yaw_rad)
        tn = c * target[0] - s * target[1]
        te = s * target[0] + c * target[1]
        goal = (tn, te, self._applied_z)
        lo, hi = XY_VEL_P_ACC_RANGE
        tau_xy = TAU_S * XY_VEL_P_ACC_DEFAULT / max(lo, min(hi, self.params["MPC_XY_VEL_P_ACC"]))
        accel = [0.0, 0.0, 0.0]
        for i in range(3):
            tau, acc = (TAU_Z_S, ACCEL_LIMIT_Z_MPS2) if i == 2 else (tau_xy, ACCEL_LIMIT_MPS2)
            dv = (goal[i] - st.vel_ned[i]) * (1 - math.exp(-dt / tau))
            lim = acc * dt
            accel[i] = max(-lim, min(lim, dv)) / dt if dt > 0 else 0.0
            st.vel_ned[i] += accel[i] * dt
            st.pos_ned[i] += st.vel_ned[i] * dt
        if self._wander is not None:
            for i, moved in enumerate(self._wander.step(dt)):
                st.pos_ned[i] += moved
        if st.tilts and dt > 0:
            # a multirotor accelerates sideways by tilting its thrust: tan(tilt) = a / g, the
            # nose down (negative pitch) to speed up forward, the right side down (positive
            # roll) to go right; reached with the attitude loop's lag (TILT_TAU_S)
            fwd = c * accel[0] + s * accel[1]
            right = -s * accel[0] + c * accel[1]
            k = 1 - math.exp(-dt / TILT_TAU_S)
            st.roll_rad += (math.atan2(right, GRAVITY_MPS2) - st.roll_rad) * k
            st.pitch_rad += (-math.atan2(fwd, GRAVITY_MPS2) - st.pitch_rad) * k
        if st.mode == "takeoff" and -st.pos_ned[2] >= self.params["MIS_TAKEOFF_ALT"]:
            self._set_mode("hold", "takeoff done")
        if st.mode == "land" and st.pos_ned[2] >= 0.0:
            st.pos_ned[2] = 0.0
            st.in_air = False
        if st.mode == "mission":
            self._mission_s += dt
            st.mission_seq = min(st.mission_count - 1, int(self._mission_s / 3.0))  # 3 s a leg

    # ------------------------------------------------------------------ telemetry out

    def _send(self, k: int) -> None:
        mav = self._conn.mav
        st = self.state
        main, sub = PX4_MODES[st.mode]
        base = ml.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | (ml.MAV_MODE_FLAG_SAFETY_ARMED if st.armed else 0)
        boot_ms = int(time.monotonic() * 1000) & 0xFFFFFFFF
        lat0, lon0, alt0 = 47.397742, 8.545594, 488.0  # PX4 SITL's default home (Zurich)
        if k % int(self.rate_hz) == 0:
            mav.heartbeat_send(ml.MAV_TYPE_QUADROTOR, ml.MAV_AUTOPILOT_PX4, base,
                               (main << 16) | (sub << 24),
                               ml.MAV_STATE_ACTIVE if st.armed else ml.MAV_STATE_STANDBY)
            sensors = 0x3FFFFFFF
            mav.sys_status_send(sensors, sensors, sensors, 200, 16000, -1, 90, 0, 0, 0, 0, 0, 0)
            mav.gps_raw_int_send(boot_ms * 1000, 3, int(lat0 * 1e7), int(lon0 * 1e7),
                                 int(alt0 * 1000), 80, 100, 0, 0, 12)
            mav.home_position_send(int(lat0 * 1e7), int(lon0 * 1e7), int(alt0 * 1000),
                                   0, 0, 0, [1, 0, 0, 0], 0, 0, 0)
            mav.mission_current_send(st.mission_seq)
        if k % 5 == 0:
            landed = ml.MAV_LANDED_STATE_IN_AIR if st.in_air else ml.MAV_LANDED_STATE_ON_GROUND
            mav.extended_sys_state_send(ml.MAV_VTOL_STATE_MC, landed)
        n, e, d = st.pos_ned
        vn, ve, vd = self._velocity()
        mav.local_position_ned_send(boot_ms, n, e, d, vn, ve, vd)
        lat = lat0 + n / 111_320.0
        lon = lon0 + e / (111_320.0 * math.cos(math.radians(lat0)))
        mav.global_position_int_send(boot_ms, int(lat * 1e7), int(lon * 1e7),
                                     int((alt0 - d) * 1000), int(-d * 1000),
                                     int(vn * 100), int(ve * 100), int(vd * 100), 0)
        mav.attitude_send(boot_ms, st.roll_rad, st.pitch_rad, st.yaw_rad, 0.0, 0.0, 0.0)

    def _send_requested(self, msg_id: int) -> None:
        if msg_id == ml.MAVLINK_MSG_ID_AUTOPILOT_VERSION:
            caps = (ml.MAV_PROTOCOL_CAPABILITY_MISSION_INT | ml.MAV_PROTOCOL_CAPABILITY_COMMAND_INT
                    | ml.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_LOCAL_NED
                    | ml.MAV_PROTOCOL_CAPABILITY_MAVLINK2)
            self._conn.mav.autopilot_version_send(caps, 1 << 24 | 14 << 16, 0, 0, 0,
                                                  [0] * 8, [0] * 8, [0] * 8, 0, 0, 1)


def main(argv: list[str] | None = None) -> int:
    """``python -m app.sim.px4 --port 14540``: a flying vehicle for desk runs of
    ``midair fly --connection udpin://0.0.0.0:14540``. Prints its mode changes."""
    import argparse

    p = argparse.ArgumentParser(prog="python -m app.sim.px4", description=main.__doc__)
    p.add_argument("--port", type=int, default=14540, help="UDP port MAVSDK listens on")
    p.add_argument("--mode", default="position", choices=sorted(PX4_MODES), help="starting mode")
    p.add_argument("--landed", action="store_true", help="start disarmed on the ground")
    args = p.parse_args(argv)
    state = SimState(armed=not args.landed, in_air=not args.landed, mode=args.mode)
    if args.landed:
        state.pos_ned[2] = 0.0
    sim = SimPx4(args.port, state=state).start()
    print(f"stand-in PX4 sending to udp 127.0.0.1:{args.port}, mode {args.mode}; Ctrl-C stops",
          flush=True)
    seen = 0
    try:
        while True:
            time.sleep(0.1)
            for t, mode, why in sim.mode_log[seen:]:
                print(f"{t:.3f} mode {mode} ({why})", flush=True)
            seen = len(sim.mode_log)
    except KeyboardInterrupt:
        pass
    finally:
        sim.stop()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
