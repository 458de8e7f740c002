"""DS servo codec: the manual's frames both ways, the encoder's refusals, the decoders' resync,
the control table, and Hypothesis properties (round trip, arbitrary bytes, bounded buffer)."""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from busgate.codecs import ds_servo as ds
from busgate.codecs.errors import EncodeError
from busgate.codecs.framing import ChecksumMismatch, Discarded, ExpectedReply
from busgate.codecs.registers import Access

# Manual chapter 2, every example frame (SYNC WRITE with its checksum corrected: see below).
COMMAND_VECTORS = [
    ("FF FF FE 07 03 2A 08 00 03 E8 DA", ds.Write(254, 0x2A, bytes.fromhex("080003e8"))),  # 2.1
    ("FF FF 01 02 01 FB", ds.Ping(1)),  # 2.3.1
    ("FF FF 01 04 02 38 02 BE", ds.Read(1, 0x38, 2)),  # 2.3.2
    ("FF FF FE 04 03 05 01 F4", ds.Write(254, 0x05, b"\x01")),  # 2.3.3
    ("FF FF 01 07 04 2A 07 D0 03 E8 07", ds.RegWrite(1, 2000, 1000)),  # 2.3.4 / 2.3.5
    ("FF FF 03 07 04 2A 03 E8 07 D0 05", ds.RegWrite(3, 1000, 2000)),  # 2.3.5
    ("FF FF FE 02 05 FA", ds.Action()),  # 2.3.5
    (
        # 2.3.6. Erratum (docs/protocols.md): the manual prints checksum 8B; its own formula
        # gives BA, which is what we send and expect.
        "FF FF FE 0E 83 2A 04 01 07 D0 03 E8 03 07 D0 03 E8 BA",
        ds.SyncWrite((ds.SyncTarget(1, 2000, 1000), ds.SyncTarget(3, 2000, 1000))),
    ),
    ("FF FF 01 02 06 F6", ds.Reset(1)),  # 2.3.7
]
REPLY_VECTORS = [
    ("FF F5 01 03 00 20 DB", ds.StatusReply(1, ds.ServoStatus(0), b"\x20")),  # 2.2
    ("FF F5 01 02 00 FC", ds.StatusReply(1, ds.ServoStatus(0))),  # 2.3.1
    ("FF F5 01 04 00 07 FF F4", ds.StatusReply(1, ds.ServoStatus(0), b"\x07\xff")),  # 2.3.2
]


def wire(text: str) -> bytes:
    return bytes.fromhex(text)


def framed(header: str, body: str) -> bytes:
    """A frame with a correct checksum around ``body`` (id len code params)."""
    raw = wire(body)
    return wire(header) + raw + bytes([ds.checksum(raw)])


def decode_all(decoder_class, data: bytes) -> list:
    decoder = decoder_class()
    decoder.feed(data)
    events = list(decoder.events())
    assert decoder.pending < decoder.max_frame
    return events


# --- golden vectors, both directions ---------------------------------------------------------


@pytest.mark.parametrize(("text", "frame"), COMMAND_VECTORS)
def test_manual_command_decodes(golden, text, frame):
    golden(ds.CommandDecoder, wire(text), [frame])


@pytest.mark.parametrize(("text", "frame"), COMMAND_VECTORS + REPLY_VECTORS)
def test_manual_frame_encodes(text, frame):
    assert ds.encode(frame) == wire(text)


@pytest.mark.parametrize(("text", "frame"), REPLY_VECTORS)
def test_manual_reply_decodes(golden, text, frame):
    golden(ds.ReplyDecoder, wire(text), [frame])


def test_manual_action_sequence_decodes_as_three_commands(golden):
    sequence = "".join(text for text, _ in COMMAND_VECTORS[4:7])
    golden(ds.CommandDecoder, wire(sequence), [frame for _, frame in COMMAND_VECTORS[4:7]])


