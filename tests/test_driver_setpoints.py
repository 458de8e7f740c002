"""What each family's frames set on the devices they address (``Driver.setpoints``), by plain
calls: the positions, speeds and efforts the authority judges against each joint, one per
target of a group frame, ``None`` for a position the gateway cannot know, none for reads and
settings; and the driver's state left as it was."""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from busgate.codecs import ds_servo as ds
from busgate.codecs import zlac706_can as can_codec
from busgate.codecs import zlac706_common as common
from busgate.codecs import zlac706_rs232 as rs_codec
from busgate.gateway.drivers.base import Driver, Setpoint
from busgate.gateway.drivers.ds_servo import DsServoDriver
from busgate.gateway.drivers.inspire_la import InspireLaDriver
from busgate.gateway.drivers.zlac706 import Zlac706Driver
from busgate.gateway.drivers.zlac706_can import Zlac706CanDriver
from busgate.gateway.drivers.zlac706_rs232 import Zlac706Rs232Driver


def setpoints(driver: Driver, text: str) -> list[Setpoint]:
    """What the command ``text`` sets, as the authority asks before planning it."""
    return driver.setpoints(driver.frames_of(driver.parse(text)))


def position(device_id: int, value: float | None) -> Setpoint:
    return Setpoint(device_id, "position", value)


def positions(driver: Driver, text: str) -> list[Setpoint]:
    """The position setpoints of ``setpoints``."""
    return [setpoint for setpoint in setpoints(driver, text) if setpoint.quantity == "position"]


# --- Inspire LA ---------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ('{"op":"move","position":1500}', [position(3, 1500)]),
        ('{"op":"move","position":0,"reply":false}', [position(3, 0)]),
        ('{"op":"follow","position":2000}', [position(3, 2000)]),
        (
            '{"op":"group_move","targets":[{"id":1,"position":1300},{"id":2,"position":1000}]}',
            [position(1, 1300), position(2, 1000)],
        ),
        (
            '{"op":"group_follow","targets":[{"id":3,"position":5},{"id":9,"position":7}]}',
            [position(3, 5), position(9, 7)],
        ),
        ('{"op":"write","index":55,"data":"1405"}', [position(3, 1300)]),  # manual 3.5.2
    ],
)
def test_la_targets_are_position_setpoints(text: str, expected: list[Setpoint]) -> None:
    assert setpoints(InspireLaDriver("rod", 3), text) == expected


@pytest.mark.parametrize(
    "text",
    [
        '{"op":"status"}',
        '{"op":"enable"}',
        '{"op":"estop"}',
        '{"op":"pause"}',
        '{"op":"save"}',
        '{"op":"clear_fault"}',
        '{"op":"read","index":55,"length":2}',
        '{"op":"set_id","new_id":4}',
        '{"op":"set_overcurrent","current_ma":1000}',
        '{"op":"set_overtemp","temp_c":70}',
        '{"op":"zero_force"}',
        '{"op":"write","index":32,"data":"e803"}',  # the over-current limit, next to the target
    ],
)
def test_la_reads_and_settings_set_nothing(text: str) -> None:
    assert setpoints(InspireLaDriver("rod", 3), text) == []


def test_la_follow_frames_set_each_follower_position() -> None:
    one, two = InspireLaDriver("a", 1), InspireLaDriver("b", 2)
    alone = InspireLaDriver.follow_request([(one, 1000)]).frame
    assert one.setpoints([alone]) == [position(1, 1000)]
    group = InspireLaDriver.follow_request([(one, 1300), (two, 700)]).frame
    assert one.setpoints([group]) == [position(1, 1300), position(2, 700)]


@given(st.integers(0, 2000))
def test_la_any_position_written_raw_is_the_setpoint(raw: int) -> None:
    d = InspireLaDriver("rod", 3)
    data = raw.to_bytes(2, "little").hex()
    assert setpoints(d, f'{{"op":"write","index":55,"data":"{data}"}}') == [position(3, raw)]
    assert setpoints(d, f'{{"op":"move","position":{raw}}}') == [position(3, raw)]


