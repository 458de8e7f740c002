"""Bytes to frames: ``CommandDecoder`` (actuator side, ``55 AA``) and ``ReplyDecoder`` (host side,
``AA 55``).

Both check the cheap header fields — length, id, instruction — as soon as the first five
bytes are in, before waiting for the body: an instruction with a fixed size must carry exactly
that length, broadcast frames must come from id 255, replies from ids 1–254. A corrupt
header is thus discarded at once instead of holding the decoder for up to 255 bytes. A
command with a sound header and checksum but an instruction we do not know becomes
``Discarded``; a reply's instruction is its command's, so a reply header naming none the host
sends is noise (a stray ``AA 55`` before a reply read as length 0xAA held the reply behind it).
"""

from __future__ import annotations

from collections.abc import Callable, Container
from typing import ClassVar

from busgate.codecs.framing import Discarded, HeaderFramedDecoder, sum8
from busgate.codecs.inspire_la.frames import (
    BROADCAST_ID,
    COMMAND_HEADER,
    CONTROL_CODES,
    FRAME_OVERHEAD,
    GROUP_ENTRY_SIZE,
    MAX_FRAME,
    MAX_GROUP_TARGETS,
    MAX_ID,
    MAX_LENGTH,
    MIN_ID,
    REPLY_HEADER,
    STATUS_COMMANDS,
    STATUS_LAYOUT,
    STATUS_REPLY_SIZE,
    TARGET_INDEX,
    ControlCode,
    ControlCommand,
    Fault,
    FollowCommand,
    GroupFollowCommand,
    GroupMoveCommand,
    Instruction,
    MoveCommand,
    ReadCommand,
    ReadReply,
    StatusReply,
    Target,
    WriteCommand,
    WriteReply,
)

#: Instruction and index without data: the shortest an unknown instruction's frame can be.
_ANY_LENGTH = range(2, MAX_LENGTH + 1)
#: Instruction, index and at least one data byte.
_WITH_DATA = range(3, MAX_LENGTH + 1)
#: The flag byte and 1 to 15 entries.
_GROUP_LENGTHS = range(
    1 + GROUP_ENTRY_SIZE, 2 + GROUP_ENTRY_SIZE * MAX_GROUP_TARGETS, GROUP_ENTRY_SIZE
)


def _exactly(value: int) -> range:
    return range(value, value + 1)


_BROADCAST_ONLY = _exactly(BROADCAST_ID)


class _LaDecoder(HeaderFramedDecoder[object]):
    """What both directions share; subclasses fill in the tables."""

    max_frame = MAX_FRAME
    #: Allowed values of the length byte, per instruction.
    lengths: ClassVar[dict[int, Container[int]]]
    #: Those of an instruction not in ``lengths``: any (framed, then ``Discarded``) or none.
    unknown_lengths: ClassVar[Container[int]] = _ANY_LENGTH
    #: Allowed device ids, per instruction (others: ``default_ids``).
    ids: ClassVar[dict[int, range]] = {}
    default_ids: ClassVar[range]
    #: Instruction → function from a checked frame to its event.
    decoders: ClassVar[dict[int, Callable[[bytes], object]]]

    def _frame_size(self, buf: bytearray, start: int) -> int | str | None:
        if len(buf) - start < FRAME_OVERHEAD:
            return None
        length, device_id, instruction = buf[start + 2 : start + 5]
        if instruction not in self.lengths and not self.unknown_lengths:
            return f"instruction {instruction:#04x} answers no command"
        if length not in self.lengths.get(instruction, self.unknown_lengths):
            return f"length {length} impossible for instruction {instruction:#04x}"
        if device_id not in self.ids.get(instruction, self.default_ids):
            return f"device id {device_id} impossible for instruction {instruction:#04x}"
        return length + FRAME_OVERHEAD

    def _checksum(self, frame: bytes) -> int:
        return sum8(frame[2:-1])

    def _decode(self, frame: bytes) -> object:
        decode = self.decoders.get(frame[4])
        if decode is None:
            return Discarded(frame, f"unknown instruction {frame[4]:#04x}")
        return decode(frame)


# Frame layout for every decoder below: 0-1 header, 2 length, 3 id, 4 instruction, 5 index,
# 6.. data, -1 checksum. Broadcast frames have no index: their entries start at 5.


def _read_command(frame: bytes) -> ReadCommand:
    return ReadCommand(frame[3], frame[5], frame[6])


def _write_command(frame: bytes) -> WriteCommand:
    return WriteCommand(frame[3], frame[5], frame[6:-1])


_MOTION: dict[Instruction, tuple[type[MoveCommand] | type[FollowCommand], bool]] = {
    Instruction.MOVE: (MoveCommand, True),
    Instruction.MOVE_NO_REPLY: (MoveCommand, False),
    Instruction.FOLLOW: (FollowCommand, True),
    Instruction.FOLLOW_NO_REPLY: (FollowCommand, False),
}


def _motion_command(frame: bytes) -> MoveCommand | FollowCommand | Discarded:
    if frame[5] != TARGET_INDEX:
        return Discarded(frame, f"motion instruction at index {frame[5]:#04x}, not 0x37")
    frame_class, reply = _MOTION[Instruction(frame[4])]
    return frame_class(frame[3], int.from_bytes(frame[6:8], "little"), reply)


