"""ZLAC706 hub-motor servo driver, CAN protocol (manual 8.1): sans-I/O codec.

``encode(frame) -> CanFrame``; ``CommandDecoder`` / ``ReplyDecoder`` fed ``CanFrame`` objects;
``expected_reply(frame)``; ``REGISTERS``, the register table as data. Unit conversions shared
with the RS232 protocol live in ``busgate.codecs.zlac706_common``.
"""

from busgate.codecs.zlac706_can.decoder import CommandDecoder, ReplyDecoder
from busgate.codecs.zlac706_can.encoder import encode, expected_reply
from busgate.codecs.zlac706_can.frames import (
    ADDRESSED,
    BROADCAST_ID,
    DEVICE_IDS,
    MAX_NODE_ID,
    TIMING,
    AlarmReport,
    Func,
    HeartbeatCurrentSpeed,
    HeartbeatPosition,
    NoSuchRegister,
    Write,
    WriteAck,
)
from busgate.codecs.zlac706_can.registers import (
    CODES,
    GAIN_REGISTERS,
    I32_MAX,
    I32_MIN,
    REGISTERS,
    AlarmReset,
    CanRegister,
    ControlWord,
    Origin,
    PositionMode,
    WorkMode,
    readings,
)

__all__ = [
    "ADDRESSED",
    "BROADCAST_ID",
    "CODES",
    "DEVICE_IDS",
    "GAIN_REGISTERS",
    "I32_MAX",
    "I32_MIN",
    "MAX_NODE_ID",
    "REGISTERS",
    "TIMING",
    "AlarmReport",
    "AlarmReset",
    "CanRegister",
    "CommandDecoder",
    "ControlWord",
    "Func",
    "HeartbeatCurrentSpeed",
    "HeartbeatPosition",
    "NoSuchRegister",
    "Origin",
    "PositionMode",
    "ReplyDecoder",
    "WorkMode",
    "Write",
    "WriteAck",
    "encode",
    "expected_reply",
    "readings",
]
