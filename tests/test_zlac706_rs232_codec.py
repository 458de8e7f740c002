"""The ZLAC706 RS232 codec against manual 8.2: every example frame both ways, ranges, properties."""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from busgate.codecs.errors import CodecError, EncodeError
from busgate.codecs.framing import ChecksumMismatch, Discarded
from busgate.codecs.zlac706_common import AlarmFlags
from busgate.codecs.zlac706_rs232 import (
    CODES,
    MONITOR,
    REGISTERS,
    WRITABLE,
    Ack,
    BusVoltage,
    CommandDecoder,
    MonitorItem,
    MonitorRequest,
    OutputCurrent,
    OutputSpeed,
    PositionWord,
    ReplyDecoder,
    Rs232Register,
    StatusReport,
    Write,
    assemble_monitor,
    encode,
    expected_reply,
    join_position,
    split_position,
)

R = Rs232Register
#: Bytes that are no address in either direction, so the golden "behind garbage" check sees
#: them as one discarded run (the default garbage starts with 00, the enable register).
GARBAGE = b"\x11\x37\xee"

# Every host frame of 8.2.1 and 8.2.2 (the torque example's "stop 00 00 01 00" has a wrong
# checksum: stop is 00 00 00 00, as in the table).
MANUAL_COMMANDS = [
    ("00000101", Write(R.ENABLE, 1)),
    ("00000000", Write(R.ENABLE, 0)),
    ("0200c4c6", Write(R.MODE, 0xC4)),
    ("0200c0c2", Write(R.MODE, 0xC0)),
    ("0200d0d2", Write(R.MODE, 0xD0)),
    ("0200c1c3", Write(R.MODE, 0xC1)),
    ("53000053", Write(R.ORIGIN, 0)),
    ("4a00004a", Write(R.CLEAR_FAULT, 0)),
    ("51000051", Write(R.POSITION_MODE, 0)),
    ("51000152", Write(R.POSITION_MODE, 1)),
    ("0932326d", Write(R.POSITION_RAMP, 0x3232)),
    ("0a141432", Write(R.SPEED_RAMP, 0x1414)),
    ("1d00526f", Write(R.SPEED_LIMIT, 0x52)),
    ("1d00a4c1", Write(R.SPEED_LIMIT, 0xA4)),
    ("1d014866", Write(R.SPEED_LIMIT, 0x148)),
    ("50000050", Write(R.POSITION_HIGH, 0)),
    ("0527103c", Write(R.POSITION_LOW, 10000)),
    ("50ffff4e", Write(R.POSITION_HIGH, -1)),
    ("05d8f0cd", Write(R.POSITION_LOW, 0xD8F0)),
    ("0600888e", Write(R.SPEED, 136)),
    ("06ff787d", Write(R.SPEED, -136)),
    ("06011118", Write(R.SPEED, 273)),
    ("06feeff3", Write(R.SPEED, -273)),
    ("0602222a", Write(R.SPEED, 546)),
    ("06fddee1", Write(R.SPEED, -546)),
    ("2d01f422", Write(R.RATED_CURRENT, 500)),
    ("2d03e818", Write(R.RATED_CURRENT, 1000)),
    ("2d0bb8f0", Write(R.RATED_CURRENT, 3000)),
    ("2d1388c8", Write(R.RATED_CURRENT, 5000)),
    ("2d1f408c", Write(R.RATED_CURRENT, 8000)),
    ("08000008", Write(R.TORQUE, 0)),
    ("0800c8d0", Write(R.TORQUE, 200)),
    ("0801f4fd", Write(R.TORQUE, 500)),
    ("0803e8f3", Write(R.TORQUE, 1000)),
    ("0809c4d5", Write(R.TORQUE, 2500)),
    ("800080", MonitorRequest()),
]

