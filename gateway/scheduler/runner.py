"""The bus runner: one dedicated thread per bus carries out the planner's decisions.

Rules of this file:

1. The bus thread owns the planner, the drivers and the bus owner. Other threads (zenoh's, the
   event loop) only call ``submit`` / ``estop`` / ``follow`` / ``stop``, which hand work over
   through a lock-free inbox and a wake-up flag (``flag.Flag``) and return at once: nothing
   they do can delay a frame. A caller that hands e-stops over and has Python of its own to
   run next (a log line, more messages) first waits, at most ``ESTOP_SENT_S``, for each
   e-stop's first exchange (``let_estops_go``): waiting, it leaves the bus threads the
   interpreter. An e-stop handed over while another's frames are going is not waited for:
   its devices are being stopped already, and a client putting e-stops in a loop must not
   hold its zenoh link for an exchange a put. The bus thread, for its part, writes an
   e-stop's first frame before it publishes news or ends what the e-stop ends (``work``
   rules).
2. Waiting is to an absolute deadline: the owner's idle work (``BusOwner.idle_until``), woken
   early when new work arrives or a frame nobody asked for brought events (news without events,
   a heartbeat's values, is published in the pause and the wait goes on), then a spin
   (``clock.sleep_until``) from the thread's learnt wake-up lead before the deadline. A UART
   line idles to the lead: one wait. A line with frames to take in (CAN) idles to
   ``UNINTERRUPTED_S`` before it (a look at the frames that came meanwhile, taken at the
   lead, would eat it), then waits to the lead in a wait only an e-stop cuts short. New work
   in the last ``UNINTERRUPTED_S`` does not cut the wait short (a follow tick goes; anything
   else is decided again at its moment), but an e-stop does, on either line:
   the frame it would wait for is not sent, and the e-stop's go a gap after the line's last
   exchange, not a gap after that frame. What starts at the deadline is decided (and its
   frame encoded) just before, so at the deadline only the write is left; a wait cut short
   decides again. A new target of a running follow stream is stored where the next tick
   reads it, without waking the thread. Each wait costs the thread some 30 µs of CPU in the
   kernel (docs/performance.md), so an exchange waits as few times as its timing allows.
3. A lost link closes the port, fails what was queued with ``bus_unavailable``, stops the
   streams, marks the devices offline and reconnects with backoff (``link``); the devices are
   re-initialised once it is back.
4. Results go back through ``concurrent.futures.Future`` (``outcomes``: thread-safe, and
   awaitable from asyncio with ``asyncio.wrap_future``); device events and each new device
   state go out through ``telemetry``.
5. A client's command is authorised (``authority``) on the bus thread (``work``), right before
   it is planned; it must start within ``COMMAND_START_S`` of being handed over, else it is dropped
   and answered ``busy``; a command or reset that crossed to a worker, within that of when the
   gateway took it (``taken_at``, bus clock), however late the worker read it. A job whose
   future was cancelled before it started is never sent.
6. What one caller hands over within ``together`` reaches the bus thread at once, on its exit,
   in order: one drain of the inbox takes it all before the thread plans or sends anything, so
   an e-stop among it takes out what came before it as if they had come in one turn (a
   command waiting, not a read; a reset; a stream's new target). Only one thread at a time
   holds a bus so (a worker's reader, ``worker`` rule 9).
"""

from __future__ import annotations

import contextlib
import logging
import math
import threading
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import Future
from typing import Any

