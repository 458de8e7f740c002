"""A bus worker: a process of its own running some of a gateway's buses (docs/workers.md).

``python -m busgate.gateway.service.worker FD LEVEL``, started by the daemon (never forked
from it: zenoh's threads do not survive ``fork()``), talks over the inherited socket ``FD``
(``worker_link``) and logs at the daemon's ``LEVEL``. Its first message is the validated
config, the names of its buses and the buses to e-stop at once (the claims standing on them
follow as ordinary ``claims`` messages);
it builds the buses exactly as the daemon builds its own (``assembly.build_bus``) and runs
them. Rules of this file:

1. The daemon's calls are carried out on the runner by the name the link allows
   (``worker_link.CALLS``, ``CLAIM_OPS``), in the order they came; a call's future answers it,
   and a call withdrawn (``withdraw``: cancelled in the daemon) cancels its future here, so
   that a job that has not started never does. A command and a reset carry the time the
   daemon took them (``taken_at``), by which their bus judges their start deadline
   (``runner`` rule 5): one read late (the worker stalled) is answered ``busy``, never sent.
2. States, events and (with a flight recorder) frames go to the outbox as the bus threads make
   them; each bus's ``PlaysView`` and device ids when they changed (looked at when a bus
   thread published a new view or a call was answered, a ``MIRROR_S`` apart at most often),
   and every ``BEAT_S`` whether each bus thread keeps its schedule, whether its bus is open
   (or why its last attempt to open it failed) and its statistics (``workers`` rule 1 reads
   them). With no trajectory playing, the
   mirror thread wakes only for the beat.
3. When the socket closes (the daemon went), ``stop`` comes or SIGTERM, the buses stop in
   order (streams, safe state, close) and the process ends. SIGTERM only closes the socket's
   reading side, so that the stop is the same whatever the main thread was doing when it
   came; once stopping, a SIGTERM more (the daemon's death signal right after its socket
   closed) is ignored. Stopped by a SIGTERM of its own, it ends with ``STOPPED_ON_SIGTERM``
   (``systemctl stop`` sends one to every process of the service at once: its supervisor may
   read this end before the daemon has begun its stop). SIGINT, SIGHUP and SIGUSR1 are the
   daemon's to act on: a Ctrl-C, or a terminal that closes, reaches the whole process group,
   and ``systemctl kill -s USR1`` (an incident file) every process of the service (left to
   their defaults, each ended the worker at once, its devices as they were). Once its buses
   run, whatever it can catch ends it through that stop (an error out of ``run`` too), so an
   exit status, not a signal, tells its supervisor that its devices were put in their safe
   state (``workers.safe_stopped``).
4. A message that cannot be carried out, and a mirror turn that fails, are bugs: logged, and
   the worker goes on.
5. When a bus of the gateway asks for SCHED_FIFO, every thread of the worker runs under it
   (``assembly.realtime_process``), as the daemon's do.
6. The gateway e-stops every bus at once, one message each. Once every bus of the worker has
   been handed its e-stop, the reader waits for their first exchanges before it reads on
   (``runner.let_estops_go``, ``runner`` rule 1), so that the bus threads have the interpreter
   first; a wait after each would leave the next buses' e-stops in the socket meanwhile.
7. What start-up made (the modules, the config, the buses) lives as long as the worker and is
   frozen out of the garbage collector once the buses run (``gc.freeze``), as the daemon's
   is: a full collection walking it holds the interpreter, every bus thread of the worker
   with it, for milliseconds.
8. A worker whose interpreter hangs ends by the kernel's hand after ``HANG_LIMIT_S``: each
   beat sets the process's timer again, and SIGALRM's default action ends the process when
   no beat came. The daemon's supervisor kills a silent worker sooner; this is for a worker
   whose daemon is gone (killed: its death signal is a SIGTERM, which a hung interpreter
   never acts on), so that it does not hold its ports for ever. A stopped worker (SIGSTOP)
   takes no signal but SIGKILL: it ends once continued.
9. The reader takes the messages already waiting in the socket before it acts on any (those
   sent while it was stalled, stopped or behind), ``WAITING_MAX`` datagrams at most past the
   one it woke for (a flood coming as fast as it reads must not hold back what it has read,
   an e-stop among it), and each bus given an e-stop among them is handed its messages together
   (``runner.together``, ``runner`` rule 6): its bus thread takes the e-stop in the same turn
   as the calls that came before it, which it takes out as in one process (a command waiting
   is answered ``estopped``, not a read; a reset; a stream's target), so that nothing the
   daemon sent before an e-stop goes to the wire after the e-stop reached the worker. Handed
   one at a time, a move read just before the e-stop could go out while the reader read on
   (a stalled worker's move went ahead of its e-stop frames, answered ok). Chosen over each
   call carrying the daemon's count of e-stops: that count helps only once the e-stop has
   been read, and the move was sent before. Reordering (the e-stop before what came before
   it) would carry out a reset sent before the e-stop after it. What the reader took before
   the e-stop was in the socket reached its bus before it, as a command handed to a bus
   thread in one process before the e-stop.
"""

