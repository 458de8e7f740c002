"""The ZLAC706 drivers, by plain calls (what each op's frames do in the authority's eyes:
``tests/test_frame_effects.py``): what an order rule says when it refuses, a power-up
forgetting the power stage, and an answer clearing the count of writes gone unanswered."""

from __future__ import annotations

import math
import re

import pytest

from busgate.codecs import zlac706_can as can_codec
from busgate.codecs.zlac706_common import AlarmFlags
from busgate.errors import CommandError, DeviceRefusedError, RefusedError
from busgate.gateway.api.commands import _kind_command
from busgate.gateway.drivers.base import OFFLINE_AFTER
from busgate.gateway.drivers.zlac706_can import Zlac706CanDriver
from busgate.gateway.drivers.zlac706_rs232 import Zlac706Rs232Driver
from busgate.gateway.drivers.zlac706_state import REBOOT_POSITION_JUMP
from busgate.gateway.scheduler.tickers import commanded
from busgate.schemas import zlac706
from busgate.schemas.api import JointCommand
from busgate.schemas.joints import Joint, JointTable
from tests.test_driver_zlac706 import (
    MANUAL_MONITOR,
    event_types,
    plan,
    rs_events,
    run,
)


def refusal(driver, text: str) -> str:
    with pytest.raises(CommandError) as refused:
        plan(driver, text)
    return str(refused.value)


def follow_refusal(driver, payload: dict) -> str:
    """Why ``driver`` refuses the follow target ``payload``."""
    with pytest.raises(CommandError) as refused:
        driver.follow_target(payload)
    return str(refused.value)


def test_an_order_rule_says_what_the_write_needs_and_where_the_motor_is() -> None:
    driver = Zlac706CanDriver("w", 1)
    assert refusal(driver, '{"op":"velocity","rpm":10}') == (
        "a speed target (velocity) needs velocity mode (set_mode velocity first): its mode "
        "is not known, and the device would ignore it")
    assert refusal(driver, '{"op":"move","position":10}') == (
        "a position target (move) needs position mode (set_mode position first): its mode "
        "is not known, and the device would ignore it")
    run(driver, plan(driver, '{"op":"set_mode","mode":"torque"}'))
    assert refusal(driver, '{"op":"move","position":10}') == (
        "a position target (move) needs position mode (set_mode position first): the motor "
        "is in torque mode, and the device would ignore it")
    run(driver, plan(driver, '{"op":"set_mode","mode":"position"}'))
    assert refusal(driver, '{"op":"move","position":10}') == (
        "move before enable: in position mode the ZLAC706 silently ignores a target sent "
        "before the motor is enabled; send enable first")
    run(driver, plan(driver, '{"op":"enable"}'))
    assert refusal(driver, '{"op":"set_mode","mode":"velocity"}') == (
        "set_mode velocity while the motor is enabled: disable first (the mode is chosen "
        "before enable)")


def test_a_power_up_forgets_the_power_stage_and_the_speed_sent() -> None:
    driver = Zlac706CanDriver("w", 1, heartbeat_ms=10)
    for text in ('{"op":"set_mode","mode":"velocity"}', '{"op":"enable"}',
                 '{"op":"velocity","rpm":100}'):
        run(driver, plan(driver, text))
    assert driver.keepalive(0.0) is not None
    driver.take_position(100_000, 0.0)
    driver.take_position(0, 0.0)  # the counter back at 0 from far away: the drive powered up
    assert driver.telemetry(0.0)["enabled"] is False
    assert driver.commanded_speed_raw == 0 and driver.keepalive(0.0) is None


def test_a_relative_move_leaves_no_place_for_a_stream_to_start_from_but_where_it_is() -> None:
    """A relative target is a step, not a place: after one, back in absolute mode, a stream
    starts from the position measured. An outside audit saw the step (500) taken for the
    target, and a stream "to where it already is" (4500) swing the wheel back towards 500."""
    driver = Zlac706CanDriver("w", 1)
    for text in ('{"op":"set_mode","mode":"position"}',
                 '{"op":"set_position_mode","relative":false}', '{"op":"enable"}',
                 '{"op":"move","position":4000}', '{"op":"set_position_mode","relative":true}',
                 '{"op":"move","position":500}'):
        run(driver, plan(driver, text))
    assert driver.telemetry(0.0)["target"] is None
    driver.take_position(4500, 0.0)
    run(driver, plan(driver, '{"op":"set_position_mode","relative":false}'))
    assert driver.follows == "position" and commanded(driver, 0.0) == 4500


