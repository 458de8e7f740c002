"""Clients' puts and queries, taken off zenoh's receiving threads by threads of our own.

zenoh-python runs a plain Python callback on a thread of its own, fed through a channel of
256 that *blocks* zenoh's receiving thread when full. A client putting or getting faster than
Python handles (a control loop with no sleep, or a hostile one) filled it, and the receiving
threads (two in zenoh's pool) then waited on Python for every link they serve: two clients
flooding a ``cmd`` key held an e-stop put 0.2-2 s before it reached the buses
(docs/performance.md, "An e-stop under a flood of commands").

Rules of this file:

1. Zenoh's receiving threads never wait on Python for a client's put or query: each waits
   in a ring of zenoh's (``RingChannel``: ``BACKLOG``, fewer on a key of large payloads,
   ``backlog_for``; what it holds is bounded by the session's largest message,
   ``schemas.zenoh_session.MAX_RECEIVED``) for the intake's own thread, which takes them in
   the order they came. When the ring is full zenoh drops the oldest: a put so
   dropped is lost, a query so dropped is ended by zenoh with no reply (its getter hears that
   no gateway answered).
2. A handler's exception is logged and the thread goes on: a bug must not lose every later
   put or query.
3. ``take_waiting`` takes what waits without handling it, and never waits: an e-stop takes
   what was put before it, which must never act after a reset that follows at once.
4. ``close`` ends the handling and undeclares the subscriber or queryable: what still waits
   is dropped (zenoh ends a query so dropped with no reply), and the thread ends with its
   channel (``join`` waits for that a bounded time). A daemon thread must not be in zenoh's
   code when the interpreter exits, and a backlog handled after the session is gone would
   only be refused.
5. With ``estops`` (the gateway's count of e-stops), each put or query is handled with the
   count it was taken under (``taken.estops_when_taken``, on its thread): work it hands to
   another thread (a play's lane) or does slowly (a ROS 2 trajectory's decoding) is judged
   by it, and refused ``estopped`` when an e-stop came meanwhile.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from typing import Any, Generic, TypeVar

import zenoh

from busgate.gateway.api.taken import taken_under

log = logging.getLogger(__name__)

#: Puts or queries received and not yet taken, a key's (rule 1): a burst of this many is
#: taken whole, some 80 ms of a thread's work for follow targets; past that, under a flood,
#: the oldest are dropped.
BACKLOG = 4096
#: What a key whose payloads are large may hold waiting, in bytes (``backlog_for``).
BACKLOG_BYTES = 16 * 1024 * 1024
#: How long ``join`` waits for the thread to end (rule 4).
JOIN_S = 1.0

Item = TypeVar("Item", zenoh.Sample, zenoh.Query)


class Intake(Generic[Item]):
    """One key's puts or queries (rule 1), each handed to ``handle`` on the thread ``name``."""

    def __init__(
        self,
        name: str,
        source: Any,
        handle: Callable[[Item], None],
        estops: Callable[[], int] | None = None,
    ) -> None:
        self._source = source
        self._handle: Callable[[Item], None] = handle
        self._estops = estops
        self._stopped = False
        self._thread = threading.Thread(target=self._take, name=name, daemon=True)
        self._thread.start()

    def take_waiting(self) -> list[Item]:
        """What waits, taken unhandled (rule 3)."""
        waiting: list[Item] = []
        while (item := self._source.try_recv()) is not None:
            waiting.append(item)
        return waiting

    def close(self) -> None:
        """Hand nothing more on, and undeclare (rule 4)."""
        self._stopped = True
        self._source.undeclare()

    def join(self) -> bool:
        """Wait ``JOIN_S`` at most for the thread to end once closed (rule 4); whether it did."""
        self._thread.join(JOIN_S)
        return not self._thread.is_alive()

    def _take(self) -> None:
        name = self._thread.name
        for item in self._source:
            if self._stopped:
                continue  # taken, left unhandled, until the channel's end ends the loop
            if self._estops is not None:
                taken_under(self._estops())
            try:
                self._handle(item)
            except Exception:  # rule 2
                log.exception("%s: what came on %s could not be handled", name, item.key_expr)


def backlog_for(largest: int) -> int:
    """The ring of a key whose payloads take up to ``largest`` bytes: ``BACKLOG``, fewer
    where so many would hold more than ``BACKLOG_BYTES`` (a trajectory's megabyte: 16), and
    never under 4."""
    return max(4, min(BACKLOG, BACKLOG_BYTES // largest))


def take_puts(
    session: zenoh.Session,
    key: str,
    handle: Callable[[zenoh.Sample], None],
    name: str,
    backlog: int = BACKLOG,
    estops: Callable[[], int] | None = None,
) -> Intake[zenoh.Sample]:
    """The puts on ``key``, each handed to ``handle`` on the thread ``name``."""
    ring: zenoh.handlers.RingChannel[zenoh.Sample] = zenoh.handlers.RingChannel(backlog)
    return Intake(name, session.declare_subscriber(key, ring), handle, estops)


def take_queries(
    session: zenoh.Session,
    key: str,
    handle: Callable[[zenoh.Query], None],
    name: str,
    backlog: int = BACKLOG,
    estops: Callable[[], int] | None = None,
) -> Intake[zenoh.Query]:
    """The queries on ``key``, each handed to ``handle`` on the thread ``name``."""
    ring: zenoh.handlers.RingChannel[zenoh.Query] = zenoh.handlers.RingChannel(backlog)
    return Intake(name, session.declare_queryable(key, ring), handle, estops)


def take_liveliness(
    session: zenoh.Session, key: str, handle: Callable[[zenoh.Sample], None], name: str
) -> Intake[zenoh.Sample]:
    """The liveliness tokens' comings and goings on ``key``, each handed to ``handle`` on the
    thread ``name``."""
    ring: zenoh.handlers.RingChannel[zenoh.Sample] = zenoh.handlers.RingChannel(BACKLOG)
    return Intake(name, session.liveliness().declare_subscriber(key, ring), handle)