# The ack of note (1) and the monitor examples of 8.2.1.
MANUAL_REPLIES = [
    ("0909", Ack(R.POSITION_RAMP)),
    ("80000080", StatusReport(AlarmFlags(0))),
    ("80000181", StatusReport(AlarmFlags.RUNNING)),
    ("80000282", StatusReport(AlarmFlags.OVER_CURRENT)),
    ("80000484", StatusReport(AlarmFlags.OVER_VOLTAGE)),
    ("80000888", StatusReport(AlarmFlags.ENCODER_FAULT)),
    ("80001090", StatusReport(AlarmFlags.OVER_TEMPERATURE)),
    ("800020a0", StatusReport(AlarmFlags.UNDER_VOLTAGE)),
    ("800040c0", StatusReport(AlarmFlags.OVERLOAD)),
    ("e1001cfd", BusVoltage(28)),
    ("e20011f3", OutputCurrent(17)),
    ("e4010ef3", OutputSpeed(270)),
    ("e60000e6", PositionWord(MonitorItem.COMMANDED_POSITION_HIGH, 0)),
    ("e727101e", PositionWord(MonitorItem.COMMANDED_POSITION_LOW, 10000)),
    ("e80000e8", PositionWord(MonitorItem.FEEDBACK_POSITION_HIGH, 0)),
    ("e9271020", PositionWord(MonitorItem.FEEDBACK_POSITION_LOW, 10000)),
]
MONITOR_EXAMPLE = "80000181 e1001cfd e20011f3 e4010ef3 e60000e6 e727101e e80000e8 e9271020"


@pytest.mark.parametrize(("wire", "frame"), MANUAL_COMMANDS)
def test_manual_commands(golden, wire: str, frame: object) -> None:
    assert encode(frame).hex() == wire
    golden(CommandDecoder, bytes.fromhex(wire), [frame], garbage=GARBAGE)


@pytest.mark.parametrize(("wire", "frame"), MANUAL_REPLIES)
def test_manual_replies(golden, wire: str, frame: object) -> None:
    assert encode(frame).hex() == wire
    golden(ReplyDecoder, bytes.fromhex(wire), [frame], garbage=GARBAGE)


def test_monitor_reply_stream_and_assembly(golden) -> None:
    wire = bytes.fromhex(MONITOR_EXAMPLE)
    frames = [frame for _, frame in MANUAL_REPLIES[-7:]]
    frames.insert(0, StatusReport(AlarmFlags.RUNNING))
    golden(ReplyDecoder, wire, frames, garbage=GARBAGE)
    reply = assemble_monitor(reversed(frames))
    assert reply.alarms == AlarmFlags.RUNNING
    assert (reply.voltage_v, reply.current_a, round(reply.speed_rpm)) == (28, 0.17, 99)
    assert reply.commanded_position_raw == reply.feedback_position_raw == 10000


def test_monitor_assembly_names_missing_frames() -> None:
    frames = [frame for _, frame in MANUAL_REPLIES[1:] if not isinstance(frame, BusVoltage)]
    with pytest.raises(CodecError, match="BUS_VOLTAGE"):
        assemble_monitor(frames[-7:])


def test_negative_position_halves() -> None:
    assert split_position(-10000) == (-1, 0xD8F0)
    assert join_position(-1, 0xD8F0) == -10000
    assert join_position(*split_position(-(1 << 31))) == -(1 << 31)


def test_ack_and_monitor_addresses_are_disjoint() -> None:
    assert WRITABLE.isdisjoint(MONITOR)
    assert set(MONITOR) == set(MonitorItem)
    assert set(WRITABLE) == set(Rs232Register)
    # The monitor request's first byte is the status item: it is no register on the host side.
    assert MonitorItem.STATUS not in WRITABLE


def test_position_mode_register_is_51_not_52() -> None:
    assert Rs232Register.POSITION_MODE == 0x51
    assert REGISTERS.at(0x52) is None


def test_expected_reply() -> None:
    ack = expected_reply(Write(R.SPEED, 136))
    assert (ack.wire_bytes, ack.frames, ack.source_id) == (2, 1, None)
    assert ack.matches(Ack(R.SPEED))
    assert not ack.matches(Ack(R.MODE))  # another write's ack, come late
    monitor = expected_reply(MonitorRequest())
    assert (monitor.wire_bytes, monitor.frames) == (32, 8)
    assert all(monitor.matches(frame) for _, frame in MANUAL_REPLIES[1:])
    assert not monitor.matches(Ack(R.SPEED))
    assert expected_reply(Ack(R.SPEED)) is None


@pytest.mark.parametrize(
    ("decoder_class", "wire", "expected"),
    [
        (CommandDecoder, "80058585", Discarded),  # a "monitor request" with data
        (CommandDecoder, "06008880", ChecksumMismatch),
        (ReplyDecoder, "0908", ChecksumMismatch),  # an ack's second byte repeats the first
        (ReplyDecoder, "e1001cfe", ChecksumMismatch),
        (CommandDecoder, "ffff", Discarded),
        (ReplyDecoder, "0301", Discarded),
    ],
)
def test_bad_input_makes_error_events(decoder_class, wire: str, expected: type) -> None:
    decoder = decoder_class()
    decoder.feed(bytes.fromhex(wire))
    assert isinstance(next(decoder.events()), expected)


