"""The Inspire LA codec: every example frame of the manual both ways, the ranges, the decoders'
behaviour on damaged input, and what answers what."""

from __future__ import annotations

import typing
from dataclasses import replace

import pytest
from hypothesis import given
from hypothesis import strategies as st

from busgate.codecs import inspire_la as la
from busgate.codecs.errors import EncodeError
from busgate.codecs.framing import NEED_DATA, ChecksumMismatch, Discarded
from busgate.codecs.inspire_la import (
    CommandDecoder,
    ControlCode,
    ControlCommand,
    Fault,
    FollowCommand,
    GroupFollowCommand,
    GroupMoveCommand,
    MoveCommand,
    ReadCommand,
    ReadReply,
    ReplyDecoder,
    StatusReply,
    Target,
    WriteCommand,
    WriteReply,
    encode,
    expected_reply,
)

# Every command frame printed in the manual (section), with the frame it stands for.
MANUAL_COMMANDS = [
    ("3.5.1 read", "55 AA 03 01 01 62 02 69", ReadCommand(1, 0x62, 2)),
    ("3.5.2 write", "55 AA 04 01 02 37 14 05 57", WriteCommand(1, 0x37, bytes.fromhex("1405"))),
    ("3.5.3 move", "55 AA 04 01 21 37 14 05 76", MoveCommand(1, 1300)),
    ("3.5.3 move, no reply", "55 AA 04 01 03 37 14 05 58", MoveCommand(1, 1300, reply=False)),
    ("3.5.4 e-stop", "55 AA 03 01 04 00 23 2B", ControlCommand(1, ControlCode.ESTOP)),
    ("3.7.1 set id", "55 AA 03 03 02 02 02 0C", WriteCommand(3, 2, b"\x02")),
    ("3.7.2 move", "55 AA 04 03 21 37 E8 03 4A", MoveCommand(3, 1000)),
    ("3.7.2 move, no reply", "55 AA 04 03 03 37 E8 03 2C", MoveCommand(3, 1000, reply=False)),
    ("3.7.2 follow", "55 AA 04 03 20 37 E8 03 49", FollowCommand(3, 1000)),
    # Erratum (docs/protocols.md): the manual prints checksum 28; the sum of the bytes is 42.
    ("3.7.2 follow, no reply", "55 AA 04 03 19 37 E8 03 42", FollowCommand(3, 1000, reply=False)),
    ("3.7.3 e-stop", "55 AA 03 03 04 00 23 2D", ControlCommand(3, ControlCode.ESTOP)),
    ("3.7.4 enable", "55 AA 03 03 04 00 04 0E", ControlCommand(3, ControlCode.ENABLE)),
    ("3.7.5 over-temp", "55 AA 04 03 02 62 C1 02 2E", WriteCommand(3, 0x62, bytes.fromhex("c102"))),
    ("3.7.5 rewarm", "55 AA 04 03 02 64 5D 02 CC", WriteCommand(3, 0x64, bytes.fromhex("5d02"))),
    ("3.7.6 over-current", "55 AA 04 01 02 20 E8 03 12", WriteCommand(1, 32, b"\xe8\x03")),
    ("3.7.7 save", "55 AA 03 03 04 00 20 2A", ControlCommand(3, ControlCode.SAVE)),
    ("3.7.8 status", "55 AA 03 01 04 00 22 2A", ControlCommand(1, ControlCode.STATUS)),
    ("3.7.9 clear fault", "55 AA 03 01 04 00 1E 26", ControlCommand(1, ControlCode.CLEAR_FAULT)),
    # Section 3.5.3 gives the broadcast layout without an example; these follow it.
    ("3.5.3 group move", "55 AA 07 FF F2 01 14 05 02 E8 03 FF",
     GroupMoveCommand((Target(1, 1300), Target(2, 1000)))),
    ("3.5.3 group follow", "55 AA 04 FF F3 0F D0 07 DC", GroupFollowCommand((Target(15, 2000),))),
]  # fmt: skip

