"""Frames to CAN frames: the one place the ZLAC706 CAN frame ranges are checked.

Every frame is ``group func 00 reg`` and four value bytes, big-endian. A write to a known
register is checked against ``REGISTERS`` (and its ``CODES``); a write to an unknown register
is still encodable as any i32, because a simulated node must be able to receive one to answer
``FF`` (the gateway's driver refuses them before they get here).
"""

from __future__ import annotations

from collections.abc import Callable

from busgate.codecs.can_frame import CanFrame
from busgate.codecs.errors import EncodeError
from busgate.codecs.framing import ExpectedReply
from busgate.codecs.registers import require_range
from busgate.codecs.zlac706_can.frames import (
    ALARM_REGISTER,
    BROADCAST_ID,
    DATA_LENGTH,
    MAX_NODE_ID,
    AlarmReport,
    Func,
    HeartbeatCurrentSpeed,
    HeartbeatPosition,
    HeartbeatRegister,
    NoSuchRegister,
    Write,
    WriteAck,
)
from busgate.codecs.zlac706_can.registers import CODES, I32_MAX, I32_MIN, REGISTERS

#: For each frame kind: its function code to a node, and to all (identifier 0).
FUNCS: dict[type, tuple[Func, Func | None]] = {
    Write: (Func.WRITE, Func.BROADCAST_WRITE),
    WriteAck: (Func.WRITE_ACK, Func.BROADCAST_ACK),
    NoSuchRegister: (Func.NO_SUCH_REGISTER, Func.BROADCAST_NO_SUCH_REGISTER),
    HeartbeatPosition: (Func.HEARTBEAT, None),
    HeartbeatCurrentSpeed: (Func.HEARTBEAT, None),
    AlarmReport: (Func.NO_SUCH_REGISTER, None),
}


def encode(frame: object) -> CanFrame:
    """The CAN frame of ``frame``; raises ``EncodeError`` when a value is out of range.

    >>> from busgate.codecs.zlac706_can.registers import CanRegister
    >>> str(encode(Write(1, CanRegister.TARGET_POSITION, 123456)))
    '001#00fa00160001e240'
    >>> str(encode(HeartbeatCurrentSpeed(1, 0x1E, 0x043F)))
    '001#00fe0021001e043f'
    """
    try:
        to_node, to_all = FUNCS[type(frame)]
    except KeyError:
        raise EncodeError(f"not a ZLAC706 CAN frame: {frame!r}", field="frame") from None
    device_id = frame.device_id  # type: ignore[attr-defined]
    require_range("device_id", device_id, BROADCAST_ID if to_all else 1, MAX_NODE_ID)
    func = to_all if to_all is not None and device_id == BROADCAST_ID else to_node
    head = bytes([require_range("group", frame.group, 0, 0xFF), func, 0])  # type: ignore[attr-defined]
    return CanFrame(device_id, head + _BODIES[type(frame)](frame))


def _write_body(frame: Write) -> bytes:
    register = REGISTERS.at(require_range("register", frame.register, 0, 0xFF))
    value = frame.value
    if register is None:
        require_range("value", value, I32_MIN, I32_MAX)
    else:
        register.check(value)
        codes = CODES.get(register.address)
        if codes is not None and value not in set(codes):
            allowed = ", ".join(f"{code:#04x}" for code in codes)
            raise EncodeError(
                f"{register.name} {value:#x} is not one of {allowed}",
                field=register.name,
                value=value,
            )
    return _register_value(frame.register, value)


def _echo_body(frame: WriteAck | NoSuchRegister) -> bytes:
    require_range("register", frame.register, 0, 0xFF)
    return _register_value(frame.register, require_range("value", frame.value, I32_MIN, I32_MAX))


def _register_value(register: int, value: int) -> bytes:
    return bytes([register]) + value.to_bytes(4, "big", signed=True)


def _position_body(frame: HeartbeatPosition) -> bytes:
    require_range("position_raw", frame.position_raw, I32_MIN, I32_MAX)
    return _register_value(HeartbeatRegister.POSITION, frame.position_raw)


def _current_speed_body(frame: HeartbeatCurrentSpeed) -> bytes:
    current = require_range("current_raw", frame.current_raw, 0, 0xFFFF)
    speed = require_range("speed_raw", frame.speed_raw, -0x8000, 0x7FFF)
    return (
        bytes([HeartbeatRegister.CURRENT_SPEED])
        + current.to_bytes(2, "big")
        + speed.to_bytes(2, "big", signed=True)
    )


def _alarm_body(frame: AlarmReport) -> bytes:
    return bytes([ALARM_REGISTER, *[require_range("alarms", frame.alarms, 0, 0xFF)] * 4])


_BODIES: dict[type, Callable] = {
    Write: _write_body,
    WriteAck: _echo_body,
    NoSuchRegister: _echo_body,
    HeartbeatPosition: _position_body,
    HeartbeatCurrentSpeed: _current_speed_body,
    AlarmReport: _alarm_body,
}


def expected_reply(frame: object) -> ExpectedReply | None:
    """What answers ``frame``: a write to a node gets one 8-byte ``FB`` or ``FF`` frame from it,
    echoing its register and value ("the rest of the frame as it came", 8.1.1): the echo of
    another write, come after its own timed out, answers no other.

    A broadcast write gets ``None``: every node answers ``DB`` on the same identifier 0 with
    the same bytes, so the answers merge on the bus and cannot be counted or told apart.

    >>> from busgate.codecs.zlac706_can.registers import CanRegister
    >>> expected_reply(Write(10, CanRegister.WORK_MODE, 0x3F)).source_id
    10
    >>> expected_reply(Write(0, CanRegister.WORK_MODE, 0x3F)) is None
    True
    """
    if isinstance(frame, Write) and frame.device_id != BROADCAST_ID:
        echo = (("register", frame.register), ("value", frame.value))
        return ExpectedReply(frame.device_id, DATA_LENGTH, (WriteAck, NoSuchRegister), echo=echo)
    return None
