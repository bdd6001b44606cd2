"""The systemd side: the unit file passes `systemd-analyze verify`, its exposure score stays
low, `midair fly` runs under its sandbox, and the notification protocol (READY, WATCHDOG,
STATUS, STOPPING) reaches a real datagram socket.

The sandboxed runs need a systemd that starts transient units: the system manager (root on a
machine booted with systemd), the user's manager (`systemd-run --user`), or else, as root on a
machine without systemd as PID 1 (a container, a CI VM), a private user manager that this
file starts in its own mount and cgroup namespaces, confined to a cgroup of its own (it needs
unshare, a cgroup2 mount and the dbus-user-session package). Otherwise they skip and say why.
"""

from __future__ import annotations

import configparser
import contextlib
import json
import os
import re
import shutil
import socket
import stat
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest

from app.runtime.notify import Notifier

ROOT = Path(__file__).resolve().parents[1]
UNIT = ROOT / "systemd" / "midair.service"
NETWORK_DROP_IN = ROOT / "systemd" / "midair.service.d" / "network-link.conf"
MAX_EXPOSURE = 3.0


def _unit_here(tmp_path: Path, text: str, drop_in: bool = False) -> Path:
    """The unit in tmp_path, with the network drop-in beside it (systemd-analyze reads it)."""
    if shutil.which("systemd-analyze") is None:
        pytest.skip("systemd-analyze is not installed (apt-get install systemd)")
    unit = tmp_path / "midair.service"
    # ExecStart must name an executable that exists here: this checkout's console script
    midair = Path(sys.executable).with_name("midair")
    unit.write_text(text.replace("/opt/midair/.venv/bin/midair", str(midair)))
    if drop_in:
        (tmp_path / "midair.service.d").mkdir()
        shutil.copy(NETWORK_DROP_IN, tmp_path / "midair.service.d" / NETWORK_DROP_IN.name)
    return unit


def _verify(tmp_path: Path, text: str, drop_in: bool = False) -> subprocess.CompletedProcess[str]:
    return subprocess.run(["systemd-analyze", "verify", str(_unit_here(tmp_path, text, drop_in))],
                          capture_output=True, text=True, timeout=60)


def test_the_unit_file_verifies_without_a_warning(tmp_path: Path) -> None:
    out = _verify(tmp_path, UNIT.read_text())
    assert out.returncode == 0 and out.stderr.strip() == "" and out.stdout.strip() == "", out.stderr


def test_the_unit_with_the_network_drop_in_verifies_without_a_warning(tmp_path: Path) -> None:
    out = _verify(tmp_path, UNIT.read_text(), drop_in=True)
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


def test_the_unit_has_the_sandbox_the_issue_asks() -> None:
    svc = _service_assignments(UNIT.read_text())
    values = {k: v for k, v in svc}  # the last assignment of each
    assert values["CapabilityBoundingSet"] == "" and values["NoNewPrivileges"] == "yes"
    filters = [v for k, v in svc if k == "SystemCallFilter"]
    assert filters[0] == "@system-service" and "~@privileged @resources" in filters
    assert values["SystemCallErrorNumber"] == "EPERM"
    assert values["IPAddressDeny"] == "any" and values["IPAddressAllow"] == "localhost"
    assert values["ProtectProc"] == "invisible" and values["ProcSubset"] == "pid"
    assert values["MemoryDenyWriteExecute"] == "yes" and values["RemoveIPC"] == "yes"
    assert values["PrivateUsers"] == "yes"


# ---------------------------------------------------------------------- exposure score


