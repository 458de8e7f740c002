"""Bus budgets: how much of a bus its configured polling and follow streams take.

Rules of this file:

1. The figures come from the machinery that will run the bus, never from a copy of it: the
   runner ``build_bus`` makes (built, not started: nothing is opened), its drivers' own poll
   and follow requests, its ``LinkTiming`` (wire time, worst case) and its planner (gap,
   slack). Change a driver's poll and the budget follows.
2. Two figures per stream. *Wire* time is what the bytes occupy (our frames and the replies
   at the bus's rate). *Reserved* time is what the scheduler holds the line for: the worst
   case (frame, then the reply's deadline) plus the gap. The bus is oversubscribed when the
   reserved time passes 100 %, or when the longest poll exchange cannot fit between two
   follow ticks: polls are then skipped and telemetry goes stale. It is warned of, besides,
   when not even its shortest exchange with a reply (a device's ``poll`` or ``init``: what a
   command is at its shortest), worst case, fits in what the ticks leave of their period at
   best (their frames and replies on the wire, no more): commands then wait while every
   device streams, until they are answered ``busy``.
3. Follow streams count as if every device streamed at its period, coalesced as the runner
   coalesces them: one frame per tick for up to ``follow_group_limit`` devices of one kind
   and one period (one 0xF3 frame for 15 LA actuators, one SYNC WRITE for DS servos). Polls
   are ``poll()``, or ``init()`` where a driver polls nothing (a ZLAC706 on CAN repeats its
   init at the poll rate while offline: the worst case). CAN heartbeats take the bus too.
   ZLAC706 speed keep-alives (one frame per 0.4 s on CAN, 0.8 s on RS232, only while the
   wheel turns) are left out: about 1 % of a bus at most.
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Iterable
from dataclasses import dataclass

from busgate.errors import RefusedError
from busgate.gateway.bus.request import LinkTiming, Request
from busgate.gateway.drivers.base import Driver
from busgate.gateway.drivers.families import driver_class
from busgate.gateway.scheduler.runner import COMMAND_START_S, BusRunner
from busgate.gateway.service.assembly import build_bus
from busgate.schemas.config import CanBus, SerialBus
from busgate.schemas.families import PROTOCOLS


@dataclass(frozen=True, slots=True)
class Load:
    """One kind of traffic on a bus, per second: frames, wire time, reserved time."""

    frames: float = 0.0
    wire_s: float = 0.0
    reserved_s: float = 0.0

    def __add__(self, other: Load) -> Load:
        return Load(
            self.frames + other.frames,
            self.wire_s + other.wire_s,
            self.reserved_s + other.reserved_s,
        )

    def describe(self) -> str:
        if not self.frames:
            return "-"
        return f"{self.frames:g} frames/s, {self.wire_s * 1000:.2f} ms/s"


@dataclass(frozen=True, slots=True)
class BusBudget:
    """What one bus's configured traffic takes of it (times in seconds, shares 0–1+)."""

    bus: str
    transport: str
    rate: int
    protocol: str
    devices: int
    polling: Load
    follow: Load
    heartbeats: Load
    #: The shortest follow period, and the line left in it once every follow frame went out:
    #: at worst (each tick's worst case and gap) and at best (its wire time and gap).
    follow_period_s: float | None
    tick_free_s: float | None
    tick_room_s: float | None
    #: The longest poll exchange, worst case, plus the planner's slack before a tick.
    longest_poll_s: float
    #: The shortest exchange with a reply, worst case, plus the slack (rule 2; 0: none).
    shortest_reply_s: float
    reply_margin_s: float

    @property
    def total(self) -> Load:
        return self.polling + self.follow + self.heartbeats

    @property
    def wire_share(self) -> float:
        return self.total.wire_s

    @property
    def reserved_share(self) -> float:
        return self.total.reserved_s

    @property
    def poll_fits(self) -> bool:
        """The longest poll exchange fits between two follow ticks."""
        return self.tick_free_s is None or self.longest_poll_s <= self.tick_free_s

    @property
    def command_fits(self) -> bool:
        """The shortest exchange with a reply fits between two follow ticks (rule 2)."""
        return self.tick_room_s is None or self.shortest_reply_s <= self.tick_room_s

    @property
    def oversubscribed(self) -> bool:
        return self.reserved_share > 1.0 or not self.poll_fits

    @property
    def rate_text(self) -> str:
        return f"{self.rate} {'bit/s' if self.transport == 'can' else 'baud'}"

    def summary(self) -> str:
        """One line: the bus, its streams, and the share of it they take."""
        verdict = "OVERSUBSCRIBED" if self.oversubscribed else "fits"
        return (
            f"bus {self.bus}: {self.transport} {self.rate_text}, {self.devices} {self.protocol}; "
            f"polling {self.polling.describe()}; follow {self.follow.describe()}; "
            f"heartbeats {self.heartbeats.describe()}; "
            f"on the wire {self.wire_share:.1%}, reserved {self.reserved_share:.1%} "
            f"(worst case, gaps included): {verdict}"
        )

    def warnings(self) -> list[str]:
        """What is wrong with the budget, each with what to change."""
        found = []
        if self.reserved_share > 1.0:
            found.append(self._overload())
        if not self.poll_fits:
            found.append(self._no_room_for_polls())
        elif not self.command_fits:
            found.append(self._no_room_for_commands())
        return found

    @property
    def _rate_key(self) -> str:
        return "bitrate" if self.transport == "can" else "baudrate"

    def _no_room_for_polls(self) -> str:
        free_ms = max(self.tick_free_s or 0.0, 0.0) * 1000
        commands = "" if self.command_fits else f", and commands wait ({self._commands_wait})"
        return (
            f"oversubscribed: a poll exchange needs {self.longest_poll_s * 1000:.2f} ms (worst "
            f"case) but only {free_ms:.2f} ms are left between follow ticks every "
            f"{self._period_ms:g} ms, so polls stop while every device streams{commands}; "
            f"{self._remedies}"
        )

    def _no_room_for_commands(self) -> str:
        room_ms = max(self.tick_room_s or 0.0, 0.0) * 1000
        return (
            f"follow ticks every {self._period_ms:g} ms leave at most "
            f"{room_ms:.2f} ms between them, so commands wait while every device streams "
            f"({self._commands_wait}); {self._remedies}"
        )

    @property
    def _commands_wait(self) -> str:
        return (
            f"the shortest needs {self.shortest_reply_s * 1000:.2f} ms, worst case; each is "
            f"answered busy after {COMMAND_START_S:g} s"
        )

    @property
    def _period_ms(self) -> float:
        return (self.follow_period_s or 0.0) * 1000

    @property
    def _remedies(self) -> str:
        return (
            f"raise follow_period_ms, lower reply_margin_ms (now "
            f"{self.reply_margin_s * 1000:g} ms) or use a faster {self._rate_key}"
        )

    def _overload(self) -> str:
        head = (
            f"oversubscribed: the streams reserve {self.reserved_share:.0%} of the bus "
            f"(worst case); "
        )
        room = 1.0 - self.follow.reserved_s - self.heartbeats.reserved_s
        if room <= 0:
            return head + (
                "follow ticks and heartbeats alone take "
                f"{self.follow.reserved_s + self.heartbeats.reserved_s:.0%}: raise "
                f"follow_period_ms or split the devices over more buses"
            )
        return head + (
            f"lower poll_hz to {room / self.polling.reserved_s:.0%} of today's, lower "
            f"reply_margin_ms (now {self.reply_margin_s * 1000:g} ms, part of every "
            f"exchange's worst case), use a faster {self._rate_key} or split the devices "
            f"over more buses"
        )