def _control_command(frame: bytes) -> ControlCommand | Discarded:
    # Byte 5 is "reserved" (00 in every example); the device has no use for it, nor do we.
    if frame[6] not in CONTROL_CODES:
        return Discarded(frame, f"unknown control code {frame[6]:#04x}")
    return ControlCommand(frame[3], ControlCode(frame[6]))


def _group_targets(frame: bytes) -> tuple[Target, ...]:
    entries = frame[5:-1]
    return tuple(
        Target(entries[i], int.from_bytes(entries[i + 1 : i + 3], "little"))
        for i in range(0, len(entries), GROUP_ENTRY_SIZE)
    )


#: The length byte of the status frame, and of section 3.4.1's answer to a write.
STATUS_LENGTH = STATUS_REPLY_SIZE - FRAME_OVERHEAD
WRITE_REPLY_LENGTH = 3
#: The commands the status frame answers, besides a write (whose answer has two lengths).
_ANSWERED_BY_STATUS = tuple(i for i in STATUS_COMMANDS if i is not Instruction.WRITE)


def _status_reply(frame: bytes) -> StatusReply:
    # Bytes 5-6 read 00 22 (the status query's code) in the manual. The replies to the other
    # commands are only said to be "the same as the status query's", so they are not checked;
    # byte 4 is kept, for the exchange to tell whose answer it is (``exchange``).
    target, position, temperature, current, force_lo, faults, force_hi, in1, in2 = (
        STATUS_LAYOUT.unpack_from(frame, 7)
    )
    force = int.from_bytes(bytes((force_lo, force_hi)), "little", signed=True)
    return StatusReply(
        frame[3], target, position, temperature, current, force, Fault(faults), in1, in2, frame[4]
    )


class CommandDecoder(_LaDecoder):
    """Decodes host commands (``55 AA …``), as an actuator or a bus sniffer sees them.

    >>> decoder = CommandDecoder()
    >>> decoder.feed(bytes.fromhex("55 AA 04 03 21 37 E8 03 4A"))  # manual 3.7.2
    >>> list(decoder.events())
    [MoveCommand(device_id=3, position_raw=1000, reply=True)]
    """

    header = COMMAND_HEADER
    lengths: ClassVar[dict[int, Container[int]]] = {
        Instruction.READ: _exactly(3),
        Instruction.WRITE: _WITH_DATA,
        **{instruction: _exactly(4) for instruction in _MOTION},
        Instruction.CONTROL: _exactly(3),
        Instruction.GROUP_MOVE: _GROUP_LENGTHS,
        Instruction.GROUP_FOLLOW: _GROUP_LENGTHS,
    }
    ids: ClassVar[dict[int, range]] = {
        Instruction.GROUP_MOVE: _BROADCAST_ONLY,
        Instruction.GROUP_FOLLOW: _BROADCAST_ONLY,
    }
    default_ids = range(MIN_ID, BROADCAST_ID + 1)
    decoders: ClassVar[dict[int, Callable[[bytes], object]]] = {
        Instruction.READ: _read_command,
        Instruction.WRITE: _write_command,
        **{instruction: _motion_command for instruction in _MOTION},
        Instruction.CONTROL: _control_command,
        Instruction.GROUP_MOVE: lambda frame: GroupMoveCommand(_group_targets(frame)),
        Instruction.GROUP_FOLLOW: lambda frame: GroupFollowCommand(_group_targets(frame)),
    }


class ReplyDecoder(_LaDecoder):
    """Decodes actuator replies (``AA 55 …``), as the host sees them.

    >>> decoder = ReplyDecoder()
    >>> decoder.feed(bytes.fromhex("AA 55 04 01 01 62 58 02 C2"))  # manual 3.5.1
    >>> list(decoder.events())
    [ReadReply(device_id=1, index=98, data=b'X\\x02')]
    """

    header = REPLY_HEADER
    unknown_lengths: ClassVar[Container[int]] = ()
    lengths: ClassVar[dict[int, Container[int]]] = {
        Instruction.READ: _WITH_DATA,
        # Section 3.4.1's one reserved byte, or the status frame (sections 3.5.2, 3.7.x).
        Instruction.WRITE: (WRITE_REPLY_LENGTH, STATUS_LENGTH),
        # The status frame under the cmd byte of the command it answers (section 3.4.1: a
        # reply's cmd is its command's), besides the status query's own 04 the manual prints.
        **{instruction: _exactly(STATUS_LENGTH) for instruction in _ANSWERED_BY_STATUS},
    }
    default_ids = range(MIN_ID, MAX_ID + 1)
    decoders: ClassVar[dict[int, Callable[[bytes], object]]] = {
        Instruction.READ: lambda frame: ReadReply(frame[3], frame[5], frame[6:-1]),
        Instruction.WRITE: lambda frame: (
            WriteReply(frame[3], frame[5], frame[6])
            if frame[2] == WRITE_REPLY_LENGTH
            else _status_reply(frame)
        ),
        **{instruction: _status_reply for instruction in _ANSWERED_BY_STATUS},
    }
