"""What mutation testing (``python tools/mutation/run.py codecs``) found the codec tests leaving
open: every range edge of a frame refuses with ``EncodeError`` naming the field and the value
(rather than letting ``struct`` or ``int.to_bytes`` fail, or the wrong bytes out), the errors
keep what they carry, and a few conversions at their edges; decoders yield each event once, in
order (taken a few at a time, so one that would yield for ever fails instead of hanging),
resynchronise byte for byte and discard what they cannot use whole, with its reason; every
refusal says in words what was wrong. Pure calls."""

from __future__ import annotations

import enum
import itertools

import pytest

from busgate.codecs import ds_servo, inspire_la, zlac706_can, zlac706_rs232
from busgate.codecs.can_frame import CanFrame
from busgate.codecs.ds_servo.registers import check_write
from busgate.codecs.errors import CodecError, EncodeError
from busgate.codecs.framing import ChecksumMismatch, Discarded
from busgate.codecs.inspire_la.registers import baud_code, register_write, temperature_raw
from busgate.codecs.registers import Access, Register, RegisterMap
from busgate.codecs.timing import can_time
from busgate.codecs.zlac706_common import (
    coded_register,
    ramp_word,
    speed_raw_rounded,
    speed_raw_truncated,
    torque_raw_from_amps,
)
from busgate.errors import ConfigError, DeviceError, RefusedError


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


# -- decoders, one event at a time -----------------------------------------------------------
#
# ``events()`` stops when the buffer holds no complete frame; taking at most one event more
# than expected makes a decoder that would yield for ever (or re-yield a frame) fail here
# rather than hang.


def some_events(decoder, limit: int = 20) -> list:
    return list(itertools.islice(decoder.events(), limit))


LA_STATUS = inspire_la.ControlCommand(1, inspire_la.ControlCode.STATUS)
LA_MOVE = inspire_la.MoveCommand(2, 1000)


def test_a_stream_decoder_yields_each_frame_once_in_order():
    decoder = inspire_la.CommandDecoder()
    decoder.feed(inspire_la.encode(LA_STATUS) + inspire_la.encode(LA_MOVE))
    assert some_events(decoder) == [LA_STATUS, LA_MOVE]
    assert decoder.pending == 0


def test_a_partial_header_waits_for_the_rest_of_its_frame():
    wire = inspire_la.encode(LA_STATUS)
    decoder = inspire_la.CommandDecoder()
    decoder.feed(wire[:1])
    assert some_events(decoder) == [] and decoder.pending == 1
    decoder.feed(wire[1:])
    assert some_events(decoder) == [LA_STATUS]


def test_a_lone_byte_after_a_frame_is_no_header_even_where_the_two_would_make_one():
    # The move to 248 ends in 0x55: with the 0xAA after it the buffer ends in 55 AA, a header
    # that starts before the byte left over. That byte alone is no header: discarded at once.
    move = inspire_la.MoveCommand(1, 248)
    wire = inspire_la.encode(move)
    assert wire[-1:] + b"\xaa" == b"\x55\xaa"  # the command header
    decoder = inspire_la.CommandDecoder()
    decoder.feed(wire + b"\xaa")
    assert some_events(decoder) == [move, Discarded(b"\xaa", "no frame header")]
    assert decoder.pending == 0


def test_after_a_bad_checksum_the_rest_of_the_frame_is_discarded_byte_for_byte():
    wire = inspire_la.encode(LA_STATUS)
    bad = wire[:-1] + bytes([wire[-1] ^ 0x01])
    decoder = inspire_la.CommandDecoder()
    decoder.feed(bad + wire)
    assert some_events(decoder) == [
        ChecksumMismatch(bad, wire[-1], bad[-1]),
        Discarded(bad[1:], "no frame header"),
        LA_STATUS,
    ]


