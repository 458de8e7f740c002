"""The DS serial-bus servo protocol (v4.01) as types: constants, codes and frames.

One frozen dataclass per command (host → servo) and one for the reply (servo → host). Frames
hold values, not wire bytes: ``encoder`` turns them into bytes and is the one place their
ranges are checked, ``decoder`` turns bytes back into exactly these frames.

The manual restricts REG WRITE and SYNC WRITE to the target-position address 0x2A (position
then move time, 4 bytes), so those two are typed frames (``RegWrite``, ``SyncWrite``) rather
than address + raw bytes; WRITE can reach the whole control table and stays generic.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass
from typing import Final

from busgate.codecs.timing import ProtocolTiming

#: Command frames start with FF FF, replies with FF F5 (manual 2.1 / 2.2).
COMMAND_HEADER: Final = b"\xff\xff"
REPLY_HEADER: Final = b"\xff\xf5"

MIN_ID: Final = 1
MAX_ID: Final = 250
#: Frames carry the device id; these are the ids a device can have.
ADDRESSED: Final = True
DEVICE_IDS: Final = range(MIN_ID, MAX_ID + 1)
#: The manual states no reply time, gap or baud rate: we assume a reply within 500 µs, ask no
#: minimum gap of the protocol, default to 1 ms of idle line (the gateway's rule for every
#: UART, the LA manual's figure) and 115200 baud.
TIMING: Final = ProtocolTiming(0.0, 0.001, 50e-6, 500e-6, 115_200)
#: Every servo executes a frame sent to 254; none replies.
BROADCAST_ID: Final = 254

#: ``len`` counts the instruction (or status) byte, the parameters and the checksum byte:
#: len = N + 2 for N parameters. It is one byte, which bounds every frame.
MAX_PARAMS: Final = 0xFF - 2
#: Header (2) + id + len + instruction/status + checksum.
FRAME_OVERHEAD: Final = 6
#: The largest frame the protocol can express (len = 0xFF): 259 bytes.
MAX_FRAME: Final = FRAME_OVERHEAD + MAX_PARAMS

#: REG WRITE and SYNC WRITE only write here: target position (u16) then move time (u16).
MOVE_ADDRESS: Final = 0x2A
MOVE_DATA_SIZE: Final = 4
#: SYNC WRITE parameters: address, bytes per servo, then (id + 4 data bytes) per servo.
MAX_SYNC_TARGETS: Final = (MAX_PARAMS - 2) // (1 + MOVE_DATA_SIZE)


class Instruction(enum.IntEnum):
    """Instruction codes of a command frame (manual 2.3)."""

    PING = 0x01
    READ = 0x02
    WRITE = 0x03
    REG_WRITE = 0x04
    ACTION = 0x05
    RESET = 0x06
    SYNC_WRITE = 0x83


class ServoStatus(enum.IntFlag):
    """The status byte of every reply (manual 2.4); the other bits are always 0."""

    VOLTAGE = 0x01
    TEMPERATURE = 0x04
    OVERLOAD = 0x20  # overload or stall: set once stall protection has tripped


@dataclass(frozen=True, slots=True)
class Ping:
    """Ask a servo for its status; never broadcast."""

    device_id: int


@dataclass(frozen=True, slots=True)
class Read:
    """Read ``length`` bytes of the control table from ``address``; never broadcast."""

    device_id: int
    address: int
    length: int


@dataclass(frozen=True, slots=True)
class Write:
    """Write ``data`` to the control table at ``address``.

    ``data`` is empty for the addresses that act on the address alone (store preset 1-3 at
    0x16/0x18/0x1A, go to preset 1-3 at 0x3C-0x3E).
    """

    device_id: int
    address: int
    data: bytes


@dataclass(frozen=True, slots=True)
class RegWrite:
    """Store a move (target position, move time) until ACTION; never broadcast."""

    device_id: int
    position_raw: int
    time_ms: int


@dataclass(frozen=True, slots=True)
class Action:
    """Start every stored REG WRITE move at once; always sent to the broadcast id."""


@dataclass(frozen=True, slots=True)
class Reset:
    """Restore the factory settings of the control table."""

    device_id: int


@dataclass(frozen=True, slots=True)
class SyncTarget:
    """One servo's part of a SYNC WRITE: target position and move time."""

    device_id: int
    position_raw: int
    time_ms: int


@dataclass(frozen=True, slots=True)
class SyncWrite:
    """Move several servos with one broadcast frame (at least one target, ids distinct)."""

    targets: tuple[SyncTarget, ...]


@dataclass(frozen=True, slots=True)
class StatusReply:
    """A servo's answer to any command: its status flags and, for READ, the bytes read.

    The wire does not say which command is answered; the bus owner knows (see
    ``expected_reply``), and ``registers.values_from`` turns read bytes into named values.
    """

    device_id: int
    status: ServoStatus
    data: bytes = b""


Command = Ping | Read | Write | RegWrite | Action | Reset | SyncWrite
Frame = Command | StatusReply