def test_the_joint_op_moves_to_a_place_and_is_refused_while_positions_are_steps() -> None:
    """``{"op":"joint","position":x}`` names a place: in relative position mode, or one not
    known, the target would be a step from where the wheel is (an outside audit saw 0.5 rad
    asked and 1.1 rad reached). Refused, naming the mode and what to send."""
    table = JointTable(type="position", unit="rad", scale=2 * math.pi / 10_000)
    driver = Zlac706CanDriver("w", 1, joint=Joint.of("axle", zlac706.JOINT, table))
    command = JointCommand(op="joint", position=0.5)
    for text in ('{"op":"set_mode","mode":"position"}', '{"op":"enable"}'):
        run(driver, plan(driver, text))
    with pytest.raises(RefusedError, match="w's position mode is not known"):
        _kind_command(driver, command)
    run(driver, plan(driver, '{"op":"set_position_mode","relative":true}'))
    with pytest.raises(RefusedError, match=re.escape(
            'joint axle moves to places: w\'s position mode is relative: a target would be a '
            'step from where it is; send {"op":"set_position_mode","relative":false} first')):
        _kind_command(driver, command)
    run(driver, plan(driver, '{"op":"set_position_mode","relative":false}'))
    assert _kind_command(driver, command)["position"] == 796  # 0.5 rad


def test_a_joint_held_within_limits_takes_no_speed_stream() -> None:
    """A position joint with min and max, its drive in velocity mode: a stream of speeds would
    turn it past them (an outside audit saw a wheel held within 3 rad reach 21 rad)."""
    table = JointTable(type="position", unit="rad", scale=2 * math.pi / 10_000, min=-3, max=3)
    driver = Zlac706CanDriver("w", 1, joint=Joint.of("axle", zlac706.JOINT, table))
    run(driver, plan(driver, '{"op":"set_mode","mode":"velocity"}'))
    with pytest.raises(RefusedError, match="position the gateway cannot know"):
        driver.follow_target({"rpm": 10})
    unlimited = Zlac706CanDriver("w", 1)
    run(unlimited, plan(unlimited, '{"op":"set_mode","mode":"velocity"}'))
    assert unlimited.follow_target({"rpm": 10}) == 10.0


@pytest.mark.parametrize("driver_class", [Zlac706CanDriver, Zlac706Rs232Driver])
def test_a_drive_back_from_offline_gets_0_rpm_never_its_old_speed(driver_class) -> None:
    """Turning when it went offline (its bus went down, or its heartbeats stopped): once back,
    the keep-alive repeats 0 rpm, and what is restored ends with 0 rpm. An outside audit saw
    the wheels of a base take their old speed up again after a CAN adapter's dropout, kept
    alive with nothing commanding them."""
    driver = driver_class("w", 1)
    for text in ('{"op":"set_mode","mode":"velocity"}', '{"op":"enable"}',
                 '{"op":"velocity","rpm":100}'):
        run(driver, plan(driver, text))
    driver.went_offline("bus down")
    driver.heard(1.0)  # back, as the first answer after the bus reopened says
    assert driver.restore_pending and driver.commanded_speed_raw == 0
    stop = [request.frame for request in driver.stale_stream()]
    assert stop and [request.frame for request in driver.restore()][-len(stop):] == stop
    kept_alive = driver.keepalive(1.0)
    assert kept_alive is not None  # the drive still has the old speed preset: a stop is due
    if driver_class is Zlac706CanDriver:  # CAN's keep-alive is the speed write itself
        assert kept_alive[1].frame == stop[0]
    run(driver, driver.restore())  # the stop went: a later restore has none to send
    assert [request.frame for request in driver.restore()][-len(stop):] != stop
    idle = driver_class("w", 1)  # never commanded to turn: restored with nothing more
    run(idle, plan(idle, '{"op":"set_mode","mode":"velocity"}'))
    idle.went_offline("bus down")
    idle.heard(1.0)
    assert [request.frame for request in idle.restore()] == [
        request.frame for request in idle.applied_settings.values()]


@pytest.mark.parametrize("driver_class", [Zlac706CanDriver, Zlac706Rs232Driver])
def test_a_speed_a_client_sends_once_the_drive_is_back_is_not_undone_by_its_restore(
        driver_class) -> None:
    """The restore is built at the device's next poll, after the commands that wait for it
    (``planner`` rule 8): a client that commanded a speed as soon as the drive was back, and
    was answered ok, keeps it. An outside audit saw the restore's 0 rpm stop such a wheel
    (10 runs in 10)."""
    driver = driver_class("w", 1)
    for text in ('{"op":"set_mode","mode":"velocity"}', '{"op":"enable"}',
                 '{"op":"velocity","rpm":100}'):
        run(driver, plan(driver, text))
    driver.went_offline("heartbeats lost")
    driver.heard(1.0)
    run(driver, plan(driver, '{"op":"velocity","rpm":50}'))
    assert driver.restore_pending
    assert [request.frame for request in driver.restore()] == [
        request.frame for request in driver.applied_settings.values()]