def test_unknown_codes_still_decode() -> None:
    # The driver side must see a bad mode to refuse it; only known codes decode to names.
    (event,) = _decode_all(CommandDecoder, bytes.fromhex("02005557"))
    assert event == Write(R.MODE, 0x55) and not hasattr(event.value, "name")
    (event,) = _decode_all(CommandDecoder, bytes.fromhex("0200c4c6"))
    assert event.value.name == "PC_SPEED"


def test_garbage_run_is_one_event() -> None:
    decoder = CommandDecoder()
    decoder.feed(bytes.fromhex("ffeedd 00000101"))
    assert list(decoder.events()) == [Discarded(b"\xff\xee\xdd", "no known address"),
                                      Write(R.ENABLE, 1)]


@pytest.mark.parametrize(
    "frame",
    [
        Write(0x03, 0),  # no such register
        Write(MonitorItem.BUS_VOLTAGE, 0),  # read-only
        Write(R.SPEED, 2731),
        Write(R.SPEED, 70000),
        Write(R.TORQUE, -7501),
        Write(R.POSITION_HIGH, 0x8000),
        Write(R.POSITION_LOW, -1),
        Write(R.POSITION_KP, 0x10000),
        Write(R.SPEED_LIMIT, 2732),
        Write(R.MODE, 0xC5),
        Write(R.ENABLE, 2),
        Write(R.CLEAR_FAULT, 1),
        Write(R.RATED_CURRENT, 24001),
        Ack(MonitorItem.STATUS),
        StatusReport(AlarmFlags(0x10000)),
        BusVoltage(-1),
        OutputCurrent(0x10000),
        OutputSpeed(0x8000),
        PositionWord(MonitorItem.BUS_VOLTAGE, 0),
        PositionWord(MonitorItem.FEEDBACK_POSITION_LOW, -1),
        b"\x00\x00\x01\x01",
    ],
)
def test_out_of_range_is_refused(frame: object) -> None:
    with pytest.raises(EncodeError):
        encode(frame)


# --- properties ------------------------------------------------------------------------------


def _value(register) -> st.SearchStrategy[int]:
    codes = CODES.get(register.address)
    if codes:
        return st.sampled_from(list(codes))
    return st.integers(register.minimum, register.maximum)


writes = st.sampled_from([r for r in REGISTERS if r.access.writable]).flatmap(
    lambda r: _value(r).map(lambda v: Write(Rs232Register(r.address), v))
)
commands = st.one_of(writes, st.just(MonitorRequest()))
position_items = st.sampled_from(list(MonitorItem)[4:]).flatmap(
    lambda item: _value(REGISTERS.at(item)).map(lambda v: PositionWord(item, v))
)
replies = st.one_of(
    st.sampled_from(sorted(WRITABLE)).map(lambda a: Ack(Rs232Register(a))),
    st.integers(0, 0xFFFF).map(lambda v: StatusReport(AlarmFlags(v))),
    st.builds(BusVoltage, st.integers(0, 0xFFFF)),
    st.builds(OutputCurrent, st.integers(0, 0xFFFF)),
    st.builds(OutputSpeed, st.integers(-0x8000, 0x7FFF)),
    position_items,
)


def _decode_all(decoder_class, wire: bytes) -> list:
    decoder = decoder_class()
    decoder.feed(wire)
    return list(decoder.events())


@given(st.lists(commands, min_size=1, max_size=10))
def test_command_stream_round_trip(frames: list) -> None:
    assert _decode_all(CommandDecoder, b"".join(encode(f) for f in frames)) == frames


@given(st.lists(replies, min_size=1, max_size=10))
def test_reply_stream_round_trip(frames: list) -> None:
    assert _decode_all(ReplyDecoder, b"".join(encode(f) for f in frames)) == frames


@given(st.lists(st.binary(max_size=40), max_size=8))
def test_arbitrary_bytes_only_make_events(chunks: list[bytes]) -> None:
    for decoder_class in (CommandDecoder, ReplyDecoder):
        decoder = decoder_class()
        consumed = 0
        for chunk in chunks:
            decoder.feed(chunk)
            for event in decoder.events():
                assert not isinstance(event, Exception)
                consumed += 1
            assert decoder.pending < decoder.max_frame
        assert consumed <= sum(map(len, chunks))
