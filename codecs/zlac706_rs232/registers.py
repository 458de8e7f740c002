"""The ZLAC706 RS232 register table (manual 8.2.1) as data, and its value codes.

Every frame carries one 16-bit big-endian value, so ``size`` counts register slots (one per
address), ranges are explicit on every row, and ``signed`` says how the two bytes read
(speed, torque and the high half of a position are signed). Writable registers are what the
host sends; read-only ones are the monitor reply's items. An address is in one row only
(``RegisterMap`` refuses duplicates), which is what lets the reply decoder tell a 2-byte
acknowledgement (``X X``, X writable) from a 4-byte monitor frame (X read-only).

The manual contradicts itself on the absolute/relative register: its table says ``51`` (with
the frames ``51 00 00 51`` / ``51 00 01 52``), note (7) says ``52``. The decision (recorded in
docs/protocols.md) is for ``51``; it is ``Rs232Register.POSITION_MODE``, the one place to change.
"""

from __future__ import annotations

import enum
from typing import Final

from busgate.codecs.registers import Access, Register, RegisterMap
from busgate.codecs.zlac706_common import (
    GAIN_MAX,
    GAIN_MIN,
    MAX_SPEED_RPM,
    RAMP_UNIT,
    RAMP_WORD_MAX,
    RATED_CURRENT_MAX_MA,
    SPEED_RAW_MAX,
    SPEED_UNIT,
    TORQUE_RAW_LIMIT,
    TORQUE_RAW_PER_A,
    Gain,
    coded_register,
    speed_raw_rounded,
)

U16_MAX: Final = 0xFFFF
I16_MIN, I16_MAX = -0x8000, 0x7FFF
#: The speed limit rounds (note 8), so 1000 rpm is 2731 there, not 2730.
SPEED_LIMIT_RAW_MAX: Final = speed_raw_rounded(MAX_SPEED_RPM)


class Rs232Register(enum.IntEnum):
    """Writable addresses (first byte of a host frame)."""

    ENABLE = 0x00
    MODE = 0x02
    POSITION_LOW = 0x05
    SPEED = 0x06
    TORQUE = 0x08
    POSITION_RAMP = 0x09
    SPEED_RAMP = 0x0A
    POSITION_KP = 0x1A
    POSITION_KD = 0x1B
    POSITION_KF = 0x1C
    SPEED_LIMIT = 0x1D
    RATED_CURRENT = 0x2D
    VELOCITY_KP = 0x40
    VELOCITY_KI = 0x41
    VELOCITY_KD = 0x42
    CLEAR_FAULT = 0x4A
    POSITION_HIGH = 0x50
    POSITION_MODE = 0x51  # not 0x52 as note (7) says: see the module docstring
    ORIGIN = 0x53


class MonitorItem(enum.IntEnum):
    """Addresses of the eight frames answering the monitor request, in reply order."""

    STATUS = 0x80
    BUS_VOLTAGE = 0xE1
    CURRENT = 0xE2
    SPEED = 0xE4
    COMMANDED_POSITION_HIGH = 0xE6
    COMMANDED_POSITION_LOW = 0xE7
    FEEDBACK_POSITION_HIGH = 0xE8
    FEEDBACK_POSITION_LOW = 0xE9


#: The four monitor items that carry half of a 32-bit position.
POSITION_ITEMS: Final = frozenset(
    {
        MonitorItem.COMMANDED_POSITION_HIGH,
        MonitorItem.COMMANDED_POSITION_LOW,
        MonitorItem.FEEDBACK_POSITION_HIGH,
        MonitorItem.FEEDBACK_POSITION_LOW,
    }
)


class EnableCode(enum.IntEnum):
    DISABLE = 0x0000  # "stop": the motor is released
    ENABLE = 0x0001  # the shaft locks; valid in PC-control mode


class ControlMode(enum.IntEnum):
    """Where the driver takes its set-point from (register 02)."""

    PC_SPEED = 0xC4
    EXTERNAL_PULSES = 0xC0
    PC_POSITION = 0xD0
    PC_TORQUE = 0xC1


class PositionMode(enum.IntEnum):
    ABSOLUTE = 0x0000
    RELATIVE = 0x0001


CODES: Final[dict[int, type[enum.IntEnum]]] = {
    Rs232Register.ENABLE: EnableCode,
    Rs232Register.MODE: ControlMode,
    Rs232Register.POSITION_MODE: PositionMode,
}

#: RS232 reaches six of the eight gains: it has no current-loop gains.
GAIN_REGISTERS: Final[dict[Gain, Rs232Register]] = {
    gain: Rs232Register[gain.name] for gain in Gain if gain.name in Rs232Register.__members__
}

R, W = Access.READ, Access.WRITE


def _coded(name: str, register: Rs232Register, description: str) -> Register:
    return coded_register(name, register, CODES[register], description)


