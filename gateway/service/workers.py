"""Bus workers, seen from the gateway's process (docs/workers.md): each worker's process and
its supervisor, and ``WorkerRunner``, a bus in a worker with the ``BusRunner`` surface the
API, trajectories and the ROS face use (which buses go where is ``placement``'s).

Rules of this file:

1. A ``WorkerRunner`` answers reads from the gateway's own copy of its bus (the *shadow*: the
   same ``build_bus``, never started, its port never opened), kept as the worker last said:
   each device's state (and from it ``online`` and ``estopped``), its id, the trajectories'
   ``PlaysView``, the bus's statistics and whether it is open (or why not). Every call that
   moves or sets anything goes to the worker, in the order it was made, but that a device's
   follow or ramp target still waiting for the socket is replaced by its next one
   (``link.Outbox``). A follow target goes with the time it was taken here, by which the
   worker's stream judges it fresh (``BusRunner.follow``), not the time it came; so do a
   command and a reset, by which the worker judges their start deadline (``runner`` rule 5:
   one that waited for a stalled worker past it is answered ``busy``, never sent late). A
   play goes with its start, a scan with its deadline, both on the bus clock already.
2. Claims are taken and released here, in the one table per bus the API judges by, and each
   change goes to the worker before any later call (its bus thread judges by the same); a new
   worker is given the table as it stands, and e-stops the buses whose devices were e-stopped
   and those e-stopped by a call since their last reset, answered or not: a worker that hung
   or ended with an e-stop in its socket never carried it out, and its last states did not
   say it. So it does the buses of a worker that ended through its own stop, the daemon not
   stopping (``safe_stopped``): that stop put their devices in their safe state (an Inspire
   LA's e-stop, latched), where a new worker's drivers take them to be driving.
3. A worker that ends, or hangs (silent for ``STALL_S``, ``SLOW_START_S`` before its first
   word: it is killed), is reported once: every call waiting on it is answered
   ``bus_unavailable``, each of its devices goes offline with an event saying why (after a
   ``stream_stopped`` for each stream it ran, as a lost link's streams are told: those its
   last beat named, and those fed in the last ``RECENT_TARGET_S``), and the
   worker is started again after ``RESTART_S`` (longer each time, up to ``RESTART_MAX_S``,
   while it ends before it has run ``STEADY_S`` since its first word), with nothing to
   resume: no stream, no play, no ramp; a client commands again. A worker that ends while the
   daemon stops is none of that, nor one stopped by a SIGTERM of its own (``systemctl stop``
   signals every process of the service at once) when the daemon's stop follows within
   ``SIGTERM_WAIT_S``: read before the daemon's own SIGTERM was handled, it was taken for a
   worker's failure, its devices said offline and an incident written. While its supervisor waits
   to start it again the worker keeps its schedule for systemd's watchdog, as a bus whose
   link is lost does: its devices are offline and said so, nothing hangs (taken for hung, a
   worker's wait of 30 s had systemd kill the whole gateway after 10).
4. A worker is started and read by one supervising thread for the daemon's whole life: a
   child's death signal (``PR_SET_PDEATHSIG``) follows the thread that started it. A word of
   the worker's that cannot be taken (a bug) is logged and dropped; the thread goes on.
"""

from __future__ import annotations

import contextlib
import itertools
import logging
import signal
import socket
import subprocess
import sys
import threading
from collections.abc import Callable, Hashable
from concurrent.futures import Future, InvalidStateError
from functools import cache, partial
from typing import Any, ClassVar

from busgate.errors import BusUnavailableError
from busgate.gateway.bus.clock import now
from busgate.gateway.bus.stats import BusStats, carried
from busgate.gateway.drivers.base import DeviceEvent, Driver, Follows
from busgate.gateway.scheduler.authority import ClaimTable
from busgate.gateway.scheduler.runner import STALL_S, BusRunner
from busgate.gateway.service import worker as worker_process
from busgate.gateway.service import worker_link as link
from busgate.schemas.config import Config
from busgate.schemas.events import WORKER_ENDED_REASON

log = logging.getLogger(__name__)