def test_printed_sync_write_checksum_is_a_mismatch():
    printed = wire("FF FF FE 0E 83 2A 04 01 07 D0 03 E8 03 07 D0 03 E8 8B")
    events = decode_all(ds.CommandDecoder, printed)
    assert events[0] == ChecksumMismatch(printed, expected=0xBA, received=0x8B)


def test_reply_status_flags_decode():
    [reply] = decode_all(ds.ReplyDecoder, framed("FF F5", "07 02 25"))
    assert reply.status == ds.ServoStatus.VOLTAGE | ds.ServoStatus.TEMPERATURE | (
        ds.ServoStatus.OVERLOAD
    )


# --- resynchronisation ----------------------------------------------------------------------


@pytest.mark.parametrize("extra", [1, 2, 5])
def test_command_after_a_run_of_ff(extra):
    ping = wire("FF FF 01 02 01 FB")
    events = decode_all(ds.CommandDecoder, b"\xff" * extra + ping)
    assert events[-1] == ds.Ping(1)
    assert b"".join(e.data for e in events[:-1]) == b"\xff" * extra


def test_broadcast_command_after_a_stray_ff():
    events = decode_all(ds.CommandDecoder, wire("FF FF FF FE 02 05 FA"))
    assert events == [Discarded(b"\xff", "id 255 is neither a servo (1-250) nor broadcast (254)"),
                      ds.Action()]


def test_reply_after_a_run_of_ff():
    events = decode_all(ds.ReplyDecoder, wire("FF FF FF F5 01 02 00 FC"))
    assert events == [Discarded(wire("FF FF"), "no frame header"), ds.StatusReply(1, 0)]


@pytest.mark.parametrize(
    ("prefix", "reason"),
    [
        ("FF FF 00", "id 0 is neither a servo (1-250) nor broadcast (254)"),
        ("FF FF FB", "id 251 is neither a servo (1-250) nor broadcast (254)"),
        ("FF FF 01 03 01", "len 3 is impossible for instruction 0x01"),  # ping has no params
        ("FF FF 01 05 02", "len 5 is impossible for instruction 0x02"),  # read has two
        ("FF FF 01 02 03", "len 2 is impossible for instruction 0x03"),  # write needs an address
        ("FF FF FE 04 83", "len 4 is impossible for instruction 0x83"),
        ("FF FF 01 01 7F", "len 1 is impossible for instruction 0x7f"),
    ],
)
def test_impossible_command_header_drops_one_byte_without_waiting(prefix, reason):
    decoder = ds.CommandDecoder()
    decoder.feed(wire(prefix))
    assert decoder.next_event() == Discarded(b"\xff", reason)


@pytest.mark.parametrize(
    ("prefix", "reason"),
    [
        ("FF F5 FE", "id 254 is not a servo id (1-250)"),
        ("FF F5 00", "id 0 is not a servo id (1-250)"),
        ("FF F5 01 01", "len 1 is below 2"),
    ],
)
def test_impossible_reply_header_drops_one_byte_without_waiting(prefix, reason):
    decoder = ds.ReplyDecoder()
    decoder.feed(wire(prefix))
    assert decoder.next_event() == Discarded(b"\xff", reason)


SYNC_SHAPE = "SYNC WRITE carries id + position + move time (4 bytes) per servo"


