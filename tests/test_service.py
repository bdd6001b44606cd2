"""The systemd side: the unit file passes `systemd-analyze verify`, and the notification
protocol (READY, WATCHDOG, STATUS, STOPPING) reaches a real datagram socket."""

from __future__ import annotations

import configparser
import shutil
import socket
import subprocess
import sys
from pathlib import Path

import pytest

from app.runtime.notify import Notifier

ROOT = Path(__file__).resolve().parents[1]
UNIT = ROOT / "systemd" / "midair.service"


def _verify(tmp_path: Path, text: str) -> subprocess.CompletedProcess[str]:
    if shutil.which("systemd-analyze") is None:
        pytest.skip("systemd-analyze is not installed (apt-get install systemd)")
    unit = tmp_path / "midair.service"
    # ExecStart must name an executable that exists here: this checkout's console script
    midair = Path(sys.executable).with_name("midair")
    unit.write_text(text.replace("/opt/midair/.venv/bin/midair", str(midair)))
    return subprocess.run(["systemd-analyze", "verify", str(unit)], capture_output=True, text=True,
                          timeout=60)


def test_the_unit_file_verifies_without_a_warning(tmp_path: Path) -> None:
    out = _verify(tmp_path, UNIT.read_text())
    assert out.returncode == 0 and out.stderr.strip() == "" and out.stdout.strip() == "", out.stderr


def test_verify_would_catch_a_mistake(tmp_path: Path) -> None:
    out = _verify(tmp_path, UNIT.read_text().replace("WatchdogSec=", "WatchdogSecs="))
    assert "Unknown key 'WatchdogSecs'" in out.stderr


def test_the_unit_says_what_the_runtime_issue_asks() -> None:
    unit = configparser.ConfigParser(strict=False, interpolation=None)
    unit.optionxform = str  # type: ignore[assignment,method-assign]
    unit.read_string(UNIT.read_text())
    svc = unit["Service"]
    assert svc["Type"] == "notify" and int(svc["WatchdogSec"]) > 0
    assert svc["Restart"] == "on-failure" and svc["RestartPreventExitStatus"] == "2"
    assert svc["User"] == "midair" and {"plugdev", "dialout"} <= set(svc["SupplementaryGroups"].split())
    assert "StartLimitBurst" in unit["Unit"] and "MemoryMax" in svc and "CPUQuota" in svc
    assert svc["DevicePolicy"] == "closed" and svc["ProtectSystem"] == "strict"
    assert "midair fly" in svc["ExecStart"]
    # the camera gives up (and exits) before the watchdog would kill the process
    from app.config import CaptureConfig

    assert CaptureConfig().give_up_s < int(svc["WatchdogSec"])


def _listen(tmp_path: Path) -> socket.socket:
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(str(tmp_path / "notify.sock"))
    sock.settimeout(2.0)
    return sock


def test_notifications_reach_the_socket(tmp_path: Path) -> None:
    sock = _listen(tmp_path)
    n = Notifier({"NOTIFY_SOCKET": str(tmp_path / "notify.sock"), "WATCHDOG_USEC": "2000000"})
    assert n.enabled and n.watchdog_s == 2.0
    n.ready("flying")
    assert sock.recv(256) == b"READY=1\nSTATUS=flying"
    n.kick()
    n.kick()  # within the same quarter period: not sent again
    n.status("engaged")
    assert sock.recv(256) == b"WATCHDOG=1"
    assert sock.recv(256) == b"STATUS=engaged"
    n.stopping()
    assert sock.recv(256) == b"STOPPING=1"
    n.close()
    sock.close()


def test_outside_systemd_nothing_is_sent() -> None:
    n = Notifier({})
    assert not n.enabled
    n.ready("x")
    n.kick()  # no socket, no error
