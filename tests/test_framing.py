"""The shared codec machinery, on a toy protocol: header AB CD, length, payload, sum8."""

from __future__ import annotations

from dataclasses import dataclass

import pytest
from hypothesis import given
from hypothesis import strategies as st

from busgate import errors
from busgate.codecs import errors as codec_errors
from busgate.codecs.can_frame import CanFrame
from busgate.codecs.framing import (
    NEED_DATA,
    ChecksumMismatch,
    Discarded,
    ExpectedReply,
    HeaderFramedDecoder,
    MessageDecoder,
    NeedData,
    sum8,
)
from busgate.codecs.registers import Access, Register, RegisterMap, require_range


@dataclass(frozen=True, slots=True)
class Toy:
    device_id: int
    payload: bytes


class ToyDecoder(HeaderFramedDecoder[Toy]):
    header = b"\xab\xcd"
    max_frame = 2 + 1 + 1 + 8 + 1

    def _frame_size(self, buf, start):
        if len(buf) - start < 3:
            return None
        length = buf[start + 2]
        return f"length {length} is too long" if length > 8 else 2 + 1 + 1 + length + 1

    def _checksum(self, frame):
        return sum8(frame[2:-1])

    def _decode(self, frame):
        if frame[3] == 0:
            return Discarded(frame, "id 0 is not a device")
        return Toy(frame[3], frame[4:-1])


def toy(device_id: int, payload: bytes) -> bytes:
    body = bytes([len(payload), device_id]) + payload
    return b"\xab\xcd" + body + bytes([sum8(body)])


def test_golden_machinery_on_toy_frame(golden) -> None:
    golden(ToyDecoder, toy(7, b"\x01\x02"), [Toy(7, b"\x01\x02")])


def test_need_data_is_a_singleton_sentinel() -> None:
    assert NeedData() is NEED_DATA
    assert repr(NEED_DATA) == "NEED_DATA"
    assert ToyDecoder().next_event() is NEED_DATA


def test_trailing_partial_header_is_kept_not_discarded() -> None:
    decoder = ToyDecoder()
    decoder.feed(b"\x11\x22\xab")
    assert list(decoder.events()) == [Discarded(b"\x11\x22", "no frame header")]
    assert decoder.pending == 1
    decoder.feed(toy(1, b"")[1:])
    assert list(decoder.events()) == [Toy(1, b"")]


def test_impossible_length_drops_one_byte_and_rescans() -> None:
    decoder = ToyDecoder()
    decoder.feed(b"\xab\xcd\x30" + toy(2, b"\x05"))
    events = list(decoder.events())
    assert events[0] == Discarded(b"\xab", "length 48 is too long")
    assert events[-1] == Toy(2, b"\x05")


def test_checksum_mismatch_reports_both_sums() -> None:
    frame = bytearray(toy(3, b"\x09"))
    frame[-1] ^= 0xFF
    decoder = ToyDecoder()
    decoder.feed(bytes(frame))
    first = decoder.next_event()
    assert first == ChecksumMismatch(bytes(frame), sum8(frame[2:-1]), frame[-1])


def test_unknown_but_valid_frame_is_discarded_by_the_protocol() -> None:
    decoder = ToyDecoder()
    decoder.feed(toy(0, b"\x01"))
    assert list(decoder.events()) == [Discarded(toy(0, b"\x01"), "id 0 is not a device")]


@given(st.lists(st.binary(max_size=40), max_size=20))
def test_arbitrary_chunks_only_make_events_and_stay_bounded(chunks) -> None:
    decoder = ToyDecoder()
    for chunk in chunks:
        decoder.feed(chunk)
        for event in decoder.events():
            assert isinstance(event, Toy | Discarded | ChecksumMismatch)
        assert decoder.pending < decoder.max_frame


@given(st.binary(max_size=200), st.integers(1, 255), st.binary(max_size=8))
def test_a_frame_after_any_noise_is_found(noise, device_id, payload) -> None:
    decoder = ToyDecoder()
    decoder.feed(noise + toy(device_id, payload))
    assert Toy(device_id, payload) in list(decoder.events())


class ByteMessages(MessageDecoder[bytes, Toy]):
    max_pending = 3

    def _decode(self, message):
        return Toy(message[0], message[1:]) if message else Discarded(message, "empty")