@pytest.mark.parametrize(
    ("body", "reason"),
    [
        ("01 02 07", "unknown instruction 0x07"),
        ("01 05 40 01 02 03", "unknown instruction 0x40"),
        ("FE 02 01", "ping cannot be sent to the broadcast id 254"),
        ("FE 04 02 38 02", "read cannot be sent to the broadcast id 254"),
        ("01 05 03 38 00 00", "present_position (0x38) is read only"),
        ("01 07 04 2B 07 D0 03 E8", "REG WRITE only writes address 0x2a"),
        ("01 05 04 2A 07 D0", "REG WRITE carries position and move time (4 bytes)"),
        ("FE 07 04 2A 07 D0 03 E8", "REG WRITE cannot be sent to the broadcast id 254"),
        ("01 07 04 2A 10 00 03 E8", "target_position 4096 is out of range [0, 4095]"),
        ("01 02 05", "ACTION is always sent to the broadcast id"),
        ("01 09 83 2A 04 01 07 D0 03 E8", "SYNC WRITE is always sent to the broadcast id"),
        ("FE 09 83 2C 04 01 07 D0 03 E8", "SYNC WRITE only writes address 0x2a"),
        ("FE 07 83 2A 02 01 07 D0", SYNC_SHAPE),
        ("FE 08 83 2A 04 01 07 D0 03", SYNC_SHAPE),
        ("FE 0E 83 2A 04 01 07 D0 03 E8 01 07 D0 03 E8", "SYNC WRITE targets need distinct ids"),
    ],
)
def test_checked_command_breaking_the_rules_is_discarded_whole(body, reason):
    frame = framed("FF FF", body)
    assert decode_all(ds.CommandDecoder, frame) == [Discarded(frame, reason)]


def test_reply_with_reserved_status_bits_keeps_them():
    [reply] = decode_all(ds.ReplyDecoder, framed("FF F5", "05 02 C0"))
    assert int(reply.status) == 0xC0
    assert ds.encode(reply) == framed("FF F5", "05 02 C0")


# --- the encoder's refusals ------------------------------------------------------------------


@pytest.mark.parametrize(
    ("frame", "field"),
    [
        (ds.Ping(0), "device_id"),
        (ds.Ping(251), "device_id"),
        (ds.Ping(254), "device_id"),
        (ds.Ping(255), "device_id"),
        (ds.Read(254, 0x38, 2), "device_id"),
        (ds.Read(1, 0x43, 1), "address"),
        (ds.Read(1, -1, 1), "address"),
        (ds.Read(1, 0x42, 2), "length"),
        (ds.Read(1, 0x00, 0), "length"),
        (ds.Write(0, 0x28, b"\x01"), "device_id"),
        (ds.Write(255, 0x28, b"\x01"), "device_id"),
        (ds.Write(1, 0x38, b"\x00\x00"), "address"),  # present position: read only
        (ds.Write(1, 0x2E, b"\x00\x00"), "address"),  # current: read only
        (ds.Write(1, 0x07, b"\x00"), "address"),  # not in the table
        (ds.Write(1, 0x43, b"\x00"), "address"),  # past the table
        (ds.Write(1, 0x100, b"\x00"), "address"),
        (ds.Write(1, 0x2B, b"\x00"), "address"),  # inside target position
        (ds.Write(1, 0x2A, b"\x07"), "data"),  # ends inside target position
        (ds.Write(1, 0x2A, b"\x10\x00"), "target_position"),
        (ds.Write(1, 0x2A, b"\x07\xd0\x03"), "data"),  # ends inside move time
        (ds.Write(1, 0x05, b"\x00"), "servo_id"),
        (ds.Write(1, 0x05, b"\xfb"), "servo_id"),
        (ds.Write(1, 0x05, b"\xfe"), "servo_id"),
        (ds.Write(1, 0x28, b""), "data"),
        (ds.Write(1, 0x3C, b"\x01"), "data"),  # go to preset: address alone
        (ds.Write(1, 0x16, b"\x08\x00"), "data"),  # store preset: address alone
        (ds.Write(1, 0x14, b"\x00\x00\x08\x00"), "address"),  # runs into preset 1
        (ds.RegWrite(254, 2000, 1000), "device_id"),
        (ds.RegWrite(1, 4096, 0), "target_position"),
        (ds.RegWrite(1, -1, 0), "target_position"),
        (ds.RegWrite(1, 0, 65536), "move_time"),
        (ds.RegWrite(1, 0, -1), "move_time"),
        (ds.Reset(0), "device_id"),
        (ds.Reset(253), "device_id"),
        (ds.SyncWrite(()), "number of targets"),
        (ds.SyncWrite(tuple(ds.SyncTarget(i, 0, 0) for i in range(1, 52))), "number of targets"),
        (ds.SyncWrite((ds.SyncTarget(1, 0, 0), ds.SyncTarget(1, 5, 0))), "targets"),
        (ds.SyncWrite((ds.SyncTarget(254, 0, 0),)), "device_id"),
        (ds.SyncWrite((ds.SyncTarget(0, 0, 0),)), "device_id"),
        (ds.SyncWrite((ds.SyncTarget(2, 4096, 0),)), "target_position"),
        (ds.SyncWrite((ds.SyncTarget(2, 0, 70000),)), "move_time"),
        (ds.StatusReply(254, ds.ServoStatus(0)), "device_id"),
        (ds.StatusReply(1, ds.ServoStatus(0x100)), "status"),
        (ds.StatusReply(1, ds.ServoStatus(0), bytes(254)), "params"),
    ],
)
def test_encode_refuses_out_of_range(frame, field):
    with pytest.raises(EncodeError) as info:
        ds.encode(frame)
    assert info.value.field == field


