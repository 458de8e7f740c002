"""Who answers which command, with what: ``expected_reply`` for the bus owner.

Control and motion-with-reply commands are answered by the 22-byte status frame, under the
status query's cmd byte or the command's own (never another command's: a late answer to it).
A read is answered by ``7 + length`` bytes that must echo the index and carry ``length``
bytes, so that a late answer to an earlier read cannot be taken for this one. A write is answered
either by the one-reserved-byte frame of section 3.4.1 or by the status frame of sections
3.5.2 and 3.7.x (an erratum: docs/protocols.md): the wait is sized for the longer. Frames to
id 255 and the no-reply instructions get no answer.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from busgate.codecs.framing import ExpectedReply
from busgate.codecs.inspire_la.frames import (
    BROADCAST_ID,
    FRAME_OVERHEAD,
    STATUS_REPLY_SIZE,
    ControlCommand,
    FollowCommand,
    GroupFollowCommand,
    GroupMoveCommand,
    Instruction,
    MoveCommand,
    ReadCommand,
    ReadReply,
    StatusReply,
    WriteCommand,
    WriteReply,
)
from busgate.codecs.inspire_la.registers import ID, REGISTERS

#: A read reply is a read command's frame plus its data: header, length, id, 01, index, sum.
READ_REPLY_OVERHEAD = FRAME_OVERHEAD + 2


@dataclass(frozen=True, slots=True, kw_only=True)
class ExpectedStatus(ExpectedReply):
    """The status frame that answers a command whose cmd byte is ``command``: one under that
    byte (3.4.1) or the status query's ``04`` (the one the manual prints: LA-7). One under
    another command's byte is a late answer to that command, not this one's (a status query
    answered by a move's status frame would report a stale state)."""

    command: int

    def matches(self, event: object) -> bool:
        """True when ``event`` answers the command this was made for."""
        return (
            isinstance(event, StatusReply)
            and event.device_id == self.source_id
            and event.command in (self.command, Instruction.CONTROL)
        )


@dataclass(frozen=True, slots=True, kw_only=True)
class ExpectedRegisterReply(ExpectedReply):
    """The answer to a read or write: it must also echo ``index`` (and, for a read, carry
    ``length`` bytes). A status frame answering a write has no index: it matches on id and
    cmd byte (``02`` or ``04``).

    A write of the id register takes effect at once; the manual does not say whether the
    answer still comes from the old id, so ``new_id`` is accepted too.
    """

    index: int
    length: int | None = None
    new_id: int | None = None

    def matches(self, event: object) -> bool:
        """True when ``event`` answers the read or write this was made for."""
        # Not super().matches(): zero-argument super() breaks in slotted dataclasses on 3.11.
        if not isinstance(event, self.kinds):
            return False
        if getattr(event, "device_id", None) not in (self.source_id, self.new_id):
            return False
        if isinstance(event, StatusReply):
            return event.command in (Instruction.WRITE, Instruction.CONTROL)
        if not isinstance(event, ReadReply | WriteReply) or event.index != self.index:
            return False
        return self.length is None or (
            isinstance(event, ReadReply) and len(event.data) == self.length
        )


def expected_reply(command: object) -> ExpectedReply | None:
    """What answers ``command``, or ``None`` when nothing does.

    >>> expected_reply(MoveCommand(3, 1000)).wire_bytes  # 55 AA 04 03 21 37 E8 03 4A
    22
    >>> expected_reply(FollowCommand(3, 1000, reply=False)) is None  # 55 AA 04 03 19 …
    True
    """
    try:
        rule = _RULES[type(command)]
    except KeyError:
        raise TypeError(f"not an inspire_la command frame: {command!r}") from None
    return rule(command)


def _status(device_id: int, command: Instruction, wanted: bool = True) -> ExpectedReply | None:
    if not wanted or device_id == BROADCAST_ID:
        return None
    return ExpectedStatus(
        source_id=device_id, wire_bytes=STATUS_REPLY_SIZE, kinds=(StatusReply,), command=command
    )


def _read(command: ReadCommand) -> ExpectedReply:
    return ExpectedRegisterReply(
        source_id=command.device_id,
        wire_bytes=READ_REPLY_OVERHEAD + command.length,
        kinds=(ReadReply,),
        index=command.index,
        length=command.length,
    )


def _write(command: WriteCommand) -> ExpectedReply | None:
    if command.device_id == BROADCAST_ID:
        return None
    id_register = REGISTERS[ID]
    offset = id_register.address - command.index
    new_id = command.data[offset] if 0 <= offset < len(command.data) else None
    return ExpectedRegisterReply(
        source_id=command.device_id,
        wire_bytes=STATUS_REPLY_SIZE,  # the longer of the two possible answers
        kinds=(WriteReply, StatusReply),
        index=command.index,
        new_id=new_id,
    )


_RULES: dict[type, Callable[..., ExpectedReply | None]] = {
    ControlCommand: lambda command: _status(command.device_id, Instruction.CONTROL),
    MoveCommand: lambda command: _status(command.device_id, Instruction.MOVE, command.reply),
    FollowCommand: lambda command: _status(command.device_id, Instruction.FOLLOW, command.reply),
    ReadCommand: _read,
    WriteCommand: _write,
    GroupMoveCommand: lambda command: None,
    GroupFollowCommand: lambda command: None,
}
