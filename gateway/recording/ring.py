"""A bounded ring of timed entries: what the flight recorder keeps in memory.

Rules of this file:

1. ``append`` is cheap enough for a bus thread: a lock that nobody holds for long, a list
   append, and every ``CHUNK`` entries a chunk closed. Any thread may append.
2. A reader never holds the lock while it copies many entries: the ring is kept as closed
   chunks (never changed again) and one open chunk, so a snapshot copies the chunk list and
   the open chunk under the lock and reads the rest outside it. A closed chunk is never
   changed, so a reader may keep it.
3. It forgets by age and by count: a chunk goes once its newest entry is older than
   ``seconds`` before the newest appended, and the oldest goes whenever more than
   ``max_entries`` are held, so memory is bounded whatever the rate.
4. Every entry is a tuple whose first item is its time (``perf_counter`` seconds).
"""

from __future__ import annotations

import math
import threading
from collections import deque

#: Entries per chunk: small enough that the open one copies in microseconds.
CHUNK = 256


class Ring:
    """The entries of the last ``seconds`` (at most ``max_entries`` of them)."""

    def __init__(self, seconds: float, max_entries: int) -> None:
        self.seconds = seconds
        self._max_chunks = max(1, math.ceil(max_entries / CHUNK))
        self._lock = threading.Lock()
        self._closed: deque[list[tuple]] = deque()
        self._open: list[tuple] = []

    def append(self, entry: tuple) -> None:
        with self._lock:
            self._open.append(entry)
            if len(self._open) >= CHUNK:
                self._close_chunk(entry[0])

    def _close_chunk(self, newest: float) -> None:
        closed = self._closed
        closed.append(self._open)
        self._open = []
        horizon = newest - self.seconds
        while closed and (len(closed) > self._max_chunks or closed[0][-1][0] < horizon):
            closed.popleft()

    def chunks(self, start: float) -> list[list[tuple]]:
        """The chunks holding the entries from ``start`` on, oldest first (rule 2: the closed
        ones as they are, the open one copied); the first may begin before ``start``."""
        with self._lock:
            chunks = list(self._closed)
            tail = list(self._open)
        return [chunk for chunk in (*chunks, tail) if chunk and chunk[-1][0] >= start]

    def __len__(self) -> int:
        with self._lock:
            return sum(map(len, self._closed)) + len(self._open)