def _gain(gain: Gain) -> Register:
    return Register(
        gain.value,
        GAIN_REGISTERS[gain],
        1,
        W,
        minimum=GAIN_MIN,
        maximum=min(GAIN_MAX, U16_MAX),
        description="no range in the manual",
    )


def _word(name: str, address: int, access: Access = W, **kwargs: object) -> Register:
    """A register holding one unsigned 16-bit value unless ``kwargs`` say otherwise."""
    limits = {"minimum": 0, "maximum": U16_MAX, **kwargs}
    return Register(name, address, 1, access, **limits)  # type: ignore[arg-type]


REGISTERS: Final = RegisterMap(
    [
        _coded("enable", Rs232Register.ENABLE, "00 01 enable, 00 00 disable (PC control)"),
        _coded(
            "mode",
            Rs232Register.MODE,
            "C4 PC speed, C0 external pulses, D0 PC position, C1 PC torque",
        ),
        _word(
            "position_low",
            Rs232Register.POSITION_LOW,
            unit="pulses",
            description="low 16 bits of the target position; send after position_high",
        ),
        _word(
            "speed",
            Rs232Register.SPEED,
            minimum=-SPEED_RAW_MAX,
            maximum=SPEED_RAW_MAX,
            description="PC speed mode target",
            **SPEED_UNIT,
        ),
        _word(
            "torque",
            Rs232Register.TORQUE,
            unit="A",
            scale=float(1 / TORQUE_RAW_PER_A),
            minimum=-TORQUE_RAW_LIMIT,
            maximum=TORQUE_RAW_LIMIT,
            signed=True,
        ),
        _word(
            "position_ramp",
            Rs232Register.POSITION_RAMP,
            maximum=RAMP_WORD_MAX,
            description="high byte accel, low byte decel",
            **RAMP_UNIT,
        ),
        _word(
            "speed_ramp",
            Rs232Register.SPEED_RAMP,
            maximum=RAMP_WORD_MAX,
            description="high byte accel, low byte decel",
            **RAMP_UNIT,
        ),
        *(_gain(gain) for gain in GAIN_REGISTERS),
        _word(
            "speed_limit",
            Rs232Register.SPEED_LIMIT,
            maximum=SPEED_LIMIT_RAW_MAX,
            description="position-mode speed limit, rounded (note 8)",
            **SPEED_UNIT,
        ),
        _word(
            "rated_current",
            Rs232Register.RATED_CURRENT,
            unit="mA",
            maximum=RATED_CURRENT_MAX_MA,
            description="bounded by the 24 A peak current",
        ),
        _word("clear_fault", Rs232Register.CLEAR_FAULT, maximum=0, description="address alone"),
        _word(
            "position_high",
            Rs232Register.POSITION_HIGH,
            unit="pulses",
            minimum=I16_MIN,
            maximum=I16_MAX,
            signed=True,
            description="high 16 bits of the target position",
        ),
        _coded("position_mode", Rs232Register.POSITION_MODE, "00 absolute, 01 relative"),
        _word(
            "origin",
            Rs232Register.ORIGIN,
            maximum=0,
            description="Z-signal search; hub motors have none",
        ),
        _word("status", MonitorItem.STATUS, R, description="alarm bits, as the CAN alarm code"),
        _word("bus_voltage", MonitorItem.BUS_VOLTAGE, R, unit="V", description="±2 V"),
        _word("current", MonitorItem.CURRENT, R, unit="A", scale=0.01),
        _word(
            "measured_speed", MonitorItem.SPEED, R, minimum=I16_MIN, maximum=I16_MAX, **SPEED_UNIT
        ),
        _word(
            "commanded_position_high",
            MonitorItem.COMMANDED_POSITION_HIGH,
            R,
            minimum=I16_MIN,
            maximum=I16_MAX,
            signed=True,
            unit="pulses",
        ),
        _word("commanded_position_low", MonitorItem.COMMANDED_POSITION_LOW, R, unit="pulses"),
        _word(
            "feedback_position_high",
            MonitorItem.FEEDBACK_POSITION_HIGH,
            R,
            minimum=I16_MIN,
            maximum=I16_MAX,
            signed=True,
            unit="pulses",
        ),
        _word("feedback_position_low", MonitorItem.FEEDBACK_POSITION_LOW, R, unit="pulses"),
    ]
)

WRITABLE: Final = frozenset(r.address for r in REGISTERS if r.access.writable)
MONITOR: Final = frozenset(r.address for r in REGISTERS if not r.access.writable)


def split_position(position: int) -> tuple[int, int]:
    """A 32-bit position as (signed high 16 bits, unsigned low 16 bits), sent in that order.

    >>> split_position(-10000)
    (-1, 55536)
    """
    return position >> 16, position & U16_MAX


def join_position(high: int, low: int) -> int:
    """The 32-bit position of its two halves.

    >>> join_position(-1, 0xD8F0)
    -10000
    """
    return high << 16 | low