MANUAL_REPLIES = [
    ("3.5.1 read reply", "AA 55 04 01 01 62 58 02 C2", ReadReply(1, 0x62, b"\x58\x02")),
    # 3.5.4 status reply, with id 1 and no fault filled in for the manual's "**". The manual
    # says "0x03EB = 1000" for the target; the bytes EB 03 are 1003.
    (
        "3.5.4 status reply",
        "AA 55 11 01 04 00 22 EB 03 DE 03 14 64 00 F4 00 01 08 07 0A 07 94",
        StatusReply(1, 1003, 990, 20, 100, 500, Fault(0), 1800, 1802),
    ),
    # 3.4.1: a write answered by one reserved byte.
    ("3.4.1 write reply", "AA 55 03 01 02 37 00 3D", WriteReply(1, 0x37, 0)),
]

VECTORS = [(CommandDecoder, *v) for v in MANUAL_COMMANDS] + [
    (ReplyDecoder, *v) for v in MANUAL_REPLIES
]


@pytest.mark.parametrize(("decoder", "name", "wire", "frame"), VECTORS, ids=[v[1] for v in VECTORS])
def test_manual_vectors_decode(golden, decoder, name, wire, frame):
    golden(decoder, bytes.fromhex(wire), [frame])


@pytest.mark.parametrize(("decoder", "name", "wire", "frame"), VECTORS, ids=[v[1] for v in VECTORS])
def test_manual_vectors_encode(decoder, name, wire, frame):
    assert encode(frame) == bytes.fromhex(wire)


def test_printed_follow_checksum_is_a_mismatch():
    decoder = CommandDecoder()
    decoder.feed(bytes.fromhex("55 AA 04 03 19 37 E8 03 28"))
    first = next(decoder.events())
    assert first == ChecksumMismatch(bytes.fromhex("55AA04031937E80328"), 0x42, 0x28)


@pytest.mark.parametrize("instruction", [0x02, 0x20, 0x21])
def test_a_status_frame_under_the_cmd_byte_of_what_it_answers_is_the_status(instruction):
    """Section 3.4.1 says a reply's cmd byte is its command's; the status frame answering a
    write, a follow or a move is only printed as the status query's, with 04. A frame an
    actuator echoed so was discarded, and every move with a reply timed out."""
    printed = bytes.fromhex("AA 55 11 01 04 00 22 EB 03 DE 03 14 64 00 F4 00 01 08 07 0A 07 94")
    body = bytes((*printed[2:4], instruction, *printed[5:-1]))
    echoed = b"\xaa\x55" + body + bytes((sum(body) & 0xFF,))
    status = StatusReply(1, 1003, 990, 20, 100, 500, Fault(0), 1800, 1802)
    assert _events(ReplyDecoder, printed) == [status]
    assert _events(ReplyDecoder, echoed) == [replace(status, command=instruction)]
    assert encode(replace(status, command=instruction)) == echoed  # the byte kept both ways


STATUS_QUERY = ControlCommand(1, ControlCode.STATUS)
MOVE = MoveCommand(1, 1000)


@pytest.mark.parametrize(("command", "under", "answers"), [
    (STATUS_QUERY, 0x04, True),
    (STATUS_QUERY, 0x21, False),  # a move's answer, late: a stale state for the query's
    (STATUS_QUERY, 0x02, False),
    (MOVE, 0x21, True),
    (MOVE, 0x04, True),  # as the manual prints every status frame
    (MOVE, 0x20, False),  # a follow's, late
    (FollowCommand(1, 1000), 0x20, True),
    (FollowCommand(1, 1000), 0x21, False),
    (WriteCommand(1, 98, b"\x58\x02"), 0x02, True),
    (WriteCommand(1, 98, b"\x58\x02"), 0x04, True),
    (WriteCommand(1, 98, b"\x58\x02"), 0x21, False),
])
def test_a_status_frame_answers_only_a_command_of_the_cmd_byte_it_came_under(command, under,
                                                                            answers):
    """A late status frame under another command's cmd byte (3.4.1: a reply's is its
    command's) is that command's answer, not the next one's: an audit saw a late move's
    status taken for the next status query's. Under the status query's 04, as the manual
    prints it, it answers any: which one it is cannot be told (docs/wire.md)."""
    status = StatusReply(1, 1000, 990, 20, 100, 0, Fault(0), command=under)
    assert expected_reply(command).matches(status) is answers
    assert not expected_reply(command).matches(replace(status, device_id=2))