# --- DS servo -----------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ('{"op":"move","position":2048,"time_ms":1000}', [position(1, 2048)]),  # target + time
        ('{"op":"move","position":2000,"deferred":true}', [position(1, 2000)]),  # REG WRITE
        (
            '{"op":"group_move","targets":[{"id":1,"position":2000,"time_ms":1000},'
            '{"id":2,"position":100,"time_ms":0}]}',
            [position(1, 2000), position(2, 100)],
        ),
        ('{"op":"write","address":42,"data":"0064"}', [position(1, 100)]),
        ('{"op":"write","address":42,"data":"0fa003e8"}', [position(1, 4000)]),  # and time
        ('{"op":"goto_preset","n":1}', [position(1, None)]),  # the preset is the servo's
        ('{"op":"goto_preset","n":3}', [position(1, None)]),
        ('{"op":"reset"}', [position(1, None)]),  # the factory centre and angle limits again
    ],
)
def test_ds_targets_are_position_setpoints(text: str, expected: list[Setpoint]) -> None:
    assert setpoints(DsServoDriver("arm", 1), text) == expected


@pytest.mark.parametrize(
    "text",
    [
        '{"op":"ping"}',
        '{"op":"read","address":42,"length":2}',
        '{"op":"action"}',  # starts the REG WRITE judged when it was sent
        '{"op":"torque","on":true}',
        '{"op":"torque","on":false}',
        '{"op":"set_id","new_id":2}',
        '{"op":"store_preset","n":1}',
        '{"op":"write","address":44,"data":"03e8"}',  # the move time alone
    ],
)
def test_ds_reads_and_settings_set_nothing(text: str) -> None:
    assert setpoints(DsServoDriver("arm", 1), text) == []


@pytest.mark.parametrize(
    "frame",
    [
        ds.Write(1, 0x2A, b"\x00"),  # the target's high byte alone
        ds.Write(1, 0x2B, b"\x64"),  # its low byte alone
        ds.Write(1, ds.GOTO_PRESET_ADDRESSES[1], b""),  # go to preset 2, as a raw write
    ],
)
def test_ds_frames_the_schema_refuses_still_set_a_position_not_known(frame: ds.Write) -> None:
    # The write schema refuses these; a frame built otherwise is still judged.
    assert DsServoDriver("arm", 1).setpoints([frame]) == [position(1, None)]


def test_ds_follow_frame_sets_each_servo_position() -> None:
    one, three = DsServoDriver("a", 1), DsServoDriver("c", 3)
    frame = DsServoDriver.follow_request([(one, 2000), (three, 1000)]).frame
    assert one.setpoints([frame]) == [position(1, 2000), position(3, 1000)]


@given(st.integers(0, 4095))
def test_ds_any_position_written_raw_is_the_setpoint(raw: int) -> None:
    data = raw.to_bytes(2, "big").hex()
    text = f'{{"op":"write","address":{ds.MOVE_ADDRESS},"data":"{data}"}}'
    assert setpoints(DsServoDriver("arm", 1), text) == [position(1, raw)]


# --- ZLAC706, both wires --------------------------------------------------------------------


def can_driver() -> Zlac706CanDriver:
    return Zlac706CanDriver("wheel", 5)


def rs_driver() -> Zlac706Rs232Driver:
    return Zlac706Rs232Driver("wheel", 5)


def prepared(driver: Zlac706Driver, *texts: str) -> Zlac706Driver:
    """``driver`` with ``texts`` planned (queued, not acknowledged: the outlook has them)."""
    for text in texts:
        driver.plan(driver.parse(text))
    return driver


POSITION_MODE = ('{"op":"set_mode","mode":"position"}', '{"op":"enable"}')
ABSOLUTE = (*POSITION_MODE, '{"op":"set_position_mode","relative":false}')
RELATIVE = (*POSITION_MODE, '{"op":"set_position_mode","relative":true}')
VELOCITY_MODE = ('{"op":"set_mode","mode":"velocity"}',)
TORQUE_MODE = ('{"op":"set_mode","mode":"torque"}',)

