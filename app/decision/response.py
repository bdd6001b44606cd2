"""How fast the vehicle gets out of the way: the lateral displacement a velocity command buys
over time, and its inverse, the time a given displacement needs.

Model (along the commanded direction, from rest): nothing for ``dead_time_s``; then the
velocity follows the command as a first-order lag of time constant ``lag_s``, its change
bounded by ``accel_mps2``. The stand-in vehicle (``app.sim.px4``) flies exactly this; its
constants were fitted to PX4 SITL's SIH quadrotor (first response 0.13-0.23 s after a
command, 2 m/s commanded reached 1 m/s after ~0.7 s: ``docs/sitl.md``).
"""

from __future__ import annotations

import bisect
import math
from dataclasses import dataclass, field

STEP_S = 0.005  # integration step, s
HORIZON_S = 6.0  # the table reaches this far, s


@dataclass(frozen=True)
class ResponseModel:
    dead_time_s: float
    lag_s: float
    accel_mps2: float
    speed_mps: float  # the commanded evasion speed, m/s
    _t: list[float] = field(default_factory=list, repr=False, compare=False)
    _x: list[float] = field(default_factory=list, repr=False, compare=False)

    def __post_init__(self) -> None:
        for name in ("dead_time_s", "lag_s", "accel_mps2", "speed_mps"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0) or (name != "dead_time_s" and value == 0):
                raise ValueError(f"response model: {name} = {value}: must be > 0")
        x, v = 0.0, 0.0
        ts, xs = [0.0], [0.0]
        k = 1.0 - math.exp(-STEP_S / self.lag_s)
        lim = self.accel_mps2 * STEP_S
        dead = round(self.dead_time_s / STEP_S)
        for i in range(1, round(HORIZON_S / STEP_S) + 1):
            if i > dead:
                v += max(-lim, min(lim, (self.speed_mps - v) * k))
            x += v * STEP_S
            ts.append(i * STEP_S)
            xs.append(x)
        self._t.extend(ts)
        self._x.extend(xs)

    def displacement_m(self, t_s: float) -> float:
        """How far the vehicle has moved ``t_s`` after the command, m."""
        if t_s <= 0:
            return 0.0
        if t_s >= HORIZON_S:
            return self._x[-1] + self.speed_mps * (t_s - HORIZON_S)
        i = min(int(t_s / STEP_S), len(self._t) - 2)
        f = (t_s - self._t[i]) / STEP_S
        return self._x[i] + f * (self._x[i + 1] - self._x[i])

    def time_to_move_s(self, d_m: float) -> float:
        """How long after the command the vehicle has moved ``d_m``, s."""
        if d_m <= 0:
            return 0.0
        if d_m >= self._x[-1]:
            return HORIZON_S + (d_m - self._x[-1]) / self.speed_mps
        i = bisect.bisect_left(self._x, d_m)
        i = max(1, i)
        x0, x1 = self._x[i - 1], self._x[i]
        f = 0.0 if x1 == x0 else (d_m - x0) / (x1 - x0)
        return self._t[i - 1] + f * STEP_S
