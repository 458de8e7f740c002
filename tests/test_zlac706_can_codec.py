"""The ZLAC706 CAN codec against manual 8.1: every example frame both ways, ranges, properties."""

from __future__ import annotations

import pytest
from hypothesis import assume, given
from hypothesis import strategies as st

from busgate.codecs.can_frame import CanFrame
from busgate.codecs.errors import EncodeError
from busgate.codecs.framing import Discarded
from busgate.codecs.zlac706_can import (
    CODES,
    REGISTERS,
    AlarmReport,
    CanRegister,
    CommandDecoder,
    HeartbeatCurrentSpeed,
    HeartbeatPosition,
    NoSuchRegister,
    ReplyDecoder,
    Write,
    WriteAck,
    encode,
    expected_reply,
)
from busgate.codecs.zlac706_common import AlarmFlags

R = CanRegister

# Tables (3)–(6) and section 8.1.2, node id 1 ("报文 (ID=1)"); values as the frames print them.
MANUAL_WRITES = [
    (R.CONTROL_WORD, 0x0F, "0000000f"),
    (R.CONTROL_WORD, 0x1F, "0000001f"),
    (R.WORK_MODE, 0x2F, "0000002f"),
    (R.WORK_MODE, 0x3F, "0000003f"),
    # Erratum: table (6)'s torque-mode row prints 00 FA 00 10 00 00 00 1F; 8.1.2 step 6 is right.
    (R.WORK_MODE, 0x8F, "0000008f"),
    (R.POSITION_MODE, 0x4F, "0000004f"),
    (R.POSITION_MODE, 0x5F, "0000005f"),
    (R.ORIGIN, 0x6F, "0000006f"),
    (R.POSITION_RAMP, 0x0A0A, "00000a0a"),
    (R.MAX_SPEED, 0x0AAA, "00000aaa"),  # 1000 rpm ("0x1000" in the table is a typo)
    (R.MAX_SPEED, 0x0111, "00000111"),  # 100 rpm
    (R.ALARM_RESET, 0x7F, "0000007f"),
    (R.TARGET_POSITION, 123456, "0001e240"),
    (R.TARGET_POSITION, -123456, "fffe1dc0"),
    (R.TARGET_SPEED, 0x0555, "00000555"),  # 500 rpm
    (R.TARGET_SPEED, -2730, "fffff556"),  # -1000 rpm
    (R.SPEED_RAMP, 0x0A0A, "00000a0a"),
    (R.SPEED_RAMP, 0x0A0B, "00000a0b"),
    (R.POSITION_KP, 3000, "00000bb8"),
    (R.POSITION_KD, 1, "00000001"),
    (R.POSITION_KF, 1, "00000001"),
    (R.VELOCITY_KP, 5000, "00001388"),
    (R.VELOCITY_KI, 500, "000001f4"),
    (R.VELOCITY_KD, 0, "00000000"),
    (R.CURRENT_KP, 500, "000001f4"),
    (R.CURRENT_KD, 500, "000001f4"),
    (R.RATED_CURRENT, 8000, "00001f40"),
    (R.RATED_CURRENT, 10000, "00002710"),
    (R.TARGET_TORQUE, 1500, "000005dc"),
    (R.TARGET_TORQUE, 2500, "000009c4"),
]

# Section (6) heartbeat table and 8.1.2 step 7 log.
MANUAL_REPLIES = [
    ("001#00fe002000000000", HeartbeatPosition(1, 0)),
    ("001#00fe0021000a0000", HeartbeatCurrentSpeed(1, 0x0A, 0)),
    ("001#00fe002100070000", HeartbeatCurrentSpeed(1, 7, 0)),
    ("001#00fe00200001e1e2", HeartbeatPosition(1, 123362)),
    ("001#00fe0021001e043f", HeartbeatCurrentSpeed(1, 30, 1087)),
    ("001#00fe002100030000", HeartbeatCurrentSpeed(1, 3, 0)),
    ("001#00fe002100040000", HeartbeatCurrentSpeed(1, 4, 0)),
    ("001#00fe0020000f423f", HeartbeatPosition(1, 999999)),
    *(
        (f"001#00ff00eb{code:02x}{code:02x}{code:02x}{code:02x}", AlarmReport(1, AlarmFlags(code)))
        for code in (0x02, 0x04, 0x08, 0x10, 0x20, 0x40, 0x01)
    ),
]


def _decode(decoder_class, frame: CanFrame) -> list:
    decoder = decoder_class()
    decoder.feed(frame)
    return list(decoder.events())


