"""One base's twist as its wheels' ticks see it: the latest command, held for its time, and
the twist each tick sends, moved toward the command within the base's limits.

Rules of this file:

1. A command is a target twist (saturated: ``kinematics`` rule 2) and the bus-clock time it
   holds until: ``cmd_timeout_s`` after it came, or its ``duration_s``. After that the target
   is 0, and the base ramps down at its deceleration limits, as a stale stream.
2. The wheels are played as a trajectory of both (``BusRunner.play``, one start for both):
   each wheel's tick asks ``sample`` for the twist at its slot's time, so both wheels of a
   slot send speeds of one twist, whichever bus or thread asks first. The twist moves toward
   the target by the time between slots, never by how late a tick runs.
3. ``finished`` tells when the base has come to rest with no command holding it, sampled at
   rest for two slots in a row (so both wheels have sent the first slot's 0): its play can
   end, leaving both wheels at 0 rpm.
4. Commands come from any thread (one lock); samples come from the bus threads.
5. A base stopped outside its ramp (a wheel left its play: an e-stop, a refusal, a wheel
   gone) is at rest as far as the drive knows: its next play starts from 0, and the twist
   it says it sent is 0. Started from the twist sent before, the first command after an
   e-stop and its reset sent the wheels at that old speed at once.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Any

from busgate.gateway.base.kinematics import Geometry, Twist
from busgate.schemas.joints import Joint

#: A wheel's follow payload at a slot's time since the play's start.
WheelSampler = Callable[[float], dict[str, Any]]


class Drive:
    """The twist of one base, commanded and sent (the rules above)."""

    def __init__(self, geometry: Geometry, left: Joint, right: Joint) -> None:
        self.geometry = geometry
        self.joints = (left, right)
        self._lock = threading.Lock()
        self._target = Twist()
        self._until = 0.0  # bus clock: the target holds until then (rule 1)
        self._start = 0.0  # the play's start, bus clock
        self._sent: tuple[float, Twist] = (0.0, Twist())  # slot time since start, twist
        self._rest_slots = 0  # slots in a row sampled at rest (rule 3)

    def command(self, twist: Twist, now: float, hold_s: float) -> Twist:
        """A new target twist from ``now`` for ``hold_s``; the twist that will be driven."""
        target = self.geometry.saturated(twist)
        with self._lock:
            self._target, self._until = target, now + hold_s
        return target

    def stop(self) -> None:
        """The target is 0 from now: the base ramps down (rule 1)."""
        with self._lock:
            self._target, self._until = Twist(), 0.0

    def halt(self) -> None:
        """The wheels were stopped outright (rule 5): the target is 0, and so is the twist."""
        with self._lock:
            self._target, self._until = Twist(), 0.0
            self._sent, self._rest_slots = (self._sent[0], Twist()), 0

    def begin(self, start: float, twist: Twist) -> None:
        """A play of both wheels from ``start`` (bus clock), the base at ``twist`` then."""
        with self._lock:
            self._start, self._sent, self._rest_slots = start, (0.0, twist), 0

    def sample(self, t_s: float) -> Twist:
        """The twist at slot time ``t_s`` since the play's start (rule 2)."""
        with self._lock:
            last_t, last = self._sent
            if t_s <= last_t:
                return last
            held = self._start + t_s <= self._until
            target = self._target if held else Twist()
            twist = self.geometry.step(last, target, t_s - last_t)
            self._sent = (t_s, twist)
            self._rest_slots = self._rest_slots + 1 if twist == Twist() else 0
            return twist

    def sampler(self, side: int) -> WheelSampler:
        """The follow payload of wheel ``side`` (0 left, 1 right) at each slot."""
        joint = self.joints[side]

        def sample(t_s: float) -> dict[str, Any]:
            speed = self.geometry.wheels(self.sample(t_s))[side]
            payload, _ = joint.kind_follow(None, speed)
            return payload

        return sample

    def finished(self, now: float) -> bool:
        """At rest, with no command holding it, for two slots: every wheel's 0 of the first
        has gone out (each wheel samples a slot before its tick leaves, rule 3)."""
        with self._lock:
            return now > self._until and self._rest_slots >= 2

    @property
    def sent(self) -> Twist:
        """The twist of the last slot sampled."""
        with self._lock:
            return self._sent[1]

    @property
    def held_until(self) -> float:
        """Bus clock: when the target stops holding (rule 1)."""
        with self._lock:
            return self._until