#: A worker that ended is started again after this long.
RESTART_S = 0.5
#: The longest wait before starting again a worker that keeps ending soon after its start
#: (each such end doubles the wait: a worker that cannot start does not spin a core).
RESTART_MAX_S = 30.0
#: How long a worker runs past its first word before its end is a worker's end, not a start
#: that failed (the next wait is ``RESTART_S`` again).
STEADY_S = 10.0
#: A device sent a target this recently may have a stream its worker's last beat did not
#: name yet (rule 3): longer than a stream stays fresh without one (``tickers.MIN_FRESH_S``).
RECENT_TARGET_S = 1.0
#: How long a new worker is given to say its first word before start-up goes on without it.
FIRST_WORD_S = 5.0
#: How long a worker just started may take to say its first word (an interpreter's start on a
#: slow computer with a cold cache) before it is taken for hung.
SLOW_START_S = 20.0
#: How long a stopping worker is given to stop its buses before it is killed.
STOP_S = 2.0
#: How long the supervisor of a worker stopped by a SIGTERM of its own waits for the daemon's
#: stop before that end is a worker's end (rule 3): ``systemctl stop`` signals them together.
SIGTERM_WAIT_S = 2.0
#: What the end of a worker that put its devices in their safe state adds (rule 2).
SAFE_STATE_SENT = "its devices put in their safe state, e-stopped until a reset"


def restart_delay(previous_s: float, *, steady: bool) -> float:
    """How long to wait before starting a worker again: ``RESTART_S`` after one that ran
    steadily (``STEADY_S`` past its first word), twice the wait before after one that did not
    (up to ``RESTART_MAX_S``)."""
    if steady or previous_s <= 0.0:
        return RESTART_S
    return min(2 * previous_s, RESTART_MAX_S)


class ForwardedClaims(ClaimTable):
    """A bus's claim table, each change also sent to its worker (rule 2): a change and its
    word go together (``_in_order``), so the worker's table goes through the same changes in
    the same order, whichever threads make them."""

    def __init__(self, send: Callable[[tuple], None], bus: str) -> None:
        super().__init__()
        self._send = send
        self._bus = bus
        self._in_order = threading.Lock()

    def claim(self, device: str, client: str, ttl_s: float, now: float) -> None:
        with self._in_order:
            super().claim(device, client, ttl_s, now)
            self._send(("claims", self._bus, "claim", (device, client, ttl_s, now)))

    def hold(self, device: str, client: str, ttl_s: float, now: float) -> bool:
        with self._in_order:
            new = super().hold(device, client, ttl_s, now)
            self._send(("claims", self._bus, "hold", (device, client, ttl_s, now)))
        return new

    def release(self, device: str, client: str, now: float) -> bool:
        with self._in_order:
            released = super().release(device, client, now)
            self._send(("claims", self._bus, "release", (device, client, now)))
        return released

    def drop_client(self, client: str) -> list[str]:
        with self._in_order:
            dropped = super().drop_client(client)
            self._send(("claims", self._bus, "drop_client", (client,)))
        return dropped

    def hand_over(self, moment: float) -> None:
        """The claims that hold at ``moment`` to a new worker, as ``claim`` takes them; no
        change comes between (it follows, in order)."""
        with self._in_order, self._lock:
            for device, held in self._holders.items():
                if held.until > moment:
                    claim = (device, held.client, held.until - moment, moment)
                    self._send(("claims", self._bus, "claim", claim))


@cache
def mirrored(driver_class: type[Driver]) -> type[Driver]:
    """``driver_class`` as a shadow's driver: ``estopped`` is what its worker last said
    (rule 1); everything else is the family's own."""

    def estopped(self: Any) -> bool:
        return bool(getattr(self, "said_estopped", False))

    name = f"Mirrored{driver_class.__name__}"
    return type(name, (driver_class,), {"estopped": property(estopped)})


