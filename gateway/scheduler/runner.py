"""The bus runner: one dedicated thread per bus carries out the planner's decisions.

Rules of this file:

1. The bus thread owns the planner, the drivers and the bus owner. Other threads (zenoh's, the
   event loop) only call ``submit`` / ``estop`` / ``follow`` / ``stop``, which hand work over
   through a lock-free inbox and a wake-up event and return at once: nothing they do can delay
   a frame.
2. Waiting is to an absolute deadline: sleep most of the way, spin the last fraction of a
   millisecond (``clock.sleep_until``), waking early only when new work arrives. What starts
   at the deadline is decided (and its frame encoded) just before, so at the deadline only
   the write is left. A new target of a running follow stream is stored where the next tick
   reads it, without waking the thread.
3. A lost link closes the port, fails what was queued with ``bus_unavailable``, stops the
   streams, marks the devices offline and reconnects with backoff (0.1 s doubling to 2 s);
   the devices are re-initialised once it is back.
4. Results go back through ``concurrent.futures.Future`` (thread-safe, and awaitable from
   asyncio with ``asyncio.wrap_future``); device events go to ``on_event`` and each new device
   state to ``on_state`` (the latest also stays in ``states``); neither may block.
5. A client's command is authorised (``authority``) on the bus thread, right before it is
   planned; it must start within ``COMMAND_START_S`` of being handed over, else it is dropped
   and answered ``busy``. A job whose future was cancelled before it started is never sent.
"""

from __future__ import annotations

import contextlib
import logging
import os
import threading
import time
from collections import deque
from collections.abc import Callable, Iterable
from concurrent.futures import Future, InvalidStateError
from typing import Any

from busgate.codecs.errors import (
    BusgateError,
    BusIOError,
    BusUnavailableError,
    CommandError,
    DeviceTimeoutError,
    RefusedError,
)
from busgate.gateway.bus.can_owner import IDLE_BATCH_S
from busgate.gateway.bus.clock import now, sleep_until, tighten_timer_slack
from busgate.gateway.bus.request import Exchange, LinkTiming, Request
from busgate.gateway.bus.stats import BusCounters, BusStats
from busgate.gateway.drivers.base import DeviceEvent, Driver
from busgate.gateway.scheduler.authority import Authority
from busgate.gateway.scheduler.planner import BusPlanner, Job, Priority, Slot
from busgate.gateway.scheduler.streams import FollowStreams
from busgate.gateway.scheduler.tickers import FollowTicker, KeepaliveTicker

log = logging.getLogger(__name__)

BACKOFF_FIRST_S, BACKOFF_MAX_S = 0.1, 2.0
#: Longest the thread sleeps without looking at its inbox, heartbeats and stop flag.
IDLE_SLICE_S = 0.05
#: How long before a deadline the exchange that starts then is prepared.
PREPARE_S = 0.003
#: Telemetry older than this many poll periods is marked stale.
STALE_PERIODS = 3
#: The last stretch before a deadline is waited out by the bus owner, right before its
#: write, so that nothing runs between the deadline and the frame.
FINAL_WAIT_S = 0.001
#: A bus thread whose loop has not turned for this long is stuck: it turns at least every
#: ``IDLE_SLICE_S`` while its bus is up and every backoff (``BACKOFF_MAX_S`` at most) while down.
STALL_S = 2 * BACKOFF_MAX_S
#: How often a device that went offline is asked whether it is back.
OFFLINE_PROBE_S = 0.25
#: A command not started this long after it was handed over is dropped, answered ``busy``.
COMMAND_START_S = 2.0
#: How often a bus that stays down is reported again after its first warning.
DOWN_REPORT_S = 60.0


class BusyError(BusgateError):
    """The bus's command queue is full, or a command found no room before its deadline;
    nothing was sent: try again."""

    code = "busy"


