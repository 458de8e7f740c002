"""The ZLAC706 RS232 protocol as types: one frame class per frame kind, both directions.

Host → driver: ``Write`` (``addr hi lo sum``, sum = low 8 bits of addr + hi + lo) and the
3-byte ``MonitorRequest`` (``80 00 80``). Driver → host: ``Ack`` (``addr addr``) after a
write, and after a monitor request eight 4-byte frames (``StatusReport``, ``BusVoltage``,
``OutputCurrent``, ``OutputSpeed`` and four ``PositionWord``). The link is point to point: no
frame carries a device id.

Frames hold raw values so that decode(encode(f)) == f; measured values also carry their
conversion to named units, computed from the raw value.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Final

from busgate.codecs.timing import ProtocolTiming
from busgate.codecs.zlac706_common import AlarmFlags, amps_from_current_raw, rpm_from_speed_raw
from busgate.codecs.zlac706_rs232.registers import MonitorItem

#: No frame carries an id: a port drives one driver, and the id in a configuration is only
#: a label (one byte, like the other families' ids).
ADDRESSED: Final = False
DEVICE_IDS: Final = range(0, 256)
#: The manual states no RS232 baud rate, acknowledgement time or gap: we assume an
#: acknowledgement within 1 ms, default to 1 ms of idle line (the gateway's rule for every
#: UART, the LA manual's figure) and 115200 baud; the bus config names the rate.
TIMING: Final = ProtocolTiming(0.0, 0.001, 100e-6, 1e-3, 115_200)
#: The monitor request: address 80, one data byte 00, its sum.
MONITOR_REQUEST: Final = b"\x80\x00\x80"
FRAME_SIZE: Final = 4
ACK_SIZE: Final = 2
#: Eight 4-byte frames answer a monitor request.
MONITOR_FRAMES: Final = 8


@dataclass(frozen=True, slots=True)
class Write:
    """Host → driver: write the 16-bit ``value`` to ``register`` (an ``Rs232Register``)."""

    register: int
    value: int


@dataclass(frozen=True, slots=True)
class MonitorRequest:
    """Host → driver: ask for the eight monitor frames (``80 00 80``)."""


@dataclass(frozen=True, slots=True)
class Ack:
    """Driver → host: the write to ``register`` was received (``addr addr``)."""

    register: int


@dataclass(frozen=True, slots=True)
class StatusReport:
    """Monitor frame 80: the status word, the same bits as the CAN alarm code."""

    alarms: AlarmFlags


@dataclass(frozen=True, slots=True)
class BusVoltage:
    """Monitor frame E1: DC bus voltage (±2 V)."""

    voltage_v: int


@dataclass(frozen=True, slots=True)
class OutputCurrent:
    """Monitor frame E2: output current, A × 100."""

    current_raw: int
    current_a: float = field(init=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "current_a", amps_from_current_raw(self.current_raw))


@dataclass(frozen=True, slots=True)
class OutputSpeed:
    """Monitor frame E4: measured speed, raw (16384 per 6000 rpm)."""

    speed_raw: int
    speed_rpm: float = field(init=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "speed_rpm", rpm_from_speed_raw(self.speed_raw))


@dataclass(frozen=True, slots=True)
class PositionWord:
    """Monitor frames E6–E9: one half of the commanded or feedback position (pulses).

    ``item`` is a ``MonitorItem``; high halves are signed, low halves unsigned.
    """

    item: int
    value: int


Command = Write | MonitorRequest
MonitorFrame = StatusReport | BusVoltage | OutputCurrent | OutputSpeed | PositionWord
Reply = Ack | MonitorFrame

#: The monitor item each single-valued monitor frame kind reports, and the field holding it.
MONITOR_FIELDS: Final[dict[type, tuple[MonitorItem, str]]] = {
    StatusReport: (MonitorItem.STATUS, "alarms"),
    BusVoltage: (MonitorItem.BUS_VOLTAGE, "voltage_v"),
    OutputCurrent: (MonitorItem.CURRENT, "current_raw"),
    OutputSpeed: (MonitorItem.SPEED, "speed_raw"),
}