class WorkerProcess:
    """One worker: its process, its supervisor, the calls waiting for an answer."""

    def __init__(self, index: int, config: Config, shadows: list[BusRunner]) -> None:
        self.index = index
        self.config = config
        self.runners = {shadow.name: WorkerRunner(shadow, self) for shadow in shadows}
        self.on_event = shadows[0].telemetry.on_event  # every bus's: the daemon's events
        self.beat: dict[str, link.BusBeat] = {}
        #: How the last worker ended (``None``: none has), its buses' reason to be down until
        #: the next one's first beat says how they are.
        self.ended_because: str | None = None
        self.last_word = now()
        self.process: subprocess.Popen | None = None
        self.outbox: link.Outbox | None = None
        #: When the running worker said its first word (``None``: not yet, since it started).
        self._first_word_at: float | None = None
        #: When the supervisor starts an ended worker again (``None``: one runs, rule 3).
        self._restart_at: float | None = None
        self._pending: dict[int, Future] = {}
        #: Buses e-stopped by a call, or by their worker's own stop, since their last reset
        #: (rule 2): the next worker e-stops them as it starts.
        self._estopped: set[str] = set()
        #: How many e-stops each bus was called to, a reset's answer judged by it (``_reset_done``).
        self._estop_calls: dict[str, int] = {}
        self._ids = itertools.count()
        self._lock = threading.Lock()
        self._stopping = threading.Event()
        self._first_word = threading.Event()
        self._supervisor = threading.Thread(
            target=self._supervise, name=f"worker{index}", daemon=True
        )

    @property
    def buses(self) -> str:
        return ", ".join(self.runners)

    # -- life (rule 4) ------------------------------------------------------------------------

    def start(self) -> None:
        """Start the supervisor, which starts the worker."""
        self._supervisor.start()

    def wait_first_word(self, timeout: float = FIRST_WORD_S) -> bool:
        """Whether the worker said its first word (its buses built, their threads started)
        within ``timeout``."""
        return self._first_word.wait(timeout)

    def stopping(self) -> None:
        """The daemon stops: an end of the worker from now on is no worker's end, and it is
        not started again (rule 3); ``stop`` follows."""
        self._stopping.set()

    def stop(self) -> None:
        """Stop the worker's buses in order (streams, safe state, close), then the worker:
        returns once no worker runs, even one its supervisor was starting meanwhile (told to
        stop by ``_spawn``), after ``STOP_S`` by killing it."""
        self.stopping()
        with self._lock:
            outbox = self.outbox
        if outbox is not None:
            outbox.put(("stop",), urgent=True)
        if self._supervisor.ident is None:  # never started
            return
        given_up_at = now() + STOP_S
        self._supervisor.join(STOP_S)  # it ends once its worker has ended
        process = self.process
        if process is not None:
            try:  # a wait, not ``poll``: that says "running" while the supervisor waits too
                process.wait(max(given_up_at - now(), 0.1))
            except subprocess.TimeoutExpired:
                log.warning("worker %d did not stop in %.0f s: killed", self.index, STOP_S)
                process.kill()
                process.wait()
        self._supervisor.join(STOP_S)

    def keeping_schedule(self, stall_s: float = STALL_S) -> bool:
        """The worker is running, has said a word within ``stall_s`` (``_silent_too_long``)
        and says each of its bus threads keeps its schedule (systemd's watchdog is pinged only
        while every worker does; a trajectory plays only while its buses' workers do, within
        half a second)."""
        process = self.process
        if process is None or process.poll() is not None:
            return self._restarting()
        return not self._silent_too_long(stall_s) and all(
            beat.on_schedule for beat in self.beat.values()
        )

    def _restarting(self) -> bool:
        """The worker ended and its supervisor waits to start it again, due within ``STALL_S``
        (rule 3)."""
        restart_at = self._restart_at
        return restart_at is not None and now() < restart_at + STALL_S

    def _silent_too_long(self, stall_s: float = STALL_S) -> bool:
        """Silent for ``stall_s`` since its last word (``SLOW_START_S`` before its first)."""
        spoken = self._first_word_at is not None
        return now() - self.last_word > (stall_s if spoken else SLOW_START_S)

    def _supervise(self) -> None:
        delay_s = 0.0
        while not self._stopping.is_set():
            try:
                process, sock = self._spawn()
                self._read(sock)
                self._ended(process)
                first_word = self._first_word_at
            except Exception:  # a bug, or no process to be had (EMFILE): try again, later
                log.exception("worker %d: its supervisor failed", self.index)
                first_word = None  # as a worker that ended before its first word: backing off
            if self._stopping.is_set():  # it ended because the gateway stops: nothing to say
                return
            ran_s = 0.0 if first_word is None else now() - first_word
            delay_s = restart_delay(delay_s, steady=ran_s >= STEADY_S)
            self._restart_at = now() + delay_s
            if delay_s > RESTART_S:
                when = "before" if first_word is None else f"{ran_s:.1f} s after"
                log.warning(
                    "worker %d ended %s its first word: started again in %.0f s",
                    self.index,
                    when,
                    delay_s,
                )
            if self._stopping.wait(delay_s):
                return
            log.info("worker %d: starting it again", self.index)

    def _spawn(self) -> tuple[subprocess.Popen, socket.socket]:
        ours, theirs = link.pair()
        process = subprocess.Popen(
            [
                sys.executable,
                "-m",
                worker_process.__name__,
                str(theirs.fileno()),
                logging.getLevelName(logging.getLogger().getEffectiveLevel()),
            ],
            pass_fds=[theirs.fileno()],
        )
        theirs.close()
        outbox = link.Outbox(ours, f"worker{self.index}-send")
        with self._lock:  # an e-stop comes before (in the start) or after (a call), never lost
            estopped = {name for name, r in self.runners.items() if r.any_estopped()}
            estopped |= self._estopped
            outbox.put(("start", self.config, list(self.runners), sorted(estopped)))
            self.process, self.outbox, self.last_word = process, outbox.start(), now()
            self._restart_at = None
        if estopped:  # its devices say so from its first states; the log says why
            log.warning(
                "worker %d: buses %s e-stopped as it starts: e-stopped since their last reset "
                "of the whole bus, or put in their safe state by the worker before (a device's "
                "own reset leaves its bus e-stopped for the next worker); reset them to move "
                "again",
                self.index,
                ", ".join(sorted(estopped)),
            )
        self._first_word_at = None
        # The claims that stand, once the outbox is the worker's: a change made meanwhile
        # comes after them, in order (``ForwardedClaims.hand_over``).
        moment = now()
        for runner in self.runners.values():
            runner.claims.hand_over(moment)
        if self._stopping.is_set():  # stopped while it was starting
            outbox.put(("stop",))
        return process, ours

    # -- calls ----------------------------------------------------------------------------------

    def call(self, bus: str, method: str, *args: Any, **kwargs: Any) -> Future:
        """``method`` of ``bus``'s runner in the worker; its future, settled by the answer."""
        future: Future = Future()
        with self._lock:  # registered before its answer can be read
            outbox = self.outbox
            if method == "estop":  # kept until its reset: a new worker e-stops the bus (rule 2)
                self._estopped.add(bus)
                self._estop_calls[bus] = self._estop_calls.get(bus, 0) + 1
            if outbox is None:
                future.set_exception(BusUnavailableError(f"bus {bus}: its worker is down"))
                return future
            if method == "reset_estop" and args == (None,):  # the whole bus, by its worker
                estop_calls = self._estop_calls.get(bus, 0)
                future.add_done_callback(partial(self._reset_done, bus, estop_calls))
            call_id = next(self._ids)
            outbox.put_now(("call", call_id, bus, method, args, kwargs))  # refused here, if so
            self._pending[call_id] = future
        future.add_done_callback(partial(self._withdraw_if_cancelled, call_id))
        return future

    def _reset_done(self, bus: str, estop_calls: int, future: Future) -> None:
        """A whole bus's reset answered: done, and no e-stop called since it was, the next
        worker no longer e-stops the bus; failed (its worker ended or hung first, with the
        reset, and maybe the e-stop, still in its socket), it still does (rule 2)."""
        if future.cancelled() or future.exception() is not None:
            return
        with self._lock:
            if self._estop_calls.get(bus, 0) == estop_calls:
                self._estopped.discard(bus)

    def _withdraw_if_cancelled(self, call_id: int, future: Future) -> None:
        """A call cancelled here (its client was answered without it) is withdrawn in the
        worker too: a job that has not started there never will (``runner`` rule 5)."""
        if not future.cancelled():
            return
        with self._lock:
            self._pending.pop(call_id, None)
        self.send(("withdraw", call_id))

    def tell(self, bus: str, method: str, *args: Any, **kwargs: Any) -> None:
        """``method`` of ``bus``'s runner in the worker, with no answer."""
        self.send(("call", None, bus, method, args, kwargs))

    def target(self, bus: str, method: str, device: str, *args: Any) -> None:
        """``method`` (``follow``, ``ramp``) of ``bus``'s runner with ``device``'s new target,
        with no answer: one still waiting for the socket gives it its place
        (``link.Outbox``)."""
        self.send(("call", None, bus, method, (device, *args), {}), latest_of=(bus, device))

    def send(self, message: tuple, *, latest_of: Hashable = None) -> None:
        """``message`` to the worker (dropped while there is none: a new one is told what
        stands, rule 2)."""
        outbox = self.outbox
        if outbox is not None:
            outbox.put_now(message, latest_of=latest_of)

    # -- the worker's words -------------------------------------------------------------------

    def _read(self, sock: socket.socket) -> None:
        reader = link.Reader(sock)
        while True:
            try:
                message = reader.receive(link.BEAT_S)
            except TimeoutError:
                self._check_silence()
                continue
            if message is None:
                break
            self.last_word = now()
            if self._first_word_at is None:
                self._first_word_at = self.last_word
            for said in link.unbatched(message):
                handle = self._HANDLERS.get(said[0])
                if handle is None:
                    log.error("worker %d said what no worker says: %r", self.index, said[:1])
                    continue
                try:
                    handle(self, *said[1:])
                except Exception:  # a bug: this word is lost, not the worker's supervision
                    log.exception("worker %d: its %r could not be taken", self.index, said[0])
        sock.close()

    def _check_silence(self) -> None:
        """A worker silent for ``STALL_S`` hangs (it says a word every ``BEAT_S``): it is
        killed, and ends as any worker ends (rule 3)."""
        silent_s, process = now() - self.last_word, self.process
        if self._silent_too_long() and process is not None and process.poll() is None:
            log.error(
                "worker %d (buses %s) silent for %.1f s: killed", self.index, self.buses, silent_s
            )
            process.kill()

    def _settle(self, call_id: int, ok: bool, value: Any) -> None:
        with self._lock:
            future = self._pending.pop(call_id, None)
        if future is None:
            return
        with contextlib.suppress(InvalidStateError):  # its caller gave up on it meanwhile
            if ok:
                future.set_result(value)
            else:
                future.set_exception(link.rebuilt(*value))

    def _on_state(self, bus: str, device: str, state: dict[str, Any]) -> None:
        self.runners[bus].took_state(device, state)

    def _on_event(self, event: DeviceEvent) -> None:
        self.on_event(event)

    def _on_frame(self, bus: str, frame: tuple) -> None:
        tap = self.runners[bus].tap
        if tap is not None:
            tap(frame)

    def _on_plays(self, bus: str, view: Any, ids: dict[str, int]) -> None:
        self.runners[bus].took_plays(view, ids)

    def _on_beat(self, beat: dict[str, link.BusBeat]) -> None:
        self.beat = beat
        self._first_word.set()

    _HANDLERS: ClassVar[dict[str, Callable[..., None]]] = {
        "result": _settle,
        "state": _on_state,
        "event": _on_event,
        "frame": _on_frame,
        "plays": _on_plays,
        "beat": _on_beat,
    }

    def _ended(self, process: subprocess.Popen) -> None:
        """Rule 3: the worker is gone; answer what waited on it, take its devices offline."""
        with self._lock:
            outbox, self.outbox = self.outbox, None
            waiting, self._pending = self._pending, {}
            # Its counts carried on as its last beat goes, in one step (``statistics``).
            last_beat, self.beat = self.beat, {}
            for runner in self.runners.values():
                beat = last_beat.get(runner.name)
                runner.count_on(None if beat is None else beat.statistics)
        if outbox is not None:
            outbox.close()
        code = process.wait()
        self._first_word.set()  # start-up goes on: its buses are down
        safe = safe_stopped(code, ran=self._first_word_at is not None)
        how = _how_it_ended(code) + (f"; {SAFE_STATE_SENT}" if safe else "")
        self.ended_because = f"{WORKER_ENDED_REASON} ({how})"
        gone = BusUnavailableError(f"the worker of its bus ended ({how})")
        for future in waiting.values():
            with contextlib.suppress(InvalidStateError):  # its caller gave up on it meanwhile
                future.set_exception(gone)
        if self._daemon_stops(code):
            return
        if safe:  # before the next worker's start reads it (rule 2)
            with self._lock:
                self._estopped.update(self.runners)
        log.error("worker %d (buses %s) ended: %s", self.index, self.buses, how)
        for runner in self.runners.values():
            beat = last_beat.get(runner.name)
            runner.worker_ended(self.ended_because, beat.streaming if beat else frozenset())

    def _daemon_stops(self, code: int) -> bool:
        """The daemon is stopping, or (the worker ended on a SIGTERM of its own) begins to
        within ``SIGTERM_WAIT_S`` (rule 3). The daemon's stop is waited for, never guessed
        from the signal: a worker sent a SIGTERM alone is reported and started again as any
        worker that ends; and the daemon, not the worker, knows whether it stops."""
        if code in (worker_process.STOPPED_ON_SIGTERM, -signal.SIGTERM):
            return self._stopping.wait(SIGTERM_WAIT_S)
        return self._stopping.is_set()


