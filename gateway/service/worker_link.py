"""What crosses between the gateway's process and a bus worker (docs/workers.md).

One Unix socket pair per worker (``SOCK_SEQPACKET``: one message per send, never split or
merged), each message a pickled tuple whose first item names it. Rules of this file:

1. Each end acts only on the messages it knows by name (the daemon: ``start``, ``call``,
   ``claims``, ``stop``; a worker: ``result``, ``states``, ``events``, ``frames``,
   ``plays``, ``beat``) and logs any other: a worker is a child of the daemon, but what it
   is sent is still checked.
2. An exception crosses as its class's name, code, message and attributes, and is built
   again on the other side (busgate's errors take keyword attributes that pickle does not
   give back): ``portable`` and ``rebuilt``.
3. A send never blocks a bus thread: the socket is written by one sender thread per end,
   from an outbox (``Outbox``).
"""

from __future__ import annotations

import logging
import pickle
import socket
import threading
from collections import deque
from typing import Any

import busgate.errors as errors_module

log = logging.getLogger(__name__)

#: A message ``Outbox.put_now`` pickled already (the first item of what it queues).
_PICKLED = "pickled"
#: The largest message either end sends: a batch of states, or a scan's result.
MAX_MESSAGE = 1 << 20
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
#: Most states or events in one message (well under ``MAX_MESSAGE``).
BATCH_MAX = 512
#: How often a worker says how its bus threads are doing.
BEAT_S = 0.1


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
    return socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)


def receive(sock: socket.socket) -> tuple | None:
    """The next message, or ``None`` once the other end has gone (``TimeoutError`` when the
    socket has a timeout and nothing came within it)."""
    try:
        data = sock.recv(MAX_MESSAGE)
    except TimeoutError:
        raise
    except OSError:
        return None
    return pickle.loads(data) if data else None


class Outbox:
    """Messages for the socket, sent in order by a thread of their own (rule 3); messages of
    the same batchable kind waiting together go as one."""

    BATCHED = frozenset({"states", "events", "frames"})
    #: Messages waiting at most: a peer that stopped reading loses the oldest, never the
    #: memory of the process that writes.
    BACKLOG = 65_536

    def __init__(self, sock: socket.socket, name: str) -> None:
        self._sock = sock
        self._queue: deque[tuple] = deque(maxlen=self.BACKLOG)
        self._ready = threading.Event()
        self._closed = False
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)

    def start(self) -> Outbox:
        self._thread.start()
        return self

    def put(self, message: tuple) -> None:
        """``message`` out, pickled by the sender thread (for a bus thread: rule 3)."""
        self._queue.append(message)
        self._ready.set()

    def put_now(self, message: tuple) -> None:
        """``message`` out, pickled here first: what cannot cross is refused to its caller
        (``pickle.PicklingError``, ``TypeError``), not lost on the way."""
        self._queue.append((_PICKLED, pickle.dumps(message, pickle.HIGHEST_PROTOCOL)))
        self._ready.set()

    def close(self) -> None:
        self._closed = True
        self._ready.set()
        self._thread.join(1.0)

    def _run(self) -> None:
        while True:
            self._ready.wait()
            self._ready.clear()
            while self._queue:
                if not self._send(self._coalesced()):
                    return
            if self._closed:
                return

    def _coalesced(self) -> tuple:
        first = self._queue.popleft()
        if first[0] not in self.BATCHED:  # one message, or one already pickled
            return first
        items = list(first[1])
        while self._queue and self._queue[0][0] == first[0] and len(items) < BATCH_MAX:
            items.extend(self._queue.popleft()[1])
        return (first[0], items)

    def _send(self, message: tuple) -> bool:
        """``False`` once the peer has gone; a message that cannot be pickled is logged and
        dropped (a bug: the sender goes on with the next)."""
        try:
            data = message[1] if message[0] is _PICKLED else pickle.dumps(message, -1)
        except (pickle.PicklingError, TypeError, AttributeError):
            log.exception("a %r message cannot cross to the other process", message[0])
            return True
        try:
            self._sock.send(data)
        except OSError:
            return False
        return True
