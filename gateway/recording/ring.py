"""A bounded ring of timed entries: what the flight recorder keeps in memory.

Rules of this file:

1. ``append`` is cheap enough for a bus thread: a lock that nobody holds for long, a list
   append, and every ``CHUNK`` entries a chunk closed. Any thread may append.
2. A reader never holds the lock while it copies many entries: the ring is kept as closed
   chunks (never changed again) and one open chunk, so a snapshot copies the chunk list and
   the open chunk under the lock and reads the rest outside it. A closed chunk is never
   changed, so a reader may keep it.
3. It forgets by age, by count and by size: a chunk goes once its newest entry is older than
   ``seconds`` before the newest appended, and the oldest goes whenever more than
   ``max_entries`` are held or their bytes pass ``max_bytes``, so memory is bounded whatever
   the rate and whatever a peer sends. A chunk is closed early once its bytes reach a
   sixteenth of ``max_bytes``.
4. Every entry is a tuple whose first item is its time (``perf_counter`` seconds) and whose
   third its bytes (a payload, a frame).
"""

from __future__ import annotations

import math
import threading
from collections import deque

#: Entries per chunk: small enough that the open one copies in microseconds.
CHUNK = 256


class Ring:
    """The entries of the last ``seconds`` (at most ``max_entries`` of them, holding at most
    ``max_bytes``)."""

    def __init__(self, seconds: float, max_entries: int, max_bytes: int) -> None:
        self.seconds = seconds
        self._max_chunks = max(1, math.ceil(max_entries / CHUNK))
        self._max_bytes = max_bytes
        self._chunk_bytes = max(1, max_bytes // 16)
        self._lock = threading.Lock()
        self._closed: deque[list[tuple]] = deque()
        self._closed_sizes: deque[int] = deque()  # the bytes of each closed chunk
        self._closed_bytes = 0
        self._open: list[tuple] = []
        self._open_bytes = 0

    def append(self, entry: tuple) -> None:
        with self._lock:
            self._open.append(entry)
            self._open_bytes += len(entry[2])
            if len(self._open) >= CHUNK or self._open_bytes >= self._chunk_bytes:
                self._close_chunk(entry[0])

    def _close_chunk(self, newest: float) -> None:
        closed, sizes = self._closed, self._closed_sizes
        closed.append(self._open)
        sizes.append(self._open_bytes)
        self._closed_bytes += self._open_bytes
        self._open, self._open_bytes = [], 0
        horizon = newest - self.seconds
        while closed and (
            len(closed) > self._max_chunks
            or self._closed_bytes > self._max_bytes
            or closed[0][-1][0] < horizon
        ):
            closed.popleft()
            self._closed_bytes -= sizes.popleft()

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
