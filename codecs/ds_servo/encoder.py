"""Frames to wire bytes, and what reply each command brings.

This is the one place frame values are checked against the manual (ids, addressing rules,
the control table's ranges): the decoder re-encodes what it parsed, so a frame it yields is
always one ``encode`` accepts and gives back byte for byte.

Wire format: ``header id len code params… sum`` with ``len = len(params) + 2`` and
``sum = ~(id + len + code + params) & 0xFF``; multi-byte values are big-endian.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from busgate.codecs.ds_servo.frames import (
    BROADCAST_ID,
    COMMAND_HEADER,
    FRAME_OVERHEAD,
    MAX_ID,
    MAX_PARAMS,
    MAX_SYNC_TARGETS,
    MIN_ID,
    MOVE_ADDRESS,
    MOVE_DATA_SIZE,
    REPLY_HEADER,
    Action,
    Frame,
    Instruction,
    Ping,
    Read,
    RegWrite,
    Reset,
    StatusReply,
    SyncWrite,
    Write,
)
from busgate.codecs.ds_servo.registers import REGISTERS, check_read, check_write, values_from
from busgate.codecs.errors import EncodeError
from busgate.codecs.framing import ExpectedReply
from busgate.codecs.registers import require_range


def checksum(body: bytes | bytearray) -> int:
    """The manual's checksum of ``id len code params…``: the low byte of the inverted sum.

    >>> hex(checksum(bytes.fromhex("01 02 01")))   # ping id 1 (manual 2.3.1)
    '0xfb'
    """
    return ~sum(body) & 0xFF


def encode(frame: Frame) -> bytes:
    """The wire bytes of ``frame``; ``EncodeError`` when a value is outside the manual's range.

    >>> encode(RegWrite(device_id=1, position_raw=2000, time_ms=1000)).hex(" ")
    'ff ff 01 07 04 2a 07 d0 03 e8 07'
    >>> encode(Ping(device_id=254))
    Traceback (most recent call last):
    ...
    busgate.codecs.errors.EncodeError: ping cannot be sent to the broadcast id 254
    """
    try:
        parts = _PARTS[type(frame)]
    except KeyError:
        raise TypeError(f"not a ds_servo frame: {frame!r}") from None
    header, device_id, code, params = parts(frame)
    if len(params) > MAX_PARAMS:
        raise EncodeError(
            f"{len(params)} parameter bytes do not fit one frame (at most {MAX_PARAMS})",
            field="params",
            value=len(params),
        )
    body = bytes([device_id, len(params) + 2, code]) + params
    return header + body + bytes([checksum(body)])


@dataclass(frozen=True, slots=True, kw_only=True)
class ExpectedStatus(ExpectedReply):
    """A status reply carrying ``data_length`` bytes: a READ's, the bytes read; any other
    command's, none. The wire does not say which command a status answers, so its length is
    what tells a late answer to another command (a write's, empty) from a READ's own.

    A write of the id, and a factory reset, give the servo another id at once; the manual
    does not say which one answers, so ``new_id`` is taken too (as an LA's is)."""

    data_length: int
    new_id: int | None = None

    def matches(self, event: object) -> bool:
        """True when ``event`` is this command's status reply."""
        return (
            isinstance(event, self.kinds)
            and getattr(event, "device_id", None) in (self.source_id, self.new_id)
            and len(getattr(event, "data", b"")) == self.data_length
        )


def expected_reply(frame: Frame) -> ExpectedReply | None:
    """The status reply a command brings (``ExpectedStatus``), or ``None`` (broadcast, ACTION,
    SYNC WRITE, a reply).

    >>> expected_reply(Read(device_id=1, address=0x38, length=2)).wire_bytes
    8
    >>> expected_reply(Write(device_id=254, address=0x05, data=b"\\x01")) is None
    True
    """
    try:
        data_bytes = _REPLY_DATA[type(frame)](frame)
    except KeyError:
        raise TypeError(f"not a ds_servo frame: {frame!r}") from None
    device_id = getattr(frame, "device_id", BROADCAST_ID)
    if data_bytes is None or device_id == BROADCAST_ID:
        return None
    return ExpectedStatus(
        source_id=device_id,
        wire_bytes=FRAME_OVERHEAD + data_bytes,
        kinds=(StatusReply,),
        data_length=data_bytes,
        new_id=id_given(frame),
    )


def id_given(frame: Frame) -> int | None:
    """The id ``frame`` gives its servo: a write of the id register's, a reset's factory id
    (manual 2.3.7: "all data"); ``None`` for any other frame.

    >>> id_given(Write(device_id=3, address=0x05, data=b"\\x07")), id_given(Reset(device_id=3))
    (7, 1)
    """
    if isinstance(frame, Reset):
        return REGISTERS.default("servo_id")
    if isinstance(frame, Write):
        return values_from(frame.address, frame.data).get("servo_id")
    return None


def move_data(position_raw: int, time_ms: int) -> bytes:
    """Target position then move time, as written at 0x2A: checked, big-endian.

    >>> move_data(2000, 1000).hex()
    '07d003e8'
    """
    REGISTERS["target_position"].check(position_raw)
    REGISTERS["move_time"].check(time_ms)
    return position_raw.to_bytes(2, "big") + time_ms.to_bytes(2, "big")


def _servo_id(device_id: int, what: str) -> int:
    """A single servo's id: broadcast is refused by name, since it is the usual mistake."""
    if device_id == BROADCAST_ID:
        raise EncodeError(
            f"{what} cannot be sent to the broadcast id {BROADCAST_ID}",
            field="device_id",
            value=device_id,
        )
    return require_range("device_id", device_id, MIN_ID, MAX_ID)


def _any_id(device_id: int) -> int:
    if device_id == BROADCAST_ID:
        return device_id
    return require_range("device_id", device_id, MIN_ID, MAX_ID)


def _read(frame: Read) -> bytes:
    check_read(frame.address, frame.length)
    return bytes([frame.address, frame.length])


def _write(frame: Write) -> bytes:
    check_write(frame.address, frame.data)
    return bytes([frame.address]) + frame.data


def _sync_write(frame: SyncWrite) -> bytes:
    targets = frame.targets
    require_range("number of targets", len(targets), 1, MAX_SYNC_TARGETS)
    ids = [_servo_id(target.device_id, "a SYNC WRITE target") for target in targets]
    if len(set(ids)) != len(ids):
        raise EncodeError("SYNC WRITE targets need distinct ids", field="targets", value=ids)
    params = bytearray([MOVE_ADDRESS, MOVE_DATA_SIZE])
    for target in targets:
        params.append(target.device_id)
        params += move_data(target.position_raw, target.time_ms)
    return bytes(params)


def _status(frame: StatusReply) -> int:
    return require_range("status", frame.status, 0, 0xFF)


# Each entry gives (header, id, instruction or status byte, parameters), values checked.
_PARTS: dict[type, Callable[[Any], tuple[bytes, int, int, bytes]]] = {
    Ping: lambda f: (COMMAND_HEADER, _servo_id(f.device_id, "ping"), Instruction.PING, b""),
    Read: lambda f: (COMMAND_HEADER, _servo_id(f.device_id, "read"), Instruction.READ, _read(f)),
    Write: lambda f: (COMMAND_HEADER, _any_id(f.device_id), Instruction.WRITE, _write(f)),
    RegWrite: lambda f: (
        COMMAND_HEADER,
        _servo_id(f.device_id, "REG WRITE"),
        Instruction.REG_WRITE,
        bytes([MOVE_ADDRESS]) + move_data(f.position_raw, f.time_ms),
    ),
    Action: lambda f: (COMMAND_HEADER, BROADCAST_ID, Instruction.ACTION, b""),
    Reset: lambda f: (COMMAND_HEADER, _any_id(f.device_id), Instruction.RESET, b""),
    SyncWrite: lambda f: (COMMAND_HEADER, BROADCAST_ID, Instruction.SYNC_WRITE, _sync_write(f)),
    StatusReply: lambda f: (REPLY_HEADER, _servo_id(f.device_id, "a reply"), _status(f), f.data),
}

# Data bytes of the status reply each frame brings when sent to one servo; None: no reply.
_REPLY_DATA: dict[type, Callable[[Any], int | None]] = {
    Ping: lambda f: 0,
    Read: lambda f: f.length,
    Write: lambda f: 0,
    RegWrite: lambda f: 0,
    Reset: lambda f: 0,
    Action: lambda f: None,
    SyncWrite: lambda f: None,
    StatusReply: lambda f: None,
}