def test_message_decoder_drops_oldest_when_full_and_says_so() -> None:
    decoder = ByteMessages()
    for i in range(1, 6):
        decoder.feed(bytes([i]))
    assert decoder.pending == 3
    events = list(decoder.events())
    assert events[0] == Discarded(b"", "2 frames dropped: decoder queue full")
    assert events[1:] == [Toy(3, b""), Toy(4, b""), Toy(5, b"")]
    assert decoder.next_event() is NEED_DATA


def test_expected_reply_matches_kind_and_source() -> None:
    expected = ExpectedReply(source_id=4, wire_bytes=22, kinds=(Toy,))
    assert expected.matches(Toy(4, b""))
    assert not expected.matches(Toy(5, b""))
    assert not expected.matches(Discarded(b"", "x"))


def test_register_check_uses_table_bounds_then_size_bounds() -> None:
    target = Register("target", 0x37, 2, Access.READ_WRITE, minimum=0, maximum=2000)
    assert target.check(2000) == 2000
    with pytest.raises(codec_errors.EncodeError, match="target 2001 is out of range"):
        target.check(2001)
    offset = Register("offset", 0x14, 2, Access.READ_WRITE, signed=True)
    assert offset.check(-32768) == -32768
    with pytest.raises(codec_errors.EncodeError):
        offset.check(32768)
    assert target.limits == (0, 2000) and offset.limits == (-32768, 32767)
    assert not Register("pos", 1, 2, Access.READ).access.writable
    assert not Register("go", 1, 1, Access.WRITE).access.readable


def test_require_range_refuses_non_integers() -> None:
    for bad in (True, 1.0, "1", None):
        with pytest.raises(codec_errors.EncodeError, match="must be an integer"):
            require_range("x", bad, 0, 10)


def test_register_map_lookups_and_overlap_guards() -> None:
    a = Register("a", 2, 2, Access.READ_WRITE)
    b = Register("b", 5, 1, Access.READ)
    table = RegisterMap([b, a])
    assert [r.name for r in table] == ["a", "b"] and len(table) == 2
    assert table["a"] is a and table.at(3) is a and table.at(4) is None
    assert table.covering(3, 3) == [a, None, b]
    assert RegisterMap([Register("d", 1, 1, Access.READ_WRITE, default=7)]).default("d") == 7
    with pytest.raises(KeyError, match="no default"):
        table.default("a")
    with pytest.raises(ValueError, match="defined twice"):
        RegisterMap([a, a])
    with pytest.raises(ValueError, match="in two registers"):
        RegisterMap([a, Register("c", 3, 1, Access.READ)])


def test_can_frame_text_round_trip_and_refusals() -> None:
    frame = CanFrame.parse("001#00fa0011fffff556")
    assert frame == CanFrame(1, bytes.fromhex("00fa0011fffff556"))
    assert str(frame) == "001#00fa0011fffff556"
    for bad in ("00fa", "#00", "xyz#00", "800#00", "001#" + "00" * 9, "001#0"):
        with pytest.raises(codec_errors.EncodeError):
            CanFrame.parse(bad)


def test_error_tree_codes_and_builtin_twins() -> None:
    """The codecs' errors join busgate's one tree (``busgate.errors``) with codes of their own."""
    encode = codec_errors.EncodeError
    assert issubclass(encode, ValueError) and encode.code == "out_of_range"
    assert issubclass(encode, errors.CommandError), "a command the wire cannot carry"
    assert issubclass(codec_errors.CodecError, errors.BusgateError)
    assert issubclass(errors.DeviceTimeoutError, TimeoutError)
    assert issubclass(errors.BusUnavailableError, ConnectionError)
    silent = errors.DeviceTimeoutError("no reply", device="la1", device_id=1)
    assert (silent.device, silent.device_id) == ("la1", 1)
    assert silent.code == "device_timeout"
    config = errors.ConfigError("bad baud", path="buses[0].baudrate")
    assert config.path == "buses[0].baudrate"
    # The SDK's classes (busgate.client.errors) mirror these codes, one class per code of a
    # reply, on purpose: what a client catches, not what busgate raises on its side.
    own = [cls.code for cls in _all_subclasses(errors.BusgateError)
           if "code" in vars(cls) and cls.__module__ != "busgate.client.errors"]
    assert len(set(own)) == len(own), "every class that names a code names a new one"


def _all_subclasses(cls):
    found = {cls}  # each once, though a class may have two parents in the tree
    for sub in cls.__subclasses__():
        found |= _all_subclasses(sub)
    return found
