"""One decision of the planner carried out: the exchange, and what it tells everyone it was for.

Its own module because an exchange's consequences are many and must come in one order: the
devices it was for (an answer: heard, then applied; silence: missed), the ticker that sent
it (when the next tick is due), the planner (the line is busy until its end; a retry or the
job's next request), the job (a failure for good, a scan's probe) and the counters. Bus
thread only. Rules:

1. A device that answered is marked heard here, the one place, before its driver applies
   the answer: the owner has matched the answer to the request already. Every driver a
   frame was for is told it went (``Driver.went``) before its answer, or its silence.
2. After a timeout, no exchange that expects a reply starts for ``late_reply_holdoff_s``, so
   that a late reply is flushed rather than taken for the next one's (a scan's probes are
   not held: a probe's answer names its id).
3. A lost link (``BusIOError``) is the caller's: nothing of the slot has been recorded then.
   Only the last words of a bus that stops (``last_words``) are sent whatever fails.
4. A frame of a device's command that moves other devices (a group frame) is told to each
   of them once it went (``Driver.moved_by``); the answer, if any, is the sender's alone.
   A device that answered "not done" (``DeviceRefusedError``) fails its job with it.
"""

from __future__ import annotations

import math

from busgate.errors import BusIOError, DeviceRefusedError, DeviceTimeoutError
from busgate.gateway.bus.clock import now, sleep_until
from busgate.gateway.bus.owner import BusOwner
from busgate.gateway.bus.request import Exchange, Request
from busgate.gateway.bus.stats import BusCounters
from busgate.gateway.drivers.base import EVERY, Driver, Effect
from busgate.gateway.scheduler import outcomes
from busgate.gateway.scheduler.devices import BusDevices, tell_unsent
from busgate.gateway.scheduler.planner import BusPlanner, Job, Slot
from busgate.gateway.scheduler.tickers import FollowTicker, KeepaliveTicker
from busgate.gateway.scheduler.trajectory_ticks import TrajectoryTicker