def bus_budget(bus: SerialBus | CanBus) -> BusBudget:
    """The budget of ``bus`` as ``busgate run`` would drive it (nothing is opened)."""
    runner = build_bus(bus)
    timing, gap = runner.timing, runner.planner.gap_s
    # Steady state: what each online device's poll sends (nothing, for a ZLAC706 on CAN, whose
    # telemetry is its heartbeats); an offline device's probes come OFFLINE_PROBE_S apart.
    polls = [(p.poll_period_s, p.driver.poll()) for p in runner.pollers]
    polling = sum((_load(timing, gap, requests, 1 / period) for period, requests in polls), Load())
    ticks = _follow_frames(runner)
    follow = sum((_load(timing, gap, [request], 1 / period) for period, request in ticks), Load())
    shortest = min((period for period, _ in ticks), default=None)
    tick_free = tick_room = None
    if shortest is not None:
        tick_free = shortest - sum(timing.worst_case(r) + gap for _, r in ticks)
        tick_room = shortest - sum(_wire_s(timing, r) + gap for _, r in ticks)
    longest = max((timing.worst_case(r) for _, requests in polls for r in requests), default=0.0)
    answered = [
        timing.worst_case(r)
        for driver in runner.drivers.values()
        for r in [*driver.poll(), *driver.init()]
        if r.expected is not None
    ]
    quickest = min(answered, default=0.0)
    return BusBudget(
        bus=bus.name,
        transport=bus.transport,
        rate=bus.baudrate if isinstance(bus, SerialBus) else bus.bitrate,
        protocol=bus.protocol,
        devices=len(bus.devices),
        polling=polling,
        follow=follow,
        heartbeats=_heartbeats(bus, timing),
        follow_period_s=shortest,
        tick_free_s=tick_free,
        tick_room_s=tick_room,
        longest_poll_s=longest + runner.planner.slack_s if longest else 0.0,
        shortest_reply_s=quickest + runner.planner.slack_s if quickest else 0.0,
        reply_margin_s=timing.margin_s,
    )


