"""The bus planner: given its state and ``now``, the next exchange to start, or when to wake.

It is pure — no I/O, no clock, no threads — so every timing rule is tested with a fake clock.
The rules it enforces:

1. Gap: no frame starts before ``gap_s`` after the line went idle (our last frame, plus its
   reply when one was expected, or its timeout).
2. Precedence: e-stop > commands > follow ticks > polling.
3. Follow ticks keep their slot: nothing starts unless its worst-case duration plus the gap
   (and at least ``HOST_SLACK_S``, the host's own time to take in a reply) ends before the
   next tick is due; a due tick goes out at once. A late tick is not made up by
   a burst (tickers schedule the next tick a full period after the one actually sent).
4. Bounded: commands wait in a bounded queue (``push_command`` says no when full, or when the
   command's client has ``CLIENT_SHARE`` of it waiting already: one client's flood leaves
   room for the others'); a stop the gateway makes itself (a stream's 0 rpm) is never refused
   (``push_stop``), however full the queue. Polls are never queued — a device has at most one
   poll waiting, and each period a poll misses (the host stalled, or the bus has no room for
   it) is skipped and counted; an e-stop is never refused, but one that comes while another
   waits, not started, joins it (``push_estop``).
5. After a timeout, no exchange that expects a reply starts before ``hold_replies_until``:
   a reply that comes late is then flushed as stale instead of being taken for the answer to
   the next request (frames without a reply, such as follow ticks, may still go).
6. Deadlines: a command not started by its ``start_by`` is dropped (``expired``), never sent
   later: its client has been answered. A scan's probes all start by the scan's ``start_by``.
7. Scans wait in a lane of their own, after commands and due polls: a long scan interleaves
   with everything else instead of holding the command queue.
8. One device's jobs never interleave, and each is decided from the state the jobs before it
   left: a device's jobs go in the order they came (precedence is between devices), one
   that has started runs to its end before another of its device starts (an e-stop's goes
   first all the same), and a device's poll is built only when none of its commands waits.
   A poll's frames may depend on what the gateway knows of the device (an offline device's
   ``init`` releases a motor no client has enabled): a client's enable never goes between
   them. A poll built but not started gives way to a command of its device that comes
   (``withdrawn``), and is built again once the commands are done, from the state they
   left: a poll that waits for room before a tick never holds its device's commands. A job
   is a job of each device it moves (``Job.devices``: a group frame's too), and one for
   ``EVERY_DEVICE`` (a reset of the whole bus) of every device, in that order; a scan's
   probes address no device of the bus and keep their lane.
An exchange that may be retried (idempotent, at most ``MAX_RETRIES`` times) goes back to the
head of its job.
"""

from __future__ import annotations

import enum
import itertools
import math
from collections import deque
from collections.abc import Sequence
from collections.abc import Set as AbstractSet
from concurrent.futures import Future
from dataclasses import dataclass, field
from typing import Protocol

from busgate.gateway.bus.request import LinkTiming, Request
from busgate.gateway.scheduler.spacing import FollowSpacing

MAX_RETRIES = 2
#: The host's time, after a reply, to interpret it and have the next tick's frame ready.
HOST_SLACK_S = 0.0008
COMMAND_QUEUE = 64
#: The device of a job for every device of the bus (an e-stop, a reset of them all; a scan).
EVERY_DEVICE = "*"
#: How many of a bus's waiting commands may be one client's (rule 4): half, so that a client
#: reading every device of a full bus at once (an LA bus carries 15, a DS bus more) is not
#: refused, and a flood leaves the other half to the rest.
CLIENT_SHARE = COMMAND_QUEUE // 2


class Priority(enum.IntEnum):
    ESTOP = 0
    COMMAND = 1
    FOLLOW = 2
    POLL = 3