def test_a_status_frame_under_a_cmd_byte_no_answer_has_is_not_encoded():
    with pytest.raises(EncodeError, match="a status frame comes under cmd 04, 20, 21, 02"):
        encode(StatusReply(1, 0, 0, 0, 0, 0, Fault(0), command=0x01))


def test_status_reply_fault_bits_and_negative_values():
    reply = StatusReply(7, 0, -20, -5, 0, -500, Fault.STALL | Fault.OVER_CURRENT)
    wire = encode(reply)
    assert wire[14:17] == bytes((0x0C, 0x05, 0xFE))  # force low, faults, force high
    decoder = ReplyDecoder()
    decoder.feed(wire)
    assert list(decoder.events()) == [reply]


def test_status_reply_keeps_unknown_fault_bits():
    reply = StatusReply(1, 0, 0, 0, 0, 0, Fault(0x31))
    decoder = ReplyDecoder()
    decoder.feed(encode(reply))
    [event] = decoder.events()
    assert event.faults == 0x31 and Fault.STALL in event.faults


def test_control_reserved_byte_is_ignored():
    raw = bytes.fromhex("03 03 04 07 23")
    decoder = CommandDecoder()
    decoder.feed(b"\x55\xaa" + raw + bytes((sum(raw) & 0xFF,)))
    assert list(decoder.events()) == [ControlCommand(3, ControlCode.ESTOP)]


# --- ranges -------------------------------------------------------------------------------

OUT_OF_RANGE = [
    MoveCommand(0, 1000),
    MoveCommand(256, 1000),
    MoveCommand(1, -1),
    MoveCommand(1, 2001),
    MoveCommand(1, 1000.0),
    FollowCommand(1, 2001, reply=False),
    FollowCommand(0, 10),
    ControlCommand(1, 0x05),
    ControlCommand(1, 0x104),
    ControlCommand(0, ControlCode.ESTOP),
    ReadCommand(255, 0x62, 2),  # broadcast read: nobody would answer
    ReadCommand(0, 0x62, 2),
    ReadCommand(1, 255, 1),
    ReadCommand(1, 0, 0),
    ReadCommand(1, 0, 254),
    ReadCommand(1, 254, 2),
    WriteCommand(1, 0, b"\xaa"),  # table header, reserved
    WriteCommand(1, 3, b"\x00"),  # reserved
    WriteCommand(1, 90, b"\x00"),  # 90-97: missing from the table, reserved
    WriteCommand(1, 102, b"\x00"),  # reserved
    WriteCommand(1, 1, b"\x00\x01"),  # starts on a reserved byte
    WriteCommand(1, 26, b"\x00\x00"),  # current position, read only
    WriteCommand(1, 77, b"\x00"),  # force, read only
    WriteCommand(1, 2, b"\x00"),
    WriteCommand(1, 2, b"\xff"),
    WriteCommand(1, 12, b"\x04"),
    WriteCommand(1, 31, b"\x00"),
    WriteCommand(1, 32, (299).to_bytes(2, "little")),
    WriteCommand(1, 32, (1501).to_bytes(2, "little")),
    WriteCommand(1, 55, (2001).to_bytes(2, "little")),
    WriteCommand(1, 98, (249).to_bytes(2, "little")),
    WriteCommand(1, 98, (801).to_bytes(2, "little")),
    WriteCommand(1, 100, (199).to_bytes(2, "little")),
    WriteCommand(1, 100, (751).to_bytes(2, "little")),
    WriteCommand(1, 98, bytes.fromhex("c102 a002")),  # limit 70.5 °C, rewarm 67.2 °C
    WriteCommand(1, 55, b""),
    WriteCommand(1, 256, b"\x00"),
    WriteCommand(0, 55, b"\x00\x00"),
    GroupMoveCommand(()),
    GroupMoveCommand(tuple(Target(i, 0) for i in range(1, 17))),
    GroupMoveCommand((Target(0, 0),)),
    GroupFollowCommand((Target(255, 0),)),
    GroupFollowCommand((Target(1, 0), Target(1, 5))),
    GroupFollowCommand((Target(1, 2001),)),
    StatusReply(255, 0, 0, 0, 0, 0, Fault(0)),
    StatusReply(1, 0x10000, 0, 0, 0, 0, Fault(0)),
    StatusReply(1, 0, -0x8001, 0, 0, 0, Fault(0)),
    StatusReply(1, 0, 0, 128, 0, 0, Fault(0)),
    StatusReply(1, 0, 0, 0, -1, 0, Fault(0)),
    StatusReply(1, 0, 0, 0, 0, 0x8000, Fault(0)),
    StatusReply(1, 0, 0, 0, 0, 0, 0x100),
    StatusReply(1, 0, 0, 0, 0, 0, Fault(0), -1),
    StatusReply(1, 0, 0, 0, 0, 0, Fault(0), 0, 0x10000),
    ReadReply(0, 0x62, b"\x00"),
    ReadReply(1, 0x62, b""),
    ReadReply(1, 255, b"\x00"),
    WriteReply(1, 255, 0),
    WriteReply(1, 55, 256),
    WriteReply(255, 55, 0),
    "55aa",
]