@pytest.mark.parametrize("garbage", [b"\x00", b"\x00\x13\x37"])
def test_a_frame_split_after_garbage_waits_for_its_body(garbage):
    for decoder, wire, event in [
        (inspire_la.ReplyDecoder(), inspire_la.encode(LA_REPLY), LA_REPLY),
        (ds_servo.ReplyDecoder(), ds_servo.encode(DS_REPLY), DS_REPLY),
    ]:
        for cut in range(1, len(wire)):
            decoder.feed(garbage + wire[:cut])
            assert some_events(decoder) == [Discarded(garbage, "no frame header")], cut
            decoder.feed(wire[cut:])
            assert some_events(decoder) == [event], cut


LA_REPLY = inspire_la.StatusReply(1, 0, 0, 25, 0, 0, inspire_la.Fault(0))
DS_REPLY = ds_servo.StatusReply(1, ds_servo.ServoStatus(0), b"\x07\xff")


def test_a_message_decoder_reports_a_full_queue_once_then_the_rest():
    decoder = zlac706_can.ReplyDecoder()
    beat = zlac706_can.HeartbeatPosition(1, 7)
    for _ in range(decoder.max_pending + 2):
        decoder.feed(zlac706_can.encode(beat))
    events = some_events(decoder, decoder.max_pending + 2)
    assert events[0] == Discarded(b"", "2 frames dropped: decoder queue full")
    assert events[1:] == [beat] * decoder.max_pending
    assert some_events(decoder) == []


def test_rs232_frames_are_yielded_once_and_unknown_bytes_between_them_discarded():
    from busgate.codecs.zlac706_rs232.registers import Rs232Register

    # The speed write 06 00 00 06 ends in a byte that is itself a known address.
    speed = zlac706_rs232.Write(Rs232Register.SPEED, 0)
    position = zlac706_rs232.Write(Rs232Register.POSITION_LOW, 10000)
    decoder = zlac706_rs232.CommandDecoder()
    decoder.feed(zlac706_rs232.encode(speed) + b"\x01" + zlac706_rs232.encode(position))
    assert some_events(decoder) == [speed, Discarded(b"\x01", "no known address"), position]


def test_an_rs232_checksum_mismatch_names_the_byte_received():
    decoder = zlac706_rs232.CommandDecoder()
    decoder.feed(bytes.fromhex("05 27 10 00"))  # position low 10000, checksum 3c
    assert some_events(decoder, 1) == [ChecksumMismatch(bytes.fromhex("05 27 10 00"), 0x3C, 0)]


def test_an_rs232_monitor_request_with_data_is_discarded_by_its_first_byte_with_its_reason():
    """A stray 80 before a monitor request made ``80 80 00``, whose sum passes: it was
    discarded whole, and every request after it was read out of step."""
    decoder = zlac706_rs232.CommandDecoder()
    decoder.feed(bytes.fromhex("80 80 00 80 80 00 80"))
    assert some_events(decoder) == [
        Discarded(b"\x80", "a monitor request carries no data"),
        zlac706_rs232.MonitorRequest(),
        zlac706_rs232.MonitorRequest(),
    ]
    decoder = zlac706_rs232.CommandDecoder()
    decoder.feed(bytes.fromhex("80 01 81"))
    assert some_events(decoder, 1) == [Discarded(b"\x80", "a monitor request carries no data")]


def test_a_monitor_reply_names_every_item_it_lacks():
    from busgate.codecs.zlac706_rs232 import assemble_monitor

    with pytest.raises(CodecError) as missing:
        assemble_monitor([])
    assert str(missing.value) == (
        "monitor reply incomplete: no STATUS, BUS_VOLTAGE, CURRENT, SPEED, "
        "COMMANDED_POSITION_HIGH, COMMANDED_POSITION_LOW, FEEDBACK_POSITION_HIGH, "
        "FEEDBACK_POSITION_LOW"
    )


