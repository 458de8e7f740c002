"""Periodic traffic: follow streams (coalesced per tick) and device keep-alives.

Rules of this file:

1. A tick is due a full period after the previous tick actually started, never earlier, so no
   interval is shorter than the period and a late tick is not made up by a burst.
2. A follow stream holds only while fresh: a new target within ``max(3 periods, 100 ms)``.
   A stale stream is dropped at the next tick and reported through ``on_stale``.
3. Streams of one driver kind and one period share a ticker, up to the kind's
   ``follow_group_limit`` per frame (15 Inspire LA actuators in one 0xF3 broadcast frame, many
   DS servos in one SYNC WRITE); more streams open another ticker.
4. What a tick sends of a stream is its latest target held within the device's joint limits
   (``limiter``), from where the device was commanded when the stream started; the first
   tick that holds a target back raises a ``limited`` event, once per stream. A ramp that
   ended held back (on a limit, where the device stays) hands its telling to the device's
   next stream, which says nothing again: a ROS controller's command beyond a limit each
   period is one ramp after another, told once, and told anew only after a ramp that ends
   unheld.
5. A ramp (``ends_on_target``: a one-shot speed the gateway brings a velocity joint to at its
   max_acceleration, a ROS command's position or speed) never goes stale: it ends, through
   ``on_reached``, with the tick that sends its target (held within the limits: a target
   beyond one ends on the limit), and the device keeps it. Once that tick went,
   ``on_ramp_sent`` says when (where the device is held: ``plays`` rule 4).
6. A stream's limiter steps once per tick that goes on the wire: a tick built and then put
   off (the line taken by a command, an e-stop) is built again from where the last one sent
   left it, so no step on the wire is ever larger than the limits allow.
7. A stream carries what its device followed when it began (``Driver.follows``: a ZLAC706's
   positions or speeds, by its mode). When the device follows something else now (its mode
   was changed), the stream ends as a stale one does, before its next tick or when a target
   of the other kind starts a new one, so a speed never goes out as a position.
8. A stream's device is left out of a tick due less than its follow period after another
   sender's last follow target to it (a command's ``follow``, a trajectory's last tick, a
   stream on another ticker: ``spacing``), or while a command carrying it one still waits
   to go out; it is in the first tick after that. A tick that would carry none is put off
   to when the first of them may go.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from busgate.gateway.bus.request import Request
from busgate.gateway.bus.stats import BusCounters
from busgate.gateway.drivers.base import Driver
from busgate.gateway.scheduler.limiter import StreamLimiter
from busgate.gateway.scheduler.spacing import FollowSpacing

MIN_FRESH_S = 0.1
FRESH_PERIODS = 3


@dataclass(slots=True)
class FollowStream:
    """One device's stream. ``latest`` is ``(target, when)``, replaced whole (one atomic
    assignment) by whichever thread has a new target, and read by the bus thread at a tick."""

    driver: Driver
    latest: tuple[Any, float]
    limiter: StreamLimiter
    told_limited: bool = False
    #: The last tick built held the target back (rule 4).
    held: bool = False
    ends_on_target: bool = False  # a ramp (rule 5)
    #: The limiter before the last tick built, while that tick is not sent (rule 6).
    unsent: tuple[float | None, float] | None = None

    def sent_value(self) -> float | None:
        """Where its ticks sent the device last (a tick built and put off is not: rule 6),
        or where it started from before its first."""
        return self.unsent[0] if self.unsent is not None else self.limiter.value

    def next_target(self) -> float:
        """The latest target, held within the joint's limits (rule 4), a step from the last
        tick sent (rule 6)."""
        limiter = self.limiter
        if self.unsent is not None:  # the tick built last was put off: step from before it
            limiter.value, limiter.rate = self.unsent
        self.unsent = (limiter.value, limiter.rate)
        wanted = self.latest[0]
        target, limit = limiter.step(wanted)
        self.held = limit is not None
        if self.held and not self.told_limited:
            self.told_limited = True
            joint = self.driver.joint
            value = (
                joint.position_si(wanted)
                if limiter.follows == "position"
                else joint.velocity_si(wanted)
            )
            self.driver.emit("limited", joint=joint.name, limit=limit, value=value)
        return target


def commanded(driver: Driver, now: float) -> float | None:
    """Where a stream of ``driver`` starts from: its commanded position target (the one last
    sent, when its telemetry does not say it yet; else its measured position), or its
    commanded speed (else 0), in the family's units."""
    declaration, telemetry = driver.joint.declaration, driver.telemetry(now)
    if driver.follows == "position":
        sent = driver.sent_position_raw()
        if sent is not None:  # an LA's last follow tick: no telemetry says it before a poll
            return sent
        target = telemetry.get(declaration.target)
        return target if target is not None else telemetry.get(declaration.position)
    speed = telemetry.get(declaration.target_speed_rpm or "")
    return 0.0 if speed is None else speed


