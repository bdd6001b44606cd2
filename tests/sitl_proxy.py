"""A UDP relay between PX4's offboard/API port and one MAVSDK client, for the SITL tests.

PX4 SITL sends its offboard link to UDP 14540; the relay binds that port in PX4's place
and forwards every datagram to the client (MAVSDK listening with
``udpin://0.0.0.0:<client_port>``), and the client's replies back to PX4. It can cut the link
both ways (:meth:`MavlinkProxy.cut`, :meth:`MavlinkProxy.restore`), and it reads what it
relays: from the client to PX4 every mode request (``COMMAND_LONG``/``COMMAND_INT``
``MAV_CMD_DO_SET_MODE``, ``MAV_CMD_MISSION_START``, ``SET_MODE``) and every velocity
setpoint; from PX4 the mode in each heartbeat, the mission's current item and command acks.

Only the messages it counts are decoded (pymavlink, common dialect): the frames are walked
by their headers, so relaying PX4's full-rate onboard stream costs little.
"""

from __future__ import annotations

import math
import os
import selectors
import socket
import threading
import time
from dataclasses import dataclass

os.environ.setdefault("MAVLINK20", "1")
from pymavlink.dialects.v20 import common as ml  # noqa: E402

# PX4 custom modes (px4_custom_mode.h): (main, sub) -> the mode names midair uses
PX4_MODES: dict[tuple[int, int], str] = {
    (1, 0): "manual", (2, 0): "altitude", (3, 0): "position", (6, 0): "offboard",
    (7, 0): "manual", (4, 1): "ready", (4, 2): "takeoff", (4, 3): "hold", (4, 4): "mission",
    (4, 5): "return", (4, 6): "land", (4, 7): "follow", (4, 8): "precland",
}

_COUNTED_UP = {  # client -> PX4
    ml.MAVLINK_MSG_ID_COMMAND_LONG, ml.MAVLINK_MSG_ID_COMMAND_INT, ml.MAVLINK_MSG_ID_SET_MODE,
    ml.MAVLINK_MSG_ID_SET_POSITION_TARGET_LOCAL_NED,
}
_COUNTED_DOWN = {  # PX4 -> client
    ml.MAVLINK_MSG_ID_HEARTBEAT, ml.MAVLINK_MSG_ID_MISSION_CURRENT, ml.MAVLINK_MSG_ID_COMMAND_ACK,
}


def px4_mode(custom_mode: int) -> str:
    """The mode name of a PX4 custom mode word (main << 16 | sub << 24)."""
    main, sub = (custom_mode >> 16) & 0xFF, (custom_mode >> 24) & 0xFF
    return PX4_MODES.get((main, sub)) or PX4_MODES.get((main, 0)) or f"px4 {main}.{sub}"


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def mavlink_frames(buf: bytes):
    """(message id, frame bytes) of every MAVLink v1/v2 frame in one datagram."""
    i, n = 0, len(buf)
    while i < n:
        stx = buf[i]
        if stx == 0xFD and i + 10 <= n:
            total = 12 + buf[i + 1] + (13 if buf[i + 2] & 0x01 else 0)
            msgid = buf[i + 7] | buf[i + 8] << 8 | buf[i + 9] << 16
        elif stx == 0xFE and i + 6 <= n:
            total = 8 + buf[i + 1]
            msgid = buf[i + 5]
        else:
            i += 1
            continue
        yield msgid, buf[i:i + total]
        i += total


@dataclass(frozen=True)
class ModeRequest:
    t: float  # monotonic, when relayed, s
    mode: str  # as midair names them; "mission" for MAV_CMD_MISSION_START too
    how: str  # "DO_SET_MODE", "MISSION_START" or "SET_MODE"
    forwarded: bool  # False: sent while the link was cut (PX4 never saw it)


@dataclass(frozen=True)
class Setpoint:
    t: float
    velocity: tuple[float, float, float]  # as sent: body FRD or local NED, m/s
    frame: int  # MAV_FRAME_*
    forwarded: bool


