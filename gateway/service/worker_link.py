"""What crosses between the gateway's process and a bus worker (docs/workers.md).

One Unix socket pair per worker (``SOCK_SEQPACKET``: one datagram per send, never split or
merged), each message a pickled tuple whose first item names it. Rules of this file:

1. Each end acts only on the messages it knows by name (a worker: ``start``, ``call``,
   ``withdraw``, ``claims``, ``stop``; the daemon: ``result``, ``state``, ``event``, ``frame``,
   ``plays``, ``beat``; either: a ``batch`` of them, in order) and logs any other: a worker
   is a child of the daemon, but what it is sent is still checked.
2. An exception crosses as its class's name, code, message and attributes, and is built
   again on the other side (busgate's errors take keyword attributes that pickle does not
   give back): ``portable`` and ``rebuilt``.
3. A send never blocks a bus thread: the socket is written by one sender thread per end,
   from an outbox (``Outbox``), or by a caller of ``put_now`` when nothing waits and the
   socket takes it at once. The socket never has a timeout: the sender waits for room as
   long as the peer lives, and what the socket cannot take at once is queued: never lost
   but for what a newer message makes worthless (a state, a beat), and a device's target
   replaced by its next one (``Outbox``).
4. A message larger than ``PART`` crosses in parts of ``PART`` bytes, in order, joined by the
   ``Reader`` of the other end: a kernel's send buffer (by default some 416 KiB of datagram
   at most) never decides what can cross. One larger than ``MAX_MESSAGE`` is a bug: the
   sender logs and drops it (``put_now`` refuses it to its caller); the link goes on.
"""

from __future__ import annotations

import itertools
import logging
import pickle
import select
import socket
import threading
from collections import deque
from collections.abc import Hashable
from typing import Any, NamedTuple

import busgate.errors as errors_module
from busgate.gateway.bus.flag import Flag
from busgate.gateway.bus.stats import BusStats

log = logging.getLogger(__name__)

#: A message ``Outbox.put_now`` pickled already (the first item of what it queues).
_PICKLED = "pickled"
#: The largest message either end sends (a config, a trajectory's samplers, a scan's result).
MAX_MESSAGE = 16 << 20
#: The most of a message one datagram carries (rule 4), well under any send buffer.
PART = 1 << 16
#: What a datagram starts with: a whole message, a part with more to come, the last part.
_WHOLE, _MORE, _LAST = b"=", b"+", b"."
#: The send buffer each end asks for (the kernel may give less): room for a few parts.
SEND_BUFFER = 1 << 20
#: What a worker may be asked to do to a runner: the runner's methods of the same name.
CALLS = frozenset(
    {
        "submit",
        "scan",
        "stop_stream",
        "estop",
        "reset_estop",
        "follow",
        "ramp",
        "play",
        "stop_playing",
    }
)
#: What a worker may be asked to do to a bus's claims: ``ClaimTable``'s methods.
CLAIM_OPS = frozenset({"claim", "hold", "release", "drop_client"})
#: Most messages in one batch (a batch of states: some 30 KiB).
BATCH_MAX = 64
#: How long the first message of a batch waits for more, unless one is urgent.
GATHER_S = 0.002
#: How often a worker says how its bus threads are doing.
BEAT_S = 0.1


class BusBeat(NamedTuple):
    """What a worker's ``beat`` says of each of its buses (``worker.Worker._beat``)."""

    on_schedule: bool  # its thread keeps its schedule (the watchdog's word)
    is_open: bool
    statistics: BusStats
    open_failure: str | None  # why it is not open
    streaming: frozenset[str]  # the devices its follow streams and ramps drive


class _Target:
    """A device's target waiting in an ``Outbox``, which the device's next one may replace."""

    __slots__ = ("key", "message")

    def __init__(self, key: Hashable, message: tuple) -> None:
        self.key, self.message = key, message


def portable(exc: BaseException) -> tuple[str, str, str, dict[str, Any]]:
    """``exc`` as plain values: its class's name, its code, its message, its attributes."""
    attributes = {k: v for k, v in vars(exc).items() if isinstance(v, str | int | float | None)}
    return type(exc).__name__, getattr(exc, "code", "internal"), str(exc), attributes


def rebuilt(name: str, code: str, message: str, attributes: dict[str, Any]) -> BaseException:
    """The exception ``portable`` described: busgate's own class when it has one by that name,
    else a ``BusgateError`` carrying the code."""
    cls = getattr(errors_module, name, None)
    if not (isinstance(cls, type) and issubclass(cls, errors_module.BusgateError)):
        cls = errors_module.BusgateError
    exc = cls.__new__(cls)
    Exception.__init__(exc, message)
    exc.__dict__.update(attributes)
    exc.code = code
    return exc


def pair() -> tuple[socket.socket, socket.socket]:
    """The two ends: the daemon's, and the one the worker inherits."""
    ends = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    for end in ends:
        end.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, SEND_BUFFER)
    return ends


def unbatched(message: tuple) -> list[tuple]:
    """The messages ``message`` carries: those of a ``batch`` in order, or itself."""
    return message[1] if message[0] == "batch" else [message]