def test_rs232_refusals_say_what_the_register_is_not_and_which_codes_are_allowed():
    from busgate.codecs.zlac706_rs232.registers import Rs232Register

    for frame in (zlac706_rs232.Write(0x77, 0), zlac706_rs232.Ack(0x77)):
        error = refused(zlac706_rs232.encode, frame, field="register", value=0x77)
        assert str(error) == "119 is not a writable RS232 register"
    error = refused(
        zlac706_rs232.encode, zlac706_rs232.PositionWord(0x77, 0), field="register", value=0x77
    )
    assert str(error) == "119 is not a position item"
    error = refused(
        zlac706_rs232.encode,
        zlac706_rs232.Write(Rs232Register.MODE, 0x7777),
        field="mode",
        value=0x7777,
    )
    assert str(error) == "mode 30583 is not one of 0x00c4, 0x00c0, 0x00d0, 0x00c1"


# -- ZLAC706 CAN decoding --------------------------------------------------------------------


def decoded(decoder, text: str):
    decoder.feed(CanFrame.parse(text))
    (event,) = some_events(decoder)
    return event


@pytest.mark.parametrize(
    ("text", "reason"),
    [
        ("001#00fe0021001e04", "7 data bytes, ZLAC706 frames have 8"),
        ("001#00fe0121001e043f", "register high byte is not 0"),
        ("001#0077002100000000", "function 0x77 is not a node reply"),
        ("000#00fe0021001e043f", "heartbeat on the broadcast identifier"),
        ("001#00fe0099001e043f", "heartbeat register 0x99 is unknown"),
        ("000#00fb001600000001", "function 0xfb belongs on a node identifier"),
        ("001#00db001600000001", "function 0xdb belongs on identifier 0"),
    ],
)
def test_a_node_frame_that_is_no_reply_is_discarded_whole_with_its_reason(text, reason):
    frame = CanFrame.parse(text)
    assert decoded(zlac706_can.ReplyDecoder(), text) == Discarded(frame.data, f"{text}: {reason}")


@pytest.mark.parametrize(
    ("text", "reason"),
    [
        ("001#0077002100000000", "function 0x77 is not a host command"),
        ("001#00fa00160000", "6 data bytes, ZLAC706 frames have 8"),
        ("000#00fa001600000001", "function 0xfa belongs on a node identifier"),
        ("001#00da001600000001", "function 0xda belongs on identifier 0"),
    ],
)
def test_a_host_frame_that_is_no_command_is_discarded_whole_with_its_reason(text, reason):
    frame = CanFrame.parse(text)
    expected = Discarded(frame.data, f"{text}: {reason}")
    assert decoded(zlac706_can.CommandDecoder(), text) == expected


def test_a_position_heartbeat_takes_all_four_bytes():
    beat = decoded(zlac706_can.ReplyDecoder(), "001#00fe002012345678")
    assert beat == zlac706_can.HeartbeatPosition(1, 0x12345678)


def test_zlac706_can_refusals_name_the_field():
    refused(zlac706_can.encode, object(), field="frame", value=None)
    refused(zlac706_can.encode, zlac706_can.Write(200, 0x16, 0), field="device_id", value=200)
    refused(zlac706_can.encode, zlac706_can.Write(1, 0x16, 0, group=256), field="group", value=256)


# -- DS servo, the edges ---------------------------------------------------------------------


def test_ds_servo_ids_run_to_250_in_commands_and_replies():
    for decoder, frame in [
        (ds_servo.CommandDecoder(), ds_servo.Ping(250)),
        (ds_servo.ReplyDecoder(), ds_servo.StatusReply(250, ds_servo.ServoStatus(0), b"")),
    ]:
        decoder.feed(ds_servo.encode(frame))
        assert some_events(decoder) == [frame]


def test_ds_servo_addresses_outside_a_byte_are_refused_as_such_and_0_as_no_register():
    error = refused(check_write, 0, b"\x01", field="address", value=0)
    assert str(error) == "address 0x00 is not in the control table"
    error = refused(check_write, 0x100, b"\x01", field="address", value=0x100)
    assert str(error) == "address 256 is out of range [0, 255]"