@pytest.mark.parametrize(("register", "value", "data"), MANUAL_WRITES)
def test_manual_write_and_its_echo(register: int, value: int, data: str) -> None:
    write = Write(1, register, value)
    wire = CanFrame.parse(f"001#00fa00{register:02x}{data}")
    assert encode(write) == wire
    assert _decode(CommandDecoder, wire) == [write]
    echo = CanFrame.parse(f"001#00fb00{register:02x}{data}")
    assert encode(WriteAck(1, register, value)) == echo
    assert _decode(ReplyDecoder, echo) == [WriteAck(1, register, value)]


@pytest.mark.parametrize(("text", "frame"), MANUAL_REPLIES)
def test_manual_heartbeats_and_alarms(text: str, frame: object) -> None:
    assert encode(frame) == CanFrame.parse(text)
    assert _decode(ReplyDecoder, CanFrame.parse(text)) == [frame]


def test_heartbeat_converts_to_named_units() -> None:
    (event,) = _decode(ReplyDecoder, CanFrame.parse("001#00fe0021001e043f"))
    assert event.current_a == 0.3
    assert round(event.speed_rpm) == 398  # the manual's 1087 / 8192 × 3000


def test_alarm_report_flags() -> None:
    (event,) = _decode(ReplyDecoder, CanFrame.parse("001#00ff00eb88888888"))
    assert event.alarms == AlarmFlags.ENCODER_FAULT | AlarmFlags.EXTERNAL_CONTROL
    assert event.alarms.faults == AlarmFlags.ENCODER_FAULT


def test_decoded_codes_are_named() -> None:
    (event,) = _decode(CommandDecoder, CanFrame.parse("001#00fa00100000001f"))
    assert event.register.name == "CONTROL_WORD" and event.value.name == "ENABLE"


def test_broadcast_uses_identifier_zero_and_da() -> None:
    write = Write(0, R.WORK_MODE, 0x3F)
    assert str(encode(write)) == "000#00da00190000003f"
    assert _decode(CommandDecoder, encode(write)) == [write]
    assert _decode(ReplyDecoder, CanFrame.parse("000#00db00190000003f")) == [
        WriteAck(0, R.WORK_MODE, 0x3F)
    ]
    assert _decode(ReplyDecoder, CanFrame.parse("000#00df00330000003f")) == [
        NoSuchRegister(0, 0x33, 0x3F)
    ]


def test_unknown_register_reply() -> None:
    frame = NoSuchRegister(10, 0x33, 7)
    assert str(encode(frame)) == "00a#00ff003300000007"
    assert _decode(ReplyDecoder, encode(frame)) == [frame]


def test_expected_reply() -> None:
    expected = expected_reply(Write(10, R.TARGET_SPEED, 0x555))
    assert expected.source_id == 10 and expected.wire_bytes == 8 and expected.frames == 1
    assert expected.matches(WriteAck(10, R.TARGET_SPEED, 0x555))
    assert expected.matches(NoSuchRegister(10, R.TARGET_SPEED, 0x555))
    assert not expected.matches(WriteAck(11, R.TARGET_SPEED, 0x555))
    assert not expected.matches(HeartbeatPosition(10, 0))
    # the echo of another write (an alarm reset's, come after it timed out) answers no other
    assert not expected.matches(WriteAck(10, R.ALARM_RESET, 0x7F))
    assert not expected.matches(WriteAck(10, R.TARGET_SPEED, 0x111))
    assert expected_reply(Write(0, R.TARGET_SPEED, 0x555)) is None
    assert expected_reply(HeartbeatPosition(10, 0)) is None


@pytest.mark.parametrize(
    ("decoder_class", "text", "reason"),
    [
        (CommandDecoder, "001#00fa001900", "data bytes"),
        (CommandDecoder, "001#00fa01190000003f", "high byte"),
        (CommandDecoder, "001#00fb00190000003f", "not a host command"),
        (CommandDecoder, "000#00fa00190000003f", "node identifier"),
        (CommandDecoder, "001#00da00190000003f", "identifier 0"),
        (ReplyDecoder, "001#00fa00190000003f", "not a node reply"),
        (ReplyDecoder, "001#00db00190000003f", "identifier 0"),
        (ReplyDecoder, "000#00fb00190000003f", "node identifier"),
        (ReplyDecoder, "001#00fe002200000000", "heartbeat register"),
        (ReplyDecoder, "000#00fe002000000000", "broadcast identifier"),
        (ReplyDecoder, "001#00fe0020000000", "data bytes"),
    ],
)
def test_malformed_frames_are_discarded(decoder_class, text: str, reason: str) -> None:
    (event,) = _decode(decoder_class, CanFrame.parse(text))
    assert isinstance(event, Discarded) and reason in event.reason