def test_sync_write_takes_fifty_targets():
    frame = ds.SyncWrite(tuple(ds.SyncTarget(i, 4095, 65535) for i in range(1, 51)))
    encoded = ds.encode(frame)
    assert len(encoded) == 6 + 2 + 5 * 50
    assert decode_all(ds.CommandDecoder, encoded) == [frame]


def test_largest_frame_decodes():
    reply = ds.StatusReply(1, ds.ServoStatus(0), bytes(253))  # len = 0xFF
    encoded = ds.encode(reply)
    assert len(encoded) == ds.MAX_FRAME == 259
    assert decode_all(ds.ReplyDecoder, encoded) == [reply]


@pytest.mark.parametrize("function", [ds.encode, ds.expected_reply])
def test_foreign_objects_are_a_type_error(function):
    with pytest.raises(TypeError):
        function(ExpectedReply(1, 6, ()))


def test_writes_the_table_allows():
    ds.check_write(0x2A, wire("0FFF FFFF"))  # position and time in one write (manual 2.1)
    ds.check_write(0x14, wire("FFFE"))  # centre offset is signed: -2
    ds.check_write(0x09, wire("0000 0FFF"))  # min and max angle together
    for address in ds.ADDRESS_ONLY_WRITES:
        ds.check_write(address, b"")


# --- expected replies ------------------------------------------------------------------------


def status(device_id: int, wire_bytes: int, new_id: int | None = None) -> ds.ExpectedStatus:
    return ds.ExpectedStatus(source_id=device_id, wire_bytes=wire_bytes,
                             kinds=(ds.StatusReply,), data_length=wire_bytes - 6, new_id=new_id)


@pytest.mark.parametrize(
    ("frame", "expected"),
    [
        (ds.Ping(7), status(7, 6)),
        (ds.Read(1, 0x38, 2), status(1, 8)),
        (ds.Read(2, 0x00, 0x43), status(2, 6 + 0x43)),
        (ds.Write(3, 0x28, b"\x01"), status(3, 6)),
        (ds.RegWrite(1, 2000, 1000), status(1, 6)),
        (ds.Reset(250), status(250, 6, new_id=1)),  # the factory id
        (ds.Write(3, 0x05, b"\x07"), status(3, 6, new_id=7)),
        (ds.Write(254, 0x05, b"\x01"), None),
        (ds.Reset(254), None),
        (ds.Action(), None),
        (ds.SyncWrite((ds.SyncTarget(1, 0, 0),)), None),
        (ds.StatusReply(1, ds.ServoStatus(0)), None),
    ],
)
def test_expected_reply(frame, expected):
    assert ds.expected_reply(frame) == expected


def test_expected_reply_matches_its_servo_only_with_the_bytes_it_asked_for():
    expected = ds.expected_reply(ds.Read(1, 0x38, 2))
    assert expected.matches(ds.StatusReply(1, ds.ServoStatus(0), b"\x07\xff"))
    assert not expected.matches(ds.StatusReply(2, ds.ServoStatus(0), b"\x07\xff"))
    # a write's status, come late: no bytes, or too few, answer no READ
    assert not expected.matches(ds.StatusReply(1, ds.ServoStatus(0)))
    assert not expected.matches(ds.StatusReply(1, ds.ServoStatus(0), b"\x07"))
    assert not ds.expected_reply(ds.Write(1, 0x28, b"\x01")).matches(
        ds.StatusReply(1, ds.ServoStatus(0), b"\x07\xff"))


