"""The take-over / release state machine, driven tick by tick like the flight adapter does."""

from __future__ import annotations

import math

from app.config import FlightConfig
from app.decision.policy import EVADE, NONE, STOP, Command
from app.flight.engagement import (
    ENGAGED,
    MONITOR,
    REQUESTING,
    ZERO,
    Decision,
    Engagement,
    VehicleState,
)

EVADE_CMD = Command(EVADE, 0.0, 2.0, -2.0, 1, "object 1 at 0.9 m")
CALM = Command(NONE)
DT = 0.05  # control period, s


def vs(t: float, mode: str = "position", *, connected: bool = True, armed: bool = True,
       in_air: bool = True, alt: float | None = 10.0) -> VehicleState:
    return VehicleState(t, connected, armed, in_air, mode, alt, mode_t_s=t)


def engaged(e: Engagement, t: float = 0.0, mode: str = "position") -> float:
    """Bring ``e`` to engaged; return the time."""
    out = e.tick(vs(t, mode), Decision(EVADE_CMD, t))
    assert out.state == REQUESTING and out.start_offboard and out.setpoint == (0.0, 2.0, -2.0)
    t += DT
    out = e.tick(vs(t, "offboard"), Decision(EVADE_CMD, t))
    assert e.state == ENGAGED and out.setpoint == (0.0, 2.0, -2.0)
    return t


def test_takes_over_only_when_armed_airborne_high_enough_and_in_an_allowed_mode() -> None:
    refusals = [
        (vs(0, armed=False), "disarmed"),
        (vs(0, in_air=False), "on the ground"),
        (vs(0, alt=1.0), "below 2 m"),
        (vs(0, alt=None), "altitude unknown"),
        (vs(0, alt=math.nan), "altitude unknown"),
        (vs(0, mode="manual"), "mode manual not allowed"),
        (vs(0, mode="land"), "mode land not allowed"),
        (VehicleState(5.0, True, True, True, "position", 10.0, mode_t_s=2.0), "no recent mode report"),
    ]
    for state, reason in refusals:
        e = Engagement(FlightConfig(), 3.0)
        out = e.tick(state, Decision(EVADE_CMD, state.t_s))
        assert out.state == MONITOR and not out.start_offboard and out.setpoint in (None, ZERO)
        assert out.status is not None and reason in out.status and len(out.status) <= 50
    for mode in ("position", "hold", "mission"):
        assert Engagement(FlightConfig(), 3.0).tick(vs(0, mode), Decision(EVADE_CMD, 0.0)).start_offboard


def test_shadow_mode_never_commands_and_says_what_it_would_do_once() -> None:
    e = Engagement(FlightConfig(mode="shadow"), 3.0)
    outs = [e.tick(vs(k * DT), Decision(EVADE_CMD, k * DT)) for k in range(5)]
    assert all(o.setpoint is None and not o.start_offboard for o in outs)  # not even warm-up
    assert [o.status is not None for o in outs] == [True, False, False, False, False]
    assert "would evade" in (outs[0].status or "")


def test_emergency_stop_streams_zero_and_speed_is_clamped() -> None:
    e = Engagement(FlightConfig(), max_speed_mps=1.0)
    out = e.tick(vs(0), Decision(Command(EVADE, 0.0, 3.0, 4.0, 1), 0.0))
    assert out.setpoint is not None and math.isclose(math.hypot(*out.setpoint), 1.0)
    e2 = Engagement(FlightConfig(), 3.0)
    t = engaged(e2)
    out = e2.tick(vs(t + DT, "offboard"), Decision(Command(STOP, object_id=1), t + DT))
    assert out.setpoint == (0.0, 0.0, 0.0)