def _security(tmp_path: Path, drop_in: bool = False) -> tuple[float, str]:
    """`systemd-analyze security --offline=yes`: the overall exposure and the table."""
    unit = _unit_here(tmp_path, UNIT.read_text(), drop_in)
    out = subprocess.run(["systemd-analyze", "security", "--offline=yes", "--no-pager", str(unit)],
                         capture_output=True, text=True, timeout=60)
    if out.returncode != 0 and "offline" in out.stderr:
        pytest.skip(f"systemd-analyze is too old for --offline (systemd >= 250): {out.stderr.strip()}")
    found = re.search(r"Overall exposure level for \S+: (\d+(?:\.\d+)?)", out.stdout)
    assert found, out.stdout + out.stderr
    return float(found.group(1)), out.stdout


def test_the_exposure_score_is_at_most_3(tmp_path: Path) -> None:
    score, table = _security(tmp_path)
    assert score <= MAX_EXPOSURE, f"systemd-analyze security: {score} > {MAX_EXPOSURE}\n{table}"
    assert "allow list with only localhost entries" in table


def test_the_exposure_score_with_a_network_link_is_at_most_3(tmp_path: Path) -> None:
    score, table = _security(tmp_path, drop_in=True)
    assert "allow list with non-localhost entries" in table  # the drop-in was read
    assert score <= MAX_EXPOSURE, f"systemd-analyze security: {score} > {MAX_EXPOSURE}\n{table}"


# ---------------------------------------------------------------------- the sandbox, for real


def _service_assignments(text: str) -> list[tuple[str, str]]:
    """Every KEY=VALUE of the [Service] section in order (repeated keys kept)."""
    out: list[tuple[str, str]] = []
    section = ""
    for raw in text.splitlines():
        line = raw.strip()
        if not line or line.startswith(("#", ";")):
            continue
        if line.startswith("["):
            section = line
            continue
        if section == "[Service]" and "=" in line:
            key, value = line.split("=", 1)
            out.append((key.strip(), value.strip()))
    return out


# [Service] keys the sandboxed run does not take from the unit, and why
NOT_PASSED = {
    "ExecStart": "the run is this checkout's `python -m app.cli fly` against the stand-in vehicle",
    "User": "there is no midair user on a test machine: the run keeps the manager's user",
    "Group": "as User",
    "SupplementaryGroups": "no camera and no UART here (the device groups: test_the_device_groups_...)",
    "StateDirectory": "the run writes nothing (--no-record)",
    "WorkingDirectory": "the checkout instead of /var/lib/midair",
    "Restart": "one run: a failure fails the test instead of restarting",
    "RestartSec": "as Restart",
    "RestartPreventExitStatus": "as Restart",
}

_HOMES = ("/root", "/home", "/run/user")  # what ProtectHome= hides
_TMPS = ("/tmp", "/var/tmp")  # what PrivateTmp= replaces


def _under(path: str, dirs: tuple[str, ...]) -> bool:
    return any(path == d or path.startswith(d + "/") for d in dirs)


def sandbox_properties(text: str) -> list[str]:
    """The unit's [Service] properties as ``KEY=VALUE`` for systemd-run's ``-p``, adapted to
    a test machine where they must be: ReadOnlyPaths optional (no /etc/midair here), Nice only
    for root, and this interpreter, its venv and this checkout bound in, read-only, where the
    unit would hide them: in a home directory (pyenv in /root, a clone in ~/src: then
    ProtectHome=tmpfs instead of yes, which hides even what is bound) or in /tmp."""
    needed = sorted({os.path.realpath(p) for p in (sys.base_prefix, sys.prefix, ROOT)})
    in_home = [p for p in needed if _under(p, _HOMES)]
    in_tmp = [p for p in needed if _under(p, _TMPS)]
    props: list[str] = []
    for key, value in _service_assignments(text):
        if key in NOT_PASSED:
            continue
        if key == "Nice" and os.geteuid() != 0:
            continue  # a negative niceness needs CAP_SYS_NICE, which a user manager lacks
        if key == "ReadOnlyPaths":
            value = " ".join(p if p.startswith("-") else "-" + p for p in value.split())
        if key == "ProtectHome" and in_home:
            value = "tmpfs"
        props.append(f"{key}={value}")
    hidden = in_home + in_tmp
    if hidden:
        props.append("BindReadOnlyPaths=" + " ".join(hidden))
    return props