def write(sock: socket.socket, data: bytes, flags: int = 0) -> None:
    """``data`` (a pickled message) on ``sock``: one datagram, or its parts (rule 4; only a
    blocking send may send parts, lest a message be left half sent)."""
    if len(data) <= PART:
        sock.sendmsg([_WHOLE, data], [], flags)
        return
    whole = memoryview(data)
    for start in range(0, len(data), PART):
        end = start + PART
        sock.sendmsg([_MORE if end < len(data) else _LAST, whole[start:end]])


class Reader:
    """The messages that come on one socket, a message's parts joined (rule 4)."""

    def __init__(self, sock: socket.socket) -> None:
        self.sock = sock
        self._parts: list[bytes] = []
        self._size = 0
        self._incoming = select.poll()
        self._incoming.register(sock, select.POLLIN)

    def receive(self, timeout_s: float | None = None) -> tuple | None:
        """The next message, or ``None`` once the other end has gone; ``TimeoutError`` when
        nothing came for ``timeout_s`` (parts read so far are kept). The wait is a ``poll``:
        a socket timeout would make the same socket's sends wait and fail too (rule 3)."""
        while True:
            if timeout_s is not None and not self._incoming.poll(timeout_s * 1000):
                raise TimeoutError(f"nothing came for {timeout_s} s")
            try:
                data = self.sock.recv(PART + 1)
            except OSError:
                return None
            if not data:
                return None
            tag, body = data[:1], memoryview(data)[1:]
            if tag in (_MORE, _LAST):
                self._parts.append(bytes(body))
                self._size += len(body)
                if tag == _MORE:
                    if self._size > MAX_MESSAGE:  # a bug on the other side: this one is lost
                        log.error("a message over %d bytes came: dropped", MAX_MESSAGE)
                        self._parts, self._size = [], 0
                    continue
                body = memoryview(b"".join(self._parts))
                self._parts, self._size = [], 0
            elif tag != _WHOLE:  # a bug on the other side: lost, not the link
                log.error("a datagram that is no message nor part of one: dropped")
                continue
            elif self._parts:  # a bug on the other side: the parts are lost, not this one
                log.error("a message cut short after %d parts: dropped", len(self._parts))
                self._parts, self._size = [], 0
            try:
                return pickle.loads(body)
            except Exception:  # a bug on the other side: this message is lost, not the link
                log.exception("a message of %d bytes could not be read: dropped", len(body))
                return ("batch", [])

    def waiting(self, most: int) -> list[tuple]:
        """The messages already in the socket, ``most`` at most, without waiting for one more
        (a message whose first part is there is read whole); none once the other end has gone
        (``receive`` says so next)."""
        messages: list[tuple] = []
        while len(messages) < most and self._incoming.poll(0):
            message = self.receive()
            if message is None:
                break
            messages.append(message)
        return messages


