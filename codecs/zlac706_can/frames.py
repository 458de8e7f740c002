"""The ZLAC706 CAN protocol as types: function codes and one frame class per frame kind.

Every frame is 8 data bytes ``group func 00 reg d0 d1 d2 d3`` on the standard identifier of
the node (manual 8.1.1). The host writes (``FA``, or ``DA`` to identifier 0 for all nodes);
the node echoes the write (``FB``/``DB``) or answers "no such register" (``FF``/``DF``); on its
own it sends heartbeats (``FE``) and, while in alarm, alarm reports (``FF`` with register
``EB``). There is no checksum in the frame: the CAN controller's CRC covers it.

Frames hold raw register values, so that decode(encode(f)) == f exactly; measured values
(heartbeats) also carry their conversion to named units, computed from the raw value.
Identifier 0 is the broadcast identifier: a ``Write`` or a reply with ``device_id`` 0 is the
one-to-many form (``DA``/``DB``/``DF``).
"""

from __future__ import annotations

import enum
from dataclasses import dataclass, field
from typing import Final

from busgate.codecs.timing import ProtocolTiming
from busgate.codecs.zlac706_common import AlarmFlags, amps_from_current_raw, rpm_from_speed_raw

#: The one-to-many identifier: every node executes a ``DA`` write sent to it.
BROADCAST_ID: Final = 0
#: Node ids the vendor tool can set (manual 8.1.2: 0–109); 0 is taken by broadcast.
MAX_NODE_ID: Final = 109
#: Frames carry the node id; these are the ids a node can have.
ADDRESSED: Final = True
DEVICE_IDS: Final = range(1, MAX_NODE_ID + 1)
#: CAN arbitrates the bus itself, so no gap; the manual gives 500 kbit/s and no reply time.
TIMING: Final = ProtocolTiming(0.0, 0.0, 100e-6, 1e-3, 500_000)
DATA_LENGTH: Final = 8
#: An alarm report is ``FF`` with this register and the alarm code in all four data bytes.
ALARM_REGISTER: Final = 0xEB


class Func(enum.IntEnum):
    """Function codes (byte 1)."""

    WRITE = 0xFA
    WRITE_ACK = 0xFB
    NO_SUCH_REGISTER = 0xFF  # also the alarm report, told apart by register EB
    BROADCAST_WRITE = 0xDA
    BROADCAST_ACK = 0xDB
    BROADCAST_NO_SUCH_REGISTER = 0xDF
    HEARTBEAT = 0xFE


class HeartbeatRegister(enum.IntEnum):
    POSITION = 0x20
    CURRENT_SPEED = 0x21


@dataclass(frozen=True, slots=True)
class Write:
    """Host → node: write ``value`` (i32) to ``register``; ``device_id`` 0 writes to all."""

    device_id: int
    register: int  # a CanRegister when the register is known
    value: int
    group: int = 0


@dataclass(frozen=True, slots=True)
class WriteAck:
    """Node → host: the write was taken (``FB``, ``DB`` on identifier 0); the write echoed."""

    device_id: int
    register: int
    value: int
    group: int = 0


@dataclass(frozen=True, slots=True)
class NoSuchRegister:
    """Node → host: the written register does not exist (``FF``, ``DF`` on identifier 0)."""

    device_id: int
    register: int
    value: int
    group: int = 0


@dataclass(frozen=True, slots=True)
class HeartbeatPosition:
    """Node → host, periodic: feedback position in pulses."""

    device_id: int
    position_raw: int
    group: int = 0


@dataclass(frozen=True, slots=True)
class HeartbeatCurrentSpeed:
    """Node → host, periodic: output current (A × 100, u16) and speed (raw, i16)."""

    device_id: int
    current_raw: int
    speed_raw: int
    group: int = 0
    current_a: float = field(init=False)
    speed_rpm: float = field(init=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "current_a", amps_from_current_raw(self.current_raw))
        object.__setattr__(self, "speed_rpm", rpm_from_speed_raw(self.speed_raw))


@dataclass(frozen=True, slots=True)
class AlarmReport:
    """Node → host, instead of heartbeats while in alarm: the alarm code."""

    device_id: int
    alarms: AlarmFlags
    group: int = 0


Command = Write
Reply = WriteAck | NoSuchRegister | HeartbeatPosition | HeartbeatCurrentSpeed | AlarmReport
