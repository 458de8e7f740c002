"""The motion of a simulated ZLAC706's hub motor: constant-acceleration segments, and the speed
ramps and position trapezoids built from them.

Kinematics only, in pulses, pulses/s and pulses/s²: the driver model (``zlac706_motor.py``)
turns its settings (raw speeds, ramp words, targets) into the rates and speeds asked for here,
and knows nothing of how a profile is laid out. Rules of this file:

1. A motion is a short tuple of ``Segment``s, each of constant acceleration, the last of which
   runs for ever; the state at any time is read off it, so nothing ticks.
2. A new profile starts from the state the old one gives at the time it is planned; a rate of
   ``inf`` jumps (a zero ramp), and a reversal goes through standstill.
"""

from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass(frozen=True, slots=True)
class Segment:
    """Constant acceleration from ``start_s`` for ``duration_s`` (pulses, pulses/s, /s²)."""

    start_s: float
    position: float
    speed: float
    accel: float = 0.0
    duration_s: float = math.inf

    @property
    def end_s(self) -> float:
        return self.start_s + self.duration_s

    def at(self, t: float) -> tuple[float, float]:
        """Position and speed at ``t``."""
        dt = min(max(t - self.start_s, 0.0), self.duration_s)
        return self.position + (self.speed + self.accel * dt / 2) * dt, self.speed + self.accel * dt


Motion = tuple[Segment, ...]


def segment_at(motion: Motion, t: float) -> Segment:
    return next((s for s in reversed(motion) if s.start_s <= t), motion[0])


def hold(position: float, t: float) -> Motion:
    return (Segment(t, position, 0.0),)


class _Path:
    """Builds a motion piece by piece from a start state; a rate of ``inf`` jumps."""

    def __init__(self, t: float, position: float, speed: float) -> None:
        self.segments: list[Segment] = []
        self.t, self.position, self.speed = t, position, speed

    def change_speed(self, speed: float, rate: float) -> _Path:
        duration = abs(speed - self.speed) / rate
        if duration > 0:
            self._add(math.copysign(rate, speed - self.speed), duration)
        self.speed = speed  # exact, whatever rounding the segment left
        return self

    def cruise(self, duration: float) -> _Path:
        if duration > 0:
            self._add(0.0, duration)
        return self

    def end(self, position: float | None = None) -> Motion:
        """The motion, ending in a cruise (at ``position`` exactly, when given)."""
        last = self.position if position is None else position
        return (*self.segments, Segment(self.t, last, self.speed))

    def _add(self, accel: float, duration: float) -> None:
        segment = Segment(self.t, self.position, self.speed, accel, duration)
        self.segments.append(segment)
        self.t = segment.end_s
        self.position, self.speed = segment.at(self.t)


def speed_motion(start: Segment, t: float, speed: float, accel: float, decel: float) -> Motion:
    """From the state ``start`` gives at ``t``, ramp to ``speed`` and keep it; reversing goes
    through standstill (decelerating, then accelerating)."""
    path = _Path(t, *start.at(t))
    if path.speed * speed < 0:
        path.change_speed(0.0, decel)
    return path.change_speed(speed, accel if abs(speed) > abs(path.speed) else decel).end()


def position_motion(
    start: Segment, t: float, target: int, top: float, accel: float, decel: float
) -> Motion:
    """The trapezoid from the state at ``t`` to ``target`` with cruise speed ``top`` (or a
    triangle when the distance is too short to reach it). A motor moving away from the target,
    or too fast to stop before it, first stops, then sets out from there."""
    path = _Path(t, *start.at(t))
    if path.speed * (target - path.position) < 0 or (
        path.speed**2 / (2 * decel) > abs(target - path.position)
    ):
        path.change_speed(0.0, decel)
    distance, direction = abs(target - path.position), math.copysign(1.0, target - path.position)
    v0 = abs(path.speed)
    if top <= 0 or distance == 0:
        return path.end()
    up = accel if top >= v0 else decel
    if abs(top**2 - v0**2) / (2 * up) + top**2 / (2 * decel) > distance:
        reach = 1 / (2 * accel) + 1 / (2 * decel)  # a triangle: accelerate, then decelerate
        top = math.sqrt((distance + v0**2 / (2 * accel)) / reach) if reach else top
        up = accel
    cruise = distance - abs(top**2 - v0**2) / (2 * up) - top**2 / (2 * decel)
    path.change_speed(direction * top, up).cruise(cruise / top)
    return path.change_speed(0.0, decel).end(target)
