"""A trajectory as a pure function of time: the value each device is sent at a tick's time.

Rules of this file:

1. Pure: no clock, no thread, no I/O. ``Path.at(t_s)`` is a function of ``t_s`` (seconds from
   the trajectory's start) alone, so the bus threads only evaluate it and tests check it with
   any times they like.
2. Between two points each device follows one polynomial segment: ``linear`` (positions),
   ``cubic`` (Hermite: positions and velocities, 0 where not given) or ``quintic`` (positions,
   velocities and accelerations, 0 where not given). Before the first point the device moves
   from its start (where it is commanded when the trajectory starts, at rest) over the same
   kind of segment; a first point at ``t_s`` = 0 is that start itself. After the last point
   it holds the last point's value.
3. A position is sent as the interpolant rounded to the nearest unit, halves away from zero
   (``sent``): the same rule in every test and on every wire. A speed (rpm) is sent as it is:
   the codec scales it to its wire's finer unit, which rounding to whole rpm would throw away.
4. A path is in the device's raw units, whatever the play's ``units``: a play in joint units
   has each point converted first (``raw_knot``: the position by the joint's calibration,
   velocity and acceleration divided by its scale), unrounded and unclamped, so everything
   downstream (bounds, ticks, feedback) is raw and a value past a limit stays past it.
"""

from __future__ import annotations

import bisect
import math
from collections.abc import Sequence
from dataclasses import dataclass
from itertools import pairwise
from typing import get_args

from busgate.schemas.joints import Joint
from busgate.schemas.trajectory import Interpolation, TrajectoryPlay, TrajectoryPoint

INTERPOLATIONS: tuple[str, ...] = get_args(Interpolation)


@dataclass(frozen=True, slots=True)
class Knot:
    """One point of one device: when, where, and how fast (units and units per second)."""

    t_s: float
    value: float
    velocity: float = 0.0
    acceleration: float = 0.0


def coefficients(a: Knot, b: Knot, interpolation: str) -> tuple[float, ...]:
    """The segment from ``a`` to ``b`` as a polynomial in ``s`` (0 at ``a``, 1 at ``b``): its
    coefficients from the constant up. Integer factors only, so exact numbers (the tests'
    ``Fraction``s) give exact coefficients; the bounds (``trajectory.bounds``) read the same
    polynomial the ticks evaluate."""
    span = b.t_s - a.t_s
    d = b.value - a.value
    if interpolation == "linear":
        return (a.value, d)
    v0, v1 = a.velocity * span, b.velocity * span
    if interpolation == "cubic":  # Hermite
        return (a.value, v0, 3 * d - 2 * v0 - v1, -2 * d + v0 + v1)
    a0, a1 = a.acceleration * span**2, b.acceleration * span**2
    c3 = (20 * d - 12 * v0 - 8 * v1 - 3 * a0 + a1) / 2
    c4 = (-30 * d + 16 * v0 + 14 * v1 + 3 * a0 - 2 * a1) / 2
    c5 = (12 * d - 6 * v0 - 6 * v1 - a0 + a1) / 2
    return (a.value, v0, a0 / 2, c3, c4, c5)


def _horner(coefficients: Sequence[float], s: float) -> float:
    value = coefficients[-1]
    for c in reversed(coefficients[:-1]):
        value = value * s + c
    return value


def sent(value: float) -> int:
    """What goes on the wire for a position ``value``: the nearest unit, halves away from zero
    (rule 3). The fraction is compared, not ``value + 0.5`` floored, which rounds in floating
    point (0.49999999999999994 + 0.5 is 1.0) and past 2**52 is no longer a half.

    >>> sent(2.5), sent(-2.5), sent(2.49), sent(-0.4), sent(0.49999999999999994)
    (3, -3, 2, 0, 0)
    """
    whole = math.floor(abs(value))
    magnitude = whole + (abs(value) - whole >= 0.5)
    return magnitude if value >= 0 else -magnitude


class Path:
    """One device's trajectory: its knots from the start, and how to join them."""

    def __init__(self, start: float, knots: Sequence[Knot], interpolation: str) -> None:
        if interpolation not in INTERPOLATIONS:
            raise ValueError(f"interpolation is one of {', '.join(INTERPOLATIONS)}")
        if not knots or knots[0].t_s < 0 or any(b.t_s <= a.t_s for a, b in pairwise(knots)):
            raise ValueError("a path needs points at strictly increasing times from 0")
        first = [] if knots[0].t_s == 0 else [Knot(0.0, start)]  # rule 2: the start
        self.knots: tuple[Knot, ...] = (*first, *knots)
        self.interpolation = interpolation
        self._times = [knot.t_s for knot in self.knots]
        #: Each segment's polynomial in its own ``s`` (``coefficients``), in order.
        self.segments = [coefficients(a, b, interpolation) for a, b in pairwise(self.knots)]

    @property
    def end_s(self) -> float:
        """When the last point is reached; the path holds its value from then on."""
        return self.knots[-1].t_s

    def at(self, t_s: float) -> float:
        """The interpolant at ``t_s`` seconds from the start (rule 2)."""
        if t_s >= self.end_s:
            return self.knots[-1].value
        if t_s <= 0:
            return self.knots[0].value
        after = bisect.bisect_right(self._times, t_s)
        a, b = self.knots[after - 1], self.knots[after]
        return _horner(self.segments[after - 1], (t_s - a.t_s) / (b.t_s - a.t_s))


def paths_of(
    play: TrajectoryPlay, starts: Sequence[float], joints: Sequence[Joint] | None = None
) -> list[Path]:
    """One ``Path`` per device of ``play``, in its order, each from the device's start value
    (its last target, or its measured value, raw), joined as ``play.interpolation_used``;
    ``joints`` (the devices' own, in order) convert a play in joint units (rule 4)."""
    if len(starts) != len(play.devices):
        raise ValueError(f"{len(starts)} start values for {len(play.devices)} devices")
    if joints is not None and len(joints) != len(play.devices):
        raise ValueError(f"{len(joints)} joints for {len(play.devices)} devices")
    return [
        path_of(play, device, start, None if joints is None else joints[device])
        for device, start in enumerate(starts)
    ]


def path_of(play: TrajectoryPlay, device: int, start: float, joint: Joint | None = None) -> Path:
    """The path of the ``device``-th device of ``play`` from ``start`` (raw), its points
    converted by ``joint`` when the play is in joint units (rule 4)."""
    knots = [_knot(point, device) for point in play.points]
    if play.units == "joint":
        if joint is None:
            raise ValueError("a play in joint units needs each device's joint")
        knots = [raw_knot(knot, joint) for knot in knots]
    return Path(start, knots, play.interpolation_used)


def raw_knot(knot: Knot, joint: Joint) -> Knot:
    """``knot`` in SI (a position, its velocity and acceleration) in ``joint``'s raw units,
    unrounded (rule 4)."""
    return Knot(
        knot.t_s,
        joint.position_raw(knot.value),
        knot.velocity / joint.scale,
        knot.acceleration / joint.scale,
    )


def _knot(point: TrajectoryPoint, device: int) -> Knot:
    """The point's knot for the ``device``-th device (velocity and acceleration 0 when not
    given)."""
    return Knot(
        point.t_s,
        point.values[device],
        point.velocities[device] if point.velocities is not None else 0.0,
        point.accelerations[device] if point.accelerations is not None else 0.0,
    )
