"""The Inspire LA UART protocol's vocabulary: constants, codes, and one frame class per message.

Rules of this file: it holds data only (no encoding, no decoding), so the encoder, the
decoders and the simulators share one definition of every message. Commands go host →
actuator (header ``55 AA``), replies actuator → host (header ``AA 55``). Every frame that
names an actuator calls it ``device_id``; positions are the actuator's raw 0–2000 stroke units
(the mm per unit depend on the model's stroke), hence ``position_raw``.
"""

from __future__ import annotations

import enum
import struct
from dataclasses import dataclass

from busgate.codecs.timing import ProtocolTiming

COMMAND_HEADER = b"\x55\xaa"
REPLY_HEADER = b"\xaa\x55"

#: Header (2), length, id and checksum: a frame is ``length + FRAME_OVERHEAD`` bytes long.
FRAME_OVERHEAD = 5
#: The length byte is a u8 and counts the instruction and index bytes besides the data.
MAX_LENGTH = 0xFF
MAX_DATA = MAX_LENGTH - 2
#: The largest frame either direction can carry (a 253-byte write or read reply).
MAX_FRAME = MAX_LENGTH + FRAME_OVERHEAD

MIN_ID = 1
MAX_ID = 254
#: Frames carry the device id; these are the ids a device can have.
ADDRESSED = True
DEVICE_IDS = range(MIN_ID, MAX_ID + 1)
#: Baud rates in the order of their codes in register 12: the only ones an actuator runs at.
BAUD_RATES = (19200, 57600, 115200, 921600)
#: Manual 3.4.2: replies after 120 µs, up to 800 µs when a control task interrupts; "keep
#: commands at least 1 ms apart". 921600 baud is the D-type factory default.
TIMING = ProtocolTiming(0.001, 0.001, 120e-6, 800e-6, 921_600, rates=BAUD_RATES)
#: Every actuator executes a frame sent to 255; none answers it.
BROADCAST_ID = 0xFF

#: Addresses 0–254 make the control table.
TABLE_SIZE = 255
#: Motion instructions always write the target position register (55–56).
TARGET_INDEX = 0x37
#: Broadcast motion frames carry 1 to 15 (id, position) entries of 3 bytes.
MAX_GROUP_TARGETS = 15
GROUP_ENTRY_SIZE = 3
#: The status reply: ``AA 55 11 id 04 00 22`` + 14 bytes of status + checksum.
STATUS_REPLY_SIZE = 22
#: Those 14 bytes: target u16, position i16, temperature i8, current u16, force low byte,
#: faults, force high byte, two internal u16 — little-endian throughout.
STATUS_LAYOUT = struct.Struct("<HhbHBBBHH")


class Instruction(enum.IntEnum):
    """The ``cmd`` byte (for broadcast frames the flag byte that takes its place)."""

    READ = 0x01
    WRITE = 0x02
    MOVE_NO_REPLY = 0x03
    CONTROL = 0x04
    FOLLOW_NO_REPLY = 0x19
    FOLLOW = 0x20
    MOVE = 0x21
    GROUP_MOVE = 0xF2
    GROUP_FOLLOW = 0xF3


#: The cmd bytes a status frame comes under: the status query's (``CONTROL``, as the manual
#: prints it), or that of the command it answers (erratum LA-7). A write's own answer may be
#: the one-reserved-byte frame instead (LA-2).
STATUS_COMMANDS = (Instruction.CONTROL, Instruction.FOLLOW, Instruction.MOVE, Instruction.WRITE)


class ControlCode(enum.IntEnum):
    """Single-control (``0x04``) codes, the data byte of ``55 AA 03 id 04 00 code sum``."""

    ENABLE = 0x04  # power stage on ("work")
    PAUSE = 0x14  # power stage off; a new target moves it again
    CLEAR_FAULT = 0x1E
    SAVE = 0x20  # copy the control table from RAM to flash
    STATUS = 0x22
    ESTOP = 0x23  # power stage off; needs ENABLE before it moves again


CONTROL_CODES = frozenset(ControlCode)


class Fault(enum.IntFlag):
    """Fault flags of the status reply (byte 15)."""

    STALL = 0x01
    OVER_TEMPERATURE = 0x02
    OVER_CURRENT = 0x04
    MOTOR_FAULT = 0x08


# --- commands (host → actuator) -----------------------------------------------------------


@dataclass(frozen=True, slots=True)
class ReadCommand:
    """``0x01``: read ``length`` bytes of the control table from ``index``."""

    device_id: int
    index: int
    length: int


@dataclass(frozen=True, slots=True)
class WriteCommand:
    """``0x02``: write ``data`` into the control table from ``index``."""

    device_id: int
    index: int
    data: bytes


@dataclass(frozen=True, slots=True)
class MoveCommand:
    """Positioning: ``0x21`` answered by a status reply, ``0x03`` when ``reply`` is false."""

    device_id: int
    position_raw: int
    reply: bool = True


@dataclass(frozen=True, slots=True)
class FollowCommand:
    """Follow mode (a target every 10–50 ms): ``0x20`` with a status reply, ``0x19`` without."""

    device_id: int
    position_raw: int
    reply: bool = True


@dataclass(frozen=True, slots=True)
class ControlCommand:
    """``0x04``: a single-control code (enable, e-stop, pause, save, status, clear fault)."""

    device_id: int
    code: ControlCode


@dataclass(frozen=True, slots=True)
class Target:
    """One actuator's entry in a broadcast motion frame."""

    device_id: int
    position_raw: int


@dataclass(frozen=True, slots=True)
class GroupMoveCommand:
    """``0xF2`` to id 255: positioning targets for up to 15 actuators; nobody answers."""

    targets: tuple[Target, ...]


@dataclass(frozen=True, slots=True)
class GroupFollowCommand:
    """``0xF3`` to id 255: follow-mode targets for up to 15 actuators; nobody answers."""

    targets: tuple[Target, ...]


# --- replies (actuator → host) ------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class StatusReply:
    """The 22-byte status frame that answers control, motion and (per 3.5.2) write commands.

    ``force_g`` is only meaningful on force-sensing models (LAF, LASF); its low and high bytes
    sit on either side of the fault byte on the wire. ``internal_1``/``internal_2`` are the
    manual's undocumented "internal data". ``command`` is the cmd byte it came under: the
    status query's ``04``, as the manual prints it, or that of the command it answers (3.4.1:
    a reply's cmd is its command's; erratum LA-7).
    """

    device_id: int
    target_raw: int
    position_raw: int
    temperature_c: int
    current_ma: int
    force_g: int
    faults: Fault
    internal_1: int = 0
    internal_2: int = 0
    command: int = Instruction.CONTROL


@dataclass(frozen=True, slots=True)
class ReadReply:
    """``0x01`` answer: the bytes of the control table from ``index`` on."""

    device_id: int
    index: int
    data: bytes


@dataclass(frozen=True, slots=True)
class WriteReply:
    """``0x02`` answer as section 3.4.1 describes it: one reserved data byte.

    Sections 3.5.2 and 3.7.x say a write is answered by the status frame instead; both are
    accepted (docs/protocols.md, erratum "reply to a write").
    """

    device_id: int
    index: int
    reserved: int = 0
