"""Writing a frame to a tty, waiting for room rather than spinning.

Why its own module: the serial owner and the SLCAN adapter both write to a tty opened without
blocking, and pyserial's ``write`` retries a write the kernel refuses (``EAGAIN``) at once, in
a loop with no wait: a wedged USB adapter, whose far end takes no more bytes, took a core for
as long as the write's timeout ran (and for ever with none, as python-can's SLCAN writes had).
"""

from __future__ import annotations

import contextlib
import os
import select

from busgate.gateway.bus.clock import now

#: While a tty takes no bytes, a write is tried again this often at the least: a tty is told
#: writable only once fewer than 256 bytes wait in its driver, when a few bytes may fit before.
RETRY_S = 0.005


def write_all(fd: int, data: bytes, timeout_s: float) -> bool:
    """Write all of ``data`` to ``fd``, waiting for room up to ``timeout_s`` in all; whether it
    all went. One ``write`` in the usual case."""
    rest = memoryview(data)
    deadline = now() + timeout_s
    while True:
        with contextlib.suppress(BlockingIOError):  # no room: waited for below
            rest = rest[os.write(fd, rest) :]
        if not rest:
            return True
        left = deadline - now()
        if left <= 0:
            return False
        select.select([], [fd], [], min(left, RETRY_S))