both_wires = pytest.mark.parametrize("make", [can_driver, rs_driver], ids=["can", "rs232"])


@both_wires
@pytest.mark.parametrize("target", [0, 10_000, -10_000, 123_456, -(2**31)])
def test_zlac_absolute_position_is_the_target(make, target: int) -> None:
    d = prepared(make(), *ABSOLUTE)
    # RS232 sends the high half then the low half: one setpoint, the two joined.
    assert positions(d, f'{{"op":"move","position":{target}}}') == [position(5, target)]


@both_wires
def test_zlac_relative_position_is_judged_from_the_measured_position(make) -> None:
    d = prepared(make(), *RELATIVE)
    assert positions(d, '{"op":"move","position":500}') == [position(5, None)]  # none measured
    d.take_position(-12_000, 0.0)
    assert positions(d, '{"op":"move","position":500}') == [position(5, -11_500)]
    assert positions(d, '{"op":"move","position":-70000}') == [position(5, -82_000)]


@both_wires
def test_zlac_position_mode_not_known_is_a_position_not_known(make) -> None:
    d = prepared(make(), *POSITION_MODE)
    d.take_position(100, 0.0)
    assert positions(d, '{"op":"move","position":500}') == [position(5, None)]


@both_wires
@pytest.mark.parametrize("rpm", [0, 500, -1000, 123.4])
def test_zlac_speed_is_a_velocity_setpoint_in_rpm(make, rpm: float) -> None:
    d = prepared(make(), *VELOCITY_MODE)
    found = setpoints(d, f'{{"op":"velocity","rpm":{rpm}}}')
    [(device_id, quantity, value)] = [s for s in found if s.quantity == "velocity"]
    assert (device_id, quantity) == (5, "velocity")
    # Turning, it goes to wherever it is stopped: a position not known (none for a stop).
    assert positions(d, f'{{"op":"velocity","rpm":{rpm}}}') == ([position(5, None)] if rpm
                                                                  else [])
    # The speed the wire carries (truncated toward zero, a step is 0.37 rpm), in rpm.
    assert value == common.rpm_from_speed_raw(common.speed_raw_truncated(rpm))
    assert value == pytest.approx(rpm, abs=0.37)


@both_wires
@pytest.mark.parametrize(("amps", "raw"), [(8, 2500), (-4.8, -1500), (0.001, 0), (24, 7500)])
def test_zlac_torque_is_an_effort_setpoint_in_amperes(make, amps: float, raw: int) -> None:
    d = prepared(make(), *TORQUE_MODE)
    # The current the wire carries, to its 3.2 mA step.
    expected = [Setpoint(5, "effort", raw / 312.5)] + ([position(5, None)] if raw else [])
    assert setpoints(d, f'{{"op":"torque","current_a":{amps}}}') == expected


def test_zlac_can_raw_writes_go_through_the_roles() -> None:
    d = prepared(can_driver(), *ABSOLUTE)
    reg = can_codec.CanRegister
    assert positions(d, f'{{"op":"write","register":{reg.TARGET_POSITION},"value":-5}}') == [
        position(5, -5)
    ]
    assert setpoints(d, f'{{"op":"write","register":{reg.TARGET_SPEED},"value":2730}}') == [
        Setpoint(5, "velocity", common.rpm_from_speed_raw(2730)), position(5, None)
    ]
    assert setpoints(d, f'{{"op":"write","register":{reg.TARGET_TORQUE},"value":-7500}}') == [
        Setpoint(5, "effort", -24.0), position(5, None)
    ]
    # Position mode's top speed: a move never runs faster, so it is a speed too.
    assert setpoints(d, f'{{"op":"write","register":{reg.MAX_SPEED},"value":100}}') == [
        Setpoint(5, "velocity", common.rpm_from_speed_raw(100))
    ]