from __future__ import annotations

import contextlib
import ctypes
import gc
import logging
import os
import signal
import socket
import sys
import threading
from concurrent.futures import Future
from functools import partial
from typing import Any, NoReturn

from busgate.gateway.bus.clock import now, tune_interpreter
from busgate.gateway.bus.flag import Flag
from busgate.gateway.drivers.base import DeviceEvent
from busgate.gateway.scheduler import authority
from busgate.gateway.scheduler.runner import BusRunner, let_estops_go
from busgate.gateway.service import logs
from busgate.gateway.service import worker_link as link
from busgate.gateway.service.assembly import (
    STOP_TIMEOUT_S,
    build_bus,
    realtime_process,
    stop_together,
)
from busgate.schemas.config import Config

log = logging.getLogger("busgate.gateway.service.worker")  # as run: __main__

#: How often at most each bus's trajectories and device ids are looked at (rule 2).
MIRROR_S = 0.01
#: The most datagrams the reader takes from its socket past the one it woke for before it
#: acts on what it read (rule 9).
WAITING_MAX = 64
#: How long a worker's interpreter may hang before the kernel ends it (rule 8): past the
#: supervisor's patience (``runner.STALL_S`` after a beat, ``workers.SLOW_START_S`` before
#: the first), so that a worker whose daemon lives is reported and restarted first.
HANG_LIMIT_S = 30.0
PR_SET_PDEATHSIG = 1
#: The exit status of a worker that stopped on a SIGTERM of its own, not on the daemon's
#: ``stop`` (rule 3): as a shell says a death by SIGTERM, so that its supervisor tells it from
#: a failure (``workers`` rule 3).
STOPPED_ON_SIGTERM = 128 + signal.SIGTERM


