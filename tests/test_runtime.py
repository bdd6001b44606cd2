"""The whole process on a desk: a recording as the camera, perception in its worker thread,
the offboard coroutine, MAVSDK, and the PX4-faithful vehicle over UDP — and what happens
when the camera stalls, perception fails, or systemd sends SIGTERM mid-evasion."""

from __future__ import annotations

import asyncio
import json
import math
import signal
import socket
import subprocess
import sys
import threading
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest

pytest.importorskip("mavsdk")
pytest.importorskip("pymavlink")

from app.cli import main  # noqa: E402
from app.config import Config, RecordConfig  # noqa: E402
from app.perception.pipeline import Perception  # noqa: E402
from app.runtime.notify import Notifier  # noqa: E402
from app.runtime.process import LatestSlot, fly  # noqa: E402
from app.runtime.record import FlightRecord  # noqa: E402
from app.runtime.sources import open_source  # noqa: E402
from app.sim.px4 import SimPx4, SimState  # noqa: E402
from app.sim.synthetic import ball_scene, render, write_recording  # noqa: E402
from tests.conftest import free_udp_port, vehicle, wait_for  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
# 1.2 s of quiet sky first (the offboard path warms up), then a ball from the upper left;
# the first evasion comes at frame ~90 (3 s)
BALL = ball_scene()


def flying(v: Any) -> bool:
    return bool(v.armed and v.in_air and v.mode == "position" and v.altitude_m)


def evasions(sim: SimPx4, after: float = 0.0) -> list[tuple[float, float, float]]:
    return [r.velocity_body for r in sim.received
            if r.t >= after and r.velocity_body and r.velocity_body != (0.0, 0.0, 0.0)]


def jsonl(path: Path) -> list[dict[str, Any]]:
    return [json.loads(line) for line in path.read_text().splitlines()]