class DevicePoller:
    """A driver's telemetry reads at its poll rate (a ``planner.Poller``); an offline device
    is asked at most every ``OFFLINE_PROBE_S``, so that one silent device (each of its polls
    a timeout, its retries and a hold-off) does not take its neighbours' share of the bus."""

    def __init__(self, driver: Driver, poll_hz: float, start: float) -> None:
        self.driver = driver
        self.device = driver.name
        self.poll_period_s = 1.0 / poll_hz
        self.next_due = start

    @property
    def period_s(self) -> float:
        if self.driver.online:
            return self.poll_period_s
        return max(self.poll_period_s, OFFLINE_PROBE_S)

    def build(self) -> list[Request]:
        driver = self.driver
        if not driver.online:
            return driver.init()
        if driver.restore_pending:  # it rebooted: its settings again, then the poll
            driver.restore_pending = False
            return driver.restore() + driver.poll()
        return driver.poll()


class BusRunner:
    """Runs one bus: its owner, its planner, its drivers, on a thread of its own."""

    def __init__(
        self,
        name: str,
        owner: Any,
        timing: LinkTiming,
        drivers: Iterable[Driver],
        *,
        poll_hz: dict[str, float],
        on_event: Callable[[DeviceEvent], None] = lambda event: None,
        on_state: Callable[[str, dict[str, Any]], None] = lambda device, state: None,
        realtime_priority: int | None = None,
        late_reply_holdoff_s: float = 0.01,
    ) -> None:
        self.name = name
        self.late_reply_holdoff_s = late_reply_holdoff_s
        self.owner = owner
        self.timing = timing
        self.drivers = {driver.name: driver for driver in drivers}
        self.authority = Authority(name, self.drivers)
        self.counters: BusCounters = owner.counters
        self.planner = BusPlanner(timing)
        start = now()
        self.pollers = [
            DevicePoller(driver, poll_hz[name], start)
            for name, driver in self.drivers.items()
            if poll_hz.get(name)
        ]
        self._keepalives = {name: KeepaliveTicker(d) for name, d in self.drivers.items()}
        self.planner.tickers = list(self._keepalives.values())
        self.planner.pollers = self.pollers
        self._poll_periods = {p.device: p.poll_period_s for p in self.pollers}
        self.states: dict[str, dict[str, Any]] = {}
        self.streams = FollowStreams(self.planner, self.counters, self.drivers)
        self._min_write_s = float("inf")
        self._dirty: set[str] = set(self.drivers)
        self.on_event = on_event
        self.on_state = on_state
        self.realtime_priority = realtime_priority
        self._inbox: deque[Callable[[], None]] = deque()
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._backoff = BACKOFF_FIRST_S
        self._opened_once = False
        self._down_since: float | None = None
        self._down_reported = 0.0
        self._down_attempts = 0
        self.last_turn = now()
        self._thread = threading.Thread(target=self._run, name=f"bus-{name}", daemon=True)

    # -- any thread -------------------------------------------------------------------------

    def start(self) -> BusRunner:
        self._thread.start()
        return self

    @property
    def alive(self) -> bool:
        return self._thread.is_alive()

    def keeping_schedule(self, stall_s: float = STALL_S) -> bool:
        """The bus thread is alive and has turned its loop within ``stall_s`` (the daemon's
        systemd watchdog pings only while every bus keeps its schedule)."""
        return self.alive and now() - self.last_turn < stall_s

    @property
    def native_id(self) -> int | None:
        """The bus thread's kernel thread id (for per-thread CPU figures)."""
        return self._thread.native_id

    def statistics(self) -> BusStats:
        return self.counters.snapshot(now())

    def submit(self, device: str, command: Any, client: str | None = None) -> Future:
        """Carry out a validated command on ``device`` for ``client`` (``None``: anonymous);
        the future gets the result dict, or the refusal."""
        start_by = now() + COMMAND_START_S
        return self._hand_over(
            lambda future: self._plan_command(device, command, client, start_by, future)
        )

    def scan(self, requests: list[Request], start_by: float) -> Future:
        """Send each probe once, all starting by ``start_by``, and collect what answered: the
        future gets a list of ``(request, reply events or None)``. For commissioning. Probes
        only ask, so they need no authorisation."""
        job = Job("*", deque(requests), keep_going=True, outcomes=[], start_by=start_by, scan=True)
        return self._hand_over(lambda future: self._queue_job(job, future))

    def unsolicited(self, event: object, when: float) -> None:
        """A frame nobody asked for (a heartbeat): to its device's driver (bus thread only)."""
        device_id = getattr(event, "device_id", None)
        for driver in self.drivers.values():
            if driver.device_id == device_id:
                driver.unsolicited(event, when)
                self._dirty.add(driver.name)
                return

    def stop_stream(self, device: str, reason: str) -> None:
        """End ``device``'s follow stream now (its client went away), as if it went stale."""
        self._inbox.append(lambda: self.streams.end(device, reason))
        self._wake.set()

    def estop(self) -> Future:
        """Put every device of the bus in its safe state, ahead of everything else."""
        return self._hand_over(self._plan_estop)

    def follow(self, device: str, target: Any) -> None:
        """The latest follow target of ``device`` (validated with its driver's
        ``follow_target``); streaming starts, or goes on, at the device's period."""
        moment = now()
        if self.streams.store_latest(device, target, moment):
            return
        self._inbox.append(lambda: self._start_stream(device, target, moment))
        self._wake.set()

    def stop(self, timeout: float = 1.0) -> None:
        """Stop the streams, put the devices in their safe state, close the bus."""
        self._stop.set()
        self._wake.set()
        if self._thread.is_alive():
            self._thread.join(timeout)
        self.owner.close()

    def _hand_over(self, action: Callable[[Future], None]) -> Future:
        future: Future = Future()
        self._inbox.append(lambda: action(future))
        self._wake.set()
        return future

    # -- bus thread: inbox ------------------------------------------------------------------

    def _plan_command(
        self, device: str, command: Any, client: str | None, start_by: float, future: Future
    ) -> None:
        driver = self.drivers.get(device)
        try:
            if driver is None:
                raise CommandError(f"no device {device!r} on bus {self.name}")
            self.authority.check(driver.effects(command), client)
            requests = driver.plan(command)
        except BusgateError as exc:
            _settle(future, error=exc)
            return
        except Exception as exc:  # a driver bug: answered ``internal``, the bus goes on
            log.exception("bus %s: planning %r for %s failed", self.name, command, device)
            _settle(future, error=exc)
            return
        self._queue_job(Job(device, deque(requests), start_by=start_by), future)

    def _queue_job(self, job: Job, future: Future) -> None:
        job.context = future
        if not self.owner.is_open:
            _settle(future, error=BusUnavailableError(f"bus {self.name} is down"))
        elif not job.requests:
            _settle(future, result=self._result(job))
        elif not self.planner.push_command(job):
            self.counters.busy_commands += 1
            _settle(
                future, error=BusyError(f"bus {self.name}: command queue full; nothing was sent")
            )

    def _plan_estop(self, future: Future) -> None:
        for job in self.planner.drop_commands():
            self._fail(
                job, RefusedError("estopped", "an e-stop cancelled it before it was carried out")
            )
        self.streams.end_all("estop")
        requests = [r for driver in self.drivers.values() for r in driver.safe_stop()]
        self.planner.push_estop(Job("*", deque(requests), keep_going=True, context=future))

    def _start_stream(self, device: str, target: Any, moment: float) -> None:
        driver = self.drivers.get(device)
        if driver is not None and self.owner.is_open:
            self.streams.start(driver, target, moment)

    # -- bus thread: the loop ---------------------------------------------------------------

    def _run(self) -> None:
        self._ask_realtime()
        tighten_timer_slack()
        try:
            while not self._stop.is_set():
                self.last_turn = now()
                try:
                    if not self._ensure_open():
                        continue
                    self._drain_inbox()
                    self._step()
                    self._publish()
                except Exception as exc:  # a bug must not leave the bus without its thread
                    log.exception("bus %s: unexpected error; reopening the bus", self.name)
                    self._link_lost(BusIOError(f"unexpected {type(exc).__name__}: {exc}"), None)
        finally:
            self._shut_down()

    def _step(self) -> None:
        """Start what is due now; or prepare what is due soon and wait for its moment."""
        decision = self.planner.decide(now())
        self._answer_expired()
        if isinstance(decision, Slot):
            self._execute(decision)
            return
        if decision - now() > PREPARE_S:
            self._wait_until(decision - PREPARE_S, precise=False)
            return
        prepared = self.planner.decide(decision)
        if not isinstance(prepared, Slot) or prepared.priority is not Priority.FOLLOW:
            # Only a follow tick is worth an uninterruptible wait; anything else waits where
            # new work (an e-stop) can still wake it, and is decided again at its moment.
            self._wait_until(decision)
        elif self._wait_until(decision - FINAL_WAIT_S, precise=False):
            self._execute(prepared, at=decision)

    def _answer_expired(self) -> None:
        for job in self.planner.take_expired():
            if job.scan:
                probed = len(job.outcomes or ())
                message = (
                    f"bus {self.name}: the scan found no room to probe its last "
                    f"{len(job.requests)} ids ({probed} probed) before its deadline; "
                    "nothing more was sent"
                )
            else:
                message = (
                    f"bus {self.name}: the command found no room on the bus within "
                    f"{COMMAND_START_S:.0f} s and was dropped; nothing was sent"
                )
            self.counters.busy_commands += 1
            self._fail(job, BusyError(message))

    def _drain_inbox(self) -> None:
        self._wake.clear()
        while self._inbox:
            self._inbox.popleft()()

    def _execute(self, slot: Slot, *, at: float | None = None) -> None:
        source = slot.source
        if isinstance(source, Job) and not source.started and not self._may_start(source):
            return
        previous_end = self.planner.line_free
        try:
            exchange = self.owner.exchange(slot.request, at=at)
        except DeviceTimeoutError as exc:
            failed, start, end, error = True, now(), now(), exc
            if not (isinstance(source, Job) and source.scan):  # a probe's reply matches its id
                self.planner.hold_replies_until = end + self.late_reply_holdoff_s
            self._note_failure(slot, end)
        except BusIOError as exc:
            self._link_lost(exc, slot)
            return
        else:
            failed, start, end = False, exchange.start, exchange.end
            self._note_success(slot, exchange)
            if previous_end > float("-inf"):
                self.counters.gap(start - previous_end)
            self.counters.busy_s += end - start
        if not isinstance(slot.source, Job):
            slot.source.sent(start - self._fastest_write(exchange if not failed else None))
        done = self.planner.finished(slot, end, failed=failed)
        if isinstance(source, Job):
            # A request that is tried again is still at the head of its job; only a failure
            # for good is the job's error (a retry that succeeds leaves none behind).
            retried = failed and bool(source.requests) and source.requests[0] is slot.request
            if retried:
                self.counters.retries += 1
            else:
                if failed:
                    source.error = error
                if source.outcomes is not None:
                    source.outcomes.append((slot.request, None if failed else exchange.reply))
        if done is not None:
            self._complete(done)

    def _may_start(self, job: Job) -> bool:
        """Mark a job's future running; ``False`` (and the job dropped) when it was cancelled
        (its client was answered without it)."""
        future = job.context
        if not isinstance(future, Future):
            return True
        if not future.done() and future.set_running_or_notify_cancel():
            return True
        self.planner.discard(job)
        return False

    def _fastest_write(self, exchange: Exchange | None) -> float:
        """The quickest write call seen on this bus. A tick counts as started that long before
        its write returned: the frame was in the kernel no earlier, so scheduling the next
        tick a period after that never makes an interval short, while the write call's usual
        duration does not add to every interval (a write held up for long still does)."""
        if exchange is not None and exchange.write_s < self._min_write_s:
            self._min_write_s = exchange.write_s
        return 0.0 if self._min_write_s == float("inf") else self._min_write_s

    def _note_success(self, slot: Slot, exchange: Exchange) -> None:
        """Hand the reply (possibly none, for frames without one) to every driver the frame
        was for: the job's device, or each device of a coalesced follow frame."""
        if isinstance(slot.source, FollowTicker):
            drivers = [stream.driver for stream in slot.source.streams.values()]
        else:
            drivers = [d for d in [self._driver_for(slot)] if d is not None]
        for driver in drivers:
            self._dirty.add(driver.name)
            if exchange.reply:
                driver.heard(exchange.end)
                if driver.refreshes_keepalive(slot.request):
                    self._keepalives[driver.name].sent(exchange.start)
            result = driver.apply(slot.request, exchange.reply, exchange.end)
            if isinstance(slot.source, Job) and result:
                slot.source.replies.append(result)

    def _note_failure(self, slot: Slot, end: float) -> None:
        driver = self._driver_for(slot)
        if driver is not None:
            self._dirty.add(driver.name)
            driver.missed(end)

    def _driver_for(self, slot: Slot) -> Driver | None:
        """The device a job's request is for, or (keep-alives, e-stops) the one it addresses."""
        if isinstance(slot.source, Job) and slot.source.device in self.drivers:
            return self.drivers[slot.source.device]
        if isinstance(slot.source, KeepaliveTicker):
            return slot.source.driver
        expected = slot.request.expected
        if expected is None:
            return None
        for driver in self.drivers.values():
            if expected.source_id in (driver.device_id, None):
                return driver
        return None

    def _complete(self, job: Job) -> None:
        future = job.context
        if not isinstance(future, Future) or future.done():
            return
        if job.outcomes is not None:
            _settle(future, result=job.outcomes)
        elif job.error is not None and not job.keep_going:
            _settle(future, error=job.error)
        else:
            _settle(future, result=self._result(job))

    def _result(self, job: Job) -> dict[str, Any]:
        result: dict[str, Any] = {}
        for reply in job.replies:
            result.update(reply)
        driver = self.drivers.get(job.device)
        if driver is not None:
            result["state"] = self._state(driver, now())
        return result

    def _fail(self, job: Job, exc: BusgateError) -> None:
        future = job.context
        if isinstance(future, Future):
            _settle(future, error=exc)

    def _wait_until(self, deadline: float, *, precise: bool = True) -> bool:
        """Wait for ``deadline`` (spinning the last fraction only when ``precise``); ``False``
        when woken earlier by new work (or a lost link)."""
        if deadline - now() > IDLE_SLICE_S:
            deadline = now() + IDLE_SLICE_S
        idle = getattr(self.owner, "idle_until", None)
        if idle is not None:
            return self._idle_can(idle, deadline)
        margin = 0.001 if precise else 0.0
        remaining = deadline - now()
        if remaining > margin and self._wake.wait(remaining - margin):
            return False
        if precise:
            sleep_until(deadline)
        return not self._wake.is_set()

    def _idle_can(self, idle: Callable[..., None], deadline: float) -> bool:
        """Take in heartbeats until ``deadline``, one batch (``IDLE_BATCH_S``) at a time; back to
        the loop after the first batch that brought any, so that it is published now."""
        try:
            while now() < deadline and not self._wake.is_set() and not self._dirty:
                idle(min(deadline, now() + IDLE_BATCH_S), self._wake.wait)
        except BusIOError as exc:
            self._link_lost(exc, None)
            return False
        return not self._wake.is_set() and now() >= deadline

    def _publish(self) -> None:
        """Events out, and a fresh state for each device something happened to."""
        moment = now()
        for name, driver in self.drivers.items():
            check = getattr(driver, "check_heartbeat", None)
            if check is not None:
                check(moment)
            events = driver.drain_events()
            for event in events:
                self._log_event(event)
                self.on_event(event)
                if event.type == "rebooted":  # its targets are stale: a fresh command moves it
                    self.streams.end(name, "device rebooted")
            if events or name in self._dirty:
                self.states[name] = state = self._state(driver, moment)
                self.on_state(name, state)
        self._dirty.clear()
        self.counters.skipped_polls = self.planner.skipped_polls

    def _state(self, driver: Driver, moment: float) -> dict[str, Any]:
        """The driver's state, marked ``stale`` when its telemetry is more than
        ``STALE_PERIODS`` poll periods old (an oversubscribed bus, or a device not answering)."""
        state = driver.state(moment)
        state["ts"] = time.time()  # clients compare it with their own clock: wall time
        period = self._poll_periods.get(driver.name)
        age = state.get("last_reply_age_s")
        state["stale"] = period is not None and (age is None or age > STALE_PERIODS * period)
        return state

    def _log_event(self, event: DeviceEvent) -> None:
        details = " ".join(f"{key}={value}" for key, value in event.fields.items())
        log.info(
            "bus %s device %s: %s%s",
            self.name,
            event.device,
            event.type,
            f" ({details})" if details else "",
        )

    # -- bus thread: link up and down -------------------------------------------------------

    def _ensure_open(self) -> bool:
        if self.owner.is_open:
            return True
        try:
            self.owner.open()
        except BusUnavailableError as exc:
            self._report_down(exc)
            self._stop.wait(self._backoff)
            self._backoff = min(self._backoff * 2, BACKOFF_MAX_S)
            self._drain_inbox()
            return False
        self._down_since = None
        log.info("bus %s up on %s", self.name, self.owner.port)
        if self._opened_once:
            self.counters.reconnects += 1
        self._opened_once = True
        self._backoff = BACKOFF_FIRST_S
        self.planner.line_free = now()
        for poller in self.planner.pollers:
            poller.next_due = now()
        return True

    def _report_down(self, exc: BusUnavailableError) -> None:
        """The first failed open is logged; then at most one summary every ``DOWN_REPORT_S``."""
        moment = now()
        self._down_attempts += 1
        if self._down_since is None:
            self._down_since = self._down_reported = moment
            self._down_attempts = 0
            log.warning(
                "bus %s down: %s; retrying every %.1f-%.0f s",
                self.name,
                exc,
                BACKOFF_FIRST_S,
                BACKOFF_MAX_S,
            )
        elif moment - self._down_reported >= DOWN_REPORT_S:
            self._down_reported = moment
            log.warning(
                "bus %s still down after %.0f s (%d attempts): %s",
                self.name,
                moment - self._down_since,
                self._down_attempts,
                exc,
            )

    def _link_lost(self, exc: BusIOError, slot: Slot | None) -> None:
        log.warning("bus %s lost: %s", self.name, exc)
        if slot is not None and isinstance(slot.source, Job):
            self._fail(slot.source, BusUnavailableError(str(exc)))
        for job in self.planner.drop_commands():
            self._fail(job, BusUnavailableError(f"bus {self.name} went down"))
        self.streams.end_all("bus down")
        for driver in self.drivers.values():
            driver.went_offline("bus down")
        self.owner.close()

    def _ask_realtime(self) -> None:
        if self.realtime_priority is None:
            return
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(self.realtime_priority))
        except (PermissionError, OSError) as exc:
            log.warning(
                "bus %s: SCHED_FIFO %d refused (%s); running at normal priority",
                self.name,
                self.realtime_priority,
                exc,
            )

    def _shut_down(self) -> None:
        """Last deeds of the bus thread: safe state for every device, then close."""
        self.streams.end_all("shutdown")
        for job in self.planner.drop_commands():
            self._fail(job, BusUnavailableError(f"bus {self.name} is stopping"))
        if self.owner.is_open:
            for driver in self.drivers.values():
                for request in driver.safe_stop():
                    try:
                        sleep_until(self.planner.line_free + self.timing.gap_s)
                        exchange = self.owner.exchange(request)
                        self.planner.line_free = exchange.end
                    except (DeviceTimeoutError, BusIOError):
                        self.planner.line_free = now()
        self._drain_inbox()
        self._publish()


def _settle(future: Future, *, result: Any = None, error: BaseException | None = None) -> None:
    """Give ``future`` its outcome, unless it already has one or was cancelled (its client was
    answered without it)."""
    with contextlib.suppress(InvalidStateError):
        if error is not None:
            future.set_exception(error)
        else:
            future.set_result(result)
