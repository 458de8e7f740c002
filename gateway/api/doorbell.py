"""What wakes the publishing loop when it waits with nothing to do.

The loop publishes in rounds while there is work: a round that published something (rounds
of ``bridge.TELEMETRY_EVERY_S``), a trajectory running, a base driving, a refusal held back
for its interval (``bridge.PUBLISH_EVERY_S``), a joints message held back for its interval.
With none of those it waits for the next state or event rather than waking every round for
nothing: on this project's host an asyncio loop that sleeps 5 ms at a time takes some 2 % of
a core doing nothing.

Rules of this file:

1. A ``Mailbox`` is a deque whose ``append`` rings its doorbell: the bus threads, the worker
   links, the API and zenoh's threads hand the loop states and events through two of them.
2. A ring costs a look at one attribute while the loop is not waiting, and wakes it (once,
   through ``call_soon_threadsafe``) while it is. What was appended before the wait began is
   seen by the wait's own first look (``has_news``), so nothing waits out a wait.
"""

from __future__ import annotations

import asyncio
import contextlib
from collections import deque
from collections.abc import Callable
from typing import Any


class Doorbell:
    """Rung from any thread; waited on by the loop's publishing round."""

    def __init__(self) -> None:
        self._loop: asyncio.AbstractEventLoop | None = None
        self._waiting: asyncio.Future[None] | None = None

    def ring(self) -> None:
        """Wake the wait under way, if any (rule 2)."""
        waiting, loop = self._waiting, self._loop
        if waiting is None or loop is None:
            return
        self._waiting = None
        with contextlib.suppress(RuntimeError):  # the loop closed meanwhile: nothing waits
            loop.call_soon_threadsafe(_settle, waiting)

    async def wait(self, timeout: float, has_news: Callable[[], bool]) -> None:
        """Until a ring, at most ``timeout`` seconds; not at all when ``has_news()`` already."""
        loop = self._loop = asyncio.get_running_loop()
        waiting: asyncio.Future[None] = loop.create_future()
        self._waiting = waiting
        if has_news():  # appended before the wait began (rule 2)
            self._waiting = None
            return
        timer = loop.call_later(timeout, _settle, waiting)
        try:
            await waiting
        finally:
            timer.cancel()
            self._waiting = None


def _settle(waiting: asyncio.Future[None]) -> None:
    if not waiting.done():
        waiting.set_result(None)


class Mailbox(deque):
    """A deque whose ``append`` rings ``ring`` (rule 1)."""

    def __init__(self, ring: Callable[[], None], maxlen: int) -> None:
        super().__init__(maxlen=maxlen)
        self._ring = ring

    def append(self, item: Any) -> None:
        super().append(item)
        self._ring()