@pytest.fixture(scope="module")
def ball(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_recording(BALL, tmp_path_factory.mktemp("ball") / "rec")


@pytest.mark.asyncio
@pytest.mark.timeout(90)
async def test_approaching_ball_makes_the_vehicle_evade_and_the_record_replays(
        ball: Path, tmp_path: Path) -> None:
    notify = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    notify.bind(str(tmp_path / "notify.sock"))
    notify.settimeout(0.2)
    messages: list[str] = []

    def listen() -> None:  # as systemd does, all the time
        while not notify._closed:  # type: ignore[attr-defined]
            try:
                messages.append(notify.recv(256).decode())
            except (TimeoutError, OSError):
                pass

    listener = threading.Thread(target=listen, daemon=True)
    listener.start()
    notifier = Notifier({"NOTIFY_SOCKET": str(tmp_path / "notify.sock"), "WATCHDOG_USEC": "400000"})
    source = open_source(ball)
    record = FlightRecord(replace(RecordConfig(), dir=str(tmp_path / "records"), frames="color+depth"),
                          Config(), source.camera).start()
    async with vehicle(SimState(mode="position"), flying) as (sim, link):
        stats = await fly(Config(), source, link, install_signals=False, record=record,
                          notifier=notifier)
    record.close(stats.summary())
    assert stats.frames_in == 110 and stats.frames_processed >= 100 and stats.ended_by == "end of recording"
    assert any(m == "offboard" for _, m, _ in sim.mode_log)
    moves = evasions(sim)
    # away from where it passes (upper left): right and/or down, never up or left
    assert moves and all(v[1] >= 0 and v[2] >= 0 and v[1] + v[2] > 0 for v in moves)
    assert sim.mode == "hold"  # handed back after the ball passed / at the end
    # latency accounted per frame, capture -> perceived -> decided -> setpoint on its way
    s = stats.summary()
    assert 0 < s["capture_to_perceived_median_ms"] <= s["capture_to_decision_median_ms"]  # type: ignore[operator]
    assert s["capture_to_decision_median_ms"] <= s["capture_to_setpoint_median_ms"]  # type: ignore[operator]
    # systemd heard READY and the perception loop's watchdog kicks (every 0.1 s here)
    notify.close()
    listener.join(timeout=2)
    assert messages[0].startswith("READY=1") and messages.count("WATCHDOG=1") >= 10
    # the record: shared-clock logs and a recording folder that replays to the same tracks
    kinds = [e["event"] for e in jsonl(record.folder / "events.jsonl")]
    assert kinds[0] == "start" and "command" in kinds and kinds[-1] == "end"
    decisions = jsonl(record.folder / "decisions.jsonl")
    assert any(d["action"] == "evade" for d in decisions)
    assert jsonl(record.folder / "latency.jsonl") and jsonl(record.folder / "telemetry.jsonl")
    # the attitude the decision derotates by is in the record (the stand-in hovers level)
    assert any(t["attitude_rad"] == [0.0, 0.0, 0.0] for t in jsonl(record.folder / "telemetry.jsonl"))
    out = tmp_path / "replayed"
    assert main(["replay", str(record.folder), "--out", str(out), "--no-video"]) == 0
    recorded = (record.folder / "tracks.csv").read_text()
    assert recorded.count("\n") > 20
    assert (out / "tracks.csv").read_text() == recorded


@pytest.mark.asyncio
@pytest.mark.timeout(90)
@pytest.mark.parametrize(("mount", "carried"), [("body", True), ("gimbal", True), ("body", False)])
async def test_the_vehicles_turns_reach_the_decision_as_the_cameras_rotation(
        ball: Path, mount: str, carried: bool, monkeypatch: pytest.MonkeyPatch) -> None:
    # the stand-in rocks its reported roll by 0.2 rad every 0.1 s: a camera fixed to the body
    # turns with it and the decision is handed that turn, frame to frame; one a gimbal holds
    # level is not (its yaw does not change); a recording played as the camera is not the
    # vehicle's camera, and gets neither the turns nor the velocity
    from app.decision.policy import DecisionMaker

    turns: list[np.ndarray | None] = []
    egos: list[object] = []
    step = DecisionMaker.step

    def spy(self: DecisionMaker, *args: Any, **kwargs: Any) -> Any:
        turns.append(kwargs.get("derotation"))
        egos.append(kwargs.get("ego"))
        return step(self, *args, **kwargs)

    monkeypatch.setattr(DecisionMaker, "step", spy)
    cfg = replace(Config(), decision=replace(Config().decision, camera_mount=mount))
    async with vehicle(SimState(mode="position"), flying) as (sim, link):
        async def rock() -> None:
            while True:
                sim.state.roll_rad = 0.2 - sim.state.roll_rad
                await asyncio.sleep(0.1)

        rocking = asyncio.create_task(rock())
        source = open_source(ball)
        source.carried = carried  # played as if it were the vehicle's own D435i
        try:
            await fly(cfg, source, link, install_signals=False)
        finally:
            rocking.cancel()
    given = [t for t in turns if t is not None]
    if not carried:
        assert len(turns) > 50 and not given and not any(egos)
        return
    assert sum(e is not None for e in egos) >= 0.8 * len(egos)
    assert len(given) >= 0.8 * len(turns) > 50  # the attitude is fresh for nearly every frame
    # how far each turn moves the principal point, px
    moved = [float(np.hypot(*((t @ np.array([320.0, 240.0, 1.0]))[:2] / (t @ np.array([320.0, 240.0, 1.0]))[2]
                              - np.array([320.0, 240.0])))) for t in given]
    corner = [float(np.hypot(*((t @ np.array([0.0, 0.0, 1.0]))[:2] / (t @ np.array([0.0, 0.0, 1.0]))[2])))
              for t in given]
    if mount == "body":
        # a roll of 0.2 rad turns the image about its centre: a corner moves by ~0.2 x 400 px
        assert sum(c > 40.0 for c in corner) >= 10
    else:
        assert max(corner) < 1e-6 and max(moved) < 1e-6


@pytest.mark.asyncio
@pytest.mark.timeout(120)
async def test_camera_stall_mid_evasion_holds_then_recovers(tmp_path: Path) -> None:
    rs = pytest.importorskip("pyrealsense2")
    del rs
    from hardware.realsense import RealSenseSource, write_realsense_recording

    path = write_realsense_recording((f for f, _ in render(BALL)), BALL.camera(), BALL.fps,
                                     tmp_path / "ball.db3")
    cfg = replace(Config(), capture=replace(Config().capture, frame_timeout_ms=1000.0))
    source = RealSenseSource(cfg.capture, path)
    record = FlightRecord(replace(RecordConfig(), dir=str(tmp_path / "records"), frames="none")).start()
    stall: dict[str, float] = {}

    async def stall_at_first_evasion(sim: SimPx4) -> None:
        await wait_for(lambda: bool(evasions(sim)), timeout=30)
        source.playback.pause()  # the USB link stops delivering, mid-evasion
        stall["t"] = time.monotonic()

    async with vehicle(SimState(mode="position"), flying) as (sim, link):
        watcher = asyncio.create_task(stall_at_first_evasion(sim))
        stats = await fly(cfg, source, link, install_signals=False, record=record)
        await watcher
    record.close(stats.summary())
    t_stall = stall["t"]
    events = jsonl(record.folder / "events.jsonl")
    resumed = next(e for e in events if e["event"] == "camera_resumed")
    t_resumed = record.t0 + float(resumed["t"])
    assert stats.camera_stalls == 1 and source.restarts == 1
    assert any(e["event"] == "camera_stall" for e in events)
    assert t_resumed - t_stall >= 1.0
    # dead-man: stale decisions give zero velocity within max_decision_age_ms (+ a tick),
    # then the vehicle is left in Hold, while the camera is silent
    # (frames already in the SDK's queue at the pause still arrive: the stall starts at the last)
    stalled = next(e for e in events if e["event"] == "camera_stall")
    t_last = record.t0 + float(stalled["since_s"])
    assert t_last >= t_stall - 0.05
    during = [r.velocity_body for r in sim.received if t_last + 0.15 + 0.1 <= r.t <= t_resumed]
    assert during and all(v in (None, (0.0, 0.0, 0.0)) for v in during)
    assert any(m == "hold" and t_last < t < t_resumed + 0.2 for t, m, _ in sim.mode_log)
    # recovery: the pipeline restarted, frames flowed again and were processed
    assert stats.frames_in > 150 and stats.frames_processed > 150
    # frames were not saved, the tracks still were (every processed frame, with its capture time)
    tracks = jsonl(record.folder / "tracks.jsonl")
    assert len(tracks) > 150 and any(t["tracks"] for t in tracks)
    assert not (record.folder / "tracks.csv").exists()
    assert sim.mode == "hold"


def test_perception_error_stops_control_first_and_exits_1(
        ball: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    push = Perception.push

    def failing(self: Perception, frame: Any) -> Any:
        if frame.index == 95:  # mid-evasion
            raise RuntimeError("injected fault in perception")
        return push(self, frame)

    monkeypatch.setattr(Perception, "push", failing)
    port = free_udp_port()
    sim = SimPx4(port, state=SimState(mode="position")).start()
    try:
        code = main(["fly", "--camera", str(ball), "--connection", f"udpin://0.0.0.0:{port}",
                     "--record", str(tmp_path / "records")])
        time.sleep(0.3)
    finally:
        sim.stop()
    assert code == 1
    assert evasions(sim), "the fault came before any evasion"
    last = [r.velocity_body for r in sim.received if r.velocity_body is not None][-1]
    assert last == (0.0, 0.0, 0.0) and sim.mode == "hold"  # zero, then Offboard left
    run = next((tmp_path / "records").iterdir())
    errors = [e for e in jsonl(run / "events.jsonl") if e["event"] == "error"]
    assert errors and "injected fault" in errors[0]["error"]
    assert "injected fault" in json.loads((run / "summary.json").read_text())["ended_by"]


@pytest.mark.timeout(90)
def test_sigterm_during_an_evasion_zeroes_leaves_offboard_and_exits_0(ball: Path, tmp_path: Path) -> None:
    port = free_udp_port()
    sim = SimPx4(port, state=SimState(mode="position")).start()
    proc = subprocess.Popen(
        [sys.executable, "-m", "app.cli", "fly", "--camera", str(ball),
         "--connection", f"udpin://0.0.0.0:{port}", "--record", str(tmp_path / "records")],
        cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        t0 = time.monotonic()
        while not evasions(sim) and time.monotonic() - t0 < 60 and proc.poll() is None:
            time.sleep(0.01)
        assert evasions(sim), "no evasion before the end"
        t_term = time.monotonic()
        proc.send_signal(signal.SIGTERM)
        _out, err = proc.communicate(timeout=20)
        t_exit = time.monotonic()
        time.sleep(0.3)
    finally:
        if proc.poll() is None:
            proc.kill()
        sim.stop()
    assert proc.returncode == 0, err
    assert "Traceback" not in err
    assert t_exit - t_term < 8.0
    last = [r for r in sim.received if r.velocity_body is not None][-1]
    assert last.t > t_term and last.velocity_body == (0.0, 0.0, 0.0)  # zero, sent after SIGTERM
    holds = [t for t, m, _ in sim.mode_log if m == "hold" and t > t_term]
    assert holds and holds[0] - t_term < 2.0 and sim.mode == "hold"
    run = next((tmp_path / "records").iterdir())
    kinds = [e["event"] for e in jsonl(run / "events.jsonl")]
    assert "signal" in kinds
    assert json.loads((run / "summary.json").read_text())["ended_by"] == "SIGTERM"


def test_latest_slot_keeps_only_the_newest() -> None:
    async def go() -> None:
        slot: LatestSlot[int] = LatestSlot()
        for i in range(5):
            slot.put(i)
        assert slot.get() == 4 and slot.version == 5 and slot.event.is_set()

    asyncio.run(go())


def test_fly_with_an_unreachable_autopilot_exits_4(ball: Path, tmp_path: Path) -> None:
    proc = subprocess.run(
        [sys.executable, "-m", "app.cli", "fly", "--camera", str(ball), "--connection",
         f"udpin://0.0.0.0:{free_udp_port()}", "--record", str(tmp_path / "records"),
         "--config", str(Path(__file__).parent / "_short_timeout.yaml")],
        capture_output=True, text=True, timeout=60)
    assert proc.returncode == 4
    assert "no autopilot answered" in proc.stderr and "Traceback" not in proc.stderr
    run = next((tmp_path / "records").iterdir())
    assert "no autopilot answered" in json.loads((run / "summary.json").read_text())["ended_by"]


def test_fly_with_a_missing_camera_file_exits_3(tmp_path: Path) -> None:
    proc = subprocess.run(
        [sys.executable, "-m", "app.cli", "fly", "--camera", str(tmp_path / "nope.db3"), "--no-record"],
        capture_output=True, text=True, timeout=60)
    assert proc.returncode == 3
    assert "nope.db3: no such file or folder" in proc.stderr and "Traceback" not in proc.stderr


def test_an_unwritable_record_folder_does_not_keep_the_guard_on_the_ground(tmp_path: Path) -> None:
    blocker = tmp_path / "records"
    blocker.write_text("a file where the record folder should be")
    proc = subprocess.run(
        [sys.executable, "-m", "app.cli", "fly", "--camera", "synthetic", "--connection",
         f"udpin://0.0.0.0:{free_udp_port()}", "--record", str(blocker),
         "--config", str(Path(__file__).parent / "_short_timeout.yaml")],
        capture_output=True, text=True, timeout=60)
    assert "flight record disabled" in proc.stderr and str(blocker) in proc.stderr
    assert proc.returncode == 4  # it went on to the autopilot (none here), not stopped by the disk


class _Jittery:
    """A recording whose frames arrive with scheduling jitter (0-20 ms, seeded): the
    frames themselves, and their own times, are those of the recording."""

    def __init__(self, path: Path, seed: int) -> None:
        self.inner = open_source(path)
        self.rng = np.random.default_rng(seed)
        for name in ("name", "fps", "has_depth", "camera", "live"):
            setattr(self, name, getattr(self.inner, name))

    def __len__(self) -> int:
        return len(self.inner)

    def __iter__(self) -> Any:
        for frame in self.inner:
            time.sleep(float(self.rng.uniform(0.0, 0.02)))
            yield frame

    def close(self) -> None:
        self.inner.close()


@pytest.mark.asyncio
@pytest.mark.timeout(120)
async def test_a_recording_played_twice_as_the_camera_gives_the_same_tracks_and_decisions(
        ball: Path, tmp_path: Path) -> None:
    """Perception runs on the recording's own frame times and sees every frame, whatever
    the playback's timing: two playbacks with different jitter agree frame for frame."""
    runs = []
    for seed in (1, 2):
        record = FlightRecord(replace(RecordConfig(), dir=str(tmp_path / f"r{seed}"), frames="none"),
                              Config()).start()
        async with vehicle(SimState(mode="position"), flying) as (sim, link):
            stats = await fly(Config(), _Jittery(ball, seed), link,  # type: ignore[arg-type]
                              install_signals=False, record=record)
        record.close(stats.summary())
        assert stats.frames_dropped == 0 and stats.frames_in == 110
        tracks = [(r["frame"], r["tracks"]) for r in jsonl(record.folder / "tracks.jsonl")]
        decided = [(d["frame"], d["action"], d["velocity_frd_mps"], d["objects"])
                   for d in jsonl(record.folder / "decisions.jsonl")]
        runs.append((tracks, decided))
    assert len(runs[0][1]) >= 100 and any(a == "evade" for _, a, _, _ in runs[0][1])
    assert runs[0] == runs[1]


def test_the_synthetic_camera_throws_balls_until_stopped() -> None:
    from app.sim.synthetic import ThrowsSource

    source = ThrowsSource(seed=3)
    source.CHUNK_FRAMES = 40  # cross chunk boundaries often
    frames = []
    for frame in source:
        frames.append((frame.index, frame.t_s, int(frame.color.mean())))
        if len(frames) == 30 * 25:  # 25 s of an endless source
            break
    assert [f[0] for f in frames] == list(range(1, 751))
    assert np.allclose(np.diff([f[1] for f in frames]), 1 / 30)
    assert len(source.throws) >= 3  # one every few seconds
    for ob in source.throws:  # each aimed to pass within 0.5 m of the camera
        fly_s = ob.start_xyz_m[2] / -ob.velocity_mps[2]
        miss = [p + v * fly_s for p, v in zip(ob.start_xyz_m[:2], ob.velocity_mps[:2], strict=True)]
        assert math.hypot(*miss) <= 0.5 * math.sqrt(2) + 1e-9
    with pytest.raises(ValueError, match="seconds = 0: must be > 0"):
        ThrowsSource(seconds=0)


def test_fly_synthetic_runs_until_its_seconds_are_up(tmp_path: Path) -> None:
    port = free_udp_port()
    sim = SimPx4(port, state=SimState(mode="position")).start()
    try:
        t0 = time.monotonic()
        proc = subprocess.run(
            [sys.executable, "-m", "app.cli", "fly", "--camera", "synthetic", "--mode", "shadow",
             "--connection", f"udpin://0.0.0.0:{port}", "--seconds", "9", "--no-record"],
            capture_output=True, text=True, timeout=90)
        took = time.monotonic() - t0
    finally:
        sim.stop()
    assert proc.returncode == 0, proc.stderr[-2000:]
    summary = json.loads(proc.stdout[proc.stdout.index("{"):])
    assert summary["ended_by"] == "9 s up" and took >= 9
    assert summary["frames_in"] >= 200
    assert any(t.startswith("midair shadow: would evade") for t in sim.status_texts), sim.status_texts
    assert all(m != "offboard" for _, m, _ in sim.mode_log)  # shadow never commands