def test_a_new_id_is_answered_from_either_id_the_manual_does_not_say_which():
    set_id = ds.expected_reply(ds.Write(3, 0x05, b"\x07"))
    assert set_id.matches(ds.StatusReply(3, ds.ServoStatus(0)))
    assert set_id.matches(ds.StatusReply(7, ds.ServoStatus(0)))
    assert not set_id.matches(ds.StatusReply(5, ds.ServoStatus(0)))
    assert ds.expected_reply(ds.Reset(3)).matches(ds.StatusReply(1, ds.ServoStatus(0)))
    assert not ds.expected_reply(ds.Ping(3)).matches(ds.StatusReply(1, ds.ServoStatus(0)))


# --- the control table -----------------------------------------------------------------------

R, W, RW = Access.READ, Access.WRITE, Access.READ_WRITE
# Manual chapter 3, row by row: name, address, size, access, default.
MANUAL_TABLE = [
    ("firmware_version", 0x03, 2, R, None),
    ("servo_id", 0x05, 1, RW, 1),
    ("stall_protection_time", 0x06, 1, RW, 3),
    ("min_angle", 0x09, 2, RW, 0),
    ("max_angle", 0x0B, 2, RW, 4095),
    ("max_torque", 0x10, 2, RW, 800),
    ("speed_adjust", 0x12, 1, RW, 30),
    ("unload_condition", 0x13, 1, RW, 0),
    ("centre_offset", 0x14, 2, RW, 0),
    ("preset_1", 0x16, 2, RW, 2048),
    ("preset_2", 0x18, 2, RW, 2048),
    ("preset_3", 0x1A, 2, RW, 2048),
    ("motor_mode", 0x1C, 1, RW, None),
    ("motor_direction", 0x1D, 1, RW, None),
    ("torque_enable", 0x28, 1, RW, None),
    ("target_position", 0x2A, 2, RW, None),
    ("move_time", 0x2C, 2, RW, 0),
    ("current", 0x2E, 2, R, None),
    ("lock_flag", 0x30, 1, RW, None),
    ("present_position", 0x38, 2, R, None),
    ("speed", 0x3A, 2, R, None),
    ("goto_preset_1", 0x3C, 1, W, None),
    ("goto_preset_2", 0x3D, 1, W, None),
    ("goto_preset_3", 0x3E, 1, W, None),
    ("temperature", 0x3F, 1, R, None),
    ("reg_write_pending", 0x40, 1, R, None),
    ("speed_adjust_16", 0x41, 2, RW, None),
]


def test_control_table_is_the_manuals():
    rows = [(r.name, r.address, r.size, r.access, r.default) for r in ds.REGISTERS]
    assert rows == MANUAL_TABLE
    assert ds.TABLE_END == 0x43
    assert ds.REGISTERS["centre_offset"].signed
    assert (ds.REGISTERS["move_time"].unit, ds.REGISTERS["current"].unit) == ("ms", "mA")
    assert ds.REGISTERS["temperature"].unit == "°C"
    assert ds.REGISTERS["stall_protection_time"].unit == "s"


@pytest.mark.parametrize(
    ("address", "data", "values"),
    [
        (0x38, "07FF", {"present_position": 2047}),  # manual 2.3.2
        (0x2A, "07D0 03E8 0064", {"target_position": 2000, "move_time": 1000, "current": 100}),
        (0x14, "FFFE", {"centre_offset": -2}),
        (0x2B, "D0 03E8", {"move_time": 1000}),  # starts inside a register: skipped
        (0x38, "07", {}),  # ends inside one
        (0x00, "0000 00 011C 05", {"firmware_version": 0x011C, "servo_id": 5}),  # across a gap
    ],
)
def test_values_from_read_bytes(address, data, values):
    assert ds.values_from(address, wire(data)) == values