class MavlinkProxy:
    """The relay, in its own thread. ``listen_port``: where PX4 sends (14540);
    ``client_port``: where the MAVSDK client listens (a free port by default)."""

    def __init__(self, listen_port: int = 14540, client_port: int | None = None) -> None:
        self.listen_port = listen_port
        self.client_port = client_port or free_udp_port()
        self._px4 = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._px4.bind(("0.0.0.0", listen_port))
        self._client = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._client.bind(("127.0.0.1", 0))
        self._px4_addr: tuple[str, int] | None = None  # learnt from PX4's first datagram
        self._up = True
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._mav_up = ml.MAVLink(None)
        self._mav_down = ml.MAVLink(None)
        self.mode_requests: list[ModeRequest] = []
        self.setpoints: list[Setpoint] = []
        self.heartbeats: list[tuple[float, str, bool]] = []  # (t, mode, armed) from PX4
        self.mission_current: list[tuple[float, int]] = []  # (t, seq) from PX4
        self.acks: list[tuple[float, int, int]] = []  # (t, command, result) from PX4
        self.cuts: list[tuple[float, bool]] = []  # (t, up) each change of the link
        self.last_from_px4 = -math.inf

    @property
    def client_url(self) -> str:
        return f"udpin://0.0.0.0:{self.client_port}"

    def start(self) -> MavlinkProxy:
        self._thread = threading.Thread(target=self._run, name="sitl-proxy", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        self._px4.close()
        self._client.close()

    def cut(self) -> float:
        """Drop everything both ways from now on; returns the monotonic time of the cut."""
        with self._lock:
            self._up = False
            t = time.monotonic()
            self.cuts.append((t, False))
            return t

    def restore(self) -> float:
        with self._lock:
            self._up = True
            t = time.monotonic()
            self.cuts.append((t, True))
            return t

    @property
    def up(self) -> bool:
        return self._up

    # ------------------------------------------------------------------ queries

    def requests_since(self, t: float, forwarded_only: bool = True) -> list[ModeRequest]:
        with self._lock:
            return [r for r in self.mode_requests if r.t >= t and (r.forwarded or not forwarded_only)]

    def modes_requested_since(self, t: float) -> list[str]:
        """The modes asked of PX4 after ``t``, in order, retransmissions left out."""
        return [r.mode for r in self.requests_since(t)]

    def setpoints_since(self, t: float) -> list[Setpoint]:
        with self._lock:
            return [s for s in self.setpoints if s.t >= t and s.forwarded]

    def heartbeat_modes_since(self, t: float) -> list[tuple[float, str]]:
        with self._lock:
            return [(ht, m) for ht, m, _ in self.heartbeats if ht >= t]

    # ------------------------------------------------------------------ relay

    def _run(self) -> None:
        sel = selectors.DefaultSelector()
        sel.register(self._px4, selectors.EVENT_READ, "px4")
        sel.register(self._client, selectors.EVENT_READ, "client")
        try:
            while not self._stop.is_set():
                for key, _ in sel.select(timeout=0.05):
                    sock: socket.socket = key.fileobj  # type: ignore[assignment]
                    try:
                        data, addr = sock.recvfrom(65535)
                    except OSError:
                        continue
                    now = time.monotonic()
                    if key.data == "px4":
                        self._px4_addr = addr
                        up = self._up
                        if up:
                            self.last_from_px4 = now
                            self._read_down(data, now)
                            try:
                                self._client.sendto(data, ("127.0.0.1", self.client_port))
                            except OSError:
                                pass
                    else:
                        up = self._up
                        self._read_up(data, now, up)
                        if up and self._px4_addr is not None:
                            try:
                                self._px4.sendto(data, self._px4_addr)
                            except OSError:
                                pass
        finally:
            sel.close()

    def _decode(self, mav: ml.MAVLink, frame: bytes) -> ml.MAVLink_message | None:
        try:
            return mav.decode(bytearray(frame))
        except Exception:  # a frame cut by the datagram's end, a CRC error: not counted
            return None

    def _read_up(self, data: bytes, now: float, forwarded: bool) -> None:
        for msgid, frame in mavlink_frames(data):
            if msgid not in _COUNTED_UP:
                continue
            m = self._decode(self._mav_up, frame)
            if m is None:
                continue
            kind = m.get_type()
            with self._lock:
                if kind in ("COMMAND_LONG", "COMMAND_INT"):
                    if kind == "COMMAND_LONG" and m.confirmation > 0:
                        continue  # MAVSDK's retransmission of a command already counted
                    if m.command == ml.MAV_CMD_DO_SET_MODE:
                        mode = px4_mode(int(m.param2) << 16 | int(m.param3) << 24)
                        self.mode_requests.append(ModeRequest(now, mode, "DO_SET_MODE", forwarded))
                    elif m.command == ml.MAV_CMD_MISSION_START:
                        self.mode_requests.append(ModeRequest(now, "mission", "MISSION_START",
                                                              forwarded))
                elif kind == "SET_MODE":
                    self.mode_requests.append(ModeRequest(now, px4_mode(m.custom_mode), "SET_MODE",
                                                          forwarded))
                elif kind == "SET_POSITION_TARGET_LOCAL_NED":
                    self.setpoints.append(Setpoint(now, (m.vx, m.vy, m.vz), m.coordinate_frame,
                                                   forwarded))

    def _read_down(self, data: bytes, now: float) -> None:
        for msgid, frame in mavlink_frames(data):
            if msgid not in _COUNTED_DOWN:
                continue
            m = self._decode(self._mav_down, frame)
            if m is None:
                continue
            kind = m.get_type()
            with self._lock:
                if kind == "HEARTBEAT" and m.autopilot == ml.MAV_AUTOPILOT_PX4:
                    armed = bool(m.base_mode & ml.MAV_MODE_FLAG_SAFETY_ARMED)
                    self.heartbeats.append((now, px4_mode(m.custom_mode), armed))
                elif kind == "MISSION_CURRENT":
                    self.mission_current.append((now, int(m.seq)))
                elif kind == "COMMAND_ACK":
                    self.acks.append((now, int(m.command), int(m.result)))
