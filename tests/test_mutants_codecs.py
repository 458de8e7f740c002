"""What mutation testing (``python mutation/run.py codecs``) found the codec tests leaving
open: every range edge of a frame refuses with ``EncodeError`` naming the field and the value
(rather than letting ``struct`` or ``int.to_bytes`` fail, or the wrong bytes out), the errors
keep what they carry, and a few conversions at their edges. Pure calls."""

from __future__ import annotations

import pytest

from busgate.codecs import ds_servo, inspire_la
from busgate.codecs.can_frame import CanFrame
from busgate.codecs.ds_servo.registers import check_write
from busgate.codecs.errors import (
    ConfigError,
    DeviceError,
    EncodeError,
    RefusedError,
)
from busgate.codecs.inspire_la.registers import baud_code, temperature_raw
from busgate.codecs.registers import Access, Register, RegisterMap
from busgate.codecs.timing import can_time
from busgate.codecs.zlac706_common import (
    coded_register,
    ramp_word,
    speed_raw_rounded,
    speed_raw_truncated,
    torque_raw_from_amps,
)


def refused(call, *args, field: str, value: object) -> EncodeError:
    """``call(*args)`` raises ``EncodeError`` naming ``field`` and the offending ``value``."""
    with pytest.raises(EncodeError) as caught:
        call(*args)
    error = caught.value
    assert (error.field, error.value) == (field, value)
    assert str(error) not in ("", "None")
    return error


# -- Inspire LA ------------------------------------------------------------------------------

STATUS = dict(device_id=1, target_raw=0, position_raw=0, temperature_c=25, current_ma=0,
              force_g=0, faults=inspire_la.Fault(0), internal_1=0, internal_2=0)
STATUS_RANGES = {
    "target_raw": (0, 0xFFFF), "position_raw": (-0x8000, 0x7FFF),
    "temperature_c": (-0x80, 0x7F), "current_ma": (0, 0xFFFF), "force_g": (-0x8000, 0x7FFF),
    "faults": (0, 0xFF), "internal_1": (0, 0xFFFF), "internal_2": (0, 0xFFFF),
}


@pytest.mark.parametrize("name", sorted(STATUS_RANGES))
def test_a_status_reply_takes_each_field_to_its_edges_and_refuses_past_them(name):
    lo, hi = STATUS_RANGES[name]
    for edge in (lo, hi):
        inspire_la.encode(inspire_la.StatusReply(**{**STATUS, name: edge}))
    for beyond in (lo - 1, hi + 1):
        frame = inspire_la.StatusReply(**{**STATUS, name: beyond})
        refused(inspire_la.encode, frame, field=name, value=beyond)


def test_a_control_code_must_be_a_byte_and_a_known_code():
    for code in (-1, 0x100):
        refused(inspire_la.encode, inspire_la.ControlCommand(1, code), field="code", value=code)
    unknown = next(c for c in range(0x100) if c not in set(inspire_la.ControlCode))
    refused(inspire_la.encode, inspire_la.ControlCommand(1, unknown), field="code", value=unknown)


def test_a_group_frame_carries_one_to_fifteen_distinct_actuators():
    group = inspire_la.GroupMoveCommand
    refused(inspire_la.encode, group(()), field="number of targets", value=0)
    sixteen = tuple(inspire_la.Target(i, 0) for i in range(1, 17))
    refused(inspire_la.encode, group(sixteen), field="number of targets", value=16)
    inspire_la.encode(group(sixteen[:15]))
    for bad in (0, 255):
        targets = (inspire_la.Target(1, 0), inspire_la.Target(bad, 0))
        refused(inspire_la.encode, group(targets), field="target device_id", value=bad)
    twice = (inspire_la.Target(3, 0), inspire_la.Target(4, 0), inspire_la.Target(3, 5))
    refused(inspire_la.encode, group(twice), field="targets", value=[3, 4, 3])


def test_a_write_reply_index_and_reserved_byte_are_checked():
    reply = inspire_la.WriteReply
    refused(inspire_la.encode, reply(1, inspire_la.TABLE_SIZE, 0), field="index",
            value=inspire_la.TABLE_SIZE)
    refused(inspire_la.encode, reply(1, 0, 0x100), field="reserved", value=0x100)
    assert inspire_la.encode(reply(1, inspire_la.TABLE_SIZE - 1, 0xFF))[-2] == 0xFF