def test_release_back_to_mission_or_hold_after_calm() -> None:
    for start_mode, back in (("mission", "mission"), ("position", "hold")):
        e = Engagement(FlightConfig(release_after_s=0.5), 3.0)
        t = engaged(e, mode=start_mode)
        outs = []
        for _ in range(15):
            t += DT
            outs.append(e.tick(vs(t, "offboard"), Decision(CALM, t)))
        first_leave = next(i for i, o in enumerate(outs) if o.leave_to)
        assert outs[first_leave].leave_to == back
        assert 9 <= first_leave <= 11  # about 0.5 s of calm at 20 Hz
        assert all(o.setpoint == (0.0, 0.0, 0.0) for o in outs[:first_leave])
        assert e.state == MONITOR


def test_dead_man_zero_velocity_then_hold_on_stale_decisions() -> None:
    e = Engagement(FlightConfig(max_decision_age_ms=150, stale_release_s=1.0), 3.0)
    t = engaged(e)
    last = Decision(EVADE_CMD, t)  # perception stalls: this decision only ages
    outs = []
    for _ in range(30):
        t += DT
        outs.append(e.tick(vs(t, "offboard"), last))
    assert outs[0].setpoint == (0.0, 2.0, -2.0)  # 50 ms old: still fresh
    assert outs[3].setpoint == (0.0, 0.0, 0.0)  # 200 ms old: zero
    leave = next(i for i, o in enumerate(outs) if o.leave_to)
    assert outs[leave].leave_to == "hold" and "stale" in (outs[leave].status or "")
    assert 20 <= leave <= 25


def test_pilot_mode_change_wins_and_starts_a_cooldown() -> None:
    e = Engagement(FlightConfig(pilot_cooldown_s=10.0), 3.0)
    t = engaged(e)
    out = e.tick(vs(t + DT, "position"), Decision(EVADE_CMD, t + DT))
    assert out.state == MONITOR and out.setpoint is None and not out.start_offboard
    assert "pilot took" in (out.status or "")
    # still threatened, but the pilot has it: no take-over for 10 s (zero keeps the path warm)
    for k in range(2, 150):
        o = e.tick(vs(t + k * DT, "position"), Decision(EVADE_CMD, t + k * DT))
        assert not o.start_offboard and o.setpoint in (None, ZERO)
    later = t + 10.5
    assert e.tick(vs(later, "position"), Decision(EVADE_CMD, later)).start_offboard


def test_refused_offboard_is_asked_again_then_given_up() -> None:
    e = Engagement(FlightConfig(offboard_confirm_s=1.0), 3.0)
    e.tick(vs(0.0), Decision(EVADE_CMD, 0.0))
    outs = [e.tick(vs(k * DT, "position"), Decision(EVADE_CMD, k * DT)) for k in range(1, 30)]
    gave_up = next(i for i, o in enumerate(outs) if o.state == MONITOR)
    assert "refused" in (outs[gave_up].status or "") and 19 <= gave_up <= 21
    assert 3 <= sum(o.start_offboard for o in outs[:gave_up]) <= 4  # every 0.25 s
    # a refusal is not the pilot: after a back-off of offboard_confirm_s it tries again
    t_gave_up = (gave_up + 1) * DT
    t = t_gave_up + 0.5
    assert not e.tick(vs(t, "position"), Decision(EVADE_CMD, t)).start_offboard
    t = t_gave_up + 1.05
    assert e.tick(vs(t, "position"), Decision(EVADE_CMD, t)).start_offboard


def test_link_loss_clears_the_setpoint_and_waits_for_a_fresh_mode_and_decision() -> None:
    e = Engagement(FlightConfig(), 3.0)
    t = engaged(e)
    t_loss = t + DT
    lost = e.tick(vs(t_loss, "offboard", connected=False), Decision(EVADE_CMD, t_loss))
    assert lost.setpoint == (0.0, 0.0, 0.0) and "link lost" in (lost.status or "")
    # link back; the mode in hand was reported before the outage: zero until it is reported anew
    t = t_loss + 0.3
    stale_mode = VehicleState(t, True, True, True, "offboard", 10.0, mode_t_s=t_loss - 0.5)
    assert e.tick(stale_mode, Decision(EVADE_CMD, t)).setpoint == (0.0, 0.0, 0.0)
    # mode re-reported (still Offboard), but the decision in hand predates the reconnection
    t += DT
    assert e.tick(vs(t, "offboard"), Decision(EVADE_CMD, t - 0.33)).setpoint == (0.0, 0.0, 0.0)
    t += DT
    assert e.tick(vs(t, "offboard"), Decision(EVADE_CMD, t)).setpoint == (0.0, 2.0, -2.0)


