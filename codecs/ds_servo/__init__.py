"""DS (德晟) serial-bus smart servos, protocol v4.01: half-duplex UART-TTL or RS485.

Commands ``FF FF id len instr params… sum``, replies ``FF F5 id len status params… sum``,
big-endian values, ids 1-250, 254 broadcast (no reply). ``frames`` holds the types,
``registers`` the control table, ``encoder`` the wire format and its rules, ``decoder`` the
incremental decoders for both directions.
"""

from busgate.codecs.ds_servo.decoder import CommandDecoder, ReplyDecoder
from busgate.codecs.ds_servo.encoder import checksum, encode, expected_reply, move_data
from busgate.codecs.ds_servo.frames import (
    BROADCAST_ID,
    MAX_FRAME,
    MAX_ID,
    MAX_SYNC_TARGETS,
    MIN_ID,
    MOVE_ADDRESS,
    Action,
    Command,
    Frame,
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
from busgate.codecs.ds_servo.registers import (
    ADDRESS_ONLY_WRITES,
    GOTO_PRESET_ADDRESSES,
    PRESET_ADDRESSES,
    REGISTERS,
    TABLE_END,
    check_read,
    check_write,
    readings,
    values_from,
)

__all__ = [
    "ADDRESS_ONLY_WRITES",
    "BROADCAST_ID",
    "GOTO_PRESET_ADDRESSES",
    "MAX_FRAME",
    "MAX_ID",
    "MAX_SYNC_TARGETS",
    "MIN_ID",
    "MOVE_ADDRESS",
    "PRESET_ADDRESSES",
    "REGISTERS",
    "TABLE_END",
    "Action",
    "Command",
    "CommandDecoder",
    "Frame",
    "Instruction",
    "Ping",
    "Read",
    "RegWrite",
    "ReplyDecoder",
    "Reset",
    "ServoStatus",
    "StatusReply",
    "SyncTarget",
    "SyncWrite",
    "Write",
    "check_read",
    "check_write",
    "checksum",
    "encode",
    "expected_reply",
    "move_data",
    "readings",
    "values_from",
]