class Execution:
    """Carries out slots on one bus's owner."""

    def __init__(
        self,
        owner: BusOwner,
        planner: BusPlanner,
        devices: BusDevices,
        keepalives: dict[str, KeepaliveTicker],
        *,
        state_of: outcomes.StateOf,
        late_reply_holdoff_s: float,
    ) -> None:
        self.owner = owner
        self.planner = planner
        self.devices = devices
        self.keepalives = keepalives
        self.counters: BusCounters = owner.counters
        self.state_of = state_of
        self.late_reply_holdoff_s = late_reply_holdoff_s
        self._min_write_s = math.inf

    def run(self, slot: Slot, *, at: float | None = None) -> None:
        """Carry ``slot`` out (its write at ``at``, when given); ``BusIOError`` (rule 3)."""
        source = slot.source
        job = source if isinstance(source, Job) else None
        if job is not None and not job.started and not outcomes.may_start(job):
            self.planner.discard(job)  # its client was answered without it
            tell_unsent(job, self.devices.drivers)
            return
        previous_end = self.planner.line_free
        exchange: Exchange | None = None
        error: DeviceTimeoutError | None = None
        try:
            exchange = self.owner.exchange(slot.request, at=at)
        except DeviceTimeoutError as exc:
            error, start = exc, now()
            end = start
            if not (job is not None and job.scan):  # rule 2
                self.planner.hold_replies_until = end + self.late_reply_holdoff_s
            self._unanswered(slot, end)
        else:
            start, end = exchange.start, exchange.end
            self._answered(slot, exchange)
            # The gap from the line's last activity: the previous exchange's end, or a byte
            # read since (a late reply flushed before this write).
            line_busy = max(previous_end, exchange.last_byte_before)
            if line_busy > -math.inf:
                self.counters.gap(start - line_busy)
            self.counters.busy_s += end - start
        if not isinstance(source, Job):  # a follow or keep-alive tick: its ticker times the next
            counted = start - self._fastest_write(exchange)
            source.sent(counted)
            if isinstance(source, FollowTicker | TrajectoryTicker):
                self.planner.spacing.ticked(source.carried(), source, counted)
        else:
            self.planner.spacing.job_sent(source, start)
        done = self.planner.finished(slot, end, failed=error is not None)
        if job is not None:
            # A request that is tried again is still at the head of its job; only a failure
            # for good is the job's error (a retry that succeeds leaves none behind).
            if error is not None and job.requests and job.requests[0] is slot.request:
                self.counters.retries += 1
            else:
                reply = None if exchange is None else exchange.reply
                outcomes.record(job, slot.request, reply, error)
        if done is not None:
            outcomes.complete(done, self.state_of)

    def last_words(self, requests: list[Request]) -> None:
        """Send ``requests`` outside the plan, each once, a gap after the line went idle,
        whatever becomes of the one before: the bus's last deeds (every device's safe stop)."""
        for request in requests:
            try:
                sleep_until(self.planner.line_free + self.planner.gap_s)
                self.planner.line_free = self.owner.exchange(request).end
            except (DeviceTimeoutError, BusIOError):
                self.planner.line_free = now()

    def _fastest_write(self, exchange: Exchange | None) -> float:
        """The quickest write call seen on this bus. A tick counts as started that long before
        its write returned: the frame was in the kernel no earlier, so scheduling the next
        tick a period after that never makes an interval short, while the write call's usual
        duration does not add to every interval (a write held up for long still does)."""
        if exchange is not None and exchange.write_s < self._min_write_s:
            self._min_write_s = exchange.write_s
        return 0.0 if self._min_write_s == math.inf else self._min_write_s

    def _answered(self, slot: Slot, exchange: Exchange) -> None:
        """Hand the reply (possibly none, for frames without one) to every driver the frame
        was for: the job's device, or each device of a coalesced follow frame (rule 1)."""
        if isinstance(slot.source, FollowTicker | TrajectoryTicker):
            drivers = slot.source.carried()
        else:
            drivers = [d for d in [self._driver_for(slot)] if d is not None]
        for driver in drivers:
            self.devices.touched(driver)
            driver.went(slot.request.frame)
            if exchange.reply:
                driver.heard(exchange.end)
                if driver.refreshes_keepalive(slot.request):
                    self.keepalives[driver.name].sent(exchange.start)
            try:
                result = driver.apply(slot.request, exchange.reply, exchange.end)
            except DeviceRefusedError as refused:  # the job's error, once it ends
                if isinstance(slot.source, Job):
                    slot.source.error = refused
                continue
            if isinstance(slot.source, Job) and result:
                slot.source.replies.append(result)
        if isinstance(slot.source, Job) and slot.source.also_moves:
            for other in self._also_moved(slot.source, slot.request):
                self.devices.touched(other)
                other.moved_by(slot.request.frame)

    def _also_moved(self, job: Job, request: Request) -> list[Driver]:
        """The other devices ``request``'s frame moves, of those its job's frames move (a
        group frame sent through one device's command: none of them answers it)."""
        drivers = self.devices.drivers
        sender, frame = drivers[job.device], request.frame
        if sender.effect(frame) is not Effect.MOTION:
            return []
        ids = sender.addressed(frame)
        return [
            drivers[name]
            for name in job.also_moves
            if ids is EVERY or drivers[name].device_id in ids
        ]

    def _unanswered(self, slot: Slot, end: float) -> None:
        driver = self._driver_for(slot)
        if driver is not None:
            self.devices.touched(driver)
            driver.went(slot.request.frame)
            driver.missed(end, slot.request.frame)

    def _driver_for(self, slot: Slot) -> Driver | None:
        """The device a job's request is for, or (keep-alives, e-stops) the one it addresses."""
        source = slot.source
        if isinstance(source, Job) and source.device in self.devices.drivers:
            return self.devices.drivers[source.device]
        if isinstance(source, KeepaliveTicker):
            return source.driver
        expected = slot.request.expected
        return None if expected is None else self.devices.answering(expected)