def test_a_ds_servo_write_may_span_registers_of_different_sizes():
    check_write(0x10, bytes.fromhex("0320 1e 00"))  # max_torque, speed_adjust, unload_condition


def test_ds_servo_frames_that_cannot_be_sent_say_why():
    with pytest.raises(TypeError, match="not a ds_servo frame: <object"):
        ds_servo.encode(object())
    long_reply = ds_servo.StatusReply(1, ds_servo.ServoStatus(0), bytes(254))
    error = refused(ds_servo.encode, long_reply, field="params", value=254)
    assert str(error) == "254 parameter bytes do not fit one frame (at most 253)"
    refused(ds_servo.encode, ds_servo.Ping(254), field="device_id", value=254)
    sync = ds_servo.SyncWrite((ds_servo.SyncTarget(254, 0, 0),))
    error = refused(ds_servo.encode, sync, field="device_id", value=254)
    assert str(error) == "a SYNC WRITE target cannot be sent to the broadcast id 254"


# -- Inspire LA, the edges -------------------------------------------------------------------


def test_an_la_control_code_outside_a_byte_is_refused_as_such_and_0_as_unknown():
    error = refused(inspire_la.encode, inspire_la.ControlCommand(1, 0), field="code", value=0)
    assert str(error) == "unknown control code 0x00"
    error = refused(
        inspire_la.encode, inspire_la.ControlCommand(1, 0x100), field="code", value=0x100
    )
    assert str(error) == "code 256 is out of range [0, 255]"


def test_an_la_temperature_exactly_at_the_tolerance_is_still_whole_tenths():
    # 1e-07 * 10 is exactly the float 1e-06: the tolerance itself, not past it.
    assert temperature_raw(1e-07) == 0
    refused(temperature_raw, 2e-07, field="temp_c", value=2e-07)


def test_an_la_register_write_keeps_the_sign_of_a_signed_register():
    command = register_write(1, "force", -2)
    assert command.data == (-2).to_bytes(2, "little", signed=True)


def test_only_la_command_frames_have_an_expected_reply():
    with pytest.raises(TypeError, match="not an inspire_la command frame: <object"):
        inspire_la.expected_reply(object())


def test_the_speed_limit_rounds_up_from_one_half_not_later():
    # 5 rpm is 13.65 raw, 9 rpm is 24.58: above one half, below two thirds.
    assert [speed_raw_rounded(r) for r in (5, 9, -5)] == [14, 25, -14]


def test_an_address_only_write_reaches_the_register_at_its_address_alone():
    table = RegisterMap(
        [Register("a", 0, 2, Access.READ_WRITE), Register("b", 2, 1, Access.READ_WRITE)]
    )
    assert table.touched(1, 0) == {"a"}


# -- registers named in their units (busgate decode) -----------------------------------------


def test_a_packed_register_of_zero_is_each_part_zero_not_unknown():
    ramp = Register("ramp", 0x12, 1, Access.WRITE, unit="ms", scale=100, parts=("accel", "decel"))
    assert ramp.in_unit(0) == {"accel": 0, "decel": 0}
    assert ramp.in_unit(1) == {"accel": 0, "decel": 100}
    assert ramp.in_unit(-1) is None


def test_a_value_the_decoder_named_keeps_its_name():
    class Mode(enum.IntEnum):
        VELOCITY = 0x2F

    register = Register("mode", 0x19, 1, Access.WRITE, scale=2)
    assert register.reading(Mode.VELOCITY).value is Mode.VELOCITY
    assert register.reading(0x2F).value == 0x5E  # a plain number is scaled


def test_a_reply_names_a_register_only_at_its_first_address():
    table = RegisterMap([Register("a", 4, 2, Access.READ_WRITE)])
    assert [r.register for r in table.reading_at(4, 7)] == ["a"]
    assert table.reading_at(5, 7) == []  # the register's second byte
    assert table.reading_at(9, 7) == []  # a reserved address