from busgate.errors import (
    BusIOError,
    BusUnavailableError,
)
from busgate.gateway.bus.clock import (
    MIN_SLEEP_S,
    ask_realtime,
    name_thread,
    now,
    sleep_until,
    tighten_timer_slack,
    wake_lead,
    woke_for,
)
from busgate.gateway.bus.flag import Flag
from busgate.gateway.bus.owner import BusOwner
from busgate.gateway.bus.request import LinkTiming, Request
from busgate.gateway.bus.stats import BusCounters, BusStats
from busgate.gateway.drivers.base import DeviceEvent, Follows
from busgate.gateway.scheduler import outcomes
from busgate.gateway.scheduler.devices import BusDevices, tell_unsent
from busgate.gateway.scheduler.execution import Execution
from busgate.gateway.scheduler.link import BACKOFF_MAX_S, Reconnect
from busgate.gateway.scheduler.planner import BusPlanner, Job, Priority, Slot
from busgate.gateway.scheduler.plays import Plays
from busgate.gateway.scheduler.polling import DevicePoller
from busgate.gateway.scheduler.streams import FollowStreams
from busgate.gateway.scheduler.telemetry import Telemetry
from busgate.gateway.scheduler.tickers import KeepaliveTicker
from busgate.gateway.scheduler.trajectory_ticks import Sampler
from busgate.gateway.scheduler.work import BusWork, safe_stops
from busgate.schemas.events import BUS_DOWN_REASON

log = logging.getLogger(__name__)

#: Longest the thread sleeps without looking at its inbox, heartbeats and stop flag.
IDLE_SLICE_S = 0.05
#: How long before a deadline the exchange that starts then is prepared.
PREPARE_S = 0.003
#: The last stretch of a precise wait: only an e-stop cuts it short.
UNINTERRUPTED_S = 0.001
#: How long a caller that handed e-stops over leaves the interpreter to the bus threads
#: (rule 1): the exchange in flight, the gap and each e-stop's first exchange. Longer only
#: delays what the caller does next, never an e-stop.
ESTOP_SENT_S = 0.005
#: A bus thread whose loop has not turned for this long is stuck: it turns at least every
#: ``IDLE_SLICE_S`` while its bus is up and every backoff (``BACKOFF_MAX_S`` at most) while down.
STALL_S = 2 * BACKOFF_MAX_S
#: A command not started this long after it was handed over is dropped, answered ``busy``.
COMMAND_START_S = 2.0
#: How long the bus stays closed after an unexpected error (a bug) before it is opened again:
#: one that recurs at every turn costs a traceback a second, never a core.
UNEXPECTED_PAUSE_S = 1.0


def let_estops_go(runners: Iterable[BusRunner]) -> None:
    """Wait until each of ``runners`` (e-stops just handed over) has had its e-stop's first
    exchange, ``ESTOP_SENT_S`` at most in all (rule 1)."""
    until = now() + ESTOP_SENT_S
    for runner in runners:
        runner.estop_sent(max(0.0, until - now()))