@pytest.mark.parametrize("frame", OUT_OF_RANGE, ids=repr)
def test_out_of_range_values_are_refused(frame):
    with pytest.raises(EncodeError):
        encode(frame)


@pytest.mark.parametrize(("index", "data"), [(33, b"\x00"), (0x37, b"\x14"), (0x38, b"\x05"),
                                           (0x1F, b"\x00\x00")])
def test_a_write_of_part_of_a_register_is_refused(index, data):
    # The high byte of the over-current limit alone would make it 176 mA (the manual's least
    # is 300), and nobody could say what the register then held: refused, naming it.
    with pytest.raises(EncodeError, match=r"is 2 bytes at \d+: write them both"):
        encode(WriteCommand(1, index, data))


def test_encode_error_names_the_field():
    with pytest.raises(EncodeError) as info:
        encode(MoveCommand(1, 2001))
    assert info.value.field == "target_position" and info.value.value == 2001


# --- damaged input ------------------------------------------------------------------------


def _frame(header: str, body: str) -> bytes:
    raw = bytes.fromhex(body)
    return bytes.fromhex(header) + raw + bytes((sum(raw) & 0xFF,))


def _events(decoder_class, wire: bytes) -> list:
    decoder = decoder_class()
    decoder.feed(wire)
    return list(decoder.events())


@pytest.mark.parametrize(
    ("decoder_class", "body", "reason"),
    [
        (CommandDecoder, "02 01 7F 00", "unknown instruction 0x7f"),
        (CommandDecoder, "04 01 21 38 E8 03", "motion instruction at index 0x38, not 0x37"),
        (CommandDecoder, "03 01 04 00 99", "unknown control code 0x99"),
    ],
)
def test_well_framed_but_unknown_is_discarded_whole(decoder_class, body, reason):
    header = "55 AA" if decoder_class is CommandDecoder else "AA 55"
    wire = _frame(header, body)
    assert _events(decoder_class, wire) == [Discarded(wire, reason)]


def test_a_stray_header_before_a_reply_loses_not_the_reply():
    """An audit's noise on the line: ``AA 55`` then the manual's status reply. The stray pair
    read as a header (length 0xAA, id 0x55, instruction 0x11) held the reply behind it, waiting
    for 175 bytes, until its exchange timed out."""
    reply = bytes.fromhex("AA 55 11 01 04 00 22 EB 03 DE 03 14 64 00 F4 00 01 08 07 0A 07 94")
    events = _events(ReplyDecoder, bytes.fromhex("AA 55") + reply)
    assert [type(event) for event in events] == [Discarded, Discarded, StatusReply]
    assert events[0].reason == "instruction 0x11 answers no command"


@pytest.mark.parametrize(
    ("decoder_class", "head"),
    [
        (CommandDecoder, "55 AA FF 01 21"),  # motion frames have length 4
        (CommandDecoder, "55 AA FF 01 01"),  # reads have length 3
        (CommandDecoder, "55 AA 01 01 7F"),  # no room for instruction and index
        (CommandDecoder, "55 AA 05 FF F2"),  # broadcast length is 1 + 3N
        (CommandDecoder, "55 AA 31 FF F3"),  # N = 16
        (CommandDecoder, "55 AA 07 03 F2"),  # broadcast flag from a single id
        (CommandDecoder, "55 AA 04 00 21"),  # id 0 does not exist
        (ReplyDecoder, "AA 55 FF 01 04"),  # the status reply has length 0x11
        (ReplyDecoder, "AA 55 FF 01 02"),  # a write reply has one data byte, or is the status
        (ReplyDecoder, "AA 55 04 01 02"),
        (ReplyDecoder, "AA 55 03 01 21"),  # a move's reply is the status frame
        (ReplyDecoder, "AA 55 03 01 20"),  # a follow's too
        (ReplyDecoder, "AA 55 11 FF 04"),  # nobody answers as 255
        (ReplyDecoder, "AA 55 03 01 7F"),  # a reply is to a command the host sends
    ],
)
def test_impossible_header_is_dropped_without_waiting_for_a_body(decoder_class, head):
    decoder = decoder_class()
    decoder.feed(bytes.fromhex(head))
    event = decoder.next_event()
    assert isinstance(event, Discarded) and event.data == bytes.fromhex(head)[:1]
    assert decoder.pending == 4


