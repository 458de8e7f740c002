"""The ZLAC706 CAN register table (manual 8.1.1 tables 3–6) as data, and its value codes.

The protocol has one command, "write register ``reg`` with a signed 32-bit value"; there is
no read. Every register therefore is write-only, and ``size`` counts register slots (one
each), not bytes: every value travels as an i32 whatever it means. Ranges are explicit on
every row, taken from the manual (speeds ±1000 rpm, torque ±7500) or, where it gives none,
the wire's own (i32) — we do not invent limits.

Some registers take only a few codes (control word 0F/1F, work mode 2F/3F/8F, …): ``CODES``
names them, so the encoder refuses any other value and the decoder shows names.
"""

from __future__ import annotations

import enum
from typing import Final

from busgate.codecs.registers import Access, Reading, Register, RegisterMap
from busgate.codecs.zlac706_can.frames import Write, WriteAck
from busgate.codecs.zlac706_common import (
    GAIN_MAX,
    GAIN_MIN,
    RAMP_UNIT,
    RAMP_WORD_MAX,
    RATED_CURRENT_MAX_MA,
    SPEED_RAW_MAX,
    SPEED_UNIT,
    TORQUE_RAW_LIMIT,
    TORQUE_RAW_PER_A,
    Gain,
    coded_register,
)

I32_MIN: Final = -(1 << 31)
I32_MAX: Final = (1 << 31) - 1


class CanRegister(enum.IntEnum):
    """Register numbers (byte 3 of every frame)."""

    TARGET_TORQUE = 0x08
    CONTROL_WORD = 0x10
    TARGET_SPEED = 0x11
    POSITION_RAMP = 0x12
    SPEED_RAMP = 0x13
    MAX_SPEED = 0x14
    ALARM_RESET = 0x15
    TARGET_POSITION = 0x16
    POSITION_MODE = 0x17
    ORIGIN = 0x18
    WORK_MODE = 0x19
    POSITION_KP = 0x20
    POSITION_KD = 0x21
    POSITION_KF = 0x22
    VELOCITY_KP = 0x23
    VELOCITY_KI = 0x24
    VELOCITY_KD = 0x25
    CURRENT_KP = 0x26
    CURRENT_KD = 0x27
    RATED_CURRENT = 0x2D


class ControlWord(enum.IntEnum):
    RELEASE = 0x0F  # stop: the motor is released (free shaft)
    ENABLE = 0x1F  # start: the shaft locks; in speed mode a preset speed starts at once


class WorkMode(enum.IntEnum):
    SPEED = 0x2F
    POSITION = 0x3F
    TORQUE = 0x8F


class PositionMode(enum.IntEnum):
    ABSOLUTE = 0x4F
    RELATIVE = 0x5F


class AlarmReset(enum.IntEnum):
    RESET = 0x7F


class Origin(enum.IntEnum):
    SEARCH = 0x6F  # runs to the encoder's Z signal; hub motors have none


CODES: Final[dict[int, type[enum.IntEnum]]] = {
    CanRegister.CONTROL_WORD: ControlWord,
    CanRegister.WORK_MODE: WorkMode,
    CanRegister.POSITION_MODE: PositionMode,
    CanRegister.ALARM_RESET: AlarmReset,
    CanRegister.ORIGIN: Origin,
}

GAIN_REGISTERS: Final[dict[Gain, CanRegister]] = {gain: CanRegister[gain.name] for gain in Gain}

W = Access.WRITE


def _coded(name: str, register: CanRegister, description: str) -> Register:
    return coded_register(name, register, CODES[register], description)


def _gain(gain: Gain) -> Register:
    return Register(
        gain.value,
        GAIN_REGISTERS[gain],
        1,
        W,
        minimum=GAIN_MIN,
        maximum=GAIN_MAX,
        description="no range in the manual; defaults shown in table (5)",
    )


REGISTERS: Final = RegisterMap(
    [
        Register(
            "target_torque",
            CanRegister.TARGET_TORQUE,
            1,
            W,
            unit="A",
            scale=float(1 / TORQUE_RAW_PER_A),
            minimum=-TORQUE_RAW_LIMIT,
            maximum=TORQUE_RAW_LIMIT,
            signed=True,
            description="torque mode: ±7500 ↔ ±24 A",
        ),
        _coded("control_word", CanRegister.CONTROL_WORD, "0F release (stop), 1F enable (start)"),
        Register(
            "target_speed",
            CanRegister.TARGET_SPEED,
            1,
            W,
            minimum=-SPEED_RAW_MAX,
            maximum=SPEED_RAW_MAX,
            description="speed mode; resend within 500 ms when the feed-forward gain is 1",
            **SPEED_UNIT,
        ),
        Register(
            "position_ramp",
            CanRegister.POSITION_RAMP,
            1,
            W,
            minimum=0,
            maximum=RAMP_WORD_MAX,
            description="d2 accel, d3 decel (0 to top speed)",
            **RAMP_UNIT,
        ),
        Register(
            "speed_ramp",
            CanRegister.SPEED_RAMP,
            1,
            W,
            minimum=0,
            maximum=RAMP_WORD_MAX,
            description="d2 accel, d3 decel (0 to top speed)",
            **RAMP_UNIT,
        ),
        Register(
            "max_speed",
            CanRegister.MAX_SPEED,
            1,
            W,
            minimum=0,
            maximum=SPEED_RAW_MAX,
            description="position mode: trapezoid (cruise) speed",
            **SPEED_UNIT,
        ),
        _coded("alarm_reset", CanRegister.ALARM_RESET, "7F clears the alarm"),
        Register(
            "target_position",
            CanRegister.TARGET_POSITION,
            1,
            W,
            unit="pulses",
            minimum=I32_MIN,
            maximum=I32_MAX,
            signed=True,
            description="position mode; ignored unless the motor is enabled first",
        ),
        _coded("position_mode", CanRegister.POSITION_MODE, "4F absolute, 5F relative"),
        _coded("origin", CanRegister.ORIGIN, "6F searches the Z signal"),
        _coded("work_mode", CanRegister.WORK_MODE, "2F speed, 3F position, 8F torque"),
        *(_gain(gain) for gain in Gain),
        Register(
            "rated_current",
            CanRegister.RATED_CURRENT,
            1,
            W,
            unit="mA",
            minimum=0,
            maximum=RATED_CURRENT_MAX_MA,
            description="bounded by the 24 A peak current",
        ),
    ]
)


def readings(reply: object) -> list[Reading]:
    """The register and value a frame carries, named and in the register's unit.

    The protocol has no read: the frames that carry a register and its value are a write and
    its echo (``FB``, ``DB``). "No such register" (``FF``, ``DF``) names none, heartbeats
    and alarm reports carry their values under their own names, and a register outside the
    table stays a number: ``[]``.

    >>> from busgate.codecs.zlac706_can.decoder import ReplyDecoder
    >>> from busgate.codecs.can_frame import CanFrame
    >>> decoder = ReplyDecoder()
    >>> decoder.feed(CanFrame.parse("00a#00fb001100000555"))  # 8.1.2 step 4: 500 rpm
    >>> readings(next(decoder.events()))
    [Reading(register='target_speed', address=17, raw=1365, value=499.877929688, unit='rpm')]
    >>> readings(Write(1, CanRegister.TARGET_SPEED, -2730))  # 8.1.2: −1000 rpm, truncated
    [Reading(register='target_speed', address=17, raw=-2730, value=-999.755859375, unit='rpm')]
    """
    if not isinstance(reply, WriteAck | Write):
        return []
    return REGISTERS.reading_at(reply.register, reply.value)