class Outbox:
    """Messages for the socket, sent in order by a thread of their own (rule 3). What waits
    together goes as one ``batch``: the first message wakes the sender, which lets more
    gather for ``GATHER_S`` unless one is urgent (an answer, a call), so that a worker's states
    cost one wake-up, one pickling and one send per batch rather than each.

    A peer that stops reading (a worker stalled, before it is found silent and killed) never
    costs a message that must cross, nor the memory of the process that writes:

    - What a newer message makes worthless (``shed``: a state, a frame, a beat) waits in a
      queue of ``BACKLOG`` at most, which loses its oldest when full (counted, and logged once
      the sender moves again). Everything else (an e-stop, a call, a claim, an answer, an
      event) waits, however much waits; the two queues keep their order between them.
    - A device's target (``latest_of`` its bus and device: a follow or a ramp target) takes
      the place of the one of its device still waiting, unless a message that keeps its order
      was queued after that one: a client flooding a stalled worker with follow targets
      queues one a device, and an e-stop put behind them never waits for thousands (a ROS 2
      target renews its client's claim, a message that keeps its order: those queue each).
    """

    #: The most messages ``shed`` that wait: a peer that stopped reading loses the oldest.
    BACKLOG = 65_536

    def __init__(self, sock: socket.socket, name: str) -> None:
        self._sock = sock
        #: What waits, each with its place in the order: what must cross, and what is shed.
        self._kept: deque[tuple[int, Any]] = deque()
        self._shed: deque[tuple[int, Any]] = deque(maxlen=self.BACKLOG)
        self._order = itertools.count()
        #: Each device's target still waiting, that the device's next one may replace.
        self._targets: dict[Hashable, _Target] = {}
        self._ready = Flag()
        self._urgent = Flag()
        self._lock = threading.Lock()  # the queues, their order and what is being sent
        self._sending = False
        self._closed = False
        self._dropped = 0  # the oldest messages the full queue lost since the last log
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)

    def start(self) -> Outbox:
        self._thread.start()
        return self

    @property
    def waiting(self) -> int:
        """How many messages wait for the sender."""
        return len(self._kept) + len(self._shed)

    def put(self, message: tuple, *, urgent: bool = False, shed: bool = False) -> None:
        """``message`` out, pickled by the sender thread (for a bus thread: rule 3); ``shed``:
        a newer message makes it worthless, and it may be lost while the peer reads nothing."""
        with self._lock:
            self._queue_up(message, shed=shed)
        if urgent:
            self._urgent.set()
        self._ready.set()

    def put_now(self, message: tuple, *, latest_of: Hashable = None) -> None:
        """``message`` out at once, pickled here first: what cannot cross is refused to its
        caller (``pickle.PicklingError``, ``TypeError``, ``ValueError`` when larger than
        ``MAX_MESSAGE``), not lost on the way. Sent from the caller's thread when nothing is
        ahead of it, it is one datagram and the socket takes it without waiting (an e-stop
        goes with no thread in between), else queued for the sender. ``latest_of``: it is
        the target of that device, replacing its last one if that still waits."""
        data = pickle.dumps(message, pickle.HIGHEST_PROTOCOL)
        if len(data) > MAX_MESSAGE:
            raise ValueError(f"a {message[0]!r} message of {len(data)} bytes is too large to cross")
        with self._lock:
            if not self.waiting and not self._sending and len(data) <= PART:
                try:
                    write(self._sock, data, socket.MSG_DONTWAIT)
                    return
                except BlockingIOError:
                    pass
                except OSError:
                    return  # the peer has gone: its supervisor reports it
            self._queue_up((_PICKLED, data), latest_of=latest_of)
        self._urgent.set()
        self._ready.set()

    def _queue_up(self, message: tuple, *, shed: bool = False, latest_of: Hashable = None) -> None:
        """``message`` in its queue, or in place of its device's target (the class's rules);
        with the lock held."""
        entry: Any = message
        if latest_of is not None:
            waiting = self._targets.get(latest_of)
            if waiting is not None:
                waiting.message = message
                return
            entry = self._targets[latest_of] = _Target(latest_of, message)
        elif not shed:  # it keeps its order: no target before it is replaced by one after it
            self._targets.clear()
        if shed and len(self._shed) == self.BACKLOG:
            self._dropped += 1
        (self._shed if shed else self._kept).append((next(self._order), entry))

    def close(self) -> None:
        self._closed = True
        self._urgent.set()
        self._ready.set()
        self._thread.join(1.0)

    def _run(self) -> None:
        while True:
            self._ready.wait()
            self._ready.clear()
            self._urgent.wait(GATHER_S)
            self._urgent.clear()
            while True:
                with self._lock:
                    if not self.waiting:
                        break
                    message, self._sending = self._next(), True
                try:
                    sent = self._send(message)
                except Exception:  # a bug: this message is lost, never the sender (rule 3)
                    log.exception("a %r message could not be sent", message[0])
                    sent = True
                with self._lock:
                    self._sending = False
                    dropped, self._dropped = self._dropped, 0
                if not sent:
                    return
                if dropped:
                    log.error("%d messages lost: the other process did not read them", dropped)
            if self._closed:
                return

    def _next(self) -> tuple:
        """The next message to send: one pickled already, or what waits, as one ``batch``
        when more than one."""
        first = self._take()
        if first[0] is _PICKLED:
            return first
        batch = [first]
        while len(batch) < BATCH_MAX and (head := self._head()) is not None:
            if head[0] is _PICKLED:
                break
            batch.append(self._take())
        return first if len(batch) == 1 else ("batch", batch)

    def _queue_ahead(self) -> deque[tuple[int, Any]] | None:
        """The queue whose head comes next in the order; ``None`` when nothing waits."""
        kept, shed = self._kept, self._shed
        if not shed:
            return kept or None
        return kept if kept and kept[0][0] < shed[0][0] else shed

    def _head(self) -> tuple | None:
        """The next message, left waiting; ``None`` when nothing waits."""
        queue = self._queue_ahead()
        if queue is None:
            return None
        entry = queue[0][1]
        return entry.message if isinstance(entry, _Target) else entry

    def _take(self) -> tuple:
        """The next message, taken: a target taken is no longer replaced."""
        queue = self._queue_ahead()
        assert queue is not None  # only while something waits
        _, entry = queue.popleft()
        if not isinstance(entry, _Target):
            return entry
        if self._targets.get(entry.key) is entry:
            del self._targets[entry.key]
        return entry.message

    def _send(self, message: tuple) -> bool:
        """``False`` once the peer has gone; a message that cannot be pickled or is too large
        is logged and dropped (a bug: the sender goes on), the rest of its batch sent."""
        try:
            data = message[1] if message[0] is _PICKLED else pickle.dumps(message, -1)
        except Exception:  # what a value's pickling may raise: its own bug, not the link's
            if message[0] == "batch":  # one by one: only what cannot cross is lost
                return all(self._send(item) for item in message[1])
            log.exception("a %r message cannot cross to the other process", message[0])
            return True
        if len(data) > MAX_MESSAGE:
            if message[0] == "batch":  # one by one: only what is too large is lost
                return all(self._send(item) for item in message[1])
            log.error(
                "a %r message of %d bytes is too large to cross: dropped", message[0], len(data)
            )
            return True
        try:
            write(self._sock, data)
        except OSError:
            return False  # the peer has gone
        return True