@dataclass
class Manager:
    """How to reach a systemd manager that runs transient units here."""

    argv: list[str]  # systemd-run and its scope option
    env: dict[str, str]
    root: bool  # the manager and its units run as root (so User= and BPF filters work)
    what: str


def _responds(cmd: list[str], env: dict[str, str]) -> bool:
    try:
        out = subprocess.run(cmd + ["show", "--property=Version"], capture_output=True, text=True,
                             env=env, timeout=10)
    except (OSError, subprocess.TimeoutExpired):
        return False
    return out.returncode == 0 and out.stdout.startswith("Version=")


_PRIVATE_MANAGER = r"""
set -eu
work=$1 cgroup=$2
echo $$ > "$cgroup/cgroup.procs"
exec unshare --mount --cgroup --propagation private /bin/sh -euc '
  work=$1 systemd=$2
  # its cgroup is all it sees (a cgroup namespace): unified mode, nothing else is touched
  mount -t cgroup2 none /sys/fs/cgroup
  # /run a mount point, as on any systemd machine (a unit with API file systems would get an
  # empty one otherwise, without the notification socket)
  mountpoint -q /run || mount --bind /run /run
  # "booted with systemd", in this mount namespace only, with the nodes that hide paths
  mount -t tmpfs -o mode=0755 none /run/systemd
  mkdir /run/systemd/system /run/systemd/inaccessible
  cd /run/systemd/inaccessible
  mkdir -m 0 dir; : > reg; chmod 0 reg; mknod -m 0 chr c 0 0; mknod -m 0 blk b 0 0; mkfifo -m 0 fifo
  cd /
  # the stock user units only (the D-Bus socket systemd-run needs), none of /etc or of $HOME
  export XDG_RUNTIME_DIR="$work/runtime" SYSTEMD_UNIT_PATH=/usr/lib/systemd/user
  exec "$systemd" --user --log-target=console --log-level=notice
' sh "$work" "$3"
"""


def _cgroup2_here() -> Path | None:
    """This process's own cgroup in the cgroup2 hierarchy, if one is mounted."""
    mount = next((line.split()[4] for line in Path("/proc/self/mountinfo").read_text().splitlines()
                  if line.split(" - ")[1].startswith("cgroup2 ")), None)
    own = next((line[3:] for line in Path("/proc/self/cgroup").read_text().splitlines()
                if line.startswith("0::")), None)
    if mount is None or own is None:
        return None
    path = Path(mount + own.rstrip("/"))
    return path if path.is_dir() else None