class Worker:
    """The buses of one worker, and what carries the daemon's calls to them."""

    def __init__(
        self,
        reader: link.Reader,
        config: Config,
        buses: list[str],
        *,
        hang_limit_s: float | None = None,
    ) -> None:
        self.reader = reader
        #: The process's own timer, set again at each beat (rule 8); ``None``: not this
        #: worker's to set (it runs in a process of another's, a test's).
        self.hang_limit_s = hang_limit_s
        self.outbox = link.Outbox(reader.sock, "worker-send")
        #: The daemon's calls not yet answered, by id (rule 1: a withdrawal cancels one).
        self._calls: dict[int, Future] = {}
        #: The buses handed an e-stop since the reader last let them go (rule 6).
        self._estops_handed: set[str] = set()
        #: Something the mirror sends may have changed: a new trajectory view, an answer (rule 2).
        self._mirror_due = Flag()
        #: A SIGTERM of its own stopped it (rule 3), not the daemon's ``stop``.
        self.stopped_on_sigterm = False
        self.runners: dict[str, BusRunner] = {
            bus.name: build_bus(bus, on_event=self._event, on_state=partial(self._state, bus.name))
            for bus in config.buses
            if bus.name in buses
        }
        for runner in self.runners.values():
            runner.plays.on_view = self._mirror_due.set
        if config.recorder is not None:  # the daemon's flight recorder keeps every frame
            for name, runner in self.runners.items():
                runner.owner.tap = partial(self._frame, name)

    def run(self, estopped: list[str]) -> None:
        """Run the buses until ``stop``, the socket's end or SIGTERM (rule 3)."""
        signal.signal(signal.SIGTERM, self._stop_reading)
        done = threading.Event()
        mirror = threading.Thread(target=self._mirror, args=(done,), name="worker-mirror")
        try:
            self.outbox.start()
            for name in estopped:  # e-stopped before this worker: e-stopped from its first turn
                self.runners[name].estop()
            for runner in self.runners.values():
                runner.start()
            mirror.start()
            gc.freeze()  # rule 7
            while (received := self.reader.receive()) is not None:
                messages = list(link.unbatched(received))
                for waiting in self.reader.waiting(WAITING_MAX):  # rule 9
                    messages.extend(link.unbatched(waiting))
                if self._carry_out_all(messages):
                    return
        finally:
            signal.signal(signal.SIGTERM, signal.SIG_IGN)  # stopping already (rule 3)
            done.set()
            self._mirror_due.set()
            if mirror.ident is not None:
                mirror.join()
            stop_together(partial(r.stop, STOP_TIMEOUT_S) for r in self.runners.values())
            self.outbox.close()

    def _stop_reading(self, signum: int, frame: Any) -> None:
        """SIGTERM: the read loop ends as when the daemon's socket closes (rule 3)."""
        self.stopped_on_sigterm = True
        with contextlib.suppress(OSError):
            self.reader.sock.shutdown(socket.SHUT_RD)

    def _carry_out_all(self, messages: list[tuple]) -> bool:
        """``messages`` (read together) carried out in order, those of each bus given an
        e-stop among them handed to it together (rule 9); whether ``stop`` came."""
        estopped = list(dict.fromkeys(m[2] for m in messages if _estop_of(m) in self.runners))
        try:
            with contextlib.ExitStack() as holding:
                for bus in estopped:
                    holding.enter_context(self.runners[bus].together())
                for message in messages:
                    try:
                        if message[0] == "stop":
                            return True
                        self._carry_out(message)
                    except Exception:  # rule 4
                        log.exception("worker: a message could not be carried out")
        finally:  # handed over now (rule 6)
            for bus in estopped:
                self._handed_estop(bus)
        return False

    def _carry_out(self, message: tuple) -> None:
        kind = message[0]
        if kind == "call" and message[3] in link.CALLS and message[2] in self.runners:
            _, call_id, bus, method, args, kwargs = message
            try:
                result = getattr(self.runners[bus], method)(*args, **kwargs)
            except Exception as exc:  # a bug: told, and the worker goes on
                log.exception("bus %s: %s failed", bus, method)
                result = Future()
                result.set_exception(exc)
            if call_id is not None and isinstance(result, Future):
                self._calls[call_id] = result
                result.add_done_callback(partial(self._answer, call_id))
        elif kind == "withdraw":
            withdrawn = self._calls.get(message[1])
            if withdrawn is not None:
                withdrawn.cancel()
        elif kind == "claims" and message[2] in link.CLAIM_OPS and message[1] in self.runners:
            _, bus, op, args = message
            try:
                getattr(self.runners[bus].authority.claims, op)(*args)
            except Exception as exc:  # judged first by the daemon: a lapse in between
                log.info("bus %s: claims %s refused here: %s", bus, op, exc)
        else:
            log.error("worker: refused a message it does not know: %r", message[:1])

    def _handed_estop(self, bus: str) -> None:
        """Rule 6: once every bus has its e-stop, wait for their first exchanges."""
        self._estops_handed.add(bus)
        if self._estops_handed == self.runners.keys():
            self._estops_handed.clear()
            let_estops_go(self.runners.values())

    def _answer(self, call_id: int, future: Future) -> None:
        self._calls.pop(call_id, None)
        if not future.cancelled():  # withdrawn: the daemon answered its caller already
            exc = future.exception()
            if exc is None:
                self.outbox.put(("result", call_id, True, future.result()), urgent=True)
            else:
                self.outbox.put(("result", call_id, False, link.portable(exc)), urgent=True)
        self._mirror_due.set()  # a command may have changed a device's id (rule 2)

    def _state(self, bus: str, device: str, state: dict[str, Any]) -> None:
        self.outbox.put(("state", bus, device, state), shed=True)

    def _event(self, event: DeviceEvent) -> None:
        self.outbox.put(("event", event))

    def _frame(self, bus: str, frame: tuple) -> None:
        self.outbox.put(("frame", bus, frame), shed=True)

    def _mirror(self, done: threading.Event) -> None:
        """Rule 2: trajectories and ids when they change, the beat every ``BEAT_S``."""
        sent: dict[str, tuple[Any, dict[str, int]]] = {}
        next_beat = now()
        while not done.is_set():
            self._mirror_due.clear()  # before the look: what changes after it wakes the next
            last_turn = now()
            try:
                for name, runner in self.runners.items():
                    view = runner.plays.view
                    ids = {device: d.device_id for device, d in runner.drivers.items()}
                    last = sent.get(name)
                    if last is None or last[0] is not view or last[1] != ids:
                        sent[name] = (view, ids)
                        self.outbox.put(("plays", name, view, ids))
                if last_turn >= next_beat:
                    next_beat = last_turn + link.BEAT_S
                    self.outbox.put(("beat", self._beat()), shed=True)
                    if self.hang_limit_s is not None:
                        _hang_limit(self.hang_limit_s)
            except Exception:  # rule 4
                log.exception("worker: a mirror turn failed")
            # Until something changed or the beat is due (stopping raises the flag too); a
            # change a MIRROR_S after the last turn at the soonest.
            if self._mirror_due.wait(next_beat - now()):
                done.wait(last_turn + MIRROR_S - now())

    def _beat(self) -> dict[str, link.BusBeat]:
        return {
            name: link.BusBeat(
                on_schedule=runner.keeping_schedule(),
                is_open=runner.owner.is_open,
                statistics=runner.statistics(),
                open_failure=runner.open_failure,
                streaming=frozenset(d for d in runner.drivers if runner.streams.following(d)),
            )
            for name, runner in self.runners.items()
        }


