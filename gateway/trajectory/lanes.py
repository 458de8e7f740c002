"""Where trajectory commands wait: plays in a short lane of their own, every other command in
another, so that a cancel or a status never waits behind the plays.

Rules of this file:

1. A play is parsed, checked and sampled on the play lane's one thread, in the order plays
   came. At most ``MAX_WAITING_PLAYS`` wait there: one more is answered ``busy`` at once. A
   play that has not started ``PLAY_START_S`` after it came (its client's query is likely
   to have timed out) is answered ``busy`` and never carried out, as a device command past
   its start deadline is (``scheduler.runner`` rule 5).
2. A payload that names another op (``cancel``, ``status``), small enough to be read on
   arrival (``PEEK_BYTES``), goes to the control lane's thread, bounded the same way: a
   flood of them is ``busy``, never an unbounded queue. Whatever cannot be read on arrival
   (malformed, or large) is a play's business: it goes to the play lane and is refused there.
3. Each lane answers with the trajectory key's reply (``answer``): a refusal its envelope,
   anything else (a bug) logged and answered ``internal``, never raised to the caller.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from functools import partial
from typing import Any

from busgate.errors import BusyError, RefusedError
from busgate.gateway.bus.clock import now
from busgate.gateway.scheduler.outcomes import settled
from busgate.schemas.payload import decode_object
from busgate.schemas.replies import error_reply, failure_reply

log = logging.getLogger(__name__)

#: Plays waiting for the play lane (rule 1), beside the one it is checking.
MAX_WAITING_PLAYS = 4
#: A play not started this long after it came is answered ``busy`` (rule 1).
PLAY_START_S = 2.0
#: Control commands (cancel, status) waiting for their lane (rule 2).
MAX_WAITING_CONTROL = 64
#: Payloads up to this size are read on arrival to find their lane (rule 2): a cancel or a
#: status is a few dozen bytes.
PEEK_BYTES = 4096
CONTROL_OPS = frozenset({"cancel", "status"})

Reply = dict[str, Any]


class Lane:
    """One thread, and at most ``limit`` commands waiting for it, each started within
    ``start_s`` of its coming or answered ``busy``."""

    def __init__(self, name: str, limit: int, start_s: float | None) -> None:
        self.name = name
        self.limit = limit
        self.start_s = start_s
        self._worker = ThreadPoolExecutor(1, thread_name_prefix=name)
        self._lock = threading.Lock()
        self._waiting = 0

    def submit(self, work: Callable[[], Reply]) -> Future[Reply]:
        with self._lock:
            full = self._waiting >= self.limit
            if not full:
                self._waiting += 1
        if full:
            return settled(error_reply(BusyError(f"{self.limit} {self.name}s are waiting")))
        return self._worker.submit(self._run, work, now())

    def close(self) -> None:
        self._worker.shutdown(wait=False, cancel_futures=True)

    def _run(self, work: Callable[[], Reply], came: float) -> Reply:
        with self._lock:
            self._waiting -= 1
        waited = now() - came
        if self.start_s is not None and waited > self.start_s:
            return error_reply(
                BusyError(
                    f"the {self.name} waited {waited:.1f} s for the ones before it, over "
                    f"{self.start_s:g} s: not carried out"
                )
            )
        return work()


class TrajectoryLanes:
    """The two lanes of the trajectory key (rules 1 and 2)."""

    def __init__(self, command: Callable[..., Reply]) -> None:
        self.command = command  # (payload, came_under=: the e-stops counted when it came)
        self.plays = Lane("play", MAX_WAITING_PLAYS, PLAY_START_S)
        self.control = Lane("trajectory command", MAX_WAITING_CONTROL, None)

    def submit(
        self, payload: bytes, came_under: int | None = None, **options: Any
    ) -> Future[Reply]:
        """``payload`` in its lane; ``came_under``: the e-stops counted when it came (a play
        started after another is refused); ``options`` go to the command (``limit``)."""
        lane = self.control if _is_control(payload) else self.plays
        command = partial(self.command, came_under=came_under, **options)
        return lane.submit(lambda: answer(command, payload))

    def close(self) -> None:
        self.plays.close()
        self.control.close()


def answer(command: Callable[[bytes], Reply], payload: bytes) -> Reply:
    """``command``'s reply to ``payload``, whatever happens (rule 3)."""
    try:
        return command(payload)
    except Exception as exc:
        return failure_reply(exc, log, "trajectory command")


def _is_control(payload: bytes) -> bool:
    if len(payload) > PEEK_BYTES:
        return False
    try:
        op = decode_object(payload).get("op")
    except RefusedError:
        return False
    return isinstance(op, str) and op in CONTROL_OPS