def safe_stopped(code: int, *, ran: bool) -> bool:
    """Whether a worker that ended with ``code`` put its devices in their safe state: one whose
    buses ran (``ran``: it said its first word) ends through its stop, safe states sent, on
    whatever it can catch (``worker`` rule 3), and so with an exit status of its own
    (``STOPPED_ON_SIGTERM``, 0, or 1 for an error its stop followed out of ``Worker.run``);
    killed by a signal (SIGKILL, a crash), it sent none."""
    return ran and code >= 0


def _how_it_ended(code: int) -> str:
    """A worker's exit status in words."""
    if code == worker_process.STOPPED_ON_SIGTERM:
        return "stopped on a SIGTERM of its own"
    return f"killed by signal {-code}" if code < 0 else f"exit status {code}"


class WorkerRunner:
    """A bus run by a worker, with the ``BusRunner`` surface the gateway uses (rule 1)."""

    def __init__(self, shadow: BusRunner, worker: WorkerProcess) -> None:
        self.worker = worker
        self.name = shadow.name
        self.timing = shadow.timing
        self.devices = shadow.devices
        self.drivers = shadow.drivers
        for driver in self.drivers.values():
            driver.__class__ = mirrored(type(driver))
        self.telemetry = shadow.telemetry
        self.plays = shadow.plays
        self.authority = shadow.authority
        self.claims = ForwardedClaims(worker.send, shadow.name)
        self.authority.claims = self.claims
        self.counters = shadow.counters
        #: The counts of the workers that ran the bus before this one, and how many ended.
        self._before: BusStats | None = None
        self._restarts = 0
        #: The flight recorder's tap of this bus's frames (the daemon sets it, as an owner's).
        self.tap: Callable[[tuple], None] | None = None
        #: When each device was last sent a follow or ramp target (rule 3).
        self._fed_at: dict[str, float] = {}

    @property
    def owner(self) -> WorkerRunner:
        """What the gateway asks of a bus's owner: ``is_open`` and ``tap``."""
        return self

    @property
    def is_open(self) -> bool:
        beat = self.worker.beat.get(self.name)
        return beat is not None and beat.is_open

    @property
    def open_failure(self) -> str | None:
        """Why the bus is not open, as its worker last said (``BusRunner.open_failure``), or
        how its worker ended, when none has said since."""
        beat = self.worker.beat.get(self.name)
        return beat.open_failure if beat is not None else self.worker.ended_because

    @property
    def states(self) -> dict[str, dict[str, Any]]:
        return self.telemetry.states

    @property
    def alive(self) -> bool:
        process = self.worker.process
        return process is not None and process.poll() is None

    def keeping_schedule(self, stall_s: float = STALL_S) -> bool:
        return self.worker.keeping_schedule(stall_s)

    def statistics(self) -> BusStats:
        """The worker's last word of them, counting on from the workers before it (each
        end a reconnect): a new worker's counters start at 0, and the metrics' totals fell
        with them (an audit). Read under the worker's lock, which ``count_on`` takes with
        the beat that goes: never its counts twice, nor none."""
        with self.worker._lock:
            beat = self.worker.beat.get(self.name)
            before, restarts = self._before, self._restarts
        latest = beat.statistics if beat is not None else self.counters.snapshot(now())
        return latest if before is None else carried(before, latest, reconnects=restarts)

    def count_on(self, counted: BusStats | None) -> None:
        """Its worker ended, its statistics last ``counted`` (its last beat's): the next
        worker's count on from them (``statistics``); under the worker's lock."""
        self._restarts += 1
        if counted is not None:
            self._before = counted if self._before is None else carried(self._before, counted)

    def any_estopped(self) -> bool:
        return any(driver.estopped for driver in self.drivers.values())

    # -- what the worker said (rule 1) ----------------------------------------------------------

    def took_state(self, device: str, state: dict[str, Any]) -> None:
        driver = self.drivers[device]
        driver.online = bool(state.get("online"))
        driver.said_estopped = bool(state.get("estopped"))  # type: ignore[attr-defined]
        driver.mirror(state)
        self.telemetry.states[device] = state
        self.telemetry.on_state(device, state)

    def took_plays(self, view: Any, ids: dict[str, int]) -> None:
        self.plays.view = view
        for device, device_id in ids.items():
            self.drivers[device].device_id = device_id

    def worker_ended(self, why: str, streaming: frozenset[str]) -> None:
        """Rule 3: each stream told ended (``streaming``, its last beat's, and those fed
        lately), each device offline, with its event, its last state marked so."""
        self.plays.view = type(self.plays.view)()
        moment = now()
        fed = {device for device, at in list(self._fed_at.items()) if moment - at < RECENT_TARGET_S}
        self._fed_at.clear()
        for device in sorted(streaming | fed):
            self.telemetry.tell(DeviceEvent(device, "stream_stopped", {"reason": why}), moment)
        for name, driver in self.drivers.items():
            driver.went_offline(why)
            for event in driver.drain_events():
                self.telemetry.tell(event, moment)
            last = self.telemetry.states.get(name)
            if last is not None:
                state = {**last, "online": False, "stale": True}
                self.telemetry.states[name] = state
                self.telemetry.on_state(name, state)

    # -- calls: each carried out by the worker --------------------------------------------------

    def submit(self, device: str, command: Any, client: str | None = None) -> Future:
        """The worker's answer, whose state the shadow's driver takes first (``mirror``): a
        client told ``set_mode`` is done may stream at once, before the state's own message
        has crossed."""
        # Taken now: its start deadline is judged by that in the worker (rule 1), as in one
        # process, not by when a stalled worker read it (the bus clock is CLOCK_MONOTONIC).
        answer = self.worker.call(self.name, "submit", device, command, client, taken_at=now())
        answer.add_done_callback(partial(self._mirror_reply, device))
        return answer

    def _mirror_reply(self, device: str, answer: Future) -> None:
        reply = None if answer.cancelled() or answer.exception() else answer.result()
        state = reply.get("state") if isinstance(reply, dict) else None
        if isinstance(state, dict):
            self.drivers[device].mirror(state)

    def scan(self, requests: list, start_by: float) -> Future:
        return self.worker.call(self.name, "scan", requests, start_by)

    def estop(self) -> Future:
        return self.worker.call(self.name, "estop")

    def estop_sent(self, timeout: float) -> bool:
        """At once: the worker's socket took it, and its bus threads have an interpreter of
        their own."""
        return True

    def reset_estop(self, device: str | None = None, skip: frozenset[str] = frozenset()) -> Future:
        taken_at = now()  # its start deadline's, as a command's (rule 1)
        if skip:  # not the whole bus: a new worker still e-stops it (rule 2)
            return self.worker.call(self.name, "reset_estop", device, skip, taken_at=taken_at)
        return self.worker.call(self.name, "reset_estop", device, taken_at=taken_at)

    def stop_stream(self, device: str, reason: str) -> None:
        self.worker.tell(self.name, "stop_stream", device, reason)

    def follow(self, device: str, target: Any, follows: Follows) -> None:
        # Taken now, and judged fresh by that in the worker (rule 1): one that waited for a
        # worker stopped a while (SIGSTOP, swapping) is stale when it is read, as in one
        # process, not carried out after its client stopped sending. The bus clock is
        # CLOCK_MONOTONIC (``clock.now``): one clock for the processes of a host.
        taken_at = self._fed_at[device] = now()
        self.worker.target(self.name, "follow", device, target, follows, taken_at)

    def ramp(self, device: str, target: Any, follows: Follows) -> None:
        self._fed_at[device] = now()
        self.worker.target(self.name, "ramp", device, target, follows)

    def play(self, samplers: dict, start: float) -> None:
        self.worker.tell(self.name, "play", samplers, start)

    def stop_playing(self, device: str, *, speed: bool) -> None:
        self.worker.tell(self.name, "stop_playing", device, speed=speed)
