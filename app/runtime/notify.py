"""systemd's notification protocol (``Type=notify``, ``WatchdogSec=``), without a dependency.

systemd passes a datagram socket in ``$NOTIFY_SOCKET`` (a path, or ``@name`` for the
abstract namespace) and, with a watchdog, ``$WATCHDOG_USEC``. We send ``READY=1`` once the
camera and the autopilot are up, ``WATCHDOG=1`` from the perception loop after frames were
processed (so a stalled pipeline stops the kicks and systemd restarts the service),
``STATUS=…`` for ``systemctl status`` and ``STOPPING=1`` on the way out (sd_notify(3)).
Outside systemd every call is a no-op.
"""

from __future__ import annotations

import logging
import os
import socket
import time

log = logging.getLogger(__name__)


class Notifier:
    def __init__(self, environ: dict[str, str] | None = None) -> None:
        env = os.environ if environ is None else environ
        address = env.get("NOTIFY_SOCKET", "")
        self.address = "\0" + address[1:] if address.startswith("@") else address
        usec = env.get("WATCHDOG_USEC", "")
        self.watchdog_s = int(usec) / 1e6 if usec.isdigit() and int(usec) > 0 else None
        # kick twice per watchdog period at most (sd_watchdog_enabled(3) suggests half)
        self.kick_every_s = self.watchdog_s / 4 if self.watchdog_s else 1.0
        self._last_kick = -1e9
        self._sock: socket.socket | None = None
        if self.address:
            self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
            # never block the event loop: a datagram socket's queue is short (net.unix.
            # max_dgram_qlen, 10 by default) and a message that does not fit is dropped
            self._sock.setblocking(False)

    @property
    def enabled(self) -> bool:
        return self._sock is not None

    def send(self, message: str) -> None:
        if self._sock is None:
            return
        try:
            self._sock.sendto(message.encode(), self.address)
        except OSError as exc:  # systemd gone or the socket full: never fatal
            log.debug("sd_notify %r: %s", message, exc)

    def ready(self, status: str) -> None:
        self.send(f"READY=1\nSTATUS={status}")

    def status(self, status: str) -> None:
        self.send(f"STATUS={status}")

    def kick(self) -> None:
        """Pet the watchdog (rate-limited; call it every processed frame)."""
        now = time.monotonic()
        if now - self._last_kick >= self.kick_every_s:
            self._last_kick = now
            self.send("WATCHDOG=1")

    def stopping(self) -> None:
        self.send("STOPPING=1")

    def close(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None