@pytest.mark.parametrize("heartbeats", [False, True], ids=["acks-only", "heartbeats"])
def test_an_answer_clears_the_writes_gone_unanswered(heartbeats) -> None:
    driver = Zlac706CanDriver("w", 1, heartbeat_ms=10) if heartbeats else Zlac706CanDriver("w", 1)
    run(driver, plan(driver, '{"op":"set_mode","mode":"velocity"}'), now=1.0)
    if heartbeats:  # they alone bring it online (rule 2)
        driver.unsolicited(can_codec.HeartbeatPosition(1, 5), 1.0)
    assert driver.online
    for moment in range(OFFLINE_AFTER - 1):
        driver.missed(2.0 + moment)
    driver.heard(5.0)
    assert driver.last_reply == 5.0 and driver.online
    for moment in range(OFFLINE_AFTER - 1):
        driver.missed(6.0 + moment)
    assert driver.online  # never OFFLINE_AFTER in a row


def test_telemetry_tells_each_setting_in_its_unit() -> None:
    driver = Zlac706CanDriver("w", 1)
    fresh = driver.telemetry(0.0)
    assert fresh["faults"] == [] and fresh["measured"] is False  # no heartbeats expected
    assert fresh["position_mode"] is None
    assert driver.commanded_speed_raw == 0
    for text in ('{"op":"set_position_mode","relative":false}', '{"op":"set_mode","mode":"torque"}',
                 '{"op":"set_velocity_ramp","accel_ms":500,"decel_ms":300}', '{"op":"enable"}',
                 '{"op":"torque","current_a":1.5}'):
        run(driver, plan(driver, text))
    state = driver.telemetry(0.0)
    assert state["position_mode"] == "absolute"
    assert state["target_current_a"] == pytest.approx(1.5, abs=0.0032)
    assert state["velocity_ramp"] == {"accel_ms": 500, "decel_ms": 300}
    assert Zlac706Rs232Driver("w", 1).telemetry(0.0)["measured"] is True  # its monitor reads


def test_a_heartbeat_and_a_monitor_reply_give_the_current_in_ma() -> None:
    driver = Zlac706CanDriver("w", 1, heartbeat_ms=10)
    driver.unsolicited(can_codec.HeartbeatCurrentSpeed(1, current_raw=2345, speed_raw=0), 1.0)
    assert driver.telemetry(1.0)["current_ma"] == 23450
    rs = Zlac706Rs232Driver("w", 1)
    (request,) = rs.poll()
    rs.apply(request, rs_events(MANUAL_MONITOR.replace("e20011f3", "e2092914")), 0.0)
    assert rs.telemetry(0.0)["current_ma"] == 23450


def test_a_drive_its_monitor_reports_stopped_is_off_whatever_was_enabled_before() -> None:
    driver = Zlac706Rs232Driver("w", 1)
    for text in ('{"op":"set_mode","mode":"position"}', '{"op":"enable"}'):
        run(driver, plan(driver, text))
    (request,) = driver.poll()
    driver.apply(request, rs_events(MANUAL_MONITOR.replace("80000181", "80000080")), 0.0)
    assert driver.telemetry(0.0)["enabled"] is False
    assert "before enable" in refusal(driver, '{"op":"move","position":10}')


def test_a_disable_is_a_switch_off_and_an_enable_lifts_the_estop_latch() -> None:
    driver = Zlac706CanDriver("w", 1)
    for text in ('{"op":"set_mode","mode":"velocity"}', '{"op":"enable"}'):
        run(driver, plan(driver, text))
    driver.safe_stop()
    assert driver.estop_latched is True
    plan(driver, '{"op":"set_velocity_ramp","accel_ms":500,"decel_ms":500}')
    assert driver.estop_latched is True and driver.driving_before_estop is True
    plan(driver, '{"op":"enable"}')
    assert driver.estop_latched is False
    plan(driver, '{"op":"disable"}')
    assert driver.driving_before_estop is False  # a reset that follows leaves it off