# --- properties ------------------------------------------------------------------------------

servo_ids = st.integers(ds.MIN_ID, ds.MAX_ID)
any_ids = servo_ids | st.just(ds.BROADCAST_ID)
positions = st.integers(0, 4095)
times = st.integers(0, 0xFFFF)


def _register_value(register):
    bits = 8 * register.size
    if register.signed:
        low, high = -(1 << (bits - 1)), (1 << (bits - 1)) - 1
    else:
        low, high = 0, (1 << bits) - 1
    low = low if register.minimum is None else register.minimum
    high = high if register.maximum is None else register.maximum
    return st.integers(low, high).map(
        lambda v: v.to_bytes(register.size, "big", signed=register.signed)
    )


_WRITABLE = [
    r for r in ds.REGISTERS if r.access.writable and r.address not in ds.ADDRESS_ONLY_WRITES
]


@st.composite
def writes(draw):
    if draw(st.booleans()):
        return ds.Write(draw(any_ids), draw(st.sampled_from(sorted(ds.ADDRESS_ONLY_WRITES))), b"")
    first = draw(st.integers(0, len(_WRITABLE) - 1))
    run = [_WRITABLE[first]]
    for register in _WRITABLE[first + 1 :]:
        if register.address != run[-1].end or not draw(st.booleans()):
            break
        run.append(register)
    data = b"".join(draw(_register_value(r)) for r in run)
    return ds.Write(draw(any_ids), run[0].address, data)


@st.composite
def reads(draw):
    address = draw(st.integers(0, ds.TABLE_END - 1))
    return ds.Read(draw(servo_ids), address, draw(st.integers(1, ds.TABLE_END - address)))


sync_targets = st.builds(ds.SyncTarget, servo_ids, positions, times)
commands = st.one_of(
    st.builds(ds.Ping, servo_ids),
    reads(),
    writes(),
    st.builds(ds.RegWrite, servo_ids, positions, times),
    st.just(ds.Action()),
    st.builds(ds.Reset, any_ids),
    st.lists(
        sync_targets, min_size=1, max_size=ds.MAX_SYNC_TARGETS, unique_by=lambda t: t.device_id
    ).map(lambda targets: ds.SyncWrite(tuple(targets))),
)
replies = st.builds(
    ds.StatusReply, servo_ids, st.integers(0, 0xFF).map(ds.ServoStatus), st.binary(max_size=253)
)
# Bytes biased towards the headers and valid ids, so that random input reaches deep branches.
wire_bytes = st.lists(
    st.sampled_from([0xFF, 0xF5, 0x01, 0x02, 0x04, 0xFE, 0x83, 0x2A]) | st.integers(0, 255),
    max_size=600,
).map(bytes)


@given(st.lists(commands, min_size=1, max_size=4))
def test_commands_round_trip(frames):
    assert decode_all(ds.CommandDecoder, b"".join(map(ds.encode, frames))) == frames


@given(st.lists(replies, min_size=1, max_size=4))
def test_replies_round_trip(frames):
    assert decode_all(ds.ReplyDecoder, b"".join(map(ds.encode, frames))) == frames


@pytest.mark.parametrize(
    ("decoder_class", "kinds"),
    [(ds.CommandDecoder, ds.Command), (ds.ReplyDecoder, ds.StatusReply)],
)
@given(data=wire_bytes, chunk=st.integers(1, 64))
def test_arbitrary_bytes_only_make_events(decoder_class, kinds, data, chunk):
    decoder = decoder_class()
    for start in range(0, len(data), chunk):
        decoder.feed(data[start : start + chunk])
        for event in decoder.events():
            assert isinstance(event, kinds | Discarded | ChecksumMismatch)
            if not isinstance(event, Discarded | ChecksumMismatch):
                assert ds.encode(event) in data  # a decoded frame is one that was sent
        assert decoder.pending < decoder.max_frame