def test_zlac_rs232_raw_writes_go_through_the_roles() -> None:
    d = prepared(rs_driver(), *ABSOLUTE)
    low = rs_codec.Rs232Register.POSITION_LOW
    high = rs_codec.Rs232Register.POSITION_HIGH
    # No high half written yet: the low half alone is a target the gateway cannot know.
    assert positions(d, f'{{"op":"write","register":{low},"value":100}}') == [position(5, None)]
    # The high half sets nothing itself; the low half written after it is joined to it.
    assert setpoints(d, f'{{"op":"write","register":{high},"value":-1}}') == []
    prepared(d, f'{{"op":"write","register":{high},"value":-1}}')
    assert positions(d, f'{{"op":"write","register":{low},"value":55536}}') == [
        position(5, -10_000)
    ]
    speed, torque = rs_codec.Rs232Register.SPEED, rs_codec.Rs232Register.TORQUE
    assert setpoints(d, f'{{"op":"write","register":{speed},"value":-1365}}') == [
        Setpoint(5, "velocity", common.rpm_from_speed_raw(-1365)), position(5, None)
    ]
    assert setpoints(d, f'{{"op":"write","register":{torque},"value":1500}}') == [
        Setpoint(5, "effort", 4.8), position(5, None)
    ]


def test_zlac_rs232_move_after_a_move_joins_its_own_halves() -> None:
    d = prepared(rs_driver(), *ABSOLUTE, '{"op":"move","position":-10000}')
    assert positions(d, '{"op":"move","position":70000}') == [position(5, 70_000)]


@both_wires
@pytest.mark.parametrize(
    "text",
    [
        '{"op":"set_mode","mode":"position"}',
        '{"op":"enable"}',
        '{"op":"disable"}',
        '{"op":"set_position_mode","relative":true}',
        '{"op":"set_position_ramp","accel_ms":1000,"decel_ms":1000}',
        '{"op":"set_velocity_ramp","accel_ms":1000,"decel_ms":1000}',
        '{"op":"clear_alarm"}',
        '{"op":"set_rated_current","current_ma":8000}',
        '{"op":"set_gain","gain":"position_kp","value":100}',
    ],
)
def test_zlac_settings_set_nothing(make, text: str) -> None:
    assert setpoints(make(), text) == []


@both_wires
def test_zlac_move_runs_at_the_top_speed_set_and_an_origin_search_to_a_place_not_known(
    make,
) -> None:
    """A move in position mode runs at the drive's top speed (``None`` until one was set:
    the drive's own, 100 rpm in the manual's example); an origin search turns the motor
    until it finds the index (an outside audit saw both go past a joint's limits)."""
    d = prepared(make(), *ABSOLUTE)
    assert setpoints(d, '{"op":"move","position":10}') == [
        position(5, 10), Setpoint(5, "velocity", None)]
    assert setpoints(d, '{"op":"home"}') == [position(5, None)]
    prepared(d, '{"op":"set_max_speed","rpm":60}')
    (_, top) = setpoints(d, '{"op":"move","position":10}')
    assert top.quantity == "velocity" and top.value == pytest.approx(60, abs=0.5)


@both_wires
def test_zlac_top_speed_is_a_velocity_setpoint(make) -> None:
    (setpoint,) = setpoints(make(), '{"op":"set_max_speed","rpm":100}')
    assert setpoint.quantity == "velocity" and setpoint.value == pytest.approx(100, abs=0.5)


def test_zlac_rs232_monitor_sets_nothing() -> None:
    assert setpoints(rs_driver(), '{"op":"monitor"}') == []


@both_wires
def test_zlac_setpoints_leave_the_state_as_it_was(make) -> None:
    d = prepared(make(), *RELATIVE)
    d.take_position(7, 0.0)
    before = (d.machine.settings, d.machine.expected(), dict(d.measured))
    for text in ('{"op":"move","position":9}', '{"op":"set_mode","mode":"velocity"}'):
        d.setpoints(d.frames_of(d.parse(text)))
    assert (d.machine.settings, d.machine.expected(), dict(d.measured)) == before


@given(st.integers(-(2**31), 2**31 - 1))
def test_zlac_rs232_any_absolute_position_round_trips_through_its_halves(target: int) -> None:
    d = prepared(rs_driver(), *ABSOLUTE)
    assert positions(d, f'{{"op":"move","position":{target}}}') == [position(5, target)]