def test_a_speed_that_went_is_the_one_kept_alive_before_its_ack_and_not_before_it_went() -> None:
    """A speed still waiting to go is not kept alive (the keep-alive would send it ahead of its
    command, which may yet be taken out unsent); once it went, it is, before its ack."""
    driver = Zlac706CanDriver("w", 1)
    for text in ('{"op":"set_mode","mode":"velocity"}', '{"op":"enable"}'):
        run(driver, plan(driver, text))
    (speed,) = plan(driver, '{"op":"velocity","rpm":100}')
    assert driver.commanded_speed_raw == 0 and driver.keepalive(0.0) is None
    driver.went(speed.frame)
    assert driver.commanded_speed_raw == speed.frame.value != 0
    assert driver.refreshes_keepalive(speed)
    (enable,) = plan(driver, '{"op":"enable"}')
    assert not driver.refreshes_keepalive(enable)


def test_the_settings_restored_after_a_reboot_may_be_repeated() -> None:
    driver = Zlac706CanDriver("w", 1)
    run(driver, plan(driver, '{"op":"set_velocity_ramp","accel_ms":500,"decel_ms":500}'))
    (restore,) = driver.restore()  # nothing commanded to turn: no stop after it
    assert restore.idempotent


def test_a_reboot_is_a_jump_to_zero_of_more_than_the_bound_and_says_from_where() -> None:
    driver = Zlac706CanDriver("w", 1, heartbeat_ms=10)
    driver.take_position(REBOOT_POSITION_JUMP, 0.0)
    driver.take_position(0, 0.0)
    assert event_types(driver) == []
    driver.take_position(-REBOOT_POSITION_JUMP - 1, 0.0)
    driver.take_position(0, 0.0)
    (event,) = driver.drain_events()
    assert event.type == "rebooted"
    far = -REBOOT_POSITION_JUMP - 1
    assert event.fields["evidence"] == f"position counter back at 0 from {far}"


def test_reports_further_apart_allow_a_longer_jump_before_a_zero_is_a_reboot() -> None:
    """An outside wire audit, heartbeats 500 ms apart (the manual's example): a real move home
    at speed, 80,000 pulses in one interval (960 rpm), was taken for a reboot. The bound is
    what the motor turns at its 1000 rpm limit between the two reports, 50 ms more."""
    driver = Zlac706CanDriver("w", 1, heartbeat_ms=500)
    driver.take_position(80_000, 10.0)
    driver.take_position(0, 10.5)
    assert event_types(driver) == []
    driver.take_position(95_000, 11.0)  # past 1000 rpm over 0.55 s (91,667): no motion
    driver.take_position(0, 11.5)
    (event,) = driver.drain_events()
    assert event.type == "rebooted"


def test_a_late_echo_is_no_news_and_an_alarm_report_begins_no_reading() -> None:
    driver = Zlac706CanDriver("w", 1, heartbeat_ms=10)
    echo = can_codec.WriteAck(1, can_codec.CanRegister.TARGET_SPEED, 0)
    assert driver.unsolicited(echo, 1.0) is False
    assert driver.begins_reading(can_codec.HeartbeatPosition(1, 5))
    alarm = can_codec.AlarmReport(1, AlarmFlags(0x02))
    assert not driver.begins_reading(alarm)  # news at once, not the start of a heartbeat


def test_refusals_of_what_a_protocol_cannot_do_say_why() -> None:
    can_driver, rs = Zlac706CanDriver("w", 1), Zlac706Rs232Driver("w", 1)
    assert refusal(can_driver, '{"op":"monitor"}') == (
        "monitor is an RS232 request; on CAN the driver's heartbeat reports position, current "
        "and speed (enable it with the vendor tool)")
    assert refusal(can_driver, '{"op":"write","register":250,"value":1}') == (
        "register 0xfa is not in the ZLAC706 CAN table")
    assert "is not a writable ZLAC706 RS232 register" in refusal(
        rs, '{"op":"write","register":250,"value":1}')
    for command in ('{"op":"set_mode","mode":"position"}', '{"op":"enable"}'):
        run(rs, plan(rs, command))
        run(can_driver, plan(can_driver, command))
    assert follow_refusal(rs, {"position": 5}) == (
        "a ZLAC706 on RS232 takes a position in two frames, so its follow stream carries "
        'speeds only ({"rpm": R}); send positions as move commands')
    assert follow_refusal(can_driver, {"position": 5}) == (
        "a position follow stream needs absolute positions (set_position_mode with relative "
        "false first): the position mode is not known, and each target of a relative stream "
        "would move the motor on again")
    run(can_driver, plan(can_driver, '{"op":"set_position_mode","relative":false}'))
    can_driver.measured["position"] = None  # enabled when its power stage was not known
    assert follow_refusal(can_driver, {"position": 5}) == (
        "a position follow stream starts from where the drive holds, which is not known now "
        "(it was enabled when the gateway did not know it was off, or it has not reported its "
        "position yet): its next heartbeat tells; nothing was sent")


