"""The whole process on a desk: a recording as the camera, perception in its worker thread,
the offboard coroutine, MAVSDK, and the PX4-faithful vehicle over UDP."""

from __future__ import annotations

import asyncio
import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("mavsdk")
pytest.importorskip("pymavlink")

from app.config import Config  # noqa: E402
from app.runtime import LatestSlot, fly  # noqa: E402
from app.sources import open_source  # noqa: E402
from app.synthetic import approach_scene, write_recording  # noqa: E402
from hardware.sim_px4 import SimState  # noqa: E402
from tests.conftest import free_udp_port, vehicle  # noqa: E402


@pytest.fixture(scope="module")
def ball(tmp_path_factory: pytest.TempPathFactory) -> Path:
    # 1.2 s of quiet sky first (the offboard path warms up), then a ball from the upper left
    return write_recording(approach_scene((-0.4, -0.3, 12.8), closing_mps=4.0, frames=110),
                           tmp_path_factory.mktemp("ball") / "rec")


@pytest.mark.asyncio
@pytest.mark.timeout(90)
async def test_approaching_ball_makes_the_vehicle_evade(ball: Path) -> None:
    flying = lambda v: v.armed and v.in_air and v.mode == "position" and v.altitude_m  # noqa: E731
    async with vehicle(SimState(mode="position"), flying) as (sim, link):
        stats = await fly(Config(), open_source(ball), link, install_signals=False)
    assert stats.frames_in == 110 and stats.frames_processed >= 100
    assert any(m == "offboard" for _, m, _ in sim.mode_log)
    evasions = [r.velocity_body for r in sim.received
                if r.velocity_body and r.velocity_body != (0.0, 0.0, 0.0)]
    assert evasions and all(v[1] > 0 and v[2] > 0 for v in evasions)  # down-right, away from it
    assert sim.mode == "hold"  # handed back after the ball passed / at the end
    s = stats.summary()
    assert s["capture_to_decision_median_ms"] > 0


def test_latest_slot_keeps_only_the_newest() -> None:
    async def go() -> None:
        slot: LatestSlot[int] = LatestSlot()
        for i in range(5):
            slot.put(i)
        assert slot.get() == 4 and slot.version == 5 and slot.event.is_set()

    asyncio.run(go())


def test_fly_with_an_unreachable_autopilot_exits_4(ball: Path) -> None:
    proc = subprocess.run(
        [sys.executable, "-m", "app.cli", "fly", "--camera", str(ball), "--connection",
         f"udpin://0.0.0.0:{free_udp_port()}",
         "--config", str(Path(__file__).parent / "_short_timeout.yaml")],
        capture_output=True, text=True, timeout=60)
    assert proc.returncode == 4
    assert "no autopilot answered" in proc.stderr and "Traceback" not in proc.stderr