@contextlib.contextmanager
def _private_manager() -> Iterator[Manager]:
    systemd = next((p for p in ("/lib/systemd/systemd", "/usr/lib/systemd/systemd") if os.access(p, os.X_OK)),
                   None)
    missing = [what for what, ok in [
        ("root", os.geteuid() == 0), ("unshare", shutil.which("unshare") is not None),
        ("the systemd binary", systemd is not None),
        ("dbus-user-session", Path("/usr/lib/systemd/user/dbus.socket").is_file()
         and shutil.which("dbus-daemon") is not None)] if not ok]
    parent = _cgroup2_here()
    if parent is None:
        missing.append("a cgroup2 mount")
    if missing:
        pytest.skip("no systemd manager to run the unit under here (no systemd as PID 1, no user "
                    "manager), and a private one needs " + ", ".join(missing))
    assert parent is not None and systemd is not None
    # its runtime directory (the D-Bus and notification sockets) must stay reachable from a unit
    # with PrivateTmp=: in /run, not in /tmp; short, since socket paths are <= 108 bytes
    work = Path(tempfile.mkdtemp(prefix="midair-sd-", dir="/run"))
    (work / "runtime").mkdir(mode=0o700)
    cgroup = parent / f"midair-test-{os.getpid()}-{work.name}"
    try:
        cgroup.mkdir()
    except OSError as exc:
        shutil.rmtree(work, ignore_errors=True)
        pytest.skip(f"a private systemd manager needs a cgroup of its own: {cgroup}: {exc}")
    log = (work / "manager.log").open("w")
    proc = subprocess.Popen(["/bin/sh", "-c", _PRIVATE_MANAGER, "sh", str(work), str(cgroup), systemd],
                            stdin=subprocess.DEVNULL, stdout=log, stderr=log, start_new_session=True)
    env = {k: v for k, v in os.environ.items() if k != "DBUS_SESSION_BUS_ADDRESS"}
    env["XDG_RUNTIME_DIR"] = str(work / "runtime")
    try:
        t0 = time.monotonic()
        while not ((work / "runtime" / "bus").exists() and _responds(["systemctl", "--user"], env)):
            if proc.poll() is not None or time.monotonic() - t0 > 15:
                pytest.skip("a private systemd user manager did not come up: "
                            + (work / "manager.log").read_text()[-500:])
            time.sleep(0.1)
        yield Manager(["systemd-run", "--user"], env, root=True,
                      what="a private systemd user manager (no systemd as PID 1 here)")
    finally:
        subprocess.run(["systemctl", "--user", "exit"], env=env, capture_output=True, timeout=10)
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            pass
        kill = cgroup / "cgroup.kill"
        if kill.exists():
            with contextlib.suppress(OSError):
                kill.write_text("1")
        if proc.poll() is None:
            proc.kill()
        proc.wait(timeout=10)
        log.close()
        for _ in range(50):  # its cgroups, leaves first, once their processes are gone
            for d in sorted((p for p in cgroup.rglob("*") if p.is_dir()), key=lambda p: -len(p.parts)):
                with contextlib.suppress(OSError):
                    d.rmdir()
            with contextlib.suppress(OSError):
                cgroup.rmdir()
            if not cgroup.exists():
                break
            time.sleep(0.1)
        shutil.rmtree(work, ignore_errors=True)


@pytest.fixture(scope="module")
def manager() -> Iterator[Manager]:
    if shutil.which("systemd-run") is None or shutil.which("systemctl") is None:
        pytest.skip("systemd-run is not installed (apt-get install systemd)")
    env = dict(os.environ)
    if os.geteuid() == 0 and Path("/run/systemd/system").is_dir() and _responds(["systemctl"], env):
        yield Manager(["systemd-run"], env, root=True, what="the system manager")
    elif _responds(["systemctl", "--user"], env):
        yield Manager(["systemd-run", "--user"], env, root=os.geteuid() == 0,
                      what="the user's systemd manager")
    else:
        with _private_manager() as m:
            yield m


def _run(manager: Manager, props: list[str], argv: list[str], timeout: float,
         cwd: Path = ROOT) -> subprocess.CompletedProcess[str]:
    options = [arg for prop in props for arg in ("-p", prop)]
    return subprocess.run(
        manager.argv + ["--pipe", "--wait", "--quiet", "--collect", "--same-dir", *options, *argv],
        cwd=cwd, env=manager.env, capture_output=True, text=True, timeout=timeout)


def _skip_if_the_manager_cannot(manager: Manager, out: subprocess.CompletedProcess[str]) -> None:
    """An unprivileged user manager may be unable to set a sandbox up at all (user namespaces
    disallowed, say): systemd's own exit codes for a failed set-up step are 200 to 243."""
    if not manager.root and 200 <= out.returncode <= 243:
        pytest.skip(f"{manager.what} cannot set up the unit's sandbox here (exit {out.returncode}, "
                    "systemd.exec(5) 'Process Exit Codes'): run the tests as root")


