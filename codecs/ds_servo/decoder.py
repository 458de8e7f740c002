"""Wire bytes to frames: ``CommandDecoder`` (servo side) and ``ReplyDecoder`` (host side).

Both scan for their header and check the cheap fields (id, then ``len`` against what the
instruction allows) before waiting for a body, so a corrupted header costs one byte, not a
wait for up to 259 bytes. The command header FF FF can sit inside a run of FF bytes
(``FF FF FF 01 …``): the id byte FF is never valid, so the scan moves one byte on and finds
the real frame there.

A checked frame is parsed into its dataclass and then re-encoded, so the one set of rules in
``encoder`` decides what a valid frame is; a frame that breaks them (a ping to the broadcast
id, a write to a read-only register, an unknown instruction) becomes ``Discarded`` with the
encoder's reason.
"""

from __future__ import annotations

from collections.abc import Callable

from busgate.codecs.ds_servo.encoder import checksum, encode
from busgate.codecs.ds_servo.frames import (
    BROADCAST_ID,
    COMMAND_HEADER,
    MAX_FRAME,
    MAX_ID,
    MAX_PARAMS,
    MIN_ID,
    MOVE_ADDRESS,
    MOVE_DATA_SIZE,
    REPLY_HEADER,
    Action,
    Command,
    Instruction,
    Ping,
    Read,
    RegWrite,
    Reset,
    ServoStatus,
    StatusReply,
    SyncTarget,
    SyncWrite,
    Write,
)
from busgate.codecs.errors import EncodeError
from busgate.codecs.framing import Discarded, HeaderFramedDecoder

# Parameter counts the manual's instruction table (2.3) allows, checked from the header.
_PARAM_COUNTS: dict[int, tuple[int, int]] = {
    Instruction.PING: (0, 0),
    Instruction.READ: (2, 2),
    Instruction.WRITE: (1, MAX_PARAMS),
    Instruction.REG_WRITE: (2, MAX_PARAMS),
    Instruction.ACTION: (0, 0),
    Instruction.RESET: (0, 0),
    Instruction.SYNC_WRITE: (3, MAX_PARAMS),
}
_ANY_COUNT = (0, MAX_PARAMS)


def _u16(data: bytes) -> int:
    return int.from_bytes(data, "big")


def _move_at(params: bytes, what: str) -> None:
    """REG WRITE and SYNC WRITE only write position + time at 0x2A (manual 2.3.4, 2.3.6)."""
    if params[0] != MOVE_ADDRESS:
        raise EncodeError(
            f"{what} only writes address {MOVE_ADDRESS:#04x}", field="address", value=params[0]
        )


def _reg_write(device_id: int, params: bytes) -> RegWrite:
    _move_at(params, "REG WRITE")
    if len(params) != 1 + MOVE_DATA_SIZE:
        raise EncodeError(
            "REG WRITE carries position and move time (4 bytes)",
            field="data",
            value=params[1:].hex(),
        )
    return RegWrite(device_id, _u16(params[1:3]), _u16(params[3:5]))


def _broadcast_only(device_id: int, what: str) -> None:
    """ACTION and SYNC WRITE frames carry no servo id of their own (manual 2.3.5, 2.3.6)."""
    if device_id != BROADCAST_ID:
        raise EncodeError(
            f"{what} is always sent to the broadcast id", field="device_id", value=device_id
        )


def _action(device_id: int, params: bytes) -> Action:
    _broadcast_only(device_id, "ACTION")
    return Action()


def _sync_write(device_id: int, params: bytes) -> SyncWrite:
    _broadcast_only(device_id, "SYNC WRITE")
    _move_at(params, "SYNC WRITE")
    entry = 1 + MOVE_DATA_SIZE
    if params[1] != MOVE_DATA_SIZE or (len(params) - 2) % entry:
        raise EncodeError(
            "SYNC WRITE carries id + position + move time (4 bytes) per servo",
            field="data",
            value=params[1:].hex(),
        )
    return SyncWrite(
        tuple(
            SyncTarget(params[i], _u16(params[i + 1 : i + 3]), _u16(params[i + 3 : i + 5]))
            for i in range(2, len(params), entry)
        )
    )


