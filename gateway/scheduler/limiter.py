"""A follow stream held within its joint's limits, tick by tick: a jump in what a client sends
never becomes a jump on the wire.

Rules of this file:

1. A position target is clamped to the joint's whole raw limits (``Joint.raw_limits``). With
   ``max_velocity`` the position moves at most ``max_velocity × period`` a tick; with
   ``max_acceleration`` its velocity changes by at most ``max_acceleration × period`` a tick
   and it brakes in time to stop at the target (never faster than what stops within the
   distance left, tick by tick); a target that turns round late is overshot rather than met
   by a jerk. A step input becomes a ramp. It never leaves the limits: a stream that starts
   outside them (a device resting there) sends the nearest limit first, rather than targets
   beyond it to ramp in (the device goes there at its own pace, as to a one-shot move).
2. A speed target is clamped to ``±max_velocity`` and to the device's top speed; with
   ``max_acceleration`` it changes by at most ``max_acceleration × period`` a tick.
3. Each tick says which limit held the target back, if any; the stream reports the first
   (a ``limited`` event), once.
4. Pure: time is the tick count, the period given; the stream starts from where the device
   is commanded (or, not known, from its first target).
"""

from __future__ import annotations

import math
from typing import Literal

from busgate.schemas.joints import Joint

Limit = Literal["min", "max", "max_velocity", "max_acceleration"]


def _clamp(value: float, low: float, high: float) -> float:
    return min(max(value, low), high)


class StreamLimiter:
    """One follow stream's targets, each tick, within its joint's limits (rules 1 and 2)."""

    def __init__(
        self,
        joint: Joint,
        period_s: float,
        start: float | None,
        follows: Literal["position", "velocity"] | None = None,
    ) -> None:
        self.joint = joint
        self.period_s = period_s
        #: What the stream carries (its driver's ``follows``; by default its joint's).
        self.follows = follows or joint.follows
        scale = abs(joint.scale)
        self.low: float
        self.high: float
        if self.follows == "position":
            # Raw units: counts, counts per second, counts per second².
            self.low, self.high = joint.raw_limits
            self.max_rate = _per_raw(joint.max_velocity, scale)
            self.max_change = _per_raw(joint.max_acceleration, scale)
        else:
            # The family's speed unit, and that unit per second.
            top = joint.declaration.top_speed
            top = math.inf if top is None else top
            if joint.max_velocity is not None:
                top = min(top, abs(joint.speed_of(joint.max_velocity)))
            self.low, self.high = -top, top
            self.max_rate = math.inf
            self.max_change = (
                math.inf
                if joint.max_acceleration is None
                else abs(joint.speed_of(joint.max_acceleration))
            )
        self.value = start
        self.rate = 0.0  # the position's velocity, counts per second (rule 1)

    def step(self, wanted: float) -> tuple[float, Limit | None]:
        """The next tick's target for ``wanted``, and the limit that held it back."""
        target = _clamp(wanted, self.low, self.high)
        limit: Limit | None = None
        if target != wanted:
            limit = self._range_limit(wanted)
        if self.value is None:
            self.value = target
            return self._sent(target), limit
        if self.follows == "position":
            value, held = self._position_step(target)
        else:
            value, held = self._speed_step(target)
        self.value = value
        return self._sent(value), limit or held

    def goal(self, wanted: float) -> float:
        """What a stream aiming at ``wanted`` ends up sending: ``wanted`` within the limits, as
        the wire takes it (a ramp ends when it sends this: ``tickers`` rule 5)."""
        return self._sent(_clamp(wanted, self.low, self.high))

    def _range_limit(self, wanted: float) -> Limit:
        if self.follows == "velocity":
            return "max_velocity"
        low_side = wanted < self.low
        # A negative scale turns the raw range round: raw low is SI max.
        return "min" if low_side == (self.joint.scale > 0) else "max"

    def _position_step(self, target: float) -> tuple[float, Limit | None]:
        """Counts a tick towards ``target``: at most the speed limit's, at most one tick's
        change of speed more or less than the last, and no more than stops in time (rule 1)."""
        assert self.value is not None
        period = self.period_s
        distance = target - self.value
        direction = math.copysign(1.0, distance)
        ahead = abs(distance)
        change = self.max_change * period * period  # counts a tick, more or less each tick
        going = self.rate * period * direction  # this tick's start: counts a tick towards it
        most = min(ahead, self.max_rate * period, _stopping_step(ahead, change))
        step = max(min(most, going + change), going - change)  # past ``most`` if late to brake
        held: Limit | None = None
        if step < ahead:
            held = "max_velocity" if step == self.max_rate * period else "max_acceleration"
        value = self.value + direction * step
        self.rate = direction * step / period
        if not self.low <= value <= self.high:  # carried past a limit: stopped on it
            value, self.rate = _clamp(value, self.low, self.high), 0.0
        return value, held

    def _speed_step(self, target: float) -> tuple[float, Limit | None]:
        assert self.value is not None
        step = self.max_change * self.period_s
        value = _clamp(target, self.value - step, self.value + step)
        return value, None if value == target else "max_acceleration"

    def _sent(self, value: float) -> float:
        """What goes on the wire: a whole count inside the limits, or a speed."""
        if self.follows == "position":
            return int(_clamp(round(value), self.low, self.high))
        return value


def _stopping_step(ahead: float, change: float) -> float:
    """The largest step (counts a tick) from which steps each ``change`` smaller stop within
    ``ahead`` counts: ``s + (s - change) + … ≤ ahead``, that is ``s (s + change) ≤ 2 change
    ahead``."""
    if change == math.inf:
        return math.inf
    return (math.sqrt(change * change + 8 * change * ahead) - change) / 2


def _per_raw(limit: float | None, scale: float) -> float:
    return math.inf if limit is None else limit / scale