@dataclass(eq=False)
class Job:
    """Requests to run in order for one device, and who waits for their outcome.

    A failed request (after its retries) ends the job, unless ``keep_going`` (an e-stop must
    reach the other devices even when one of them is silent).
    """

    device: str
    requests: deque[Request]
    priority: Priority = Priority.COMMAND
    replies: list = field(default_factory=list)
    error: BaseException | None = None
    attempts: int = 0
    keep_going: bool = False
    #: The other devices its frames move (a group or broadcast frame sent through this one's
    #: command): each is told once such a frame went (``Driver.moved_by``).
    also_moves: tuple[str, ...] = ()
    #: When a list, the runner records ``(request, reply events or None)`` per request.
    outcomes: list | None = None
    #: Who waits for the outcome (a client's command, a scan, an e-stop); a poll has no one.
    future: Future | None = None
    #: A poll: when its device's next poll is due. Waiting polls go out earliest first.
    next_poll_due: float = math.inf
    #: Latest moment (``perf_counter``) the job may start; for a scan, each of its probes.
    start_by: float = math.inf
    #: Its first request has been sent: from then on it runs to its end.
    started: bool = False
    #: What planning it changed of its devices' e-stop, by device (latched, and driving when
    #: it latched): put back when it is taken out unsent (``devices.tell_unsent``).
    estop_before: dict[str, tuple[bool, bool]] = field(default_factory=dict)
    #: Whose command it is (its ``client``, ``""`` when it named none): ``None`` for the
    #: gateway's own jobs, which take no client's share (rule 4).
    client: str | None = None
    #: A client's command whose frames only read: an e-stop leaves it waiting (nothing it
    #: does moves a device), where it takes every other command out.
    reads_only: bool = False
    #: A scan: its probes wait in the scan lane, each tried once, a silent id costing its
    #: reply window and nothing more.
    scan: bool = False
    #: When the planner took it in (a count): a device's jobs go in this order (rule 8).
    order: int = 0

    @property
    def devices(self) -> tuple[str, ...]:
        """The devices it is a job of (rule 8): its own and those its frames also move."""
        return (self.device, *self.also_moves)

    def expired(self, now: float) -> bool:
        return now > self.start_by and (self.scan or not self.started)


class Ticker(Protocol):
    """Frames at a fixed period: a follow stream (one per device, or one coalesced frame, a
    ``tickers.FollowTicker``) or a device's keep-alive (``tickers.KeepaliveTicker``)."""

    period_s: float

    def next_due(self) -> float | None:
        """When the next tick is due; ``None`` while there is nothing to stream."""

    def build(self, now: float) -> Request | None:
        """The tick's frame (latest targets), or ``None`` when the streams went stale or
        none may go yet (its next tick is due later then)."""

    def sent(self, start: float) -> None:
        """The tick's frame started at ``start``: the next one is due a period later."""


class Poller(Protocol):
    """A device's telemetry reads at its ``poll_hz``."""

    device: str
    next_due: float

    @property
    def period_s(self) -> float:
        """Seconds from one poll to the next."""

    def build(self) -> list[Request]:
        """The requests of one poll."""

    def withdrawn(self) -> None:
        """The poll last built was taken out before all of it went (rule 8, an e-stop, a lost
        link): what building it handed out (a restore of the device's settings, written
        again whole: each write sets a value) is due again."""


@dataclass(frozen=True, slots=True)
class Slot:
    """The planner's decision: start ``request`` now, on behalf of ``source``."""

    request: Request
    priority: Priority
    source: Job | Ticker


