"""Velocity steps from a hover on a running PX4 SITL: how far the vehicle has moved along a
body-frame command 0.5, 0.75, 1.0 and 1.25 s after it (docs/sitl.md, "Faster commands").

    ../shared/px4-sitl/start.sh ~/px4/build/px4_sitl_lean
    .venv/bin/python tests/sitl_speed.py 3,4.5,6 [TRIALS] [DOWN]

SPEEDS (comma-separated, m/s), TRIALS each (3), DOWN the command's down part as a fraction of
its speed (0: body right). The pilot's link (14550, the ``sitl`` tests' ground station) takes
off to a hover and observes; a MAVSDK offboard link on 14540 commands. Each trial: 4 s of zero,
2 s at the speed, then zero. A development tool: it needs a PX4 build, which CI does not have.
"""

from __future__ import annotations

import asyncio
import math
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))  # the sitl tests' ground station

from test_sitl import GroundStation, bring_to_hover  # noqa: E402

MARKS_S = (0.5, 0.75, 1.0, 1.25)


async def main(speeds: list[float], trials: int, down: float) -> None:
    from mavsdk import ComponentType, Configuration
    from mavsdk.asyncio import Mavsdk
    from mavsdk.asyncio.plugins.offboard import OffboardAsync, VelocityBodyYawspeed

    gcs = GroundStation("udpin://0.0.0.0:14550")
    await gcs.connect()
    await bring_to_hover(gcs)
    mavsdk = Mavsdk(Configuration.create_with_component_type(ComponentType.COMPANION_COMPUTER))
    await mavsdk.add_any_connection("udpin://0.0.0.0:14540")
    system = await mavsdk.first_autopilot(10.0)
    assert system is not None, "no autopilot on 14540"
    off = OffboardAsync(system)
    await off.set_velocity_body(VelocityBodyYawspeed(0, 0, 0, 0))
    await asyncio.sleep(1.0)
    await off.start()
    await asyncio.sleep(3.0)
    side = math.sqrt(1 - down**2)
    for v in speeds:
        for k in range(trials):
            await asyncio.sleep(4.0)
            if gcs.v.mode != "offboard":
                print(f"mode {gcs.v.mode}: offboard again")
                await off.start()
                await asyncio.sleep(2.0)
            t0, yaw = time.monotonic(), gcs.v.samples[-1].yaw_rad
            await off.set_velocity_body(VelocityBodyYawspeed(0, v * side, v * down, 0))
            await asyncio.sleep(2.0)
            await off.set_velocity_body(VelocityBodyYawspeed(0, 0, 0, 0))
            await asyncio.sleep(4.0)
            u = (-math.sin(yaw) * side, math.cos(yaw) * side, down)  # the command's NED unit
            moved, last, at, peak = 0.0, None, {}, 0.0
            for s in (s for s in gcs.v.samples if s.t >= t0 - 0.05):
                a = sum(x * y for x, y in zip(s.vel_ned, u, strict=True))
                if last is not None:
                    moved += 0.5 * (a + last[1]) * (s.t - last[0])
                last = (s.t, a)
                peak = max(peak, a)
                for m in MARKS_S:
                    if m not in at and s.t - t0 >= m:
                        at[m] = moved
            print(f"{v:g} m/s, trial {k}: moved " + ", ".join(f"{at.get(m, math.nan):.2f} m at {m:g} s"
                                                          for m in MARKS_S) + f"; peak {peak:.2f} m/s",
                  flush=True)
    await gcs.close()


if __name__ == "__main__":
    asyncio.run(main([float(x) for x in sys.argv[1].split(",")],
                     int(sys.argv[2]) if len(sys.argv) > 2 else 3,
                     float(sys.argv[3]) if len(sys.argv) > 3 else 0.0))