def test_longest_frame_is_awaited_and_bounded():
    data = bytes(range(1, 254))  # 253 bytes: the most one frame carries
    reply = ReadReply(1, 0, data)
    wire = encode(reply)
    assert len(wire) == la.MAX_FRAME == ReplyDecoder.max_frame
    decoder = ReplyDecoder()
    decoder.feed(wire[:-1])
    assert decoder.next_event() is NEED_DATA
    assert decoder.pending == la.MAX_FRAME - 1
    decoder.feed(wire[-1:])
    assert list(decoder.events()) == [reply]


def test_good_frame_inside_a_bad_one_is_found():
    good = encode(MoveCommand(3, 1000))
    # A header whose length claims a 12-byte write swallows the good frame, then fails its sum.
    wire = bytes.fromhex("55 AA 07 01 02 37") + good
    events = _events(CommandDecoder, wire)
    assert isinstance(events[0], ChecksumMismatch)
    assert events[-1] == MoveCommand(3, 1000)


# --- properties ---------------------------------------------------------------------------

ids = st.integers(la.MIN_ID, la.MAX_ID)
command_ids = st.integers(la.MIN_ID, la.BROADCAST_ID)
positions = st.integers(0, 2000)
targets = st.lists(st.builds(Target, ids, positions), min_size=1, max_size=15,
                   unique_by=lambda t: t.device_id).map(tuple)  # fmt: skip
u16 = st.integers(0, 0xFFFF)
i16 = st.integers(-0x8000, 0x7FFF)


@st.composite
def reads(draw, frame_class):
    index = draw(st.integers(0, la.TABLE_SIZE - 1))
    length = draw(st.integers(1, min(la.MAX_DATA, la.TABLE_SIZE - index)))
    if frame_class is ReadCommand:
        return ReadCommand(draw(ids), index, length)
    return ReadReply(draw(ids), index, draw(st.binary(min_size=length, max_size=length)))


@st.composite
def writes(draw):
    """A whole writable register with a value in range."""
    register = draw(st.sampled_from([r for r in la.REGISTERS if r.access.writable]))
    value = draw(st.integers(register.minimum, register.maximum))
    data = value.to_bytes(register.size, "little", signed=register.signed)
    return WriteCommand(draw(command_ids), register.address, data)


commands = st.one_of(
    reads(ReadCommand),
    writes(),
    st.builds(MoveCommand, command_ids, positions, st.booleans()),
    st.builds(FollowCommand, command_ids, positions, st.booleans()),
    st.builds(ControlCommand, command_ids, st.sampled_from(ControlCode)),
    st.builds(GroupMoveCommand, targets),
    st.builds(GroupFollowCommand, targets),
)
faults = st.integers(0, 255).map(Fault)
replies = st.one_of(
    st.builds(StatusReply, ids, u16, i16, st.integers(-128, 127), u16, i16, faults, u16, u16),
    reads(ReadReply),
    st.builds(WriteReply, ids, st.integers(0, la.TABLE_SIZE - 1), st.integers(0, 255)),
)


@given(st.lists(commands, min_size=1, max_size=5), st.data())
def test_commands_round_trip(frames, data):
    wire = b"".join(encode(f) for f in frames)
    cut = data.draw(st.integers(0, len(wire)))
    decoder = CommandDecoder()
    decoder.feed(wire[:cut])
    events = list(decoder.events())
    decoder.feed(wire[cut:])
    assert events + list(decoder.events()) == frames
    assert decoder.pending == 0


