"""The body of a simulated Inspire LA actuator: how its rod moves, what its motor draws, how it
warms and what its force sensor reads.

The manual gives none of these figures; the ones here are plausible for a micro actuator on
8 V. Apart from the actuator (``inspire_la.py``), which owns the state, the protocol and the
protections, these are functions of the state they are given: a stroke gives the position at
any time and heating is exact over a stretch of constant current, so nothing ticks (rule 1 of
``inspire_la.py``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

# Electrical and thermal figures: a free move draws a few hundred mA, a self-locking lead screw
# holds its position on almost nothing, and the motor warms with I² over minutes.
HOLD_CURRENT_MA = 12
MOVING_CURRENT_MA = 220
#: Extra current a push against a load costs while moving.
MA_PER_GRAM_LOAD = 0.1
AMBIENT_C = 25.0
#: Equilibrium rise over ambient per A²: a continuous free move settles ~15 °C warmer.
RISE_C_PER_A2 = 300.0
THERMAL_TAU_S = 120.0

#: The force sensor: a 12-bit ADC centred on no load, in grams per count.
FORCE_ADC_MID = 2048
FORCE_ADC_MAX = 4095
GRAMS_PER_COUNT = 5


@dataclass(frozen=True, slots=True)
class Stroke:
    """The rod running at ``speed_per_s`` (raw stroke units) from ``origin`` at ``start_s``
    to ``goal``, where it stays; a hold is a stroke to where the rod is."""

    start_s: float
    origin: float
    goal: float
    speed_per_s: float

    def position(self, t: float) -> float:
        delta = self.goal - self.origin
        travelled = self.speed_per_s * max(0.0, t - self.start_s)
        return self.origin + math.copysign(min(abs(delta), travelled), delta)

    @property
    def arrival_s(self) -> float:
        return self.start_s + abs(self.goal - self.origin) / self.speed_per_s

    def moving(self, t: float) -> bool:
        return t < self.arrival_s


def current_ma(*, powered: bool, moving: bool, load_g: float) -> int:
    """The motor's current: none with the power stage off, more while moving against a load."""
    if not powered:
        return 0
    if moving:
        return round(MOVING_CURRENT_MA + MA_PER_GRAM_LOAD * abs(load_g))
    return HOLD_CURRENT_MA


def warmed(temp_c: float, current_ma: int, seconds: float) -> float:
    """The motor's temperature after ``seconds`` at ``current_ma``: first-order heating towards
    the temperature that current settles at."""
    amps = current_ma / 1000
    settle = AMBIENT_C + RISE_C_PER_A2 * amps * amps
    decay = math.exp(-seconds / THERMAL_TAU_S)
    return settle + (temp_c - settle) * decay


def force_adc(load_g: float) -> int:
    """The force sensor's ADC counts under ``load_g`` grams on the rod."""
    counts = FORCE_ADC_MID + round(load_g / GRAMS_PER_COUNT)
    return min(max(counts, 0), FORCE_ADC_MAX)


def force_g(load_g: float, zero_adc: int) -> int:
    """The force the actuator reports: the counts past its zero, in grams."""
    return (force_adc(load_g) - zero_adc) * GRAMS_PER_COUNT