class BusPlanner:
    """Decides the next exchange on one bus."""

    def __init__(self, timing: LinkTiming, *, command_queue: int = COMMAND_QUEUE) -> None:
        self.timing = timing
        self.gap_s = timing.gap_s
        #: What must be left between an exchange and the next tick: the gap, and at least
        #: the host's time to take in a reply and prepare the tick.
        self.slack_s = max(timing.gap_s, HOST_SLACK_S)
        self.line_free = -math.inf
        self.hold_replies_until = -math.inf
        self.skipped_polls = 0
        self._estops: deque[Job] = deque()
        self._commands: deque[Job] = deque()
        self._scans: deque[Job] = deque()
        self._command_limit = command_queue
        #: Jobs dropped at their deadline, for the runner to answer (``take_expired``).
        self._expired: list[Job] = []
        self._polls: dict[str, Job] = {}
        self.tickers: list[Ticker] = []
        self.pollers: Sequence[Poller] = []
        #: Each device's last follow target, from whichever ticker or command sent it.
        self.spacing = FollowSpacing()
        self._taken_in = itertools.count()

    def push_estop(self, job: Job) -> Job:
        """Queue an e-stop ahead of everything, never refused; the job that will send its
        frames. One still waiting, not started, takes ``job``'s frames (the latest, for the
        same latched devices) in place of its own and is returned: e-stops put again and
        again wait at most one behind the one on the line (rule 4)."""
        job.priority = Priority.ESTOP
        waiting = self._estops[-1] if self._estops else None
        if waiting is not None and not waiting.started:
            waiting.requests = job.requests
            return waiting
        self._estops.append(job)
        return job

    def push_command(self, job: Job) -> bool:
        """Queue a command (or a scan, in its lane); ``False`` (and nothing queued) when the
        queue is full or holds its client's share already (rule 4)."""
        queue = self._scans if job.scan else self._commands
        if len(queue) >= self._command_limit or self.share_taken(job.client):
            return False
        job.order = next(self._taken_in)
        queue.append(job)
        return True

    def push_stop(self, job: Job) -> None:
        """Queue a stop the gateway makes itself, behind the commands already waiting: never
        refused (rule 4)."""
        job.order = next(self._taken_in)
        self._commands.append(job)

    def share_taken(self, client: str | None) -> bool:
        """Whether ``client`` has its share of the waiting commands (rule 4)."""
        if client is None:
            return False
        return sum(job.client == client for job in self._commands) >= CLIENT_SHARE

    def drop_commands(self, *, keep_reads: bool = False) -> list[Job]:
        """Take every queued command, scan and poll out (an e-stop or a lost link voids them),
        but with ``keep_reads`` the commands that only read (an e-stop's: they move nothing)."""
        kept: deque[Job] = deque()
        dropped: list[Job] = []
        for job in self._commands:
            (kept if keep_reads and job.reads_only else dropped).append(job)
        dropped += [*self._scans, *self._polls.values()]
        self._commands = kept
        self._scans.clear()
        for poller in self.pollers:
            if self._polls.pop(poller.device, None) is not None:
                poller.withdrawn()
        return dropped

    def discard(self, job: Job) -> None:
        """Take ``job`` out wherever it waits (it was cancelled before it started)."""
        self._remove(job)

    def take_expired(self) -> list[Job]:
        """The jobs dropped at their deadline since the last call."""
        expired, self._expired = self._expired, []
        return expired

    @property
    def queued(self) -> int:
        return len(self._commands)

    @property
    def stopping(self) -> bool:
        """Whether an e-stop is on the line or waits for it (any thread may ask)."""
        return bool(self._estops)

    def decide(self, now: float) -> Slot | float:
        """The exchange to start at ``now``, or the time to ask again."""
        ready = self.line_free + self.gap_s
        if now < ready:
            return ready
        if self._estops:
            return self._slot(self._estops[0])
        tick_due, ticker = self._next_tick()
        if ticker is not None and tick_due <= now:
            request = ticker.build(now)
            if request is not None:
                return Slot(request, Priority.FOLLOW, ticker)
            return self.decide(now)  # nothing to send now: its next tick is later, or none
        commanded = {d for job in self._commands for d in job.devices} if self._commands else _NONE
        if commanded and self._polls:
            self._withdraw_polls(now, commanded)
        self._start_due_polls(now, commanded)
        self._expire(now)
        held = now < self.hold_replies_until
        for job in self._candidates():
            request = job.requests[0]
            if held and request.expected is not None:
                continue
            if now + self.timing.worst_case(request) + self.slack_s <= tick_due:
                return self._slot(job)
        wake = min(tick_due, self._next_poll_due(commanded))
        return min(wake, self.hold_replies_until) if held else wake

    def finished(self, slot: Slot, end: float, *, failed: bool) -> Job | None:
        """Record that ``slot`` held the line until ``end``; return its job when the job is
        over (all requests done, or failed for good), else ``None``."""
        self.line_free = max(self.line_free, end)
        if not isinstance(slot.source, Job):
            return None
        job = slot.source
        if failed and slot.request.idempotent and job.attempts < MAX_RETRIES:
            job.attempts += 1
            job.started = True
            return None
        job.started = True
        job.requests.popleft()
        job.attempts = 0
        if (failed and not job.keep_going) or not job.requests:
            self._remove(job)
            return job
        return None

    def _slot(self, job: Job) -> Slot:
        return Slot(job.requests[0], job.priority, job)

    def _next_tick(self) -> tuple[float, Ticker | None]:
        best, chosen = math.inf, None
        for ticker in self.tickers:
            due = ticker.next_due()
            if due is not None and due < best:
                best, chosen = due, ticker
        return best, chosen

    def _candidates(self) -> list[Job]:
        candidates = [*self._commands]
        if self._polls:
            candidates += sorted(self._polls.values(), key=_poll_due)
        if self._scans:
            candidates.append(self._scans[0])  # the scan lane: its first job only
        if not self._commands:  # one poll a device: nothing to put in order
            return candidates
        return _first_of_each_device(candidates)

    def _expire(self, now: float) -> None:
        for queue in (self._commands, self._scans):
            if not queue:
                continue
            for job in [job for job in queue if job.expired(now)]:
                queue.remove(job)
                self._expired.append(job)

    def _start_due_polls(self, now: float, commanded: AbstractSet[str]) -> None:
        for poller in self.pollers:
            if poller.next_due > now or _waits_for(poller.device, commanded):  # rule 8
                continue
            if poller.device in self._polls:  # the last poll has not gone out in a whole period
                self.skipped_polls += 1
                poller.next_due += poller.period_s
                continue
            if now - poller.next_due > poller.period_s:
                self.skipped_polls += 1
                poller.next_due = now
            requests = deque(poller.build())
            poller.next_due += poller.period_s
            if requests:
                self._polls[poller.device] = Job(
                    poller.device,
                    requests,
                    Priority.POLL,
                    next_poll_due=poller.next_due,
                    order=next(self._taken_in),
                )

    def _withdraw_polls(self, now: float, commanded: AbstractSet[str]) -> None:
        """Rule 8: a poll not started gives way to its device's waiting commands; it is due
        again at once, built when they are done."""
        for poller in self.pollers:
            job = self._polls.get(poller.device)
            if job is not None and not job.started and _waits_for(poller.device, commanded):
                del self._polls[poller.device]
                poller.withdrawn()
                poller.next_due = min(poller.next_due, now)

    def _next_poll_due(self, commanded: AbstractSet[str]) -> float:
        """The next poll to build: a device's that waits for its commands is built once they
        are done (the planner is asked again then)."""
        waiting = [
            p.next_due
            for p in self.pollers
            if p.device not in self._polls and not _waits_for(p.device, commanded)
        ]
        return min(waiting, default=math.inf)

    def _remove(self, job: Job) -> None:
        for queue in (self._estops, self._commands, self._scans):
            if job in queue:
                queue.remove(job)
                return
        if self._polls.get(job.device) is job:
            del self._polls[job.device]


_NONE: AbstractSet[str] = frozenset()


def _waits_for(device: str, commanded: AbstractSet[str]) -> bool:
    """Whether ``device``'s poll waits for commands (its own, or one for every device) to be
    built (rule 8); ``commanded``: the devices of the waiting commands."""
    return device in commanded or EVERY_DEVICE in commanded


def _first_of_each_device(candidates: list[Job]) -> list[Job]:
    """Rule 8: the jobs that are the first that came of each of their devices, unless a job
    for every device came before them; that one only when it came before all the others. A
    scan goes as ever."""
    first: dict[str, int] = {}
    every = earliest = math.inf
    for job in candidates:
        if job.scan:
            continue
        if job.device == EVERY_DEVICE:
            every = min(every, job.order)
        else:
            for device in job.devices:
                first[device] = min(first.get(device, job.order), job.order)
        earliest = min(earliest, job.order)

    def goes(job: Job) -> bool:
        if job.scan:
            return True
        if job.device == EVERY_DEVICE:
            return job.order == earliest
        return job.order < every and all(first[device] == job.order for device in job.devices)

    return [job for job in candidates if goes(job)]


def _poll_due(job: Job) -> float:
    """Waiting polls go out earliest first."""
    return job.next_poll_due