# What the sandbox must show from inside: printed as JSON
_PROBE = r"""
import errno, json, mmap, os, socket
from app.runtime.notify import Notifier
Notifier().ready("probing")  # Type=notify: as midair does
def err(f):
    try:
        f()
        return "ok"
    except OSError as e:
        return errno.errorcode.get(e.errno, str(e.errno))
status = dict(l.split(":", 1) for l in open("/proc/self/status") if ":" in l)
def udp(addr):
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.sendto(b"x", (addr, 9))
proc = [l.split(" - ")[1].split()[2] for l in open("/proc/self/mountinfo") if l.split()[4] == "/proc"]
print(json.dumps({
    "seccomp": status["Seccomp"].strip(), "no_new_privs": status["NoNewPrivs"].strip(),
    "cap_bounding": int(status["CapBnd"], 16),
    "write_execute": err(lambda: mmap.mmap(-1, 4096, prot=mmap.PROT_READ | mmap.PROT_WRITE | mmap.PROT_EXEC)),
    "setaffinity": err(lambda: os.sched_setaffinity(0, os.sched_getaffinity(0))),
    "setuid": err(lambda: os.setuid(os.getuid())),
    "setpriority": err(lambda: os.setpriority(os.PRIO_PROCESS, 0, 19)),
    "cpuinfo": os.path.exists("/proc/cpuinfo"),
    "proc_options": proc[-1] if proc else "",
    "udp_localhost": err(lambda: udp("127.0.0.1")),
    "udp_elsewhere": err(lambda: udp("192.0.2.1")),
}))
"""


def test_the_sandbox_takes_effect(manager: Manager) -> None:
    """The unit's properties, applied by a real systemd, do what they say (none silently
    ignored): no capabilities, the system-call filter, no W+X memory, a pid-only /proc, IP to
    localhost only."""
    out = _run(manager, sandbox_properties(UNIT.read_text()), [sys.executable, "-c", _PROBE], 60)
    _skip_if_the_manager_cannot(manager, out)
    assert out.returncode == 0, f"{manager.what}: {out.stderr}"
    seen = json.loads(out.stdout.strip().splitlines()[-1])
    assert seen["seccomp"] == "2" and seen["no_new_privs"] == "1" and seen["cap_bounding"] == 0, seen
    assert seen["write_execute"] == "EPERM", seen  # MemoryDenyWriteExecute
    assert seen["setaffinity"] == "EPERM" and seen["setuid"] == "EPERM", seen  # ~@resources, ~@privileged
    assert seen["setpriority"] == "ok", seen  # allowed again: the record writer's thread
    assert seen["udp_localhost"] == "ok", seen
    if manager.root:  # an unprivileged user manager can neither attach the IP filter nor mount /proc
        assert seen["udp_elsewhere"] == "EPERM", seen
        assert not seen["cpuinfo"] and "subset=pid" in seen["proc_options"], seen
        assert "hidepid=invisible" in seen["proc_options"], seen


@pytest.mark.timeout(120)
def test_midair_fly_runs_under_the_sandbox(manager: Manager) -> None:
    """`midair fly` under every sandboxing property of the unit (MemoryDenyWriteExecute with
    numpy, OpenCV and MAVSDK's ctypes callbacks, the system-call filter, the IP allow-list),
    as Type=notify with the watchdog: it must report ready, process frames and exit 0."""
    from app.sim.px4 import SimPx4, SimState, free_udp_port

    port = free_udp_port()
    sim = SimPx4(port, state=SimState(mode="position")).start()
    try:
        out = _run(manager, sandbox_properties(UNIT.read_text()),
                   [sys.executable, "-m", "app.cli", "fly", "--camera", "synthetic", "--seconds", "8",
                    "--mode", "shadow", "--no-record", "--connection", f"udpin://0.0.0.0:{port}"], 100)
    finally:
        sim.stop()
    _skip_if_the_manager_cannot(manager, out)
    assert out.returncode == 0, f"{manager.what}: exit {out.returncode}\n{out.stderr[-3000:]}"
    summary = json.loads(out.stdout[out.stdout.index("{"):])
    assert summary["frames_processed"] > 100, summary
    assert "Traceback" not in out.stderr, out.stderr


