"""What the ZLAC706's two protocols (CAN and RS232) share: alarm bits, role names, units.

The driver is one device with two wire formats, so the physics lives here once: the speed
scale (CAN's 8192 per 3000 rpm is RS232's 16384 per 6000 rpm, the same ratio), the torque
scale (±7500 ↔ ±24 A on both), the ramp unit (100 ms on both), the alarm bits (the CAN alarm
code is the RS232 status word) and the names of the roles a register can play (gains, work
modes). Each codec maps these roles to its own register addresses and codes.

Rules of this file: conversions go from named units to raw wire values and back; rounding is
decided here and nowhere else (speed targets truncate toward zero, the RS232 speed limit
rounds half away from zero, torque rounds to the nearest step), each as the manual's
examples require. Out-of-range values raise ``EncodeError``.
"""

from __future__ import annotations

import enum
import math
from fractions import Fraction
from typing import Final, TypedDict

from busgate.codecs.errors import EncodeError
from busgate.codecs.registers import Access, Register, require_range

__all__ = [
    "CURRENT_RAW_PER_A",
    "GAIN_MAX",
    "GAIN_MIN",
    "MAX_CURRENT_A",
    "MAX_SPEED_RPM",
    "PULSES_PER_TURN",
    "RAMP_MAX_MS",
    "RAMP_STEP_MS",
    "RATED_CURRENT_MAX_MA",
    "TORQUE_RAW_LIMIT",
    "AlarmFlags",
    "Gain",
    "Mode",
    "amps_from_current_raw",
    "named",
    "ramp_word",
    "rpm_from_speed_raw",
    "speed_raw_rounded",
    "speed_raw_truncated",
    "torque_raw_from_amps",
]

#: Hub motors are limited to ±1000 rpm (manual 8.1.2 step 4 note 3, section 3).
MAX_SPEED_RPM: Final = 1000
#: Encoder pulses per turn of the hub motor: the manual's positioning resolution, 1/10000 of a
#: turn (section 1). Position targets and reports count these.
PULSES_PER_TURN: Final = 10_000
#: Raw speed units per rpm: 8192 per 3000 rpm (CAN) = 16384 per 6000 rpm (RS232).
SPEED_RAW_PER_RPM: Final = Fraction(8192, 3000)

#: Target torque ±7500 ↔ ±24 A: 312.5 raw per ampere (2500 ↔ 8 A, 1500 ↔ 4.8 A).
TORQUE_RAW_LIMIT: Final = 7500
MAX_CURRENT_A: Final = 24
TORQUE_RAW_PER_A: Final = Fraction(TORQUE_RAW_LIMIT, MAX_CURRENT_A)
#: The peak output current (manual section 1: mean 8 A, peak 24 A) bounds the rated current.
RATED_CURRENT_MAX_MA: Final = MAX_CURRENT_A * 1000
#: Measured currents (CAN heartbeat, RS232 monitor) come as A × 100.
CURRENT_RAW_PER_A: Final = 100
_RPM_PER_SPEED_RAW: Final = float(1 / SPEED_RAW_PER_RPM)

#: Ramps are one byte each (accel, decel) in units of 100 ms, on both protocols.
RAMP_STEP_MS: Final = 100
RAMP_MAX_MS: Final = 0xFF * RAMP_STEP_MS

#: The manual gives gain examples (0–5000) but no range. Negative gains mean nothing, and the
#: widest wire (CAN) carries a signed 32-bit value; RS232's 16 bits are checked by its codec.
GAIN_MIN: Final = 0
GAIN_MAX: Final = 0x7FFF_FFFF


class AlarmFlags(enum.IntFlag):
    """The alarm code (CAN ``FF .. EB`` report) and the RS232 status word: the same bits."""

    RUNNING = 0x01
    OVER_CURRENT = 0x02
    OVER_VOLTAGE = 0x04
    ENCODER_FAULT = 0x08
    OVER_TEMPERATURE = 0x10
    UNDER_VOLTAGE = 0x20
    OVERLOAD = 0x40
    #: Not a fault: added when the driver is in external-control mode.
    EXTERNAL_CONTROL = 0x80

    @property
    def faults(self) -> AlarmFlags:
        """The fault bits alone (without running and external-control)."""
        return self & ~(AlarmFlags.RUNNING | AlarmFlags.EXTERNAL_CONTROL)


class Mode(enum.StrEnum):
    """Work modes by role; CAN (register 19) and RS232 (register 02) each have their codes."""

    POSITION = "position"
    VELOCITY = "velocity"
    TORQUE = "torque"


class Gain(enum.StrEnum):
    """The eight tunable gains by role: CAN registers 20–27, RS232 1A–1C and 40–42."""

    POSITION_KP = "position_kp"
    POSITION_KD = "position_kd"
    POSITION_KF = "position_kf"  # feed-forward: at 1 the shaft locks without a keep-alive
    VELOCITY_KP = "velocity_kp"
    VELOCITY_KI = "velocity_ki"
    VELOCITY_KD = "velocity_kd"
    CURRENT_KP = "current_kp"
    CURRENT_KD = "current_kd"