class BusRunner:
    """Runs one bus: its owner, its planner, its drivers, on a thread of its own."""

    def __init__(
        self,
        name: str,
        owner: BusOwner,
        timing: LinkTiming,
        devices: BusDevices,
        *,
        poll_hz: dict[str, float],
        on_event: Callable[[DeviceEvent], None] = lambda event: None,
        on_state: Callable[[str, dict[str, Any]], None] = lambda device, state: None,
        realtime_priority: int | None = None,
        late_reply_holdoff_s: float = 0.01,
    ) -> None:
        self.name = name
        self.owner = owner
        self.timing = timing
        self.devices = devices
        self.drivers = devices.drivers
        self.counters: BusCounters = owner.counters
        self.planner = BusPlanner(timing)
        start = now()
        self.pollers = [
            DevicePoller(driver, poll_hz[name], start)
            for name, driver in self.drivers.items()
            if poll_hz.get(name)
        ]
        self.planner.pollers = self.pollers
        keepalives = {name: KeepaliveTicker(d) for name, d in self.drivers.items()}
        self.planner.tickers = list(keepalives.values())
        periods = {poller.device: poller.poll_period_s for poller in self.pollers}
        self.telemetry = Telemetry(name, devices, periods, on_event=on_event, on_state=on_state)
        self.streams = FollowStreams(self.planner, self.counters, self.drivers)
        self.plays = Plays(self.planner, self.counters, self.drivers, self.streams)
        self._work = BusWork(
            name, owner, self.drivers, self.planner, self.streams, self.plays, self._state_of
        )
        self.authority = self._work.authority
        self._execution = Execution(
            owner,
            self.planner,
            devices,
            keepalives,
            state_of=self._state_of,
            late_reply_holdoff_s=late_reply_holdoff_s,
        )
        self.realtime_priority = realtime_priority
        self._inbox: deque[Callable[[], None]] = deque()
        #: What is handed over within ``together``, for the inbox on its exit (rule 6);
        #: ``None``: nothing holds the bus, work goes to the inbox as it is handed over.
        self._held: list[Callable[[], None]] | None = None
        #: An e-stop is among what is held.
        self._held_estop = False
        self._wake = Flag()
        #: An e-stop is in the inbox: it cuts even a wait's last stretch short (rule 2).
        self._estop_due = Flag()
        #: The last e-stop handed over has had its first exchange (``estop_sent``).
        self._estop_sent = Flag()
        #: The wait under way has slept (only such a wait teaches the wake-up lead).
        self._paused = False
        #: Events were published during the wait under way: it ends, to decide again.
        self._evented = False
        self._stop = threading.Event()
        self._reconnect = Reconnect(name)
        #: Why the last attempt to open the bus failed; ``None`` before the first attempt and
        #: once it is open (the daemon's READY and STATUS for systemd read it).
        self.open_failure: str | None = None
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

    @property
    def states(self) -> dict[str, dict[str, Any]]:
        """The last state published of each device."""
        return self.telemetry.states

    def statistics(self) -> BusStats:
        return self.counters.snapshot(now())

    def submit(
        self, device: str, command: Any, client: str | None = None, taken_at: float | None = None
    ) -> Future:
        """Carry out a validated command on ``device`` for ``client`` (``None``: anonymous);
        the future gets the result dict, or the refusal. It starts within ``COMMAND_START_S``
        of now, or of ``taken_at`` (bus clock) for a command that crossed to a worker, which
        may have read it late (rule 5)."""
        start_by = _start_by(taken_at)
        return self._hand_over(
            lambda future: self._work.plan_command(device, command, client, start_by, future)
        )

    def scan(self, requests: list[Request], start_by: float) -> Future:
        """Send each probe once, all starting by ``start_by``, and collect what answered: the
        future gets a list of ``(request, reply events or None)``. For commissioning. Probes
        only ask, so they need no authorisation."""

        return self._hand_over(lambda future: self._work.plan_scan(requests, start_by, future))

    def stop_stream(self, device: str, reason: str) -> None:
        """End ``device``'s follow stream now (its client went away, or ended it), as if it
        went stale, but reported ``stream_stopped`` with ``reason``."""
        self._put(lambda: self.streams.end(device, reason))

    def estop(self) -> Future:
        """Put every device of the bus in its safe state, ahead of everything else."""
        if not self.planner.stopping:  # else its frames are going already (rule 1)
            self._estop_sent.clear()
        return self._hand_over(self._take_estop, estop=True)

    def estop_sent(self, timeout: float) -> bool:
        """Wait, at most ``timeout``, until the last e-stop handed over has had its first
        exchange on the line (or found no line to go on); the caller lets the interpreter go
        meanwhile, to the bus thread."""
        return self._estop_sent.wait(timeout)

    def reset_estop(
        self,
        device: str | None = None,
        skip: frozenset[str] = frozenset(),
        taken_at: float | None = None,
    ) -> Future:
        """``device`` (``None``: every device of the bus but those of ``skip``) out of the
        gateway's e-stop, each in the power state it had before and holding still
        (``Driver.reset_estop``); by ``COMMAND_START_S`` after now, or ``taken_at``, as
        ``submit``."""
        start_by = _start_by(taken_at)
        return self._hand_over(lambda future: self._work.plan_reset(device, start_by, future, skip))

    def follow(
        self, device: str, target: Any, follows: Follows, taken_at: float | None = None
    ) -> None:
        """The latest follow target of ``device`` (validated with its driver's
        ``follow_target`` while it ``follows`` that: a position or a speed); streaming
        starts, or goes on, at the device's period. Its stream judges it fresh by when the
        gateway took it (``tickers`` rule 2): now, or ``taken_at`` (bus clock) for a target
        that crossed to a worker, which may have read it late."""
        moment = now() if taken_at is None else taken_at
        # Held (rule 6), it waits its turn with the rest: an e-stop after it ends its stream
        # before its tick, where stored now, a tick might send it before the e-stop came.
        if self._held is None and self.streams.store_latest(device, target, moment, follows):
            return
        self._put(lambda: self._work.start_stream(device, target, moment, follows))

    def ramp(self, device: str, target: Any, follows: Follows) -> None:
        """Bring ``device`` to ``target`` (a follow target, judged while it ``follows`` that)
        within its joint's limits, and leave it there (``tickers`` rule 5): a stream that
        never goes stale and ends on its target. Always through the bus thread, so a target
        never lands on a ramp that has just ended (a ROS command is sent once and must not be
        lost)."""
        moment = now()
        self._put(
            lambda: self._work.start_stream(device, target, moment, follows, ends_on_target=True)
        )

    def play(self, samplers: dict[str, Sampler], start: float) -> None:
        """Play each device's trajectory sampler on the grid from ``start`` (bus clock)."""
        self._put(lambda: self.plays.start(samplers, start))

    def stop_playing(self, device: str, *, speed: bool) -> None:
        """``device`` leaves its trajectory: it holds, or (``speed``) ramps to 0 rpm."""
        self._put(lambda: self.plays.stop(device, speed=speed))

    def stop(self, timeout: float = 1.0) -> None:
        """Stop the streams, put the devices in their safe state, close the bus; a thread
        that has not ended within ``timeout`` (hung) is told of: its safe state is not known
        to have gone out, where the daemon's stop would otherwise read as a clean one."""
        self._stop.set()
        self._wake.set()
        if self._thread.is_alive():
            self._thread.join(timeout)
            if self._thread.is_alive():
                log.warning(
                    "bus %s: its thread did not stop within %g s: its devices' safe state "
                    "may not have been sent",
                    self.name,
                    timeout,
                )
        self.owner.close()

    @contextlib.contextmanager
    def together(self) -> Iterator[None]:
        """What is handed over within reaches the bus thread at once, on exit, in order
        (rule 6)."""
        self._held, self._held_estop = [], False
        try:
            yield
        finally:
            held, self._held = self._held, None
            self._inbox.extend(held)  # one step: the bus thread drains none of it before all
            if self._held_estop:  # after the extend, as ``_hand_over``'s
                self._estop_due.set()
            self._wake.set()

    def _put(self, action: Callable[[], None], *, estop: bool = False) -> None:
        """``action`` for the bus thread: to its inbox, or held for it (rule 6)."""
        held = self._held
        if held is not None:
            held.append(action)
            self._held_estop |= estop
            return
        self._inbox.append(action)
        if estop:  # after the append: when the flag is seen, its e-stop is in the inbox (it
            self._estop_due.set()  # may outlive it by a drain: one wait decided again)
        self._wake.set()

    def _hand_over(self, action: Callable[[Future], None], *, estop: bool = False) -> Future:
        future: Future = Future()
        self._put(lambda: action(future), estop=estop)
        return future

    # -- bus thread: the loop ---------------------------------------------------------------

    def _run(self) -> None:
        name_thread(self._thread.name)
        if self.realtime_priority is not None:
            ask_realtime(self.realtime_priority, f"bus {self.name}")
        tighten_timer_slack()
        try:
            while not self._stop.is_set():
                self.last_turn = now()
                try:
                    if not self._ensure_open():
                        continue
                    self._drain_inbox()
                    self._step()
                    if not self._estop_due.is_set():  # else its first frame before the news
                        self._publish()
                except Exception as exc:  # a bug must not leave the bus without its thread
                    log.exception(
                        "bus %s: unexpected error; reopening the bus in %g s",
                        self.name,
                        UNEXPECTED_PAUSE_S,
                    )
                    self._link_lost(BusIOError(f"unexpected {type(exc).__name__}: {exc}"), None)
                    self._stop.wait(UNEXPECTED_PAUSE_S)
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
        if not isinstance(prepared, Slot):
            if self._wait_until(decision):  # nothing starts then: decided again at that moment
                self._arrive(decision)
        elif prepared.priority is Priority.FOLLOW:
            # A follow tick goes unless its wait was cut short or an e-stop is due (its frame
            # goes at its moment to the µs): the owner waits the rest, right before its write.
            if self._wait_until(decision):
                self._execute(prepared, at=decision)
        elif self._wait_until(decision) and self._arrive(decision):
            # Anything else is decided again when any new work came while it waited, even in
            # the last stretch; else it starts as prepared, nothing left after the gap.
            self._execute(prepared)

    def _answer_expired(self) -> None:
        for job in self.planner.take_expired():
            self.counters.busy_commands += 1
            tell_unsent(job, self.drivers)
            outcomes.fail(job, outcomes.expired(job, self.name, COMMAND_START_S))

    def _take_estop(self, future: Future) -> None:
        self._work.plan_estop(future)
        if not self.owner.is_open:  # no exchange to wait for
            self._work.end_estopped()
            self._estop_sent.set()

    def _drain_inbox(self) -> None:
        self._wake.clear()
        self._estop_due.clear()
        while self._inbox:
            self._inbox.popleft()()

    def _execute(self, slot: Slot, *, at: float | None = None) -> None:
        try:
            self._execution.run(slot, at=at)
        except BusIOError as exc:
            self._link_lost(exc, slot)
        if slot.priority is Priority.ESTOP:
            self._work.end_estopped()
            self._estop_sent.set()

    def _wait_until(self, deadline: float, *, precise: bool = True) -> bool:
        """Wait for ``deadline``, doing the owner's idle work meanwhile; ``False`` when cut
        short (rule 2, or a lost link), when an e-stop is due, or when the idle work published
        events (a device came, went, rebooted: decided again even when publishing them ran
        into the last stretch, for a tick prepared for a rebooted device is stale).
        ``precise``: the wait ends the thread's wake-up lead before ``deadline`` (its lateness
        learnt), the rest left to a spin (``sleep_until``: the caller's ``_arrive``, or the
        owner's before its write), and its last ``UNINTERRUPTED_S`` is cut short only by an
        e-stop."""
        if deadline - now() > IDLE_SLICE_S:
            deadline = now() + IDLE_SLICE_S
        if not precise:
            return bool(self._idle_until(deadline)) and not self._estop_due.is_set()
        lead_end = deadline - wake_lead()
        last_stretch = deadline - UNINTERRUPTED_S
        # A line with frames to take in (CAN) idles only to its last stretch: a look at the
        # frames that came meanwhile, taken at the lead, would eat it (some 50 µs).
        takes_frames = not math.isinf(self.owner.idle_batch_s)
        reached = self._idle_until(last_stretch if takes_frames else lead_end)
        if reached is None or self._evented or (not reached and now() < last_stretch):
            return False  # events decide again even late: a rebooted device's tick is stale
        if reached and not takes_frames and self._paused:  # only a wait that slept knows
            woke_for(lead_end)
        return self._through_last_stretch(lead_end)

    def _idle_until(self, end: float) -> bool | None:
        """The owner's idle work until ``end``: whether it got there (``False``: new work or
        events cut it short; ``None``: the link was lost)."""
        self._paused = self._evented = False
        try:
            return self.owner.idle_until(end, self._pause)
        except BusIOError as exc:
            self._link_lost(exc, None)
            return None

    def _through_last_stretch(self, lead_end: float) -> bool:
        """The rest of a precise wait, up to ``lead_end``, that only an e-stop cuts short:
        whether no e-stop is due at its end."""
        left = lead_end - now()
        if left > MIN_SLEEP_S:  # shorter, not worth a wait (as ``sleep_until`` judges)
            if self._estop_due.wait(left):
                return False
            woke_for(lead_end)
        return not self._estop_due.is_set()

    def _arrive(self, deadline: float) -> bool:
        """Wait the rest of a precise wait (``sleep_until``) to ``deadline``; whether no new
        work came meanwhile."""
        sleep_until(deadline)
        return not self._wake.is_set()

    def _pause(self, seconds: float) -> bool:
        """The owner's pause while idle: cut short by new work. News (heartbeats the owner
        took in) is published first; when it brought events (a device came, went, rebooted:
        what is planned may change) the pause is cut short, to decide again, else it goes on
        for what is left of ``seconds`` (a heartbeat bus would otherwise turn its loop, and
        decide, for every batch of heartbeats)."""
        if self.devices.has_news:
            start = now()
            if self._publish():
                self._evented = True
                return True
            seconds -= now() - start
            if seconds <= 0:
                return self._wake.is_set()
        self._paused = True
        return self._wake.wait(seconds)

    def _publish(self) -> bool:
        """The devices' events and new states out; whether there were events."""
        for name in self.telemetry.publish(now()):  # its targets are stale: a fresh command
            self.streams.end(name, "device rebooted")  # moves it again
        self.counters.skipped_polls = self.planner.skipped_polls
        return self.telemetry.had_events

    def _state_of(self, device: str) -> dict[str, Any] | None:
        driver = self.drivers.get(device)
        return None if driver is None else self.telemetry.reply_state(driver, now())

    # -- bus thread: link up and down -------------------------------------------------------

    def _ensure_open(self) -> bool:
        reconnect = self._reconnect
        if self.owner.is_open:
            if reconnect.quick_losses:
                reconnect.still_up(now())
            return True
        wait = reconnect.retry_at - now()  # lost soon after it opened: not at once
        if wait <= 0:
            try:
                self.owner.open()
            except BusUnavailableError as exc:
                self.open_failure = str(exc)
                wait = reconnect.failed(exc, now())
        if not self.owner.is_open:
            self._stop.wait(wait)
            self._drain_inbox()
            return False
        self.open_failure = None
        if not reconnect.quick_losses:  # else one of many: summed up (link rule 3)
            log.info("bus %s up on %s", self.name, self.owner.port)
        if reconnect.opened(now()):
            self.counters.reconnects += 1
        self.planner.line_free = now()
        for poller in self.planner.pollers:
            poller.next_due = now()
        return True

    def _link_lost(self, exc: BusIOError, slot: Slot | None) -> None:
        if self._reconnect.lost(exc, now()):
            log.warning("bus %s lost: %s", self.name, exc)
        if slot is not None and isinstance(slot.source, Job):
            outcomes.fail(slot.source, BusUnavailableError(str(exc)))
            if slot.priority is Priority.ESTOP:  # answered; its frames go once the bus is back
                slot.source.future = Future()
        down = BusUnavailableError(f"bus {self.name} went down")
        self._work.end_everything("bus down", "the bus lost", down)
        for driver in self.drivers.values():
            driver.went_offline(BUS_DOWN_REASON)
        self.owner.close()

    def _shut_down(self) -> None:
        """Last deeds of the bus thread: safe state for every device, then close."""
        stopping = BusUnavailableError(f"bus {self.name} is stopping")
        self._work.end_everything("shutdown", "shutdown", stopping)
        if self.owner.is_open:
            self._execution.last_words(safe_stops(self.drivers.values()))
        self._drain_inbox()
        self._publish()


def _start_by(taken_at: float | None) -> float:
    """When a command handed over now (or taken off the network at ``taken_at``, bus clock)
    must have started: ``COMMAND_START_S`` later (rule 5)."""
    return (now() if taken_at is None else taken_at) + COMMAND_START_S