@pytest.mark.timeout(120)
def test_the_realsense_sdk_plays_a_recording_under_the_sandbox(manager: Manager, tmp_path: Path) -> None:
    """The camera's side of the process (librealsense, its libusb backend, the SDK's playback)
    under the unit's sandbox: `midair fly` on a RealSense recording. No D435i here: the device
    nodes themselves are the next test's."""
    pytest.importorskip("pyrealsense2", exc_type=ImportError)
    from app.sim.px4 import SimPx4, SimState, free_udp_port
    from app.sim.synthetic import approach_scene, render
    from hardware.realsense import write_realsense_recording

    scene = approach_scene((-0.4, -0.3, 8.0), frames=90)
    recording = write_realsense_recording((f for f, _ in render(scene)), scene.camera(), scene.fps,
                                          tmp_path / "ball.db3")
    tmp_path.chmod(0o755)
    port = free_udp_port()
    sim = SimPx4(port, state=SimState(mode="position")).start()
    try:  # the recording's folder is bound into the unit's private /tmp
        out = _run(manager, [*sandbox_properties(UNIT.read_text()), f"BindReadOnlyPaths={tmp_path}"],
                   [sys.executable, "-m", "app.cli", "fly", "--camera", str(recording), "--mode", "shadow",
                    "--no-record", "--connection", f"udpin://0.0.0.0:{port}"], 100)
    finally:
        sim.stop()
    _skip_if_the_manager_cannot(manager, out)
    assert out.returncode == 0, f"{manager.what}: exit {out.returncode}\n{out.stderr[-3000:]}"
    summary = json.loads(out.stdout[out.stdout.index("{"):])
    # (the SDK's playback may skip a frame on a loaded machine: 89 of 90 seen here once)
    assert summary["frames_processed"] >= 80 and summary["ended_by"] == "end of recording", summary


def test_the_device_groups_still_open_devices_under_the_sandbox(manager: Manager) -> None:
    """PrivateUsers= maps every group but the service's own to nobody: the supplementary groups
    must still open the devices. A dialout-owned node of the serial driver, opened by an
    unprivileged user with the unit's sandbox: with the group it opens, without it does not."""
    if not manager.root:
        pytest.skip("needs a manager running as root (User=nobody)")
    try:
        import grp

        grp.getgrnam("dialout")
    except KeyError:
        pytest.skip("no dialout group here")
    if not any(line.split()[1:] == ["ttyS"] for line in Path("/proc/devices").read_text().splitlines()):
        pytest.skip("no serial driver (ttyS) here")
    work = Path(tempfile.mkdtemp(prefix="midair-dev-"))
    try:
        work.chmod(0o755)
        node = work / "ttyS0"
        os.mknod(node, 0o660 | stat.S_IFCHR, os.makedev(4, 64))  # the serial driver's ttyS0
        os.chown(node, 0, grp.getgrnam("dialout").gr_gid)
        node.chmod(0o660)  # as the udev rule makes it (mknod applied the umask)
        # a shell is no notify service; the node's folder is bound into the private /tmp
        props = [("Type=exec" if p.startswith("Type=") else p) for p in sandbox_properties(UNIT.read_text())]
        props += [f"BindReadOnlyPaths={work}", "User=nobody"]
        opener = ["/bin/sh", "-c", f'exec 3<>"{node}" && echo opened']
        with_group = _run(manager, props + ["SupplementaryGroups=dialout"], opener, 30, cwd=work)
        without = _run(manager, props, opener, 30, cwd=work)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    assert "PrivateUsers=yes" in props
    assert with_group.returncode == 0 and "opened" in with_group.stdout, with_group.stderr
    assert without.returncode != 0 and "Permission denied" in without.stderr, without.stderr


# ---------------------------------------------------------------------- sd_notify


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
