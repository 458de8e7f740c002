"""A differential drive's arithmetic: a twist and its wheels' speeds, the twist held within
the base's limits, and odometry from the wheels' measured positions.

Rules of this file:

1. Units are SI throughout: a twist is (linear m/s, angular rad/s, counter-clockwise
   positive), a wheel's speed and position are its joint's (rad/s, rad; forward positive,
   its calibration having turned a mirrored motor round).
2. Saturation keeps the path: a twist beyond ``max_linear``, ``max_angular`` or what a wheel
   can turn is scaled down as a whole (linear and angular by one factor), so the curvature
   (angular / linear) the client asked for is the one driven.
3. Acceleration moves the twist toward its target along the straight line between them in
   (linear, angular), by at most ``max_linear_accel × dt`` and ``max_angular_accel × dt`` in
   each, and each wheel's speed by at most ``max_wheel_accel × dt`` (its joint's
   ``max_acceleration``), one factor for all: from rest to a twist the curvature holds all
   the way, and a stop decelerates both together.
4. Odometry integrates the wheels' measured positions (encoder pulses, through their joints),
   never commanded speeds, at the midpoint heading of each step. Its twist is measured over
   the last ``TWIST_WINDOW_S`` at least: steps between two wheels' heartbeats are a few ms,
   and a count over one of them is noise.
5. Pure: no clock, no thread; times are given.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field

#: The shortest span odometry measures its twist over (rule 4).
TWIST_WINDOW_S = 0.1


@dataclass(frozen=True, slots=True)
class Twist:
    linear: float = 0.0  # m/s
    angular: float = 0.0  # rad/s


@dataclass(frozen=True, slots=True)
class Geometry:
    """The base's wheels and limits."""

    wheel_radius_m: float
    track_m: float
    max_linear: float
    max_angular: float
    max_linear_accel: float
    max_angular_accel: float
    max_wheel: float = math.inf  # rad/s, what each wheel may turn
    max_wheel_accel: float = math.inf  # rad/s², how fast each wheel's speed may change

    def wheels(self, twist: Twist) -> tuple[float, float]:
        """(left, right) wheel speeds in rad/s of ``twist``."""
        half_turn = twist.angular * self.track_m / 2
        return (
            (twist.linear - half_turn) / self.wheel_radius_m,
            (twist.linear + half_turn) / self.wheel_radius_m,
        )

    def twist(self, left: float, right: float) -> Twist:
        """The twist of wheels turning at ``left`` and ``right`` rad/s."""
        radius = self.wheel_radius_m
        return Twist(radius * (left + right) / 2, radius * (right - left) / self.track_m)

    def saturated(self, twist: Twist) -> Twist:
        """``twist`` scaled down as a whole to within every limit (rule 2): first within the
        base's, then within the wheels' speeds, reckoned from the twist scaled already (those
        of a huge twist, 1e307 m/s, overflowed to infinity and scaled it to 0)."""
        within_base = _scaled(
            twist,
            min(_room(twist.linear, self.max_linear), _room(twist.angular, self.max_angular)),
        )
        wheels = self.wheels(within_base)
        return _scaled(within_base, min(_room(speed, self.max_wheel) for speed in wheels))

    def step(self, now: Twist, target: Twist, dt_s: float) -> Twist:
        """The twist ``dt_s`` after ``now`` on its way to ``target`` (rule 3)."""
        d_linear, d_angular = target.linear - now.linear, target.angular - now.angular
        wheel_step = self.max_wheel_accel * dt_s
        factor = min(
            _room(d_linear, self.max_linear_accel * dt_s),
            _room(d_angular, self.max_angular_accel * dt_s),
            *(_room(d, wheel_step) for d in self.wheels(Twist(d_linear, d_angular))),
        )
        if factor >= 1.0:
            return target
        return Twist(now.linear + d_linear * factor, now.angular + d_angular * factor)


def _scaled(twist: Twist, factor: float) -> Twist:
    """``twist`` scaled by ``factor`` when it is below 1 (rule 2), else as it is."""
    if factor >= 1.0:
        return twist
    return Twist(twist.linear * factor, twist.angular * factor)


def _room(value: float, limit: float) -> float:
    """The factor that brings ``value`` within ±``limit`` (1 or more when it is)."""
    return math.inf if value == 0 else limit / abs(value)


@dataclass(frozen=True, slots=True)
class Pose:
    x: float = 0.0  # m
    y: float = 0.0  # m
    theta: float = 0.0  # rad, wrapped to (-π, π]


@dataclass(slots=True)
class Odometry:
    """The base's pose and twist, integrated from its wheels' positions (rule 4)."""

    geometry: Geometry
    pose: Pose = Pose()
    twist: Twist = Twist()
    _last: tuple[float, float, float] | None = None  # (left rad, right rad, time s)
    #: (time s, distance m, turn rad) since the start, over the last window and one before
    _travel: deque[tuple[float, float, float]] = field(default_factory=deque)

    def reset(self) -> None:
        """Back to the origin; the wheels' next reading is the new start."""
        self.pose, self.twist, self._last = Pose(), Twist(), None
        self._travel.clear()

    def take(self, left_rad: float, right_rad: float, at_s: float) -> bool:
        """The wheels' positions read at ``at_s``; ``True`` when the pose moved on."""
        last, self._last = self._last, (left_rad, right_rad, at_s)
        if last is None:
            return False
        dt = at_s - last[2]
        if dt <= 0:
            self._last = last  # the same reading again, or an older one: nothing new
            return False
        radius = self.geometry.wheel_radius_m
        d_left, d_right = (left_rad - last[0]) * radius, (right_rad - last[1]) * radius
        distance, turn = (d_left + d_right) / 2, (d_right - d_left) / self.geometry.track_m
        heading = self.pose.theta + turn / 2
        self.pose = Pose(
            self.pose.x + distance * math.cos(heading),
            self.pose.y + distance * math.sin(heading),
            math.remainder(self.pose.theta + turn, math.tau),
        )
        self.twist = self._measured(last[2], at_s, distance, turn)
        return True

    def _measured(self, from_s: float, at_s: float, distance: float, turn: float) -> Twist:
        """The twist over the last ``TWIST_WINDOW_S`` or more (rule 4), this step's
        ``distance`` and ``turn`` taken from ``from_s`` to ``at_s``."""
        travel = self._travel
        if not travel:
            travel.append((from_s, 0.0, 0.0))
        _, total, turned = travel[-1]
        travel.append((at_s, total + distance, turned + turn))
        while len(travel) > 2 and at_s - travel[1][0] >= TWIST_WINDOW_S:
            travel.popleft()
        since, start, start_turn = travel[0]
        span = at_s - since
        return Twist((total + distance - start) / span, (turned + turn - start_turn) / span)