def test_link_back_with_the_mode_never_reported_leaves_to_hold() -> None:
    e = Engagement(FlightConfig(max_mode_age_s=2.0), 3.0)
    t = engaged(e)
    e.tick(vs(t + DT, "offboard", connected=False), None)
    outs = [e.tick(VehicleState(t + 0.2 + k * DT, True, True, True, "offboard", 10.0, mode_t_s=t),
                   Decision(EVADE_CMD, t + 0.2 + k * DT)) for k in range(60)]
    leave = next(i for i, o in enumerate(outs) if o.leave_to)
    assert outs[leave].leave_to == "hold" and 39 <= leave <= 41
    assert all(o.setpoint == (0.0, 0.0, 0.0) for o in outs[:leave])


def test_link_back_in_another_mode_is_not_taken_back() -> None:
    e = Engagement(FlightConfig(), 3.0)
    t = engaged(e)
    e.tick(vs(t + DT, "offboard", connected=False), Decision(EVADE_CMD, t + DT))
    # first tick back after a short outage (under offboard_loss_s): the old mode, not yet
    # re-reported: zero while waiting for the report
    held = e.tick(VehicleState(t + 0.6, True, True, True, "offboard", 10.0, mode_t_s=t),
                  Decision(EVADE_CMD, t + 0.6))
    assert held.setpoint == (0.0, 0.0, 0.0)
    out = e.tick(vs(t + 0.7, "return"), Decision(EVADE_CMD, t + 0.7))  # the pilot: RTL
    assert out.state == MONITOR and out.setpoint in (None, ZERO) and not out.start_offboard
    assert "hands off" in (out.status or "")
    assert not e.tick(vs(t + 0.8, "position"), Decision(EVADE_CMD, t + 0.8)).start_offboard


def test_guard_mode_keeps_the_offboard_path_warm_only_when_flying() -> None:
    e = Engagement(FlightConfig(), 3.0)
    assert e.tick(vs(0.0), None).setpoint == ZERO
    assert e.tick(vs(0.1, in_air=False), None).setpoint is None
    assert e.tick(vs(0.2, armed=False), None).setpoint is None


def test_landing_while_engaged_hands_off() -> None:
    e = Engagement(FlightConfig(), 3.0)
    t = engaged(e)
    out = e.tick(vs(t + DT, "offboard", in_air=False), Decision(EVADE_CMD, t + DT))
    assert out.state == MONITOR and out.setpoint is None


def test_no_link_yet_is_not_a_lost_link() -> None:
    e = Engagement(FlightConfig(), 3.0)
    out = e.tick(vs(0.0, connected=False), None)
    assert out.status is None and out.setpoint is None
    e.tick(vs(0.1), None)
    assert "link lost" in (e.tick(vs(0.2, connected=False), None).status or "")


def test_the_acknowledged_switch_engages_before_the_mode_is_reported() -> None:
    # PX4 reports its mode in the 1 Hz heartbeat; the COMMAND_ACK of the switch comes at once
    e = Engagement(FlightConfig(), 3.0)
    t = 0.0
    e.tick(vs(t), Decision(EVADE_CMD, t))
    assert e.state == REQUESTING
    reported = -0.4  # the newest heartbeat still says Position, from before the switch
    for k in range(1, 25):  # 1.2 s of ticks, longer than offboard_confirm_s
        t = k * DT
        v = VehicleState(t, True, True, True, "position", 10.0, mode_t_s=reported,
                         offboard_ack_t_s=0.01)
        out = e.tick(v, Decision(EVADE_CMD, t))
        assert e.state == ENGAGED and out.setpoint == (0.0, 2.0, -2.0)  # no "pilot took over"
    # a report newer than the switch that says Position is the pilot: hands off
    v = VehicleState(t + DT, True, True, True, "position", 10.0, mode_t_s=t + DT, offboard_ack_t_s=0.01)
    out = e.tick(v, Decision(EVADE_CMD, t + DT))
    assert e.state == MONITOR and out.setpoint is None and "pilot" in (out.status or "")