_PARSERS: dict[int, Callable[[int, bytes], Command]] = {
    Instruction.PING: lambda device_id, params: Ping(device_id),
    Instruction.READ: lambda device_id, params: Read(device_id, params[0], params[1]),
    Instruction.WRITE: lambda device_id, params: Write(device_id, params[0], params[1:]),
    Instruction.REG_WRITE: _reg_write,
    Instruction.ACTION: _action,
    Instruction.RESET: lambda device_id, params: Reset(device_id),
    Instruction.SYNC_WRITE: _sync_write,
}


class CommandDecoder(HeaderFramedDecoder[Command]):
    """Decodes host commands, as a servo (or its simulator) receives them.

    >>> decoder = CommandDecoder()
    >>> decoder.feed(bytes.fromhex("ff ff ff 01 02 01 fb"))   # a stray FF, then ping id 1
    >>> list(decoder.events())
    [Discarded(data=b'\\xff', reason='id 255 is neither a servo (1-250) nor broadcast (254)'), \
Ping(device_id=1)]
    """

    header = COMMAND_HEADER
    max_frame = MAX_FRAME

    def _frame_size(self, buf: bytearray, start: int) -> int | str | None:
        available = len(buf) - start
        if available < 3:
            return None
        device_id = buf[start + 2]
        if not (MIN_ID <= device_id <= MAX_ID or device_id == BROADCAST_ID):
            return (
                f"id {device_id} is neither a servo ({MIN_ID}-{MAX_ID}) nor broadcast "
                f"({BROADCAST_ID})"
            )
        if available < 5:
            return None
        length, code = buf[start + 3], buf[start + 4]
        low, high = _PARAM_COUNTS.get(code, _ANY_COUNT)
        if not low + 2 <= length <= high + 2:
            return f"len {length} is impossible for instruction {code:#04x}"
        return length + 4

    def _checksum(self, frame: bytes) -> int:
        return checksum(frame[2:-1])

    def _decode(self, frame: bytes) -> Command | Discarded:
        device_id, code, params = frame[2], frame[4], frame[5:-1]
        parse = _PARSERS.get(code)
        if parse is None:
            return Discarded(frame, f"unknown instruction {code:#04x}")
        try:
            command = parse(device_id, params)
            encode(command)
        except EncodeError as exc:
            return Discarded(frame, str(exc))
        return command


class ReplyDecoder(HeaderFramedDecoder[StatusReply]):
    """Decodes servo replies, as the host receives them.

    >>> decoder = ReplyDecoder()
    >>> decoder.feed(bytes.fromhex("ff f5 01 04 00 07 ff f4"))   # manual 2.3.2: position 0x07FF
    >>> list(decoder.events())
    [StatusReply(device_id=1, status=<ServoStatus: 0>, data=b'\\x07\\xff')]
    """

    header = REPLY_HEADER
    max_frame = MAX_FRAME

    def _frame_size(self, buf: bytearray, start: int) -> int | str | None:
        available = len(buf) - start
        if available < 3:
            return None
        device_id = buf[start + 2]
        if not MIN_ID <= device_id <= MAX_ID:
            return f"id {device_id} is not a servo id ({MIN_ID}-{MAX_ID})"
        if available < 4:
            return None
        length = buf[start + 3]
        return length + 4 if length >= 2 else f"len {length} is below 2"

    def _checksum(self, frame: bytes) -> int:
        return checksum(frame[2:-1])

    def _decode(self, frame: bytes) -> StatusReply:
        return StatusReply(frame[2], ServoStatus(frame[4]), frame[5:-1])