def _load(timing: LinkTiming, gap_s: float, requests: Iterable[Request], hz: float) -> Load:
    """``requests`` repeated ``hz`` times a second."""
    total = Load()
    for request in requests:
        wire = _wire_s(timing, request)
        total += Load(hz, wire * hz, (timing.worst_case(request) + gap_s) * hz)
    return total


def _wire_s(timing: LinkTiming, request: Request) -> float:
    """What ``request`` and its reply take of the wire, at the bus's rate."""
    wire = timing.wire_time(request.wire)
    if request.expected is not None:
        wire += timing.reply_time(request.expected)
    return wire


def _follow_frames(runner: BusRunner) -> list[tuple[float, Request]]:
    """``(period, frame)`` of every follow tick, coalesced as the runner's tickers do."""
    by_period: dict[float, list[Driver]] = defaultdict(list)
    for driver in runner.drivers.values():
        by_period[driver.follow_period_s].append(driver)
    frames = []
    for period, drivers in by_period.items():
        limit = type(drivers[0]).follow_group_limit
        for first in range(0, len(drivers), limit):
            group = drivers[first : first + limit]
            targets = [(driver, _follow_target(driver)) for driver in group]
            frames.append((period, type(group[0]).follow_request(targets)))
    return frames


def _follow_target(driver: Driver) -> float:
    """A representative follow target, validated by the driver itself once the commands that
    make it ready to follow are planned (a ZLAC706's make it stream speeds: a position
    target is a frame of the same size). Frame sizes do not depend on the values: a driver
    whose joint refuses the sample (a ZLAC706 position joint with limits takes no speed
    stream, where it would turn to not being known) is sized as its family's, unlimited."""
    for command in driver.follow_preparation:
        driver.plan(driver.parse(command))
    try:
        return driver.follow_target(driver.follow_sample(0.0, 0))
    except RefusedError:
        if not driver.joint.limited:
            raise
        return _follow_target(type(driver)(driver.name, driver.device_id))


def _heartbeats(bus: SerialBus | CanBus, timing: LinkTiming) -> Load:
    """What the nodes send unasked (CAN heartbeats): wire time, and as much reserved."""
    protocol = PROTOCOLS[bus.protocol]
    total = Load()
    for device in bus.devices:
        frames = driver_class(protocol).heartbeat_frames(device.id)
        if device.heartbeat_ms and frames:
            hz = 1000 / device.heartbeat_ms
            wire = sum(timing.wire_time(protocol.codec.encode(frame)) for frame in frames) * hz
            total += Load(len(frames) * hz, wire, wire)
    return total