def test_a_switch_accepted_after_midair_gave_up_is_handed_back() -> None:
    e = Engagement(FlightConfig(), 3.0)
    e.tick(vs(0.0), Decision(EVADE_CMD, 0.0))
    t = 0.0
    while e.state == REQUESTING:  # no ack, no report: refused after offboard_confirm_s
        t += DT
        out = e.tick(vs(t), Decision(EVADE_CMD, t))
    assert e.state == MONITOR and "refused" in (out.status or "")
    t += DT  # ...but the vehicle did switch, and reports it now
    out = e.tick(vs(t, "offboard"), Decision(CALM, t))
    assert out.leave_to == "hold" and out.setpoint == ZERO and "late" in (out.status or "")


def test_after_a_release_the_stale_offboard_report_is_not_a_late_acceptance() -> None:
    """PX4 reports Offboard until its next heartbeat (1 Hz) after midair has left it: that
    report must not read as a late acceptance (a second offboard stop, a second mission
    start)."""
    e = Engagement(FlightConfig(), 3.0)
    t = engaged(e, mode="mission")
    leaves = []
    for _ in range(40):  # calm for 2 s; the vehicle still reports Offboard (mode_t_s fresh)
        t += DT
        out = e.tick(vs(t, "offboard"), Decision(CALM, t))
        if out.leave_to:
            leaves.append(out.leave_to)
    assert leaves == ["mission"]


def test_a_withheld_take_over_is_said_once_per_object_and_reason() -> None:
    e = Engagement(FlightConfig(), 3.0)
    t = engaged(e)
    e.tick(vs(t + DT, "position"), Decision(EVADE_CMD, t + DT))  # the pilot took it back
    said = []
    for k in range(2, 80):  # 4 s of cooldown with the threat still there, then another object
        t = k * DT
        cmd = EVADE_CMD if k < 60 else Command(EVADE, 0.0, -2.0, -2.0, 2, "object 2")
        out = e.tick(vs(t, "position"), Decision(cmd, t))
        if out.status:
            said.append(out.status)
    assert said == ["midair: evade held: pilot cooldown 10 s", "midair: evade held: pilot cooldown 7 s"]


def test_an_outage_longer_than_the_offboard_loss_time_gives_control_up() -> None:
    """PX4's failsafe acted during the outage and PX4 returns to Offboard by itself on the
    re-sent (zero) setpoint: midair does not read that as its own control; once the report is
    clearly new, it hands the vehicle to Hold, once."""
    e = Engagement(FlightConfig(), 3.0)
    t = engaged(e)
    for _ in range(30):  # 1.5 s without a link
        t += DT
        lost = VehicleState(t, False, True, True, "offboard", 10.0, mode_t_s=t - 2)
        out = e.tick(lost, Decision(EVADE_CMD, t))
        assert out.setpoint in (None, ZERO)
    t += DT
    out = e.tick(vs(t, "offboard"), Decision(EVADE_CMD, t))
    assert e.state == MONITOR and out.status == "midair: link was lost, hands off"
    leaves, moves = [], []
    for _ in range(60):  # 3 s: the vehicle keeps reporting Offboard (PX4 resumed it)
        t += DT
        out = e.tick(vs(t, "offboard"), Decision(EVADE_CMD, t))
        moves += [out.setpoint] if out.setpoint not in (None, ZERO) else []
        if out.leave_to:
            leaves.append((round(t, 2), out.leave_to))
    assert not moves  # the evasion is never resumed
    assert len(leaves) >= 1 and leaves[0][1] == "hold"
    assert leaves[1][0] - leaves[0][0] >= 1.5 if len(leaves) > 1 else True  # not every tick
