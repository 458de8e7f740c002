"""Frames to bytes, both directions: commands for the host, replies for the simulators.

Every frame is ``header, length, id, body, sum`` where ``body`` is the instruction (or the
broadcast flag), the index and the data, ``length == len(body)`` and ``sum`` is the low byte
of the sum of everything after the header. Each encoder checks its values against the
manual's ranges first, so nothing out of range reaches a wire (``EncodeError``).
"""

from __future__ import annotations

from collections.abc import Callable

from busgate.codecs.errors import EncodeError
from busgate.codecs.framing import sum8
from busgate.codecs.inspire_la.frames import (
    BROADCAST_ID,
    COMMAND_HEADER,
    CONTROL_CODES,
    MAX_GROUP_TARGETS,
    MAX_ID,
    MIN_ID,
    REPLY_HEADER,
    STATUS_COMMANDS,
    STATUS_LAYOUT,
    TABLE_SIZE,
    TARGET_INDEX,
    ControlCode,
    ControlCommand,
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
from busgate.codecs.inspire_la.registers import (
    REGISTERS,
    TARGET_POSITION,
    check_span,
    check_write,
)
from busgate.codecs.registers import require_range

Frame = (
    ReadCommand | WriteCommand | MoveCommand | FollowCommand | ControlCommand
    | GroupMoveCommand | GroupFollowCommand | StatusReply | ReadReply | WriteReply
)  # fmt: skip


def encode(frame: Frame) -> bytes:
    """The wire bytes of ``frame``; raises ``EncodeError`` on a value outside the manual's range.

    >>> encode(MoveCommand(3, 1000)).hex(" ")  # manual 3.7.2
    '55 aa 04 03 21 37 e8 03 4a'
    >>> encode(ControlCommand(1, ControlCode.ESTOP)).hex(" ")  # manual 3.5.4
    '55 aa 03 01 04 00 23 2b'
    """
    encoder = _ENCODERS.get(type(frame))
    if encoder is None:
        raise EncodeError(f"not an inspire_la frame: {frame!r}", field="frame", value=frame)
    return encoder(frame)


def _wire(header: bytes, device_id: int, body: bytes) -> bytes:
    checked = bytes((len(body), device_id)) + body
    return header + checked + bytes((sum8(checked),))


def _command_id(device_id: int) -> int:
    return require_range("device_id", device_id, MIN_ID, BROADCAST_ID)


def _reply_id(device_id: int) -> int:
    return require_range("device_id", device_id, MIN_ID, MAX_ID)


def _read(frame: ReadCommand) -> bytes:
    # A read sent to 255 would be executed by everyone and answered by no one.
    device_id = require_range("device_id", frame.device_id, MIN_ID, MAX_ID)
    check_span(frame.index, frame.length)
    return _wire(COMMAND_HEADER, device_id, bytes((Instruction.READ, frame.index, frame.length)))


def _write(frame: WriteCommand) -> bytes:
    device_id = _command_id(frame.device_id)
    check_write(frame.index, frame.data)
    return _wire(COMMAND_HEADER, device_id, bytes((Instruction.WRITE, frame.index)) + frame.data)


def _target(position_raw: int) -> bytes:
    register = REGISTERS[TARGET_POSITION]
    return register.check(position_raw).to_bytes(register.size, "little")


def _motion(instruction: Instruction, device_id: int, position_raw: int) -> bytes:
    body = bytes((instruction, TARGET_INDEX)) + _target(position_raw)
    return _wire(COMMAND_HEADER, _command_id(device_id), body)


def _move(frame: MoveCommand) -> bytes:
    instruction = Instruction.MOVE if frame.reply else Instruction.MOVE_NO_REPLY
    return _motion(instruction, frame.device_id, frame.position_raw)


def _follow(frame: FollowCommand) -> bytes:
    instruction = Instruction.FOLLOW if frame.reply else Instruction.FOLLOW_NO_REPLY
    return _motion(instruction, frame.device_id, frame.position_raw)


def _control(frame: ControlCommand) -> bytes:
    code = require_range("code", frame.code, 0, 0xFF)
    if code not in CONTROL_CODES:
        raise EncodeError(f"unknown control code {code:#04x}", field="code", value=code)
    # The byte between instruction and code is "reserved"; every example sends 00.
    body = bytes((Instruction.CONTROL, 0, code))
    return _wire(COMMAND_HEADER, _command_id(frame.device_id), body)


def _group(flag: Instruction, targets: tuple[Target, ...]) -> bytes:
    require_range("number of targets", len(targets), 1, MAX_GROUP_TARGETS)
    ids = [require_range("target device_id", t.device_id, MIN_ID, MAX_ID) for t in targets]
    if len(set(ids)) != len(ids):
        raise EncodeError(f"target device ids repeat: {ids}", field="targets", value=ids)
    entries = b"".join(bytes((t.device_id,)) + _target(t.position_raw) for t in targets)
    return _wire(COMMAND_HEADER, BROADCAST_ID, bytes((flag,)) + entries)


def _group_move(frame: GroupMoveCommand) -> bytes:
    return _group(Instruction.GROUP_MOVE, frame.targets)


def _group_follow(frame: GroupFollowCommand) -> bytes:
    return _group(Instruction.GROUP_FOLLOW, frame.targets)


def _status(frame: StatusReply) -> bytes:
    if frame.command not in STATUS_COMMANDS:
        raise EncodeError(
            f"a status frame comes under cmd {', '.join(f'{c:02x}' for c in STATUS_COMMANDS)}, "
            f"not {frame.command!r}",
            field="command",
            value=frame.command,
        )
    require_range("force_g", frame.force_g, -0x8000, 0x7FFF)
    force = frame.force_g & 0xFFFF
    values = STATUS_LAYOUT.pack(
        require_range("target_raw", frame.target_raw, 0, 0xFFFF),
        require_range("position_raw", frame.position_raw, -0x8000, 0x7FFF),
        require_range("temperature_c", frame.temperature_c, -0x80, 0x7F),
        require_range("current_ma", frame.current_ma, 0, 0xFFFF),
        force & 0xFF,
        require_range("faults", frame.faults, 0, 0xFF),
        force >> 8,
        require_range("internal_1", frame.internal_1, 0, 0xFFFF),
        require_range("internal_2", frame.internal_2, 0, 0xFFFF),
    )
    body = bytes((frame.command, 0, ControlCode.STATUS)) + values
    return _wire(REPLY_HEADER, _reply_id(frame.device_id), body)


def _read_reply(frame: ReadReply) -> bytes:
    check_span(frame.index, len(frame.data))
    body = bytes((Instruction.READ, frame.index)) + frame.data
    return _wire(REPLY_HEADER, _reply_id(frame.device_id), body)


def _write_reply(frame: WriteReply) -> bytes:
    require_range("index", frame.index, 0, TABLE_SIZE - 1)
    reserved = require_range("reserved", frame.reserved, 0, 0xFF)
    body = bytes((Instruction.WRITE, frame.index, reserved))
    return _wire(REPLY_HEADER, _reply_id(frame.device_id), body)


_ENCODERS: dict[type, Callable[..., bytes]] = {
    ReadCommand: _read,
    WriteCommand: _write,
    MoveCommand: _move,
    FollowCommand: _follow,
    ControlCommand: _control,
    GroupMoveCommand: _group_move,
    GroupFollowCommand: _group_follow,
    StatusReply: _status,
    ReadReply: _read_reply,
    WriteReply: _write_reply,
}
