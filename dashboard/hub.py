"""Pushes the fleet to every browser: a snapshot when one connects, then what changed, every
``PUSH_EVERY_S``, as Server-Sent Events.

Rules of this file:

1. Everything runs on the server's loop, so a browser's snapshot and its joining the
   subscribers happen between two drains: it misses no change and gets none twice.
2. Each change is encoded once, however many browsers there are.
3. A browser that falls ``BACKLOG`` messages behind is let go (its stream ends); its
   ``EventSource`` reconnects and starts again from a snapshot. Nothing waits on a slow one.
"""

from __future__ import annotations

import asyncio
import json
from collections.abc import AsyncIterator
from typing import Any

from busgate.dashboard.fleet import Fleet

PUSH_EVERY_S = 0.1
BACKLOG = 50
#: A comment line this often keeps proxies from closing a quiet stream, and tells a gone
#: browser's stream that it is gone.
KEEPALIVE_S = 15.0
_LET_GO = b""  # what ends a browser's stream


def event(name: str, body: dict[str, Any]) -> bytes:
    """One server-sent event: its name and its JSON, on one data line."""
    return f"event: {name}\ndata: {json.dumps(body, separators=(',', ':'))}\n\n".encode()


class Hub:
    def __init__(self, fleet: Fleet) -> None:
        self._fleet = fleet
        self._queues: set[asyncio.Queue[bytes]] = set()

    @property
    def browsers(self) -> int:
        return len(self._queues)

    async def stream(self, most: int) -> AsyncIterator[bytes]:
        """One browser's events, from its snapshot on, until it is let go or leaves; none
        when ``most`` browsers have streams already, counted as this one joins (a burst of
        requests each passed a count made before any of their streams began)."""
        if len(self._queues) >= most:
            return
        queue: asyncio.Queue[bytes] = asyncio.Queue(BACKLOG)
        first = event("snapshot", self._fleet.snapshot())
        self._queues.add(queue)  # rule 1: no await since the snapshot
        try:
            yield first
            while True:
                try:
                    message = await asyncio.wait_for(queue.get(), KEEPALIVE_S)
                except TimeoutError:
                    message = b": keepalive\n\n"
                if not message:  # let go
                    return
                yield message
        finally:
            self._queues.discard(queue)

    def push(self) -> None:
        """Send what changed since the last push to every browser."""
        delta = self._fleet.drain()
        if delta is None:
            return
        message = event("delta", delta)
        for queue in list(self._queues):
            try:
                queue.put_nowait(message)
            except asyncio.QueueFull:  # rule 3
                self._let_go(queue)

    def let_go(self) -> None:
        """End every browser's stream (the dashboard stops)."""
        for queue in list(self._queues):
            self._let_go(queue)

    def _let_go(self, queue: asyncio.Queue[bytes]) -> None:
        self._queues.discard(queue)
        while not queue.empty():
            queue.get_nowait()
        queue.put_nowait(_LET_GO)

    async def run(self) -> None:
        """Push every ``PUSH_EVERY_S`` until cancelled."""
        while True:
            await asyncio.sleep(PUSH_EVERY_S)
            self.push()