def test_temperatures_are_refused_finer_than_a_tenth_and_named():
    assert temperature_raw(70.3) == 703, "float noise on a 0.1 step is no finer step"
    refused(temperature_raw, 70.25, field="temp_c", value=70.25)


def test_an_unknown_baud_rate_is_refused_by_name():
    refused(baud_code, 115201, field="baudrate", value=115201)


# -- DS servo --------------------------------------------------------------------------------


def test_ds_servo_writes_are_refused_with_what_was_wrong():
    refused(check_write, -1, b"\x01", field="address", value=-1)
    refused(check_write, 0x100, b"\x01", field="address", value=0x100)
    error = refused(check_write, 0x16, b"\x01", field="data", value="01")  # store preset 1
    assert "preset_1" in str(error)
    refused(check_write, 0x28, b"", field="data", value="")
    refused(check_write, 0x38, b"\x07\xff", field="address", value=0x38)  # read only
    # A write that runs on from centre_offset over preset 1 (written by its address alone).
    error = refused(check_write, 0x14, b"\x00\x00\x00\x00", field="address", value=0x16)
    assert "preset_1" in str(error)
    error = refused(check_write, 0x2B, b"\x00", field="address", value=0x2B)
    assert "0x2b" in str(error) and "target_position" in str(error)
    refused(check_write, 0x2A, b"\x08", field="data", value="08")  # ends inside
    refused(check_write, 0x50, b"\x00", field="address", value=0x50)  # not in the table


def test_sync_write_targets_must_be_distinct():
    targets = (ds_servo.SyncTarget(1, 0, 0), ds_servo.SyncTarget(1, 10, 0))
    refused(ds_servo.encode, ds_servo.SyncWrite(targets), field="targets", value=[1, 1])


def test_only_ds_servo_frames_have_an_expected_reply():
    with pytest.raises(TypeError, match="not a ds_servo frame"):
        ds_servo.expected_reply(object())
    assert ds_servo.expected_reply(ds_servo.Action()) is None


# -- ZLAC706 units ---------------------------------------------------------------------------


def test_speeds_out_of_range_or_not_numbers_are_refused_with_the_range():
    for rpm in (1001, -1001):
        for convert in (speed_raw_truncated, speed_raw_rounded):
            error = refused(convert, rpm, field="rpm", value=rpm)
            assert "[-1000, 1000]" in str(error)
    for bad in (float("nan"), "100", True):
        refused(speed_raw_truncated, bad, field="rpm", value=bad)


def test_the_speed_limit_rounds_half_away_from_zero_and_no_earlier():
    # 0.5 rpm is 1.365 raw (rounds to 1); 0.3 rpm is 0.819 (rounds to 1); 0.1 is 0.273 (0).
    assert [speed_raw_rounded(r) for r in (0.5, 0.3, 0.1, -0.3)] == [1, 1, 0, -1]
    assert speed_raw_rounded(0.12) == 0, "0.328 raw is below one half"


def test_torque_currents_out_of_range_are_refused_with_the_range():
    for amps in (24.01, -25, float("inf"), True):
        error = refused(torque_raw_from_amps, amps, field="current_a", value=amps)
        assert "[-24, 24]" in str(error)


def test_ramps_are_refused_by_name_when_out_of_range_or_not_whole_steps():
    refused(ramp_word, 25600, 0, field="accel_ms", value=25600)
    refused(ramp_word, 0, -100, field="decel_ms", value=-100)
    refused(ramp_word, 150, 0, field="accel_ms", value=150)
    refused(ramp_word, 0, 1050, field="decel_ms", value=1050)
    assert ramp_word(25500, 0) == 0xFF00


def test_a_coded_register_is_a_write_only_word_spanning_its_codes():
    register = coded_register("mode", 0x19, (3, 1, 7), "work mode")
    assert register == Register("mode", 0x19, 1, Access.WRITE, minimum=1, maximum=7,
                                description="work mode")


# -- shared pieces ---------------------------------------------------------------------------


def test_can_frames_parse_three_hex_digit_ids_and_refuse_other_forms():
    assert CanFrame.parse(" 7FF#0102 ") == CanFrame(0x7FF, b"\x01\x02")
    assert CanFrame.parse("123#") == CanFrame(0x123, b"")
    for text in ("7FF0102", "#0102", "12G#00", "001#0"):
        refused(CanFrame.parse, text, field="frame", value=text)