def speed_raw_truncated(rpm: float) -> int:
    """Raw speed for a target speed, truncated toward zero (every speed example does so).

    >>> [hex(speed_raw_truncated(r) & 0xFFFFFFFF) for r in (500, 1000, -1000, 100)]
    ['0x555', '0xaaa', '0xfffff556', '0x111']
    """
    return math.trunc(_checked_rpm(rpm) * SPEED_RAW_PER_RPM)


def speed_raw_rounded(rpm: float) -> int:
    """Raw speed rounded half away from zero: the RS232 position-mode speed limit (note 8).

    >>> [hex(speed_raw_rounded(r)) for r in (30, 60, 120, 1)]
    ['0x52', '0xa4', '0x148', '0x3']
    """
    exact = _checked_rpm(rpm) * SPEED_RAW_PER_RPM
    return int(math.copysign(math.floor(abs(exact) + Fraction(1, 2)), exact))


def rpm_from_speed_raw(raw: int) -> float:
    """Speed in rpm of a raw speed value (heartbeat, monitor).

    >>> round(rpm_from_speed_raw(0x043F), 1)
    398.1
    """
    return raw * _RPM_PER_SPEED_RAW  # float: this runs for every heartbeat


def _checked_rpm(rpm: float) -> Fraction:
    if isinstance(rpm, bool) or not isinstance(rpm, int | float) or not math.isfinite(rpm):
        raise EncodeError(f"speed must be a finite number, not {rpm!r}", field="rpm", value=rpm)
    if not -MAX_SPEED_RPM <= rpm <= MAX_SPEED_RPM:
        raise EncodeError(
            f"speed {rpm} rpm is out of range [{-MAX_SPEED_RPM}, {MAX_SPEED_RPM}]",
            field="rpm",
            value=rpm,
        )
    return Fraction(rpm)


def torque_raw_from_amps(current_a: float) -> int:
    """Raw target torque for a current, to the nearest step of 3.2 mA.

    >>> [torque_raw_from_amps(a) for a in (8, 4.8, 0.64, 1.6, 3.2, -24)]
    [2500, 1500, 200, 500, 1000, -7500]
    """
    ok = isinstance(current_a, int | float) and not isinstance(current_a, bool)
    if not ok or not math.isfinite(current_a) or abs(current_a) > MAX_CURRENT_A:
        raise EncodeError(
            f"torque current {current_a!r} A is out of range [{-MAX_CURRENT_A}, {MAX_CURRENT_A}]",
            field="current_a",
            value=current_a,
        )
    return round(Fraction(current_a) * TORQUE_RAW_PER_A)


def amps_from_current_raw(raw: int) -> float:
    """Measured current in amperes from its A × 100 wire value.

    >>> amps_from_current_raw(0x1E)
    0.3
    """
    return raw / CURRENT_RAW_PER_A


def ramp_word(accel_ms: int, decel_ms: int) -> int:
    """The 16-bit ramp value: accel steps in the high byte, decel steps in the low byte.

    Ramps are refused, not rounded, when they are not whole 100 ms steps: a command is
    carried out as given or not at all.

    >>> hex(ramp_word(1000, 1100))
    '0xa0b'
    """
    steps = []
    for name, ms in (("accel_ms", accel_ms), ("decel_ms", decel_ms)):
        require_range(name, ms, 0, RAMP_MAX_MS)
        if ms % RAMP_STEP_MS:
            raise EncodeError(
                f"{name} {ms} is not a multiple of {RAMP_STEP_MS} ms", field=name, value=ms
            )
        steps.append(ms // RAMP_STEP_MS)
    return steps[0] << 8 | steps[1]


def named(enum_class: type[enum.IntEnum], value: int) -> int:
    """``value`` as a member of ``enum_class`` when it is one, else ``value`` itself.

    Decoders use it so that known codes print by name while unknown ones still decode.

    >>> Code = enum.IntEnum("Code", {"ENABLE": 0x1F})
    >>> named(Code, 0x1F), named(Code, 0x15)
    (<Code.ENABLE: 31>, 21)
    """
    try:
        return enum_class(value)
    except ValueError:
        return value


#: Largest raw speed on either wire: 1000 rpm truncated, the manual's own example (0x0AAA).
SPEED_RAW_MAX: Final = speed_raw_truncated(MAX_SPEED_RPM)
#: A ramp value: accel steps in the high byte, decel steps in the low byte (100 ms each).
RAMP_WORD_MAX: Final = (RAMP_MAX_MS // RAMP_STEP_MS) << 8 | RAMP_MAX_MS // RAMP_STEP_MS


class UnitFields(TypedDict, total=False):
    """``Register`` fields that say how a raw value reads, shared by registers of both wires."""

    unit: str
    scale: float
    signed: bool
    parts: tuple[str, ...]


#: How a raw speed register reads in rpm (the same scale on both wires).
SPEED_UNIT: Final[UnitFields] = {
    "unit": "rpm",
    "scale": float(1 / SPEED_RAW_PER_RPM),
    "signed": True,
}
#: How a ramp register reads: accel steps in the high byte, decel in the low one, 100 ms each.
RAMP_UNIT: Final[UnitFields] = {"unit": "ms", "scale": RAMP_STEP_MS, "parts": ("accel", "decel")}


def coded_register(name: str, address: int, codes, description: str) -> Register:
    """A one-word write-only register that takes only the given codes."""
    return Register(
        name,
        address,
        1,
        Access.WRITE,
        minimum=min(codes),
        maximum=max(codes),
        description=description,
    )