def test_ff_with_register_eb_but_mixed_bytes_is_no_such_register() -> None:
    (event,) = _decode(ReplyDecoder, CanFrame.parse("001#00ff00eb01020304"))
    assert event == NoSuchRegister(1, 0xEB, 0x01020304)


@pytest.mark.parametrize(
    "frame",
    [
        Write(110, R.WORK_MODE, 0x3F),
        Write(-1, R.WORK_MODE, 0x3F),
        Write(1, R.WORK_MODE, 0x3F, group=256),
        Write(1, 256, 0),
        Write(1, R.WORK_MODE, 0x4F),
        Write(1, R.CONTROL_WORD, 0x15),
        Write(1, R.TARGET_SPEED, 2731),
        Write(1, R.TARGET_SPEED, -2731),
        Write(1, R.MAX_SPEED, -1),
        Write(1, R.TARGET_TORQUE, 7501),
        Write(1, R.POSITION_RAMP, 0x10000),
        Write(1, R.RATED_CURRENT, 24001),
        Write(1, R.POSITION_KP, -1),
        Write(1, R.TARGET_POSITION, 1 << 31),
        Write(1, 0x33, -(1 << 31) - 1),
        Write(1, R.TARGET_SPEED, 1.5),
        WriteAck(1, R.WORK_MODE, 1 << 31),
        NoSuchRegister(1, 300, 0),
        HeartbeatPosition(0, 0),
        HeartbeatPosition(1, 1 << 31),
        HeartbeatCurrentSpeed(1, 0x10000, 0),
        HeartbeatCurrentSpeed(1, -1, 0),
        HeartbeatCurrentSpeed(1, 0, 0x8000),
        AlarmReport(1, 0x100),
        AlarmReport(0, AlarmFlags.OVERLOAD),
        "001#00fa00190000003f",
    ],
)
def test_out_of_range_is_refused(frame: object) -> None:
    with pytest.raises(EncodeError):
        encode(frame)


def test_register_table_covers_the_manual() -> None:
    assert {r.address for r in REGISTERS} == set(CanRegister)
    assert REGISTERS["target_speed"].maximum == 0x0AAA
    assert all(not r.access.readable for r in REGISTERS)  # the protocol has no read


# --- properties ------------------------------------------------------------------------------

node_ids = st.integers(1, 109)
i32 = st.integers(-(1 << 31), (1 << 31) - 1)


@st.composite
def known_writes(draw):
    register = draw(st.sampled_from(list(REGISTERS)))
    codes = CODES.get(register.address)
    value = draw(
        st.sampled_from(list(codes)) if codes else st.integers(register.minimum, register.maximum)
    )
    device_id = draw(st.integers(0, 109))
    return Write(device_id, CanRegister(register.address), value, draw(st.integers(0, 255)))


unknown_registers = st.integers(0, 255).filter(lambda r: REGISTERS.at(r) is None)
commands = st.one_of(
    known_writes(),
    st.builds(Write, st.integers(0, 109), unknown_registers, i32, st.integers(0, 255)),
)
replies = st.one_of(
    st.builds(WriteAck, st.integers(0, 109), st.integers(0, 255), i32, st.integers(0, 255)),
    st.builds(NoSuchRegister, st.integers(0, 109), st.integers(0, 255), i32, st.integers(0, 255)),
    st.builds(HeartbeatPosition, node_ids, i32, st.integers(0, 255)),
    st.builds(
        HeartbeatCurrentSpeed,
        node_ids,
        st.integers(0, 0xFFFF),
        st.integers(-0x8000, 0x7FFF),
        st.integers(0, 255),
    ),
    st.builds(AlarmReport, node_ids, st.integers(0, 255).map(AlarmFlags), st.integers(0, 255)),
)


@given(commands)
def test_command_round_trip(frame: Write) -> None:
    assert _decode(CommandDecoder, encode(frame)) == [frame]


@given(replies)
def test_reply_round_trip(frame: object) -> None:
    # The one ambiguity of the protocol: "no such register EB" echoing four equal bytes
    # is byte for byte an alarm report (see decoder docstring).
    data = bytes(encode(frame).data)
    assume(not (isinstance(frame, NoSuchRegister) and data[3] == 0xEB and len(set(data[4:])) == 1))
    assert _decode(ReplyDecoder, encode(frame)) == [frame]


can_frames = st.builds(CanFrame, st.integers(0, 0x7FF), st.binary(max_size=8))


@given(st.lists(can_frames, max_size=20))
def test_arbitrary_frames_only_make_events(frames: list[CanFrame]) -> None:
    for decoder_class in (CommandDecoder, ReplyDecoder):
        decoder = decoder_class()
        for frame in frames:
            decoder.feed(frame)
        events = list(decoder.events())
        assert len(events) == len(frames)
        assert decoder.pending == 0