def test_a_node_without_the_register_written_is_told_and_nothing_changes() -> None:
    driver = Zlac706CanDriver("w", 1)
    (request,) = plan(driver, '{"op":"write","register":20,"value":7}')
    with pytest.raises(DeviceRefusedError) as refused:
        driver.apply(request, (can_codec.NoSuchRegister(1, 0x14, 7),), 1.0)
    assert str(refused.value) == "node 1 has no register 0x14: the write was not taken"
    assert (refused.value.code, refused.value.device, refused.value.device_id) == (
        "device_refused", "w", 1)
    (event,) = driver.drain_events()
    assert (event.type, event.fields) == ("rejected", {"register": 0x14,
                                                       "reason": "no such register"})


def test_a_shadow_driver_takes_the_mode_and_power_stage_its_worker_reports() -> None:
    shadow = Zlac706CanDriver("w", 1)
    with pytest.raises(CommandError, match="its mode is not known"):
        shadow.follow_target({"rpm": 50})
    shadow.mirror({"mode": "velocity", "enabled": True})
    assert shadow.follow_target({"rpm": 50}) == 50.0
    assert shadow.telemetry(0.0)["enabled"] is True
    shadow.mirror({"online": False})  # says neither: both left as they were
    shadow.mirror({"mode": "sideways", "enabled": "yes"})  # neither is one: the same
    assert (shadow.telemetry(0.0)["mode"], shadow.telemetry(0.0)["enabled"]) == (
        "velocity", True)
    shadow.mirror({"enabled": False})
    assert shadow.telemetry(0.0)["enabled"] is False
    assert shadow.follow_target({"rpm": 50}) == 50.0  # the mode kept
    shadow.mirror({"mode": "position"})
    with pytest.raises(CommandError, match="the motor is in position mode"):
        shadow.follow_target({"rpm": 50})


@pytest.mark.parametrize("node", [1, 3])
def test_a_scan_probes_a_can_node_with_a_write_it_answers_no_such_register(node) -> None:
    probe = Zlac706CanDriver.probe(node)
    assert probe.frame.device_id == node and probe.frame.value == 0
    answer = can_codec.NoSuchRegister(node, probe.frame.register, 0)
    assert probe.expected is not None and probe.expected.matches(answer)
    assert not probe.expected.matches(can_codec.NoSuchRegister(node + 1, probe.frame.register, 0))


def test_a_scan_probes_an_rs232_drive_with_its_monitor_request_once() -> None:
    probe = Zlac706Rs232Driver.probe(1)
    assert probe.wire.hex() == "800080" and probe.expected.frames == 8
    assert not probe.idempotent


def test_an_alarm_reset_refused_says_why_in_the_manuals_words() -> None:
    driver = Zlac706CanDriver("w", 1)
    run(driver, plan(driver, '{"op":"enable"}'))
    assert refusal(driver, '{"op":"clear_alarm"}') == (
        "clear_alarm while the drive's run signal (its enable) is on: the manual warns that an "
        "alarm reset with the run signal on starts the drive again suddenly; send disable first")


def test_a_lost_answer_to_a_disable_leaves_the_run_signal_not_known() -> None:
    driver = Zlac706CanDriver("w", 1)
    run(driver, plan(driver, '{"op":"enable"}'))
    (disable,) = [r for r in plan(driver, '{"op":"disable"}') if r.frame.register == 0x10]
    driver.went(disable.frame)
    driver.missed(1.0, disable.frame)
    assert "run signal (its enable) is perhaps on" in refusal(driver, '{"op":"clear_alarm"}')


def test_a_drive_that_powered_up_again_has_its_run_signal_cut() -> None:
    """A power-up leaves the drive released: an alarm reset may go without a disable."""
    driver = Zlac706CanDriver("w", 1, heartbeat_ms=10)
    run(driver, plan(driver, '{"op":"enable"}'))
    driver.take_position(100_000, 0.0)
    driver.take_position(0, 0.0)  # the counter back at 0 from far away: the drive powered up
    assert plan(driver, '{"op":"clear_alarm"}')


def test_a_reboot_during_an_outage_is_judged_against_the_fixed_bound() -> None:
    """A review: the bound grown by the time since the last report took an outage's length
    too, so a drive that powered up again (heartbeats lost, then 0) was not told rebooted."""
    driver = Zlac706CanDriver("w", 1, heartbeat_ms=100)
    driver.take_position(100_000, 0.0)
    driver.went_offline("heartbeat lost")
    driver.drain_events()
    driver.take_position(0, 2.0)
    assert "rebooted" in event_types(driver)