def _estop_of(message: tuple) -> str | None:
    """The bus ``message`` e-stops, if it is an e-stop (rule 9); checked as ``_carry_out``
    checks, so that a malformed message is that one's failure (rule 4), not the batch's."""
    if (
        isinstance(message, tuple)
        and len(message) == 6
        and message[:1] == ("call",)
        and message[3] == "estop"
    ):
        bus = message[2]
        return bus if isinstance(bus, str) else None
    return None


def _die_with_the_daemon() -> None:
    """SIGTERM to this worker when the thread of the daemon that started it ends, however it
    ends (``PR_SET_PDEATHSIG``; refused in a sandbox without ``prctl``: then the socket
    closing stops it). Set here, after ``exec``, not in a ``preexec_fn`` (which may deadlock
    a child forked from a process with threads)."""
    libc = ctypes.CDLL(None, use_errno=True)
    libc.prctl(PR_SET_PDEATHSIG, signal.SIGTERM)


def _hang_limit(seconds: float) -> None:
    """The kernel ends this process ``seconds`` from now unless this is called again (rule
    8)."""
    signal.setitimer(signal.ITIMER_REAL, seconds)


def _stop_on_sigterm(signum: int, frame: Any) -> NoReturn:
    raise SystemExit(STOPPED_ON_SIGTERM)


def main() -> int:
    level = sys.argv[2] if len(sys.argv) > 2 else "INFO"  # the daemon's
    logs.configure(level)
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the daemon's (rule 3)
    signal.signal(signal.SIGHUP, signal.SIG_IGN)
    signal.signal(signal.SIGUSR1, signal.SIG_IGN)  # the flight recorder's, the daemon's
    signal.signal(signal.SIGTERM, _stop_on_sigterm)
    signal.signal(signal.SIGALRM, signal.SIG_DFL)  # rule 8: its default ends the process
    _die_with_the_daemon()
    _hang_limit(HANG_LIMIT_S)
    reader = link.Reader(socket.socket(fileno=int(sys.argv[1])))
    first = reader.receive()
    if first is None or first[0] != "start":
        return 2
    _, config, buses, estopped = first
    tune_interpreter()
    realtime_process(config, f"worker {os.getpid()}")
    # Its claim tables mirror the daemon's, which logs every change: one line each, not two.
    logging.getLogger(authority.__name__).setLevel(logging.ERROR)
    log.info("worker %d: buses %s", os.getpid(), ", ".join(buses))
    worker = Worker(reader, config, buses, hang_limit_s=HANG_LIMIT_S)
    worker.run(estopped)
    return STOPPED_ON_SIGTERM if worker.stopped_on_sigterm else 0


if __name__ == "__main__":
    sys.exit(main())