def test_a_best_case_can_time_has_no_stuff_bits():
    assert can_time(8, 500_000, worst_case=False) == 111 / 500_000
    assert can_time(8, 500_000) == 135 / 500_000


def test_register_maps_name_the_registers_a_write_reaches():
    table = RegisterMap([Register("a", 0, 2, Access.READ_WRITE), Register("b", 2, 1,
                                                                          Access.READ_WRITE)])
    assert table.touched(1, 2) == {"a", "b"}
    assert table.touched(2, 0) == {"b"}, "an address-only write reaches its register"
    assert table.touched(3, 4) == set()


def test_errors_keep_their_message_and_what_they_carry():
    config = ConfigError("bad port", path="buses[0].port")
    assert (str(config), config.path) == ("bad port", "buses[0].port")
    device = DeviceError("no answer", device="la1", device_id=3)
    assert (str(device), device.device, device.device_id) == ("no answer", "la1", 3)
    refusal = RefusedError("claimed", "la1 is held by another client")
    assert (refusal.code, str(refusal)) == ("claimed", "la1 is held by another client")


# -- ZLAC706 frames --------------------------------------------------------------------------

I32 = (-(2**31), 2**31 - 1)


def test_zlac706_can_replies_take_each_field_to_its_edges_and_refuse_past_them():
    from busgate.codecs import zlac706_can as zcan

    cases = [
        (lambda v: zcan.HeartbeatCurrentSpeed(1, v, 0), "current_raw", (0, 0xFFFF)),
        (lambda v: zcan.HeartbeatCurrentSpeed(1, 0, v), "speed_raw", (-0x8000, 0x7FFF)),
        (lambda v: zcan.HeartbeatPosition(1, v), "position_raw", I32),
        (lambda v: zcan.AlarmReport(1, v), "alarms", (0, 0xFF)),
        (lambda v: zcan.WriteAck(1, v, 0), "register", (0, 0xFF)),
        (lambda v: zcan.WriteAck(1, 0x16, v), "value", I32),
        (lambda v: zcan.NoSuchRegister(1, 0x99, v), "value", I32),
        (lambda v: zcan.Write(1, v, 0), "register", (0, 0xFF)),
        (lambda v: zcan.Write(1, 0x99, v), "value", I32),  # an unknown register: any i32
    ]
    for make, name, (lo, hi) in cases:
        for edge in (lo, hi):
            assert len(zcan.encode(make(edge)).data) == 8
        for beyond in (lo - 1, hi + 1):
            refused(zcan.encode, make(beyond), field=name, value=beyond)


def test_a_zlac706_can_coded_register_refuses_other_codes_by_name():
    from busgate.codecs import zlac706_can as zcan
    from busgate.codecs.zlac706_can.registers import CanRegister

    error = refused(zcan.encode, zcan.Write(1, CanRegister.CONTROL_WORD, 0x10),
                    field="control_word", value=0x10)
    assert "0x0f, 0x1f" in str(error)


def test_zlac706_rs232_frames_name_the_register_they_refuse():
    from busgate.codecs import zlac706_rs232 as rs
    from busgate.codecs.zlac706_rs232.registers import Rs232Register

    for frame in (rs.Write(0x77, 0), rs.Ack(0x77)):
        error = refused(rs.encode, frame, field="register", value=0x77)
        assert "writable RS232 register" in str(error)
    error = refused(rs.encode, rs.PositionWord(0x77, 0), field="register", value=0x77)
    assert "position item" in str(error)
    refused(rs.encode, object(), field="frame", value=None)
    error = refused(rs.encode, rs.Write(Rs232Register.MODE, 0x7777), field="mode",
                    value=0x7777)
    assert "is not one of 0x" in str(error)


def test_can_frames_refuse_long_ids_and_long_data_by_field():
    refused(CanFrame, 0x800, b"", field="arbitration_id", value=0x800)
    refused(CanFrame, -1, b"", field="arbitration_id", value=-1)
    refused(CanFrame, 1, bytes(9), field="data", value="00" * 9)
    assert "0x800" in str(refused(CanFrame, 0x800, b"", field="arbitration_id", value=0x800))


def test_errors_carry_nothing_they_were_not_given():
    assert ConfigError("x").path == ""
    assert (DeviceError("x").device, DeviceError("x").device_id) == ("", None)