class FollowTicker:
    """Sends the latest targets of its streams every ``period_s``, in one frame."""

    def __init__(
        self,
        driver_class: type[Driver],
        period_s: float,
        counters: BusCounters,
        on_stale: Callable[[Driver], None],
        on_reached: Callable[[Driver], None] = lambda driver: None,
        spacing: FollowSpacing | None = None,
        on_ramp_sent: Callable[[Driver, float], None] = lambda driver, at: None,
    ) -> None:
        self.driver_class = driver_class
        self.period_s = period_s
        self.fresh_s = max(FRESH_PERIODS * period_s, MIN_FRESH_S)
        self.spacing = spacing or FollowSpacing()  # its bus's (rule 8)
        self.counters = counters
        self.on_stale = on_stale
        self.on_reached = on_reached
        self.on_ramp_sent = on_ramp_sent
        #: The ramps the tick built last ends (rule 5): told once it went.
        self._ramps_ending: list[Driver] = []
        self.streams: dict[str, FollowStream] = {}
        #: Devices whose last ramp ended held back and told so (rule 4).
        self._ended_held: set[str] = set()
        self._due: float | None = None
        self._last_start: float | None = None
        self._continuing = False  # the next tick follows the previous one without a pause
        self._carried: list[Driver] = []

    def has_room(self, driver: Driver) -> bool:
        limit = self.driver_class.follow_group_limit
        return driver.name in self.streams or len(self.streams) < limit

    def update(
        self, driver: Driver, target: Any, now: float, *, ends_on_target: bool = False
    ) -> FollowStream:
        """A new target for ``driver`` (a ramp's, rule 5, with ``ends_on_target``); a new
        ticker, or one idle since its streams ended, starts ticking at once (a period after
        its last tick at the soonest; the pause is no follow interval)."""
        stream = self.streams.get(driver.name)
        if not self.streams:  # idle (stopped, ended, gone stale): its next tick starts anew
            self._due = None
        if stream is not None and stream.limiter.follows != driver.follows:  # rule 7
            del self.streams[driver.name]
            self.on_stale(driver)
            stream = None
        if stream is None:
            start = commanded(driver, now)
            limiter = StreamLimiter(driver.joint, self.period_s, start, driver.follows)
            told = driver.name in self._ended_held
            stream = self.streams[driver.name] = FollowStream(
                driver, (target, now), limiter, told_limited=told
            )
            self._ended_held.discard(driver.name)
        else:
            stream.latest = (target, now)
        stream.ends_on_target = ends_on_target
        if self._due is None:
            last = self._last_start
            self._due = now if last is None else max(now, last + self.period_s)
            self._continuing = False
        return stream

    def stop(self, name: str) -> None:
        self.streams.pop(name, None)

    def carried(self) -> list[Driver]:
        """The devices the last tick's frame carried: a ramp's last tick carries its device
        though its stream ended as the tick was built (rule 5), and that device's reply is
        still its own (a ZLAC706 keeps the speed it acknowledged)."""
        return self._carried

    def next_due(self) -> float | None:
        return self._due if self.streams else None

    def build(self, now: float) -> Request | None:
        self._ramps_ending.clear()
        for name, stream in list(self.streams.items()):
            stale = not stream.ends_on_target and now - stream.latest[1] > self.fresh_s
            if stale or stream.limiter.follows != stream.driver.follows:  # rules 2 and 7
                del self.streams[name]
                self.on_stale(stream.driver)
        if not self.streams:  # idle: the next ``update`` starts it anew
            return None
        targets: list[tuple[Driver, float]] = []
        soonest_held = now + self.period_s  # a command's that waits: looked at again then
        for name, stream in list(self.streams.items()):
            due = self.spacing.due(name, self.period_s, self)
            if due > now:  # another sender's target went less than a period ago (rule 8)
                soonest_held = min(soonest_held, due)
                continue
            target = stream.next_target()
            targets.append((stream.driver, target))
            if stream.ends_on_target and target == stream.limiter.goal(stream.latest[0]):
                del self.streams[name]  # this tick sends the ramp's end (rule 5)
                if stream.held and stream.told_limited:  # rule 4
                    self._ended_held.add(name)
                self.on_reached(stream.driver)
                self._ramps_ending.append(stream.driver)
        if not targets:  # every stream held off (rule 8)
            self._due = soonest_held
            return None
        self._carried = [driver for driver, _ in targets]
        return self.driver_class.follow_request(targets)

    def sent(self, start: float) -> None:
        for stream in self.streams.values():
            stream.unsent = None  # its step is on the wire (rule 6)
        if self._continuing and self._last_start is not None:
            self.counters.follow_interval(start - self._last_start, self.period_s)
        self._continuing = True
        self._last_start = start
        self._due = start + self.period_s
        for driver in self._ramps_ending:  # rule 5
            self.on_ramp_sent(driver, start)
        self._ramps_ending.clear()


class KeepaliveTicker:
    """Repeats what a device needs to keep going (a ZLAC706's speed) while it needs it."""

    def __init__(self, driver: Driver) -> None:
        self.driver = driver
        self.period_s = 0.0
        self._last_start = 0.0

    def next_due(self) -> float | None:
        need = self.driver.keepalive(self._last_start)
        if need is None:
            return None
        self.period_s = need[0]
        return self._last_start + self.period_s

    def build(self, now: float) -> Request | None:
        need = self.driver.keepalive(now)
        return None if need is None else need[1]

    def sent(self, start: float) -> None:
        self._last_start = start
