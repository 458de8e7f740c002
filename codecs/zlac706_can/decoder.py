"""CAN frames to ZLAC706 frames, for both ends of the bus.

``CommandDecoder`` (a node, or a simulator) takes the host's writes; ``ReplyDecoder`` (the
host) takes echoes, heartbeats and alarm reports. Both are fed whole ``CanFrame`` objects and
never raise: a frame that is not 8 bytes, has a non-zero register high byte, an unknown
function code, or a function code that does not fit its identifier (``DA`` is only sent to
identifier 0, ``FA`` never is) becomes ``Discarded``. There is no checksum to verify: the
CAN controller has already checked the frame's CRC.

``FF`` is both "no such register" and the alarm report; the alarm report is the one with
register ``EB`` and the same code in all four data bytes (a write to the non-existent
register EB with such a value would look the same: the manual gives no way to tell them
apart, and no host has a reason to write EB).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import TypeVar

from busgate.codecs.can_frame import CanFrame
from busgate.codecs.framing import Discarded, MessageDecoder
from busgate.codecs.zlac706_can.frames import (
    ALARM_REGISTER,
    BROADCAST_ID,
    DATA_LENGTH,
    AlarmReport,
    Command,
    Func,
    HeartbeatCurrentSpeed,
    HeartbeatPosition,
    HeartbeatRegister,
    NoSuchRegister,
    Reply,
    Write,
    WriteAck,
)
from busgate.codecs.zlac706_can.registers import CODES, CanRegister
from busgate.codecs.zlac706_common import AlarmFlags, named

#: A write-shaped frame: ``Write`` from the host, its echoes from a node.
_WriteShaped = TypeVar("_WriteShaped", bound=Write | WriteAck | NoSuchRegister)

#: Write-shaped frames: function code → (frame class, sent on the broadcast identifier).
_COMMANDS: dict[int, tuple[type[Write], bool]] = {
    Func.WRITE: (Write, False),
    Func.BROADCAST_WRITE: (Write, True),
}
_ECHOES: dict[int, tuple[type[WriteAck] | type[NoSuchRegister], bool]] = {
    Func.WRITE_ACK: (WriteAck, False),
    Func.BROADCAST_ACK: (WriteAck, True),
    Func.NO_SUCH_REGISTER: (NoSuchRegister, False),
    Func.BROADCAST_NO_SUCH_REGISTER: (NoSuchRegister, True),
}


def _check_shape(message: CanFrame) -> Discarded | None:
    if len(message.data) != DATA_LENGTH:
        return Discarded(
            message.data, f"{message}: {len(message.data)} data bytes, ZLAC706 frames have 8"
        )
    if message.data[2] != 0:
        return Discarded(message.data, f"{message}: register high byte is not 0")
    return None


def _register_write(
    message: CanFrame, table: Mapping[int, tuple[type[_WriteShaped], bool]]
) -> _WriteShaped | Discarded:
    """Decode a write-shaped frame (``group func 00 reg i32``) with ``table``."""
    group, func, _, register = message.data[:4]
    frame_class, broadcast = table[func]
    if broadcast != (message.arbitration_id == BROADCAST_ID):
        where = "identifier 0" if broadcast else "a node identifier"
        return Discarded(message.data, f"{message}: function {func:#04x} belongs on {where}")
    value = int.from_bytes(message.data[4:], "big", signed=True)
    codes = CODES.get(register)
    return frame_class(
        message.arbitration_id,
        named(CanRegister, register),
        value if codes is None else named(codes, value),
        group,
    )


class CommandDecoder(MessageDecoder[CanFrame, Command]):
    """Decodes the host's frames, as a node sees them.

    >>> decoder = CommandDecoder()
    >>> decoder.feed(CanFrame.parse("001#00fa00190000003f"))
    >>> next(decoder.events())
    Write(device_id=1, register=<CanRegister.WORK_MODE: 25>, value=<WorkMode.POSITION: 63>, group=0)
    """

    def _decode(self, message: CanFrame) -> Command | Discarded:
        bad = _check_shape(message)
        if bad is not None:
            return bad
        if message.data[1] not in _COMMANDS:
            return Discarded(
                message.data, f"{message}: function {message.data[1]:#04x} is not a host command"
            )
        return _register_write(message, _COMMANDS)


class ReplyDecoder(MessageDecoder[CanFrame, Reply]):
    """Decodes the nodes' frames, as the host sees them.

    >>> decoder = ReplyDecoder()
    >>> decoder.feed(CanFrame.parse("001#00ff00eb08080808"))
    >>> next(decoder.events())
    AlarmReport(device_id=1, alarms=<AlarmFlags.ENCODER_FAULT: 8>, group=0)
    """

    def _decode(self, message: CanFrame) -> Reply | Discarded:
        bad = _check_shape(message)
        if bad is not None:
            return bad
        func = message.data[1]
        if func == Func.HEARTBEAT:
            return _heartbeat(message)
        if func == Func.NO_SUCH_REGISTER and _is_alarm(message.data):
            return AlarmReport(message.arbitration_id, AlarmFlags(message.data[4]), message.data[0])
        if func in _ECHOES:
            return _register_write(message, _ECHOES)
        return Discarded(message.data, f"{message}: function {func:#04x} is not a node reply")


def _is_alarm(data: bytes) -> bool:
    return data[3] == ALARM_REGISTER and len(set(data[4:])) == 1


def _heartbeat(message: CanFrame) -> Reply | Discarded:
    data, device_id = message.data, message.arbitration_id
    if device_id == BROADCAST_ID:
        return Discarded(data, f"{message}: heartbeat on the broadcast identifier")
    if data[3] == HeartbeatRegister.POSITION:
        return HeartbeatPosition(device_id, int.from_bytes(data[4:], "big", signed=True), data[0])
    if data[3] == HeartbeatRegister.CURRENT_SPEED:
        current = int.from_bytes(data[4:6], "big")
        speed = int.from_bytes(data[6:], "big", signed=True)
        return HeartbeatCurrentSpeed(device_id, current, speed, data[0])
    return Discarded(data, f"{message}: heartbeat register {data[3]:#04x} is unknown")
