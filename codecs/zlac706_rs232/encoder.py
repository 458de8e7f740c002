"""Frames to bytes: the one place the ZLAC706 RS232 frame ranges are checked.

A 16-bit field is narrower than the shared commands allow (a CAN value is 32 bits), so this
is where "fits CAN but not RS232" becomes an ``EncodeError``: every value is checked against
its ``REGISTERS`` row, and a write must name a writable register (the decoder finds frames
by their first byte, so an unknown address could not be read back).
"""

from __future__ import annotations

from collections.abc import Callable

from busgate.codecs.errors import EncodeError
from busgate.codecs.framing import ExpectedReply, sum8
from busgate.codecs.registers import Register
from busgate.codecs.zlac706_rs232.frames import (
    ACK_SIZE,
    FRAME_SIZE,
    MONITOR_FIELDS,
    MONITOR_FRAMES,
    MONITOR_REQUEST,
    Ack,
    BusVoltage,
    MonitorRequest,
    OutputCurrent,
    OutputSpeed,
    PositionWord,
    StatusReport,
    Write,
)
from busgate.codecs.zlac706_rs232.registers import CODES, POSITION_ITEMS, REGISTERS, WRITABLE


def encode(frame: object) -> bytes:
    """The bytes of ``frame``; raises ``EncodeError`` when a value is out of range.

    >>> from busgate.codecs.zlac706_rs232.registers import Rs232Register
    >>> encode(Write(Rs232Register.SPEED, -136)).hex(" ")
    '06 ff 78 7d'
    >>> encode(Ack(Rs232Register.POSITION_RAMP)).hex(" ")
    '09 09'
    """
    try:
        encoder = _ENCODERS[type(frame)]
    except KeyError:
        raise EncodeError(f"not a ZLAC706 RS232 frame: {frame!r}", field="frame") from None
    return encoder(frame)


def _register(address: int, allowed: frozenset[int], what: str) -> Register:
    register = REGISTERS.at(address) if address in allowed else None
    if register is None:
        raise EncodeError(f"{address!r} is not {what}", field="register", value=address)
    return register


def _word_frame(register: Register, value: int) -> bytes:
    register.check(value)
    head = bytes([register.address]) + (value & 0xFFFF).to_bytes(2, "big")
    return head + bytes([sum8(head)])


def _write(frame: Write) -> bytes:
    register = _register(frame.register, WRITABLE, "a writable RS232 register")
    codes = CODES.get(register.address)
    if codes is not None and frame.value not in set(codes):
        allowed = ", ".join(f"{code:#06x}" for code in codes)
        raise EncodeError(
            f"{register.name} {frame.value!r} is not one of {allowed}",
            field=register.name,
            value=frame.value,
        )
    return _word_frame(register, frame.value)


def _ack(frame: Ack) -> bytes:
    register = _register(frame.register, WRITABLE, "a writable RS232 register")
    return bytes([register.address] * ACK_SIZE)


def _monitor_value(frame: StatusReport | BusVoltage | OutputCurrent | OutputSpeed) -> bytes:
    item, name = MONITOR_FIELDS[type(frame)]
    return _word_frame(REGISTERS.at(item), getattr(frame, name))  # type: ignore[arg-type]


def _position_word(frame: PositionWord) -> bytes:
    return _word_frame(_register(frame.item, POSITION_ITEMS, "a position item"), frame.value)


_ENCODERS: dict[type, Callable[..., bytes]] = {
    Write: _write,
    MonitorRequest: lambda _frame: MONITOR_REQUEST,
    Ack: _ack,
    StatusReport: _monitor_value,
    BusVoltage: _monitor_value,
    OutputCurrent: _monitor_value,
    OutputSpeed: _monitor_value,
    PositionWord: _position_word,
}


def expected_reply(frame: object) -> ExpectedReply | None:
    """What answers ``frame``: a write gets the 2-byte ``Ack`` naming its register (an ack of
    another write, come late, answers no other), a monitor request eight frames.

    The link is point to point and RS232 frames carry no id, so ``source_id`` is ``None``
    (the events have no ``device_id`` either, which is what ``matches`` compares).

    >>> expected_reply(MonitorRequest()).wire_bytes, expected_reply(MonitorRequest()).frames
    (32, 8)
    """
    if isinstance(frame, Write):
        return ExpectedReply(None, ACK_SIZE, (Ack,), echo=(("register", frame.register),))
    if isinstance(frame, MonitorRequest):
        kinds = (*MONITOR_FIELDS, PositionWord)
        return ExpectedReply(None, FRAME_SIZE * MONITOR_FRAMES, kinds, frames=MONITOR_FRAMES)
    return None
