"""The ticks of trajectories the gateway plays: each device's target sampled at its period,
on a grid shared by every bus.

Rules of this file:

1. Tick ``k`` of a trajectory is due at its slot, ``start + k × grid``, for every bus alike
   (so buses that start together stay together), and never before the previous tick's start
   plus the device's period: no interval is ever shorter than the period. The grid's period
   is the device's stretched by ``GRID_STRETCH``, never past ``LONGEST_INTERVAL_S``
   (``grid_of``): every write starts a little after it is due (the host's wake-up, the
   write call), and a grid of exactly the period would carry each tick's lateness into the
   next one's earliest start, so that it grew tick after tick; the stretch gives each
   interval that slack back, and a tick a little late is followed by one on its slot
   again. A tick that started over ``ON_TIME_S`` after its slot (the contract's alignment
   bound: a hiccup, a busy line) has drifted: the next is the first slot a full period
   after it, so the grid is never left and a late tick is not made up by a burst; unless
   that slot is more than ``LONGEST_INTERVAL_S`` after the late tick (at periods over some
   25 ms): then the next is the next slot, due a period after the late tick, since the LA's
   follow mode takes a target at most every 50 ms; the stretch brings the ticks back onto
   their slots, a hundredth of a period a tick.
2. What a tick sends is the trajectory sampled at the tick's slot (``sample(k × grid)``, a
   follow payload such as ``{"position": 1200}``, made the driver's target as a follow put's
   is), not at the moment the frame happens to leave: the wire carries the interpolant at
   the grid's times, whatever the host's jitter. The time is ``k × grid`` itself, not the
   slot's bus time less the start, whose rounding depends on how long the host has been up
   and can tip a value that is a half in exact arithmetic to either side.
3. Devices of one driver kind, one period and one start share a ticker and a frame (every
   Inspire LA of a bus in one 0xF3 frame, DS servos in one SYNC WRITE), up to the kind's
   ``follow_group_limit``.
4. ``commanded`` holds, per device, the slot time and the value of its last tick sent (a tick
   built ahead of its slot and then put off is not); other threads read it from the bus's
   published ``PlaysView`` (``plays`` rule 1), never here.
5. A device that can no longer take its target (e-stopped on its own, or its driver refuses
   the target: a ZLAC706 switched out of velocity mode) is left out of the frame and off the
   ticker, its reason in ``refused`` for ``on_tick``; its neighbours' tick goes on. With no
   device left, the slot passes without a frame. Nothing a device does makes a tick raise:
   the bus thread takes an exception for a bug and reopens the bus.
6. Tickers of one bus on one grid (devices whose frames cannot be one: a ZLAC706 a frame)
   share a ``SlotGroup``: the first tick of a slot is judged on time or late by rule 1, and
   the ticks after it in that slot, back to back behind it on the line, are judged with it,
   so that a base's second wheel does not lose every other slot to its first's exchange.
7. A device is left out of a slot due less than its follow period after another sender's
   last follow target to it (the stream or the trajectory it came from, a command's
   ``follow``: ``spacing``), or while a command carrying it one still waits to go out; it
   stays on the ticker and is in the first slot after that. With no device in it, the slot
   passes without a frame, as by rule 5.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from busgate.errors import CommandError, RefusedError
from busgate.gateway.bus.request import Request
from busgate.gateway.bus.stats import BusCounters
from busgate.gateway.drivers.base import Driver
from busgate.gateway.scheduler.spacing import FollowSpacing
from busgate.schemas.config import FOLLOW_PERIOD_MS

#: How long after its slot a tick may start and the next still be on the following slot
#: (rule 1): the 1 ms within which the buses' ticks of one slot are aligned.
ON_TIME_S = 0.001
#: The grid's period over the device's (rule 1): 1 % is 100 µs a tick at 10 ms, several times
#: what a tick usually starts late on this kind of host, so lateness does not pile up.
GRID_STRETCH = 1.01
#: The longest interval a drifted tick may leave before the next (rule 1): the longest follow
#: period the manual allows.
LONGEST_INTERVAL_S = FOLLOW_PERIOD_MS[1] / 1000
#: A sampler: seconds from the trajectory's start → the device's follow payload (one key).
Sampler = Callable[[float], dict[str, Any]]


@dataclass(slots=True)
class SlotGroup:
    """The tickers of one bus on one grid (rule 6): the last slot judged, and its verdict."""

    slot: int = -1
    on_time: bool = True


@dataclass(frozen=True, slots=True)
class Playing:
    """One device of a trajectory on this ticker."""

    driver: Driver
    sample: Sampler


class TrajectoryTicker:
    """Sends the sampled targets of its devices on the trajectory's grid, in one frame."""

    def __init__(
        self,
        driver_class: type[Driver],
        period_s: float,
        start: float,
        counters: BusCounters,
        on_tick: Callable[[TrajectoryTicker], None] = lambda ticker: None,
        group: SlotGroup | None = None,
        spacing: FollowSpacing | None = None,
    ) -> None:
        self.driver_class = driver_class
        self.period_s = period_s
        #: The grid's period (rule 1): slot ``k`` is at ``start + k × grid_s``.
        self.grid_s = grid_of(period_s)
        self.start = start
        self.counters = counters
        #: Called after each slot, its frame sent or (rule 5) passed without one.
        self.on_tick = on_tick
        self.playing: dict[str, Playing] = {}
        #: Each device's last tick sent: (seconds from the start, the value) (rule 4).
        self.commanded: dict[str, tuple[float, float]] = {}
        #: Devices ramping out of their trajectory, and when (seconds from the start) it ends.
        self.ramping: dict[str, float] = {}
        #: Devices left out because they could not take their target, and why (rule 5).
        self.refused: dict[str, str] = {}
        self._k = 0  # the next slot's index
        self._due = start  # its slot, or a period after the last tick started if that is later
        self._last_start: float | None = None
        self._built: dict[str, tuple[float, float]] = {}  # what the frame being sent carries
        self._carried: list[Driver] = []
        self.group = group or SlotGroup()
        self.spacing = spacing or FollowSpacing()  # its bus's (rule 7)

    def has_room(self, driver: Driver) -> bool:
        limit = self.driver_class.follow_group_limit
        return driver.name in self.playing or len(self.playing) < limit

    def add(self, driver: Driver, sample: Sampler) -> None:
        self.playing[driver.name] = Playing(driver, sample)

    def remove(self, name: str) -> None:
        self.playing.pop(name, None)

    def carried(self) -> list[Driver]:
        """The devices the last frame built carries."""
        return list(self._carried)

    def next_due(self) -> float | None:
        return self._due if self.playing else None

    @property
    def last_sent(self) -> float | None:
        """When (bus clock) the last frame went out; ``None`` before the first."""
        return self._last_start

    def build(self, now: float) -> Request | None:
        if not self.playing:
            return None
        t_s = self._k * self.grid_s  # rule 2: the slot's time, not now's
        targets: list[tuple[Driver, Any]] = []
        built: dict[str, tuple[float, float]] = {}
        for name, member in list(self.playing.items()):
            if self.spacing.due(name, self.period_s, self) > now:
                continue  # another sender's target went less than a period ago (rule 7)
            driver = member.driver
            payload = member.sample(t_s)
            (value,) = payload.values()
            try:
                if driver.estopped:
                    raise driver.estopped_error()
                targets.append((driver, driver.follow_target(payload)))
            except (CommandError, RefusedError) as exc:  # rule 5
                self.refused[name] = str(exc)
                self.remove(name)
                continue
            built[name] = (t_s, value)
        if not targets:
            self._pass(now)
            return None
        self._built = built
        self._carried = [driver for driver, _ in targets]
        return self.driver_class.follow_request(targets)

    def sent(self, start: float) -> None:
        if self._last_start is not None:
            self.counters.follow_interval(start - self._last_start, self.period_s)
        self._last_start = start
        self.commanded.update(self._built)  # rule 4: one assignment per device
        if self._on_time(start):  # rules 1 and 6
            self._go_to(self._k + 1)
        else:  # drifted: the first slot a full period on, within the longest interval
            skip_to = slot_index(self.start, self.grid_s, start + self.period_s)
            within = self._slot(skip_to) - start <= LONGEST_INTERVAL_S
            self._go_to(skip_to if within else self._k + 1)
        self.on_tick(self)

    def _on_time(self, start: float) -> bool:
        group = self.group
        if group.slot != self._k:  # the first tick of this slot on the bus (rule 6)
            group.slot, group.on_time = self._k, start - self._slot(self._k) <= ON_TIME_S
        return group.on_time

    def _pass(self, now: float) -> None:
        """No device could take its target (rule 5) or may have it yet (rule 7): the slot
        passes without a frame, and the next one is due after ``now`` (the planner asks again
        at once)."""
        self._go_to(max(self._k + 1, slot_index(self.start, self.grid_s, now)))
        self.on_tick(self)

    def _go_to(self, k: int) -> None:
        """Slot ``k`` is next: due at it, and never before a period after the last tick."""
        self._k = k
        last = self._last_start
        slot = self._slot(k)
        self._due = slot if last is None else max(slot, last + self.period_s)

    def _slot(self, k: int) -> float:
        return self.start + k * self.grid_s


def grid_of(period_s: float) -> float:
    """The grid's period for a device's ``period_s`` (rule 1): stretched by ``GRID_STRETCH``,
    but never past ``LONGEST_INTERVAL_S`` (a 50 ms period has no stretch: its ticks carry the
    host's lateness instead, rather than each leave 50.5 ms)."""
    return min(period_s * GRID_STRETCH, max(period_s, LONGEST_INTERVAL_S))


def next_slot(start: float, period_s: float, earliest: float) -> float:
    """The first slot ``start + k × period_s`` (k ≥ 0) at or after ``earliest`` (rule 1).

    >>> next_slot(10.0, 0.02, 10.02), next_slot(10.0, 0.02, 10.0201), next_slot(10.0, 0.02, 9.0)
    (10.02, 10.04, 10.0)
    """
    return start + slot_index(start, period_s, earliest) * period_s


def slot_index(start: float, period_s: float, earliest: float) -> int:
    """``k`` of ``next_slot``: a moment within a billionth of a period of a slot is that slot."""
    return max(0, math.ceil((earliest - start) / period_s - 1e-9))
