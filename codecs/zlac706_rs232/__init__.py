"""ZLAC706 hub-motor servo driver, RS232 protocol (manual 8.2): sans-I/O codec.

``encode(frame) -> bytes``; ``CommandDecoder`` / ``ReplyDecoder`` (byte streams);
``expected_reply(frame)``; ``REGISTERS``, the register table as data; ``assemble_monitor``
turns the eight monitor frames into one ``MonitorReply``. Unit conversions shared with the
CAN protocol live in ``busgate.codecs.zlac706_common``.
"""

from busgate.codecs.zlac706_rs232.decoder import CommandDecoder, ReplyDecoder
from busgate.codecs.zlac706_rs232.encoder import encode, expected_reply
from busgate.codecs.zlac706_rs232.frames import (
    ADDRESSED,
    DEVICE_IDS,
    MONITOR_REQUEST,
    TIMING,
    Ack,
    BusVoltage,
    MonitorRequest,
    OutputCurrent,
    OutputSpeed,
    PositionWord,
    StatusReport,
    Write,
)
from busgate.codecs.zlac706_rs232.monitor import MonitorReply, assemble_monitor, readings
from busgate.codecs.zlac706_rs232.registers import (
    CODES,
    GAIN_REGISTERS,
    MONITOR,
    REGISTERS,
    WRITABLE,
    ControlMode,
    EnableCode,
    MonitorItem,
    PositionMode,
    Rs232Register,
    join_position,
    split_position,
)

__all__ = [
    "ADDRESSED",
    "CODES",
    "DEVICE_IDS",
    "GAIN_REGISTERS",
    "MONITOR",
    "MONITOR_REQUEST",
    "REGISTERS",
    "TIMING",
    "WRITABLE",
    "Ack",
    "BusVoltage",
    "CommandDecoder",
    "ControlMode",
    "EnableCode",
    "MonitorItem",
    "MonitorReply",
    "MonitorRequest",
    "OutputCurrent",
    "OutputSpeed",
    "PositionMode",
    "PositionWord",
    "ReplyDecoder",
    "Rs232Register",
    "StatusReport",
    "Write",
    "assemble_monitor",
    "encode",
    "expected_reply",
    "join_position",
    "readings",
    "split_position",
]
