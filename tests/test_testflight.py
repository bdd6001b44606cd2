"""The test-flight state machine (paper §5-C), tick by tick."""

from __future__ import annotations

from app.config import FlightConfig
from app.decision.policy import EVADE, NONE, Command
from app.flight.engagement import ZERO, Decision, VehicleState
from app.flight.testflight import TestFlight

DT = 0.05
CFG = FlightConfig(mode="test-flight", test_altitude_m=5.0, forward_speed_mps=2.0,
                   test_max_cruise_s=10.0)


def vs(t: float, mode: str = "hold", *, armed: bool = True, in_air: bool = True,
       alt: float | None = 5.0) -> VehicleState:
    return VehicleState(t, True, armed, in_air, mode, alt, mode_t_s=t)


def to_cruise(tf: TestFlight) -> float:
    tf.request_start()
    out = tf.tick(vs(0.0, "position", armed=False, in_air=False, alt=0.0), None)
    assert out.action == "arm_takeoff" and out.takeoff_altitude_m == 5.0
    assert tf.tick(vs(1.0, "takeoff", alt=2.0), None).setpoint is None  # climbing
    t = 2.0
    tf.tick(vs(t, "hold"), None)
    assert tf.phase == "warmup"
    requested = False
    while not requested:  # zero setpoints for WARMUP_S, then the request
        t += DT
        out = tf.tick(vs(t, "hold"), Decision(Command(NONE), t))
        assert out.setpoint == ZERO
        requested = out.start_offboard
    assert t - 2.0 >= 1.2
    t += DT
    out = tf.tick(vs(t, "offboard"), Decision(Command(NONE), t))
    assert tf.phase == "cruise" and out.setpoint == (2.0, 0.0, 0.0)
    return t


def test_take_off_warm_up_then_fly_forward() -> None:
    to_cruise(TestFlight(CFG, 3.0))


def test_evade_then_hold() -> None:
    tf = TestFlight(CFG, 3.0)
    t = to_cruise(tf)
    t += DT
    out = tf.tick(vs(t, "offboard"), Decision(Command(EVADE, 0.0, -2.0, -2.0, 4, "ball"), t))
    assert tf.phase == "evade" and out.setpoint == (0.0, -2.0, -2.0)
    assert out.status == "midair: evading object 4 up-left"
    outs = []
    for _ in range(15):
        t += DT
        outs.append(tf.tick(vs(t, "offboard"), Decision(Command(NONE), t)))
    leave = next(i for i, o in enumerate(outs) if o.leave_to)
    assert outs[leave].leave_to == "hold" and tf.phase == "hold"
    assert all(o.setpoint == ZERO for o in outs[:leave])  # no more forward flight after it


def test_forward_leg_is_bounded_in_time() -> None:
    tf = TestFlight(CFG, 3.0)
    t0 = t = to_cruise(tf)
    while tf.phase == "cruise":
        t += DT
        out = tf.tick(vs(t, "offboard"), Decision(Command(NONE), t))
    assert out.leave_to == "hold" and 9.9 <= t - t0 <= 10.2


def test_pilot_and_stale_perception_and_land() -> None:
    tf = TestFlight(CFG, 3.0)
    t = to_cruise(tf) + DT
    out = tf.tick(vs(t, "position"), Decision(Command(NONE), t))
    assert tf.phase == "pilot" and out.setpoint == ZERO and not out.start_offboard
    assert tf.tick(vs(t + DT, "position"), Decision(Command(NONE), t)).setpoint is None

    tf2 = TestFlight(CFG, 3.0)
    t = to_cruise(tf2)
    last = Decision(Command(NONE), t)
    outs = []
    for _ in range(30):
        t += DT
        outs.append(tf2.tick(vs(t, "offboard"), last))
    assert outs[3].setpoint == ZERO
    assert any(o.leave_to == "hold" for o in outs)
    tf2.request_land()
    assert tf2.tick(vs(t + DT, "hold"), None).action == "land"


def test_speed_is_clamped() -> None:
    tf = TestFlight(FlightConfig(forward_speed_mps=5.0), 3.0)
    tf.request_start()
    tf.tick(vs(0.0, "position", armed=False, in_air=False, alt=0.0), None)
    t = 2.0
    tf.tick(vs(t, "hold"), None)
    while tf.phase == "warmup":
        t += DT
        tf.tick(vs(t, "offboard" if t > 3.5 else "hold"), Decision(Command(NONE), t))
    out = tf.tick(vs(t + DT, "offboard"), Decision(Command(NONE), t + DT))
    assert out.setpoint == (3.0, 0.0, 0.0)