@given(st.lists(replies, min_size=1, max_size=5))
def test_replies_round_trip(frames):
    decoder = ReplyDecoder()
    decoder.feed(b"".join(encode(f) for f in frames))
    assert list(decoder.events()) == frames


EVENT_TYPES = (Discarded, ChecksumMismatch, *typing.get_args(la.Frame))


@pytest.mark.parametrize("decoder_class", [CommandDecoder, ReplyDecoder])
@given(chunks=st.lists(st.binary(max_size=300), max_size=8))
def test_arbitrary_bytes_only_make_events(decoder_class, chunks):
    decoder = decoder_class()
    for chunk in chunks:
        decoder.feed(chunk)
        for event in decoder.events():
            assert isinstance(event, EVENT_TYPES)
        assert decoder.pending < decoder.max_frame


@given(replies)
def test_expected_reply_size_covers_the_reply(reply):
    """The reply each command expects has at most the announced size on the wire."""
    wire = encode(reply)
    if isinstance(reply, ReadReply):
        command = ReadCommand(reply.device_id, reply.index, len(reply.data))
    else:
        command = WriteCommand(reply.device_id, getattr(reply, "index", 55), b"\x00\x00")
    expectation = expected_reply(command)
    assert len(wire) <= expectation.wire_bytes
    assert expectation.matches(reply)


# --- what answers what --------------------------------------------------------------------


def _status(device_id: int) -> StatusReply:
    return StatusReply(device_id, 0, 0, 20, 0, 0, Fault(0))


@pytest.mark.parametrize(
    "command",
    [
        MoveCommand(3, 1000),
        FollowCommand(3, 1000),
        ControlCommand(3, ControlCode.STATUS),
        ControlCommand(3, ControlCode.ESTOP),
    ],
)
def test_status_answers(command):
    expectation = expected_reply(command)
    assert (expectation.source_id, expectation.wire_bytes, expectation.kinds,
            expectation.frames) == (3, la.STATUS_REPLY_SIZE, (StatusReply,), 1)
    assert expectation.matches(_status(3))
    assert not expectation.matches(_status(4))
    assert not expectation.matches(ReadReply(3, 0x37, b"\x00"))


@pytest.mark.parametrize(
    "command",
    [
        MoveCommand(3, 1000, reply=False),
        FollowCommand(3, 1000, reply=False),
        MoveCommand(255, 1000),
        ControlCommand(255, ControlCode.ESTOP),
        WriteCommand(255, 55, b"\x00\x00"),
        GroupMoveCommand((Target(1, 0),)),
        GroupFollowCommand((Target(1, 0),)),
    ],
)
def test_no_answer(command):
    assert expected_reply(command) is None


def test_read_answer_matches_its_request_only():
    expectation = expected_reply(ReadCommand(1, 0x62, 2))
    assert expectation.wire_bytes == len(bytes.fromhex("AA 55 04 01 01 62 58 02 C2"))
    assert expectation.matches(ReadReply(1, 0x62, b"\x58\x02"))
    assert not expectation.matches(ReadReply(1, 0x64, b"\x58\x02"))  # another register
    assert not expectation.matches(ReadReply(1, 0x62, b"\x58"))  # another length
    assert not expectation.matches(ReadReply(2, 0x62, b"\x58\x02"))
    assert not expectation.matches(_status(1))


def test_write_answer_is_either_form():
    expectation = expected_reply(WriteCommand(1, 0x37, bytes.fromhex("1405")))
    assert expectation.wire_bytes == la.STATUS_REPLY_SIZE
    assert expectation.matches(WriteReply(1, 0x37))
    assert expectation.matches(_status(1))
    assert not expectation.matches(WriteReply(1, 0x20))
    assert not expectation.matches(WriteReply(2, 0x37))
    assert not expectation.matches(ReadReply(1, 0x37, b"\x00"))


def test_id_change_may_be_answered_by_the_new_id():
    expectation = expected_reply(WriteCommand(3, 2, b"\x02"))  # manual 3.7.1
    assert expectation.matches(_status(3))
    assert expectation.matches(_status(2))
    assert not expectation.matches(_status(4))
    assert expected_reply(WriteCommand(3, 0x37, b"\x00\x00")).new_id is None


def test_expected_reply_refuses_non_commands():
    with pytest.raises(TypeError):
        expected_reply(_status(1))
